"""
The control tick on a bench: ``BalanceLoop`` driven tick by tick on a virtual clock.

What balance_node does each tick, without ROS or a bus: ROS messages go through the node's own
reductions (nodes/sensor_intake.imu_sample, core/sensors.JointStateReader) into the tick's
inputs; the frames the tick sends reach the wheel motors (the firmware emulated: the
configured protocol's own emulator, ``wheel_motors``), whose replies arrive before the next
tick (or are lost), and are decoded for the caller as the firmware decodes them (the
protocol's ``decode_command``); a send can be made to fail. Parameter
changes go through the node's own ParameterGuard checks. The clock moves one control period
per tick, so runs are deterministic and much faster than real time (fuzzing: tens of
microseconds per tick).
"""
import math
from typing import Any, Callable, Dict, List, Optional, Tuple
import uuid

from geometry_msgs.msg import TwistStamped
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState

from ...core.balance_loop import BalanceLoop, CmdVel, joint_state_reader, STATE_FIELDS, \
    TickInputs
from ...core.config import BalanceConfig
from ...core.protocols.base import Frame, MotorProtocol
from ...core.protocols.emulation import EmulatedMotors
from ...core.protocols.mit import MitCommand, MitProtocol
from ...core.schema import check, from_flat, with_changes
from ...nodes.params import load, ParameterGuard
from ...nodes.sensor_intake import imu_sample

#: The default configuration's wheel codec (the MIT rig's scenarios: validation/faults/rig.py).
MIT = MitProtocol()
#: One code step of the 12-bit MIT torque over +-18 N m [N m].
TORQUE_LSB = (MIT.t_max - MIT.t_min) / 4095
IDX = {name: i for i, name in enumerate(STATE_FIELDS)}
MODE = {'DISARMED': 0, 'BALANCING': 1, 'FAULT': 2, 'HOMING': 3, 'SITTING': 4, 'EXCITING': 5}
WHEEL_JOINTS = ('left_wheel_joint', 'right_wheel_joint')
LEG_JOINTS = ('left_leg_front_joint', 'left_leg_rear_joint', 'right_leg_front_joint',
              'right_leg_rear_joint')
#: Parameters that name the hip joints (l from the five-bar kinematics).
LEG_PARAMS = dict(zip(LEG_JOINTS, LEG_JOINTS))
#: Hip angles of l = 0.37 m (FiveBarLeg defaults).
NOMINAL_LEGS = (0.25, 0.25, 0.25, 0.25)


def quaternion_pitch(theta: float) -> Tuple[float, float, float, float]:
    """Orientation (x, y, z, w) of a pure pitch theta [rad] (REP 103, forward lean positive)."""
    return 0.0, math.sin(0.5 * theta), 0.0, math.cos(0.5 * theta)


def make_imu(theta: float = 0.0, theta_dot: float = 0.0, msg: Optional[Imu] = None) -> Imu:
    """Return an Imu of pitch theta [rad] and pitch rate theta_dot [rad/s], gravity on z."""
    msg = Imu() if msg is None else msg
    o = msg.orientation
    o.x, o.y, o.z, o.w = quaternion_pitch(theta)
    msg.angular_velocity.y = float(theta_dot)
    msg.linear_acceleration.z = 9.81
    return msg


def make_joints(w_left: float = 0.0, w_right: float = 0.0, legs=None) -> JointState:
    """Return the wheels' JointState (velocities [rad/s]) and, if given, four hip angles."""
    names = list(WHEEL_JOINTS)
    position = [0.0, 0.0]
    velocity = [float(w_left), float(w_right)]
    if legs is not None:
        names += list(LEG_JOINTS)
        position += [float(q) for q in legs]
        velocity += [0.0] * 4
    return JointState(name=names, position=position, velocity=velocity,
                      effort=[0.0] * len(names))


def emulated_motors(protocol: MotorProtocol, ids, directions) -> EmulatedMotors:
    """Return emulated motors of ``protocol`` (its make_emulator) with these IDs and directions."""
    return EmulatedMotors(protocol, ids, directions)


def wheel_motors(loop: BalanceLoop):
    """Return emulators of a loop's wheel motors: its protocol's, IDs and directions."""
    return emulated_motors(loop.protocol, loop.motors.ids,
                           {m.motor_id: m.direction for m in loop.motors.motors})


def decode(arbitration_id: int, data: bytes):
    """Decode a frame as MIT firmware does: 'enter' / 'exit' / 'zero', a command or None."""
    return MIT.decode_command(Frame(arbitration_id, bytes(data)))


def decode_frame(frame: Frame, protocol: MotorProtocol):
    """
    Decode a frame as ``protocol``'s motors do, or return it as it is.

    The protocol's decode_command (MIT's words above, LK's iq code or 'off', ...); a protocol
    with no decode_command gives the frame itself.
    """
    motor_side = getattr(protocol, 'decode_command', None)
    return frame if motor_side is None else motor_side(frame)


def is_zero_torque(cmd) -> bool:
    """Tell whether ``cmd`` is a torque-only MIT command of zero torque (one code step)."""
    return (isinstance(cmd, MitCommand) and cmd.kp == 0.0 and cmd.kd == 0.0
            and abs(cmd.torque) <= TORQUE_LSB)


class ArmRequest:
    """An ~/arm request handed to the next tick; ``success`` / ``message`` once answered."""

    def __init__(self, arm: bool):
        self.arm = arm
        self.success = False
        self.message = 'not handled'
        self.done = False


class LoopBench:
    """
    One BalanceLoop on a virtual clock (see the module docstring).

    params: parameter overrides {name: value} (checked as the node checks them). Attributes:
    loop (the BalanceLoop), t (the virtual monotonic time [s]), fail_with (while set, sending
    fails with this text, as a full TX queue or a bus-off would), motors (the wheel motors'
    emulators, the configured IDs and directions, the joints still): they act on every frame
    sent and reply to each.
    """

    def __init__(self, **params):
        cfg = from_flat(BalanceConfig, params)
        problems = check(cfg)
        if problems:
            raise ValueError('; '.join(problems))
        self.config = cfg
        self.period = cfg.loop.control_period
        self.loop = BalanceLoop(cfg)
        self.reader = joint_state_reader(cfg)
        self.inputs = TickInputs()
        self.t = 1000.0
        self.fail_with: Optional[str] = None
        self.sent: List[Frame] = []
        self._request: Optional[ArmRequest] = None
        self.motors = wheel_motors(self.loop)
        self._replies: List[Frame] = []   # the motors' replies to the frames of the last tick

    @property
    def has_legs(self) -> bool:
        """Return whether hip joints are configured (l from joint_states)."""
        return self.loop.sensing.has_leg_joints

    def set_wheel_motion(self, left: Tuple[float, float], right: Tuple[float, float]) -> None:
        """Set the wheels' (angle [rad], speed [rad/s]), forward positive, for the replies."""
        ids = self.loop.motors.ids
        self.motors.joints[ids[0]], self.motors.joints[ids[1]] = tuple(left), tuple(right)

    @property
    def mode(self) -> int:
        """Return the supervisor's mode as ~/state publishes it."""
        return int(self.loop.mode)

    @property
    def state(self) -> List[float]:
        """Return ~/state's values after the newest tick."""
        return self.loop.last_result.state.values()

    def feed(self, imu: Optional[Imu] = None, joints: Optional[JointState] = None) -> None:
        """Hand messages to the tick as the node's intake would (nominal ones when None)."""
        self.feed_imu(make_imu(0.02) if imu is None else imu)
        if joints is None:  # with hip joints configured, their angles count as joint states
            joints = make_joints(legs=NOMINAL_LEGS if self.has_legs else None)
        self.feed_joints(joints)

    def feed_imu(self, msg: Imu) -> None:
        """One Imu message, received now."""
        self.inputs.imu.append(imu_sample(msg, self.t))

    def feed_joints(self, msg: JointState) -> None:
        """One JointState message, received now (dropped when it has none of our joints)."""
        sample = self.reader.reduce(self.t, msg.name, msg.position, msg.velocity)
        if sample is not None:
            self.inputs.joints.append(sample)

    def feed_cmd_vel(self, msg: TwistStamped) -> None:
        """One cmd_vel message, received now."""
        self.inputs.cmd_vel = CmdVel(self.t, msg.twist.linear.x, msg.twist.angular.z)

    def request(self, arm: bool) -> ArmRequest:
        """Hand an ~/arm request to the next tick (as the service does)."""
        self._request = ArmRequest(arm)
        self.inputs.arm = arm
        return self._request

    def set_parameters(self, **changes) -> Tuple[bool, str]:
        """Check changes as balance_node does; accepted ones take effect at the next tick."""
        try:
            new = with_changes(self.config, changes)
        except ValueError as exc:
            return False, str(exc)
        problems = check(new)
        if problems:
            return False, '; '.join(problems)
        self.config = new
        self.inputs.params = {**self.inputs.params, **changes}
        return True, ''

    def tick(self, replies: bool = True) -> List[Tuple[int, Any]]:
        """
        Run one control tick one period after the previous one; return the decoded frames sent.

        ``replies``: the motors' replies to the previous tick's frames arrive just before
        (False: they are lost). A failed send (``fail_with``) sends nothing of that tick's
        frames: the motors neither see nor answer them.
        """
        self.t += self.period
        if replies:
            self.inputs.frames.extend((self.t, f) for f in self._replies)
        result = self.loop.tick(self.t, self.inputs)
        self.inputs.clear()
        self.sent = [] if self.fail_with is not None else list(result.frames)
        self._replies = [r for f in self.sent for r in self.motors.handle(f, self.t)]
        self.after_tick(result)
        protocol = self.loop.protocol
        return [(f.arbitration_id, decode_frame(f, protocol)) for f in self.sent]

    def after_tick(self, result) -> None:
        """Report the tick's send to the loop and answer a pending arm request with its reply."""
        self.loop.report_send(self.t, self.fail_with)
        req = self._request
        if req is not None and result.arm_reply is not None:
            req.success, req.message = result.arm_reply
            req.done = True
            self._request = None

    def estop(self) -> None:
        """Hand an emergency stop to the next tick (zero torque, exit: no sit-down)."""
        self.inputs.estop = True

    def arm_from_rest(self) -> Any:
        """Let the resting motors answer (exit frames every 20 ms), arm; return the request."""
        for _ in range(12):
            self.feed()
            self.tick()
        req = self.request(True)
        self.feed()
        self.tick()
        return req

    def rearm(self, imu: Optional[Imu] = None, joints: Optional[JointState] = None) -> None:
        """Stop, feed samples (nominal ones when None) and arm again: a fresh start."""
        self.estop()
        self.tick()
        self.feed(imu, joints)
        req = self.request(True)
        self.tick()
        if not req.success:
            raise RuntimeError('bench could not arm: %s' % req.message)

    def safety_values(self) -> Dict[str, Any]:
        """Return the loop's status (what /diagnostics shows), now."""
        return self.loop.status(self.t)

    @property
    def rejected_cmd_vel(self) -> int:
        """Return the cmd_vel messages dropped so far (diagnostics value rejected_cmd_vel)."""
        return self.loop.balancing.rejected_cmd_vel

    def wheel_torques(self) -> Tuple[float, float]:
        """Return the wheel torques of the newest tick as ~/state holds them [N m]."""
        s = self.loop.last_result.state
        return s.tau_left, s.tau_right

    def closed_loop(self, plant, seconds: float, x_dot_cmd: Optional[float] = None,
                    events: Optional[Dict[float, Callable[[], None]]] = None,
                    imu_gap: Tuple[float, float] = (0.0, 0.0)):
        """
        Run the loop and ``plant`` in lockstep for ``seconds``.

        Per tick the plant moves one period under the wheel torques the motors apply after the
        previous tick's frames (``motors``: the firmware's law, through the configured
        directions), its sensors go in, then the tick runs.
        ``events``: {time [s] from now: callable} run before the first tick at or after it;
        ``imu_gap``: (from, to) [s from now] during which no IMU sample arrives.
        Returns [(t [s], {motor id: the motor's torque [N m], its own direction}, mode)] per
        tick.
        """
        pending = sorted((events or {}).items())
        cmd = TwistStamped()
        motors = self.motors
        left, right = self.loop.motors.ids
        out = []
        for k in range(int(round(seconds / self.period))):
            # Times from the tick count: summing periods onto a clock near 1e3 s would move an
            # event or a window edge by one tick through rounding.
            t_tick = (k + 1) * self.period
            plant.advance(motors.torque(left, self.t), motors.torque(right, self.t),
                          self.period)
            q, gyro, _, wheels, legs = plant.sense()
            angles = plant.wheel_angles()
            self.set_wheel_motion((angles[0], wheels[0]), (angles[1], wheels[1]))
            if not imu_gap[0] <= t_tick - self.period < imu_gap[1]:
                imu = Imu()
                o, v = imu.orientation, imu.angular_velocity
                o.x, o.y, o.z, o.w = q
                v.x, v.y, v.z = gyro
                self.feed_imu(imu)
            self.feed_joints(make_joints(wheels[0], wheels[1], legs))
            if x_dot_cmd is not None:
                cmd.twist.linear.x = x_dot_cmd
                self.feed_cmd_vel(cmd)
            while pending and pending[0][0] <= t_tick + 1e-9:
                pending.pop(0)[1]()
            self.tick()
            out.append((t_tick, {i: e.motor_torque for i, e in motors.emulators.items()},
                        self.mode))
        return out


class ParameterFront(Node):
    """
    balance_node's parameters, declared and guarded as the node does, feeding a LoopBench.

    A set-parameters request goes through rclpy's descriptor checks and the node's
    ParameterGuard (nodes/params.py); what is accepted reaches the bench's next tick, as the
    node's accepted changes reach its control loop.
    """

    def __init__(self, context, bench: LoopBench):
        super().__init__('parameter_front_%s' % uuid.uuid4().hex[:8], context=context)
        cfg = load(self, BalanceConfig)
        bench.config = cfg

        def forward(changes, new_config):
            bench.config = new_config
            bench.inputs.params = {**bench.inputs.params, **changes}
        self.add_on_set_parameters_callback(ParameterGuard(cfg, forward))
