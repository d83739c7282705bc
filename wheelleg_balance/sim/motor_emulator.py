"""
The motors' firmware, emulated (pure Python: frames are core/protocols/base.Frame; no MuJoCo).

The one emulator of the motors that balance_node drives: the simulated robot (sim/robot_motors.py,
sim_node), the fault suite, the benchmark and the node tests answer CAN frames through it.
``MitMotorEmulator`` is one MIT motor; ``MitMotorBank`` a set of them without a simulator (each
joint held at an angle and speed the caller sets), what the fault suite, the benchmark and the
node tests put on their buses; ``DjiC620Emulator`` the other protocol's ESCs (at the end).
``MitMotorEmulator`` itself lives in core/protocols/mit.py, the MIT codec's emulator
(``make_emulator``), as every protocol's does; this docstring describes it.

The MIT motor follows bgkatz/motorcontrol, the mini-cheetah motor firmware whose MIT mode
CubeMars AK motors speak (file references below are to that repository; docs/simulation.md
has the table):

- power-up in rest mode: no torque. ``FF..FC`` enters motor mode with an empty command (zero
  torque until the first command), ``FF..FD`` goes back to rest, ``FF..FE`` makes the present
  position the zero, in rest mode only (Core/Src/fsm.c handles ZERO_CMD in MENU_MODE and ignores
  it in MOTOR_MODE);
- in motor mode: tau = kp (p - q) + kd (v - q_dot) + tau_ff, clamped to +-torque_limit, where q,
  q_dot are the motor's own output-shaft angle and speed; the caller evaluates it at every
  physics step, as the firmware runs it at every commutation cycle;
- one reply per frame addressed to the motor (special frames included), carrying the state at
  that moment (Core/Src/stm32f4xx_it.c packs a reply for every received frame): 6 bytes, or 8
  with temperature and error code (newer CubeMars firmware). The firmware packs it before it
  acts on the frame, so its torque field lags one frame; here it shows the torque of the frame
  just received (what the host asked for, the sooner the better for a simulation);
- a reply field beyond its range wraps around (core/protocols/mit.py float_to_uint_wrapping:
  bgkatz's float_to_uint does not clamp and pack_reply keeps the low 16 bits; CubeMars AK
  firmware wraps as well, as neurobionics/TMotorCANControl observed and corrects on the host).
  ``wrap=False`` clamps instead (firmware that saturates; neither of the two does);
- an optional command timeout: no command for ``command_timeout`` s in motor mode zeroes the
  command (``timeout_action='zero'``: kp = kd = tau_ff = 0, still in motor mode, as fsm.c does
  with CAN_TIMEOUT), or goes to rest mode (``'rest'``, firmware that disables on timeout);
- a settable temperature and error code (both reported in 8-byte replies); while the error code
  is not 0 the output is off, as the drive's protection does;
- ``reboot``: rest mode, command gone, and the position known only modulo one rotor turn: the
  encoder sits on the rotor, so after power-up the multi-turn count restarts and the output
  angle reads (rotor angle from the stored zero, in (-3 pi / 2, pi / 2]) / gear_ratio, the
  window of Core/Src/position_sensor.c's first sample (2 pi / 9 = 40 deg of output per rotor
  turn for a 9:1 gear). The stored zero survives the reboot (CubeMars writes it to flash);
- ``miswired``: the motor turns the other way than it is configured to (a bring-up fault);
  ``reply_id``: its replies carry this ID instead of its own (a fault injection: no firmware
  does that, but a host must not take such a reply for the motor's).

Conventions: q, q_dot, and the torque returned are the *joint's* (the physics side); the
motor's direction (+1 or -1) maps them: motor position = direction q - zero.
"""
from typing import Dict, Iterable, List, Mapping, Optional, Tuple

from ..core.protocols.base import Frame
from ..core.protocols.dji import CURRENT_CODE_MAX, CURRENT_MAX, DjiC620Protocol
from ..core.protocols.emulation import EmulatedMotors
# The MIT motor is its protocol's emulator (MitProtocol.make_emulator); here for the callers.
from ..core.protocols.mit import MitMotorEmulator, MitProtocol, POWER_UP_WINDOW  # noqa: F401


class MitMotorBank(EmulatedMotors):
    """
    MIT motors without a simulator: each joint at an angle and speed the caller sets (still).

    What the fault suite, the benchmark and the node tests put on their buses: the protocols'
    ``EmulatedMotors`` on MIT (the MIT motor answers only frames on its own ID), built as those
    callers name it. ids: CAN IDs; directions: {ID: +1 or -1}, motor shaft relative to the joint
    (default +1); protocol (default MitProtocol()) and the other options are
    MitMotorEmulator's, for every motor. ``silent``: IDs whose replies are lost (the motor
    still acts on the frames); fault flags of one motor (miswired, reply_id, errors) are on
    its emulator, ``motor(ID)``.
    """

    def __init__(self, ids: Iterable[int], directions: Optional[Mapping[int, int]] = None,
                 protocol: Optional[MitProtocol] = None, **options):
        super().__init__(protocol if protocol is not None else MitProtocol(), ids, directions,
                         **options)


class DjiC620Emulator:
    """
    DJI C620 ESCs with M3508 P19 motors on one bus (ESC IDs 1..8), answering current commands.

    Each command frame (0x200: ESCs 1-4, 0x1FF: 5-8; core/protocols/dji.py) sets the current of
    the ESCs it addresses and gets one feedback frame from each of those in ``esc_ids`` (the
    real ESC sends feedback at 1 kHz on its own; one per command is what a host ticking at 500
    Hz sees of it, without a clock here). The feedback carries the rotor angle and speed of the
    motor's output state (``state``: {ESC ID: (position [rad], velocity [rad/s])}, default
    still), the commanded current as the torque current (the ESC's current loop settled within
    a tick) and ``temperature`` [deg C]. ``silent``: ESC IDs whose feedback is lost.
    """

    def __init__(self, esc_ids: Iterable[int] = (1, 2),
                 protocol: Optional[DjiC620Protocol] = None, temperature: int = 25):
        self.protocol = protocol if protocol is not None else DjiC620Protocol()
        self.ids = tuple(int(i) for i in esc_ids)
        if not all(1 <= i <= 8 for i in self.ids):
            raise ValueError('C620 ESC IDs are 1..8')
        self.temperature = int(temperature)
        self.state: Dict[int, Tuple[float, float]] = dict.fromkeys(self.ids, (0.0, 0.0))
        self.currents: Dict[int, int] = dict.fromkeys(self.ids, 0)   # command codes
        self.silent = set()

    def torque(self, esc_id: int) -> float:
        """Return the output torque [N m] of ESC ``esc_id``'s motor (its own direction)."""
        p = self.protocol
        return self.currents[esc_id] * (CURRENT_MAX / CURRENT_CODE_MAX) * p.torque_constant

    def handle(self, frame: Frame, now: float = 0.0) -> List[Frame]:
        """Act on a frame as the ESCs do; return their feedback frames ([] if none is sent)."""
        codes = self.protocol.decode_command(frame)
        if codes is None:
            return []
        out = []
        for esc_id, code in codes.items():
            if esc_id not in self.currents:
                continue
            self.currents[esc_id] = code
            if esc_id in self.silent:
                continue
            position, velocity = self.state[esc_id]
            out.append(self.protocol.encode_state(esc_id, position, velocity, code,
                                                  self.temperature))
        return out
