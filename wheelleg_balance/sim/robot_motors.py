"""
The simulated robot's motors: one firmware emulator per joint, bound to RobotSim (no ROS).

Two wheel motors and, with ``RobotSim(legs='motors')``, four hip motors, each its protocol's
emulator (``MotorProtocol.make_emulator``: MIT, the C620, LK, CyberGear, DaMiao, or one
registered at run time), the wheels of one protocol, the hips of another if so configured.
``replies`` answers a CAN frame as the motors on that bus do (with the joint's true state,
quantized into the reply: a C620 group frame gets one reply per ESC it carries, a CyberGear
one comes on an extended ID); ``handle`` is its first reply; ``step`` advances
the physics one timestep at a time, every motor evaluating its impedance law at every step, as
the firmware does at its commutation rate. sim_node puts this on a CAN bus; the closed-loop
tests call it directly with frames.

Joint conventions (sim/robot_sim.py): wheels forward positive relative to the leg, hips in
FiveBarLeg's convention. A motor's position is ``direction (q - offset)``: offset is the joint
angle at which the motor reads zero (for the hips, balance_node's ``legs.offsets``).
``power_up=True`` reboots the hip motors at the start, so their reading is known only modulo
one rotor turn (what homing has to resolve).
"""
from dataclasses import dataclass
import inspect
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from .hand import Hand
from .robot_sim import LEG_JOINTS, RobotSim, WHEEL_JOINTS
from ..core.protocols.base import Frame, MotorProtocol
from ..core.protocols.emulation import EmulatedMotor
from ..core.protocols.mit import MitProtocol

#: Joint names of MotorSpec.joint: the two wheels, then the hips in LEG_JOINTS order.
JOINTS = WHEEL_JOINTS + LEG_JOINTS


@dataclass(frozen=True)
class MotorSpec:
    """
    One motor and where it sits.

    joint: a JOINTS name; motor_id: its CAN ID; direction: +1 or -1, motor shaft relative to
    the joint; offset [rad]: joint angle at the motor's zero; bus: 0 the wheels' bus, 1 a
    second bus for the legs.
    """

    joint: str
    motor_id: int
    direction: int = 1
    offset: float = 0.0
    bus: int = 0


def default_specs(wheel_ids=(1, 2), wheel_directions=(1, -1), hip_ids=(3, 4, 5, 6),
                  hip_directions=(1, 1, 1, 1), hip_offsets=(0.0, 0.0, 0.0, 0.0),
                  hip_bus: int = 0, hips: bool = True) -> List[MotorSpec]:
    """Return the MotorSpecs of the six motors (hips=False: the two wheel motors only)."""
    specs = [MotorSpec(j, i, d) for j, i, d in zip(WHEEL_JOINTS, wheel_ids, wheel_directions)]
    if hips:
        specs += [MotorSpec(j, i, d, o, hip_bus) for j, i, d, o in
                  zip(LEG_JOINTS, hip_ids, hip_directions, hip_offsets)]
    return specs


def make_emulator(protocol: MotorProtocol, motor_id: int,
                  options: Mapping[str, Any]) -> EmulatedMotor:
    """
    Return the protocol's emulator of ``motor_id`` built with the options it takes.

    The firmware options are the MIT motor's (wrap, reply_temperature: MIT's and DaMiao's
    emulators take wrap); an emulator without one keeps its own behaviour.
    """
    kind = type(protocol.make_emulator(motor_id))
    names = set(inspect.signature(kind.__init__).parameters) | set(
        inspect.signature(EmulatedMotor.__init__).parameters)
    return protocol.make_emulator(motor_id, **{k: v for k, v in options.items()
                                               if k in names})


class RobotMotors:
    """
    The motors of a RobotSim (see the module docstring).

    specs: MotorSpecs (hips need legs='motors'); protocol / hip_protocol: the wheel and hip
    motors' codecs (default MitProtocol(), the hips the wheels'), whose make_emulator builds
    each motor; gear_ratio of hip motors whose codec has none (MIT: for their reboot);
    command_timeout (0: each emulator's own default) and timeout_action apply to all motors,
    wrap and reply_temperature to the emulators that take them (make_emulator).
    """

    def __init__(self, sim: RobotSim, specs: Sequence[MotorSpec],
                 protocol: Optional[MotorProtocol] = None,
                 hip_protocol: Optional[MotorProtocol] = None, gear_ratio: float = 9.0,
                 command_timeout: float = 0.0, timeout_action: str = 'zero', wrap: bool = True,
                 reply_temperature: bool = False, power_up: bool = False):
        self.sim = sim
        self.specs = list(specs)
        protocol = protocol if protocol is not None else MitProtocol()
        hip_protocol = hip_protocol if hip_protocol is not None else protocol
        keys = [(s.bus, s.motor_id) for s in self.specs]
        joints = [s.joint for s in self.specs]
        if len(set(keys)) != len(keys) or len(set(joints)) != len(joints):
            raise ValueError('each joint once, and one motor per CAN ID and bus')
        if any(j not in JOINTS for j in joints):
            raise ValueError('joints must be among %s' % ', '.join(JOINTS))
        if sim.legs != 'motors' and any(j in LEG_JOINTS for j in joints):
            raise ValueError("hip motors need RobotSim(legs='motors')")
        self.protocol, self.hip_protocol = protocol, hip_protocol
        self.emulators: Dict[str, EmulatedMotor] = {}
        #: Per bus, (joint index, emulator) of the motors on it: every frame is offered to each
        #: (their IDs are the protocols' business: 0x140 + ID, a C620 group, a 29-bit target).
        self._on_bus: Dict[int, List[Tuple[int, EmulatedMotor]]] = {}
        timeout = {'command_timeout': command_timeout,
                   'timeout_action': timeout_action} if command_timeout > 0.0 else {}
        for spec in self.specs:
            codec = hip_protocol if spec.joint in LEG_JOINTS else protocol
            options = dict(timeout, direction=spec.direction, wrap=wrap,
                           reply_temperature=reply_temperature)
            if getattr(codec, 'gear_ratio', None) is None:   # MIT: the model's, configured
                options['gear_ratio'] = gear_ratio
            e = make_emulator(codec, spec.motor_id, options)
            e.zero = spec.direction * spec.offset
            self.emulators[spec.joint] = e
            self._on_bus.setdefault(spec.bus, []).append((JOINTS.index(spec.joint), e))
        self._motors = [(JOINTS.index(s.joint), self.emulators[s.joint]) for s in self.specs]
        self._bus = {s.joint: s.bus for s in self.specs}
        self._hips_driven = sim.legs == 'motors'
        #: Per joint: frames at the previous command_marks, ticks in a row with a new one.
        self._frames_seen: Dict[str, int] = {}
        self._streak: Dict[str, int] = {}
        self.hand = Hand(len(JOINTS))
        self._hand_on = False
        self._refresh()
        if power_up:
            for k, e in self._motors:
                if JOINTS[k] in LEG_JOINTS:
                    e.reboot(self._q[k])

    def _refresh(self) -> None:
        # Each replaced whole: the CAN thread of sim_node reads them.
        self._q, self._v, self._time = self.sim.motor_joints()

    def joint_angles(self) -> List[float]:
        """Return the six joints' angles [rad] now (JOINTS order, the physics' convention)."""
        return list(self._q)

    def motor(self, joint: str) -> EmulatedMotor:
        """Return the emulator driving a joint (KeyError if the joint has none)."""
        return self.emulators[joint]

    def replies(self, frame: Frame, bus: int = 0) -> List[Frame]:
        """Answer a frame on a bus as the motors on it do: a list of what they send back."""
        q, v, t = self._q, self._v, self._time
        out = []
        for k, e in self._on_bus.get(bus, ()):
            reply = e.handle(frame, q[k], v[k], t)
            if reply is not None:
                out.append(reply)
        return out

    def handle(self, frame: Frame, bus: int = 0) -> Optional[Frame]:
        """Answer a frame on a bus: the first motor's reply, or None (replies has them all)."""
        out = self.replies(frame, bus)
        return out[0] if out else None

    @property
    def time(self) -> float:
        """Return the simulated time [s] of the motors' view of the joints."""
        return self._time

    def command_marks(self) -> Dict[str, int]:
        """
        Return {joint: frames received} of the motors in motor mode now (see commanded).

        Called once a tick (lockstep): it also counts the ticks in a row each motor got a
        frame in (``_driven``).
        """
        seen = self._frames_seen
        for j, e in self.emulators.items():
            self._streak[j] = self._streak.get(j, 0) + 1 if e.frames > seen.get(j, 0) else 0
            seen[j] = e.frames
        return {j: e.frames for j, e in self.emulators.items() if self._driven(j, e)}

    def _driven(self, joint: str, e: EmulatedMotor) -> bool:
        """
        Tell whether balance_node drives a motor: in its torque mode and commanded.

        A motor that takes torque from power-up (LK, the C620) is in its torque mode before the
        node sends anything, and the C620 stays in it after the node's last (zero) command:
        lockstep waits for such a motor only while it got a frame in each of the last
        DRIVEN_TICKS ticks (a disarmed node's occasional zero command is not the tick's).
        """
        return e.enabled and e.frames > 0 and (
            not e.powered_enabled or self._streak.get(joint, 0) >= DRIVEN_TICKS)

    def commanded(self, marks: Dict[str, int]) -> bool:
        """
        Return True once the tick's commands are in (sim_node's lockstep), counted from marks.

        balance_node commands both wheels every tick while any motor is in motor mode, the
        hips in turns while balancing (``legs.command_divider``), and in lockstep it sends a
        tick's hip frames before its wheel frames (nodes/control_process.py); one bus delivers
        in order. So on the wheels' bus the wheels in motor mode close the tick; a motor on
        another bus (hips on their own) must have had a frame itself; with no wheel in motor
        mode (a hip enabled alone), every motor in motor mode. A motor that entered motor mode
        since counts from its enter frame; one that left it is no longer waited for.
        """
        enabled = [(j, e) for j, e in self.emulators.items() if self._driven(j, e)]
        wheels = [(j, e) for j, e in enabled if j in WHEEL_JOINTS]
        waited = wheels + [(j, e) for j, e in enabled if self._bus[j] != 0] if wheels \
            else enabled
        return all(e.frames > marks.get(j, -1) for j, e in waited)

    def torques(self) -> List[float]:
        """Evaluate every motor now: the six joint torques [N m] (JOINTS order; 0 without one)."""
        q, v, t = self._q, self._v, self._time
        tau = [0.0] * 6
        for k, e in self._motors:
            tau[k] = e.torque(q[k], v[k], t)
        return tau

    def step(self, dt: float) -> None:
        """Advance dt [s] in whole timesteps, the motors' torques evaluated at each."""
        sim = self.sim
        n = max(1, int(round(dt / sim.timestep)))
        for _ in range(n):
            tau = self.torques()
            if self.hand.targets or self._hand_on:
                self._hand_on = bool(self.hand.targets)
                sim.apply_joint_torques(self.hand.torques(self._q, self._v))
            sim.step(tau[0], tau[1], sim.timestep, tau[2:] if self._hips_driven else None)
            self._refresh()

    def motor_state(self, joint: str) -> Tuple[float, float, float]:
        """(position [rad], velocity [rad/s], torque [N m]) of a joint's motor, its own frame."""
        k = JOINTS.index(joint)
        e = self.emulators[joint]
        return e.position(self._q[k]), e.velocity(self._v[k]), e.motor_torque


#: Ticks in a row with a frame after which a motor in its torque mode from power-up counts
#: as driven (lockstep waits for it): the C620 has no mode the node leaves on a disarm.
DRIVEN_TICKS = 2
