"""
The simulated robot's MIT motors: one firmware emulator per joint, bound to RobotSim (no ROS).

Two wheel motors and, with ``RobotSim(legs='motors')``, four hip motors, each a
sim/motor_emulator.py MitMotorEmulator. ``handle`` answers a CAN frame as the motor with that
ID on that bus does (with the joint's true state, quantized into the reply); ``step`` advances
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
from typing import Dict, List, Optional, Sequence, Tuple

from .hand import Hand
from .motor_emulator import MitMotorEmulator
from .robot_sim import LEG_JOINTS, RobotSim, WHEEL_JOINTS
from ..core.protocols.base import Frame
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


class RobotMotors:
    """
    The motors of a RobotSim (see the module docstring).

    specs: MotorSpecs (hips need legs='motors'); protocol / hip_protocol: the MIT ranges of the
    wheel and hip motor models; gear_ratio of the hip motors (for their reboot); the other
    options are MitMotorEmulator's, for all motors.
    """

    def __init__(self, sim: RobotSim, specs: Sequence[MotorSpec],
                 protocol: Optional[MitProtocol] = None,
                 hip_protocol: Optional[MitProtocol] = None, gear_ratio: float = 9.0,
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
        self.emulators: Dict[str, MitMotorEmulator] = {}
        self._by_key: Dict[Tuple[int, int], Tuple[int, MitMotorEmulator]] = {}
        for spec in self.specs:
            hip = spec.joint in LEG_JOINTS
            e = MitMotorEmulator(spec.motor_id, hip_protocol if hip else protocol,
                                 gear_ratio=gear_ratio, direction=spec.direction,
                                 command_timeout=command_timeout, timeout_action=timeout_action,
                                 wrap=wrap, reply_temperature=reply_temperature)
            e.zero = spec.direction * spec.offset
            self.emulators[spec.joint] = e
            self._by_key[(spec.bus, spec.motor_id)] = (JOINTS.index(spec.joint), e)
        self._motors = [(JOINTS.index(s.joint), self.emulators[s.joint]) for s in self.specs]
        self._bus = {s.joint: s.bus for s in self.specs}
        self._hips_driven = sim.legs == 'motors'
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

    def motor(self, joint: str) -> MitMotorEmulator:
        """Return the emulator driving a joint (KeyError if the joint has none)."""
        return self.emulators[joint]

    def handle(self, frame: Frame, bus: int = 0) -> Optional[Frame]:
        """Answer a frame on a bus as the addressed motor does: its reply, or None."""
        hit = self._by_key.get((bus, frame.arbitration_id))
        if hit is None or frame.is_extended_id:
            return None
        k, e = hit
        return e.handle(frame, self._q[k], self._v[k], self._time)

    @property
    def time(self) -> float:
        """Return the simulated time [s] of the motors' view of the joints."""
        return self._time

    def command_marks(self) -> Dict[str, int]:
        """Return {joint: frames received} of the motors in motor mode now (see commanded)."""
        return {j: e.frames for j, e in self.emulators.items() if e.enabled}

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
        enabled = [(j, e) for j, e in self.emulators.items() if e.enabled]
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
