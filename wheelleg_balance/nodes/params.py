"""
The parameters of balance_node: one table with defaults, descriptions, ranges and read-only flags.

DESIGN.md section 2 fixes the names and defaults; config/balance.yaml repeats the values for the
real robot. Read-only parameters are the ones the node cannot change while running (model,
joint names, CAN set-up, loop timing); every other one is applied at the next control tick.
Ranges are checked by rclpy from the descriptors before ``validate`` sees a change; ``validate``
adds the checks that involve a name list or another parameter.
"""
from dataclasses import dataclass
import math
from typing import Any, Dict, Mapping, Optional, Tuple

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from ..core.lqr import DEFAULT_Q, DEFAULT_R
from ..core.pipeline import CONTROLLER_NAMES

#: Values of ``can.protocol``.
PROTOCOL_NAMES = ('mit', 'dji_c620')


@dataclass(frozen=True)
class Spec:
    """One parameter: default value (its type is the parameter's type), meaning, range, access."""

    name: str
    default: Any
    description: str
    lo: Optional[float] = None
    hi: Optional[float] = None
    read_only: bool = False
    step: int = 0

    def descriptor(self) -> ParameterDescriptor:
        """Return the descriptor rclpy checks (range, read-only) and `ros2 param describe`."""
        d = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.lo is None:
            return d
        if isinstance(self.default, int):
            d.integer_range = [IntegerRange(from_value=int(self.lo), to_value=int(self.hi),
                                            step=self.step)]
        elif isinstance(self.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(self.lo),
                                                         to_value=float(self.hi))]
        return d


def _f(name, default, description, lo, hi, read_only=False):
    return Spec(name, float(default), description, lo, hi, read_only)


def _direction(name, default, description):
    # IntegerRange -1..1 with step 2 admits exactly -1 and +1.
    return Spec(name, default, description, -1, 1, read_only=True, step=2)


RO = True
SPECS = (
    Spec('controller', 'ida_pbc', 'balance controller: %s; switchable live, bumpless, at the '
         'next control tick' % ' | '.join(CONTROLLER_NAMES)),
    # Model (1), Table I. m = body (pendulum), M = wheels (cart): see DESIGN.md section 1.
    _f('body_mass', 11.0, 'm: body (pendulum) mass [kg]', 0.1, 200.0, RO),
    _f('wheel_mass', 3.0, 'M: mass of both wheels (cart) [kg]', 0.01, 100.0, RO),
    _f('gravity', 9.81, 'g [m/s^2]', 1.0, 20.0, RO),
    _f('wheel_radius', 0.1, 'r_w: wheel radius [m]', 0.01, 1.0, RO),
    _f('wheel_separation', 0.47, 'd_w: distance between the wheels [m]', 0.05, 3.0, RO),
    _f('height_min', 0.37, 'lowest body height l above the wheel axle [m]', 0.05, 3.0, RO),
    _f('height_max', 0.70, 'highest body height l above the wheel axle [m]', 0.05, 3.0, RO),
    _f('height', 0.37, 'body height l [m] used when no leg joints are configured; '
       'within height_min..height_max', 0.05, 3.0),
    # IDA-PBC (11)-(13), Table I.
    _f('ida_pbc.k', 0.015, 'IDA-PBC k > 0 of M_d (Table I)', 1e-6, 10.0),
    _f('ida_pbc.m22_0', 0.04, 'IDA-PBC m22^0 >= 0 of M_d (Table I)', 0.0, 10.0),
    _f('ida_pbc.k_v', 0.05, 'IDA-PBC damping injection k_v > 0 (Table I)', 1e-6, 10.0),
    _f('ida_pbc.P', 0.2, 'IDA-PBC gain P >= 0 (Table I: 0.2; 0 makes (13) an exact IDA-PBC, '
       'docs/ida_pbc.md)', 0.0, 100.0),
    Spec('ida_pbc.compensate_offset', True, 'IDA-PBC uses theta~ - d_hat (removes the velocity '
         'bias an IMU offset causes; the paper leaves it in)', read_only=RO),
    # Output regulation (9)-(10): LQR weights of the k_x schedule over l.
    Spec('output_regulation.q_diag', [float(q) for q in DEFAULT_Q.diagonal()],
         'LQR state weights diag(Q) for [theta, theta_dot, x, x_dot] (k_x = lqr(A(l), B(l)))',
         read_only=RO),
    _f('output_regulation.r', DEFAULT_R, 'LQR input weight R [1/N^2]', 1e-9, 1e6, RO),
    _f('d_hat0', 0.0, 'initial estimate of the IMU pitch offset d [rad] at arm (the paper '
       'used 2.7 deg)', -0.5, 0.5),
    _f('yaw_rate_gain', 0.3, 'tau_gamma = yaw_rate_gain (yaw rate - yaw rate*) [N m s/rad], '
       'Sec. V-A', 0.0, 10.0),
    _f('switch_blend_time', 0.1, 'controller switch: time over which the jump in u fades out '
       '[s]', 0.0, 5.0),
    # Joints.
    Spec('left_wheel_joint', 'left_wheel_joint', 'joint_states name of the left wheel',
         read_only=RO),
    Spec('right_wheel_joint', 'right_wheel_joint', 'joint_states name of the right wheel',
         read_only=RO),
    _direction('left_wheel_direction', 1, '+1 when a positive joint_states velocity of the '
               'left wheel rolls the robot forward, else -1'),
    _direction('right_wheel_direction', 1, '+1 when a positive joint_states velocity of the '
               'right wheel rolls the robot forward, else -1'),
    Spec('left_leg_front_joint', '', 'joint_states name of the left leg front hip (q_front of '
         'core/kinematics.py FiveBarLeg); empty: no leg joints, l is the height parameter',
         read_only=RO),
    Spec('left_leg_rear_joint', '', 'joint_states name of the left leg rear hip (q_rear)',
         read_only=RO),
    Spec('right_leg_front_joint', '', 'joint_states name of the right leg front hip',
         read_only=RO),
    Spec('right_leg_rear_joint', '', 'joint_states name of the right leg rear hip',
         read_only=RO),
    Spec('leg_joint_directions', [1, 1, 1, 1], 'sign from joint_states position to the '
         'FiveBarLeg angle, order left front, left rear, right front, right rear', read_only=RO),
    Spec('leg_joint_offsets', [0.0, 0.0, 0.0, 0.0], 'FiveBarLeg angle at joint position zero '
         '[rad], same order: q = offset + direction * position', read_only=RO),
    _f('leg.thigh', 0.30, 'five-bar thigh length [m]', 0.01, 2.0, RO),
    _f('leg.shank', 0.42, 'five-bar shank length [m]', 0.01, 2.0, RO),
    _f('leg.hip_spacing', 0.10, 'distance between the two hip axes [m]', 0.0, 1.0, RO),
    _f('leg.com_height', 0.05, 'body centre of mass above the hip midpoint [m]', -1.0, 1.0, RO),
    _f('leg.com_x', 0.0, 'body centre of mass ahead of the hip midpoint [m]', -1.0, 1.0, RO),
    # Safety.
    _f('max_wheel_torque', 12.0, 'torque limit of each wheel [N m]', 0.0, 100.0),
    _f('max_pitch_rate', 35.0, '|IMU pitch rate| beyond which a sample is implausible: fault '
       '[rad/s] (35 rad/s = 2000 deg/s gyro full scale)', 1.0, 1000.0),
    _f('max_wheel_velocity', 200.0, '|wheel velocity| beyond which a sample is implausible: '
       'fault [rad/s] (200 rad/s = 20 m/s on 0.1 m wheels)', 1.0, 10000.0),
    _f('fall_angle', math.radians(45.0), '|theta~| beyond which the robot has fallen: fault '
       '[rad] (keep it above the tail rest, about 0.63 rad, to start from the tail)', 0.05, 1.5),
    _f('imu_timeout', 0.05, 'IMU sample age that is a fault [s]', 0.004, 2.0),
    _f('joint_state_timeout', 0.05, 'joint-state sample age that is a fault [s]', 0.004, 2.0),
    _f('motor_timeout', 0.05, 'time a commanded wheel motor may stay without a CAN reply [s]',
       0.004, 2.0),
    _f('cmd_vel_timeout', 0.5, 'cmd_vel age after which the references ramp to zero [s] '
       '(not a fault)', 0.01, 60.0),
    Spec('auto_arm', False, 'arm by itself once, as soon as the sensors are fresh and no fault '
         'condition is present (start-up only)', read_only=RO),
    _f('reference.max_velocity', 1.0, 'limit of x_dot* [m/s]', 0.0, 5.0),
    _f('reference.max_acceleration', 1.0, 'limit of the rate of change of x_dot* [m/s^2]',
       0.01, 50.0),
    _f('reference.max_yaw_rate', 3.0, 'limit of yaw rate* [rad/s]', 0.0, 20.0),
    _f('reference.max_yaw_acceleration', 6.0, 'limit of the rate of change of yaw rate* '
       '[rad/s^2]', 0.01, 200.0),
    # CAN.
    Spec('can.interface', 'socketcan', 'python-can interface: socketcan on the robot, virtual '
         '(one process) or udp_multicast (between processes) for tests', read_only=RO),
    Spec('can.channel', 'can0', 'python-can channel (udp_multicast: the group, e.g. '
         '239.74.163.2)', read_only=RO),
    Spec('can.udp_port', 43113, 'UDP port of the udp_multicast interface (python-can '
         'default 43113)', 1, 65535, RO),
    Spec('can.protocol', 'mit', 'wheel motor protocol: %s' % ' | '.join(PROTOCOL_NAMES),
         read_only=RO),
    Spec('can.left_motor_id', 1, 'CAN ID of the left wheel motor', 0, 2047, RO),
    Spec('can.right_motor_id', 2, 'CAN ID of the right wheel motor', 0, 2047, RO),
    _direction('can.left_direction', 1, '+1 when a positive torque of the left motor drives '
               'the wheel forward, else -1 (also applied to its feedback)'),
    _direction('can.right_direction', -1, '+1 when a positive torque of the right motor drives '
               'the wheel forward, else -1 (mirrored mounting)'),
    _f('can.send_timeout', 0.0005, 'timeout of one bus.send [s]; a send that fails is a fault',
       0.0, 0.01, RO),
    _f('can.mit.p_max', 12.5, 'MIT position range +-p_max [rad]', 0.1, 1000.0, RO),
    _f('can.mit.v_max', 50.0, 'MIT velocity range +-v_max [rad/s]', 0.1, 1000.0, RO),
    _f('can.mit.kp_max', 500.0, 'MIT kp range 0..kp_max [N m/rad]', 0.1, 10000.0, RO),
    _f('can.mit.kd_max', 5.0, 'MIT kd range 0..kd_max [N m s/rad]', 0.01, 1000.0, RO),
    _f('can.mit.t_max', 18.0, 'MIT torque range +-t_max [N m]', 0.1, 1000.0, RO),
    _f('can.dji.torque_constant', 0.3, 'dji_c620: output torque per ampere [N m/A] (M3508 '
       'P19)', 0.001, 100.0, RO),
    _f('can.dji.gear_ratio', 3591.0 / 187.0, 'dji_c620: rotor turns per output turn', 0.01,
       1000.0, RO),
    _f('can.dji.current_limit', 20.0, 'dji_c620: current limit [A] (C620: 20 A)', 0.1, 20.0,
       RO),
    # Loop and publications.
    _f('control_period', 0.002, 'control period T_s [s] (the paper: 2 ms)', 0.0005, 0.02, RO),
    _f('state_publish_rate', 100.0, 'rate of ~/state [Hz] (decimated from the control loop; '
       '0: off)', 0.0, 1000.0, RO),
    _f('odom_publish_rate', 50.0, 'rate of odom [Hz] (0: off)', 0.0, 1000.0, RO),
    _f('diagnostics_rate', 1.0, 'rate of /diagnostics [Hz]; a mode change publishes at once',
       0.1, 10.0, RO),
    Spec('odom_frame_id', 'odom', 'frame of the odometry pose', read_only=RO),
    Spec('base_frame_id', 'base_link', 'child frame of the odometry', read_only=RO),
    Spec('pose_covariance_diagonal', [0.001, 0.001, 1.0e6, 1.0e6, 1.0e6, 0.01],
         'odom pose covariance diagonal (x, y, z, roll, pitch, yaw)', read_only=RO),
    Spec('twist_covariance_diagonal', [0.001, 0.001, 1.0e6, 1.0e6, 1.0e6, 0.01],
         'odom twist covariance diagonal (x, y, z, roll, pitch, yaw)', read_only=RO),
    Spec('realtime_priority', 0, 'SCHED_FIFO priority of the control thread (0: leave the '
         'scheduler alone; needs rtprio rights)', 0, 98, RO),
    Spec('realtime_cpu', -1, 'CPU the control thread is pinned to (-1: no pinning)', -1, 1023,
         RO),
    Spec('lock_memory', False, 'lock the process in RAM (mlockall, MCL_ONFAULT) so no page '
         'fault stalls the loop; needs CAP_IPC_LOCK or a memlock limit', read_only=RO),
)

SPEC_BY_NAME = {s.name: s for s in SPECS}


def declare_all(node) -> Dict[str, Any]:
    """Declare every parameter on ``node`` and return {name: value} (overrides applied)."""
    for spec in SPECS:
        node.declare_parameter(spec.name, spec.default, spec.descriptor())
    return {spec.name: node.get_parameter(spec.name).value for spec in SPECS}


def validate(changes: Mapping[str, Any], current: Mapping[str, Any]) -> Tuple[bool, str]:
    """
    Check a set of changes against each other and the current values.

    Returns (ok, reason). rclpy has already checked types, ranges and read-only flags.
    """
    values = dict(current)
    values.update(changes)
    if values['controller'] not in CONTROLLER_NAMES:
        return False, 'unknown controller %r: one of %s' % (
            values['controller'], ', '.join(CONTROLLER_NAMES))
    if values['can.protocol'] not in PROTOCOL_NAMES:
        return False, 'unknown can.protocol %r: one of %s' % (
            values['can.protocol'], ', '.join(PROTOCOL_NAMES))
    if not values['height_min'] < values['height_max']:
        return False, 'height_min must be below height_max'
    if not values['height_min'] <= values['height'] <= values['height_max']:
        return False, 'height %.3f m outside height_min..height_max (%.3f..%.3f m)' % (
            values['height'], values['height_min'], values['height_max'])
    if values['can.protocol'] == 'mit' and values['max_wheel_torque'] > values['can.mit.t_max']:
        return False, 'max_wheel_torque %.2f N m above the motor limit can.mit.t_max %.2f N m' % (
            values['max_wheel_torque'], values['can.mit.t_max'])
    if len(values['output_regulation.q_diag']) != 4 or \
            not all(q >= 0.0 for q in values['output_regulation.q_diag']):
        return False, 'output_regulation.q_diag needs 4 non-negative weights'
    for name in ('leg_joint_directions', 'leg_joint_offsets'):
        if len(values[name]) != 4:
            return False, '%s needs 4 entries' % name
    if not all(d in (1, -1) for d in values['leg_joint_directions']):
        return False, 'leg_joint_directions entries must be 1 or -1'
    for name in ('pose_covariance_diagonal', 'twist_covariance_diagonal'):
        if len(values[name]) != 6:
            return False, '%s needs 6 entries' % name
    return True, ''
