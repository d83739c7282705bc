"""
The configuration of one robot for balance_node: every parameter once (docs/interface.md).

``BalanceConfig`` is a tree of sections (frozen dataclasses). Each field states its default,
meaning, unit, range and whether it can change while the node runs (core/schema.py); the node
derives its parameter declarations and descriptors from it, ``config/*.yaml`` are checked against
it by the tests, and the tick (core/balance_loop.py) is built from it. Read-only parameters are
those the node cannot change while running (model, joint names, CAN set-up, loop timing); the
others are applied at the next control tick.

Section prefixes give the ROS names: the model, control, joint, safety, loop and publication
sections sit at the top level (``body_mass``, ``fall_angle``), the others under their prefix
(``ida_pbc.k``, ``can.mit.t_max``).
"""
from dataclasses import dataclass
import math
from typing import List

from .auto_mode import AutoRules
from .lqr import DEFAULT_Q, DEFAULT_R, GAIN_SOURCES
from .motor_config import CanConfig, LegsConfig, RO, sign_param
from .output_regulation import HoldShape
from .params import IdaPbcGains, RobotParams
from .pipeline import MODES
from .protocols import check_motors
from .schema import param, section, to_flat

#: Values of ``clock_source``: what paces the control loop (nodes/control_process.py).
CLOCK_SOURCES = ('wall', 'imu_stamp')
#: The test buses (``can.interface``), the only ones ``clock_source: imu_stamp`` may run on: on
#: a robot's bus a silent IMU would stop the clock and every timeout with it.
TEST_INTERFACES = ('virtual', 'udp_multicast', 'socketcan_hub')


@dataclass(frozen=True)
class ControlConfig:
    """The controller and its shared tuning."""

    controller: str = param('auto', 'balance controller: %s (auto: IDA-PBC to rise and at '
                            'large angles, output regulation near upright; auto.*); '
                            'switchable live, bumpless, at the next control tick'
                            % ' | '.join(MODES), choices=MODES)
    height: float = param(0.37, 'body height l [m] used when no leg joints are configured; '
                          'within height_min..height_max', 0.05, 3.0)
    compensate_offset: bool = param(True, 'IDA-PBC uses theta~ - d_hat (removes the velocity '
                                    'bias an IMU offset causes; the paper leaves it in)',
                                    read_only=RO, name='ida_pbc.compensate_offset')
    d_hat0: float = param(0.0, 'initial estimate of the IMU pitch offset d [rad] at arm (the '
                          'paper used 2.7 deg)', -0.5, 0.5)
    yaw_rate_gain: float = param(0.3, 'tau_gamma = yaw_rate_gain (yaw rate - yaw rate*) '
                                 '[N m s/rad], Sec. V-A: the proportional term', 0.0, 10.0)
    yaw_rate_ki: float = param(2.0, "the yaw loop's integral gain [N m/rad] (on yaw rate* - "
                               "yaw rate; 0: the paper's proportional loop alone)", 0.0, 50.0)
    yaw_rate_ff: float = param(0.0, "the yaw loop's feed-forward [N m s/rad] of yaw rate* "
                               "(the tyres' scrub per rad/s, if known)", 0.0, 10.0)
    yaw_rate_source: str = param('imu', "the yaw rate the yaw loop's integral acts on: 'imu' "
                                 "(the gyro's: the body's true turn) or 'wheels' (the "
                                 "odometry's, which overstates a turn whose tyres scrub); the "
                                 "proportional term always damps the wheels' own",
                                 choices=('imu', 'wheels'))
    yaw_integral_limit: float = param(4.0, "the yaw loop's integral kept within this [N m] "
                                      '(held while a torque limit cuts the command)', 0.0,
                                      100.0)
    switch_blend_time: float = param(0.1, 'controller switch: time over which the jump in u '
                                     'fades out [s]', 0.0, 5.0)


@dataclass(frozen=True)
class OutputRegulationConfig(HoldShape):
    """Output regulation (9)-(10): the hold's shape, the LQR weights of the k_x schedule."""

    q_diag: List[float] = param([float(q) for q in DEFAULT_Q.diagonal()],
                                'LQR state weights diag(Q) for [theta, theta_dot, x, x_dot] '
                                '(k_x = lqr(A(l), B(l)))', 0.0, 1e12, read_only=RO, length=4)
    r: float = param(DEFAULT_R, 'LQR input weight R [1/N^2]', 1e-9, 1e6, read_only=RO)
    gain_source: str = param('lqr', 'the k_x of both linear controllers (output_regulation, '
                             'lqr): lqr = lqr(A(l), B(l)) from q_diag and r at each height; '
                             "table_i = Table I's k_x [150, 12, 0.001, 10] at every height, "
                             "read as each wheel's torque (x 2 / r_w; docs/linear_control.md; "
                             'config/paper_table_i.yaml)', read_only=RO,
                             choices=GAIN_SOURCES)


@dataclass(frozen=True)
class JointsConfig:
    """Names and signs of the joints in sensor_msgs/JointState."""

    left_wheel_joint: str = param('left_wheel_joint', 'joint_states name of the left wheel',
                                  read_only=RO)
    right_wheel_joint: str = param('right_wheel_joint', 'joint_states name of the right wheel',
                                   read_only=RO)
    left_wheel_direction: int = sign_param(1, '+1 when a positive joint_states velocity of the '
                                           'left wheel rolls the robot forward, else -1')
    right_wheel_direction: int = sign_param(1, '+1 when a positive joint_states velocity of '
                                            'the right wheel rolls the robot forward, else -1')
    left_leg_front_joint: str = param('', 'joint_states name of the left leg front hip '
                                      '(q_front of core/kinematics.py FiveBarLeg); empty: no leg '
                                      'joints, l is the height parameter', read_only=RO)
    left_leg_rear_joint: str = param('', 'joint_states name of the left leg rear hip (q_rear)',
                                     read_only=RO)
    right_leg_front_joint: str = param('', 'joint_states name of the right leg front hip',
                                       read_only=RO)
    right_leg_rear_joint: str = param('', 'joint_states name of the right leg rear hip',
                                      read_only=RO)
    leg_joint_directions: List[int] = param(
        [1, 1, 1, 1], 'sign from joint_states position to the FiveBarLeg angle, order left '
        'front, left rear, right front, right rear', -1, 1, read_only=RO, step=2, length=4)
    leg_joint_offsets: List[float] = param(
        [0.0, 0.0, 0.0, 0.0], 'FiveBarLeg angle at joint position zero [rad], same order: '
        'q = offset + direction * position', -10.0, 10.0, read_only=RO, length=4)

    @property
    def leg_names(self):
        """Hip joint names: left front, left rear, right front, right rear."""
        return (self.left_leg_front_joint, self.left_leg_rear_joint,
                self.right_leg_front_joint, self.right_leg_rear_joint)

    def problems(self) -> List[str]:
        """Check that a leg has both its hip names or none."""
        n = self.leg_names
        if bool(n[0]) != bool(n[1]) or bool(n[2]) != bool(n[3]):
            return ['a leg needs both its front and rear joint names']
        return []


@dataclass(frozen=True)
class LegGeometry:
    """The five-bar leg's links (core/kinematics.py FiveBarLeg)."""

    thigh: float = param(0.30, 'five-bar thigh length [m]', 0.01, 2.0, read_only=RO)
    shank: float = param(0.42, 'five-bar shank length [m]', 0.01, 2.0, read_only=RO)
    hip_spacing: float = param(0.10, 'distance between the two hip axes [m]', 0.0, 1.0,
                               read_only=RO)
    com_height: float = param(0.05, 'body centre of mass above the hip midpoint [m]', -1.0,
                              1.0, read_only=RO)
    com_x: float = param(0.0, 'body centre of mass ahead of the hip midpoint [m]', -1.0, 1.0,
                         read_only=RO)


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of the safety supervisor (core/safety.py)."""

    max_wheel_torque: float = param(12.0, 'torque limit of each wheel [N m]', 0.0, 100.0)
    max_pitch_rate: float = param(35.0, '|IMU pitch rate| beyond which a sample is '
                                  'implausible: fault [rad/s] (35 rad/s = 2000 deg/s gyro full '
                                  'scale)', 1.0, 1000.0)
    max_wheel_velocity: float = param(45.0, '|wheel velocity| beyond which a sample is '
                                      'implausible or the wheels spin free: fault [rad/s] (45 '
                                      'rad/s = 4.5 m/s on 0.1 m wheels, below the 50 rad/s an MIT '
                                      'reply can report)', 1.0, 10000.0)
    fall_angle: float = param(math.radians(45.0), '|theta~| beyond which the robot has fallen: '
                              'fault [rad] (keep it above the tail rest, about 0.63 rad, to '
                              'start from the tail)', 0.05, 1.5)
    fall_roll_angle: float = param(math.radians(30.0), '|roll| beyond which the robot lies on '
                                   "a side: fault [rad] (the paper's slope rolled it 19 deg "
                                   'with fixed legs)', 0.05, 1.5)
    tail_pitch: float = param(math.radians(36.0), 'pitch of the robot resting on its tail '
                              '[rad]', 0.1, 1.5, read_only=RO)
    arm_pose_tolerance: float = param(math.radians(10.0), 'arming from the tail: |pitch - '
                                      'tail_pitch| and |roll| within this [rad]', 0.01, 0.5)
    arm_upright_pitch: float = param(math.radians(20.0), 'arming upright: |theta~| within '
                                     'this [rad] (also the folded rest on the tail, about 10 '
                                     'deg) ...', 0.01, 0.5)
    arm_still_rate: float = param(0.3, '... and |pitch rate| below this [rad/s]', 0.01, 5.0)
    imu_timeout: float = param(0.05, 'IMU sample age that is a fault [s]', 0.004, 2.0)
    joint_state_timeout: float = param(0.05, 'joint-state sample age that is a fault [s]',
                                       0.004, 2.0)
    motor_timeout: float = param(0.05, 'time a commanded wheel motor may stay without a CAN '
                                 'reply [s]', 0.004, 2.0)
    cmd_vel_timeout: float = param(0.5, 'cmd_vel age after which the references ramp to zero '
                                   '[s] (not a fault)', 0.01, 60.0)
    imu_publisher: str = param('', "the IMU driver's node name (or /namespace/name): the only "
                               "publisher allowed on imu; '' = any one publisher. Another "
                               'publisher: arming refused, FAULT while balancing',
                               read_only=RO)
    joint_state_publisher: str = param('', 'as imu_publisher, for joint_states_in (where wheel '
                                       'or hip states come from another driver)',
                                       read_only=RO)
    cmd_vel_publisher: str = param('', 'the node allowed to publish cmd_vel (teleop_node, a '
                                   "twist_mux ...); '' = any one publisher. Another publisher: "
                                   'cmd_vel refused until it is gone (the robot brakes to a '
                                   'stand)', read_only=RO)
    cmd_height_publisher: str = param('', 'as cmd_vel_publisher, for cmd_height', read_only=RO)
    watchdog_timeout: float = param(0.1, 'the watchdog (a process of its own) kills a control '
                                    'loop that commands the motors but has not run for this '
                                    'long, and sends zero torque and exit-motor-mode to every '
                                    'motor [s]', 0.01, 5.0, read_only=RO)
    lift_wheel_inertia: float = param(0.0075, 'lifted check: one wheel with its rotor, '
                                      'inertia about the axle [kg m^2] (a 1.5 kg, 0.1 m disc)',
                                      1e-5, 1.0, read_only=RO)
    lift_window: float = param(0.02, 'lifted check: window over which wheel speed changes are '
                               "compared with a free wheel's [s]", 0.004, 0.2)
    lift_min_dv: float = param(3.0, 'lifted check: speed change a free wheel would have had '
                               'in the window, below which nothing is judged [rad/s]', 0.5,
                               50.0)
    lift_ratio: float = param(0.8, 'lifted check: measured / free-wheel speed change from '
                              'which a wheel counts as free (MuJoCo: 1.04 in the air; on the '
                              'ground <= 0.45, 0.71 under a 600 N push that topples it)', 0.2,
                              1.0)
    lift_free_time: float = param(0.03, 'lifted check: both wheels free this long is a fault '
                                  '[s] (one wheel: three times as long; a bump lifts them for '
                                  'less)', 0.0, 1.0)
    lift_min_load: float = param(0.25, 'lifted check (driven legs): share of the weight per '
                                 'leg (m g / 2, from the hip torques) below which the legs '
                                 'count as unloaded', 0.0, 1.0)
    lift_unloaded_time: float = param(0.05, 'lifted check: legs unloaded this long is a fault '
                                      '[s] (a drop of 1.2 cm takes 50 ms)', 0.01, 1.0)
    lift_still_window: float = param(0.04, 'lifted check, still body (core/lift.py): window '
                                     'over which the wheels and the pitch rate are compared '
                                     '[s]', 0.01, 0.2)
    lift_still_min_dv: float = param(0.5, "lifted check, still body: a free wheel's speed "
                                     'change in that window from which it is judged [rad/s]',
                                     0.1, 50.0)
    lift_still_ratio: float = param(0.3, 'lifted check, still body: the pitch rate changing by '
                                    "at most this share of what the wheels' acceleration gives "
                                    'on the ground (r_w / l) is a body that holds still [-]',
                                    0.0, 1.0)
    response_window: float = param(0.05, 'response check (core/response.py): window of the fit '
                                   "of the pitch's answer to the wheel torque [s]", 0.01, 0.5)
    response_min_effect: float = param(0.02, 'response check: the torque term of model (1) '
                                       'must vary by this much in a window to judge it (root '
                                       'sum of squares about its mean) [rad/s]', 0.001, 1.0)
    response_gain: float = param(-0.3, 'response check: the pitch answering with less than this '
                                 "times model (1)'s torque term (1 on the ground, -1 with the "
                                 'pitch sign or both wheel directions wrong) counts as the '
                                 'wrong sign [-]', -2.0, 0.5)
    response_time: float = param(0.05, 'response check: the wrong sign this long is a fault '
                                 "[s] (MuJoCo's experiments: at most 32 ms)", 0.01, 1.0)
    stamp_tolerance: float = param(0.1, 'an IMU sample stamped ahead of our clock by more than '
                                   'this is refused, as is one whose stamp runs backwards [s] '
                                   '(clocks of two machines that are not synchronized)', 0.0,
                                   10.0)
    auto_arm: bool = param(False, 'arm by itself once, as soon as the sensors are fresh and no '
                           'fault condition is present (start-up only)', read_only=RO)


@dataclass(frozen=True)
class ImuConfig:
    """How the IMU sits in the body (core/attitude.py)."""

    imu_mounting_rpy: List[float] = param(
        [0.0, 0.0, 0.0], "the IMU frame's rotation relative to base_link [roll, pitch, yaw] "
        "[rad] (REP 103, as a URDF joint origin's rpy); the small unknown pitch offset d is "
        "the observer's", -6.3, 6.3, read_only=RO, length=3)


@dataclass(frozen=True)
class ReferenceConfig:
    """Limits of the reference shaping of cmd_vel (core/safety.py ReferenceShaper)."""

    max_velocity: float = param(1.0, 'limit of x_dot* [m/s]', 0.0, 5.0)
    max_acceleration: float = param(1.0, 'limit of the rate of change of x_dot* [m/s^2]', 0.01,
                                    50.0)
    max_yaw_rate: float = param(3.0, 'limit of yaw rate* [rad/s]', 0.0, 20.0)
    max_yaw_acceleration: float = param(6.0, 'limit of the rate of change of yaw rate* '
                                        '[rad/s^2]', 0.01, 200.0)


#: Values of ``wheel_state_source``.
WHEEL_STATE_SOURCES = ('can', 'joint_states')


@dataclass(frozen=True)
class WheelStateConfig:
    """Where the wheel speeds come from (core/wheel_state.py)."""

    wheel_state_source: str = param(
        'can', "can: the wheel motors' CAN replies (the robot: the encoders sit in the foot "
        "motors); joint_states: another driver's sensor_msgs/JointState on joint_states_in",
        read_only=RO, choices=WHEEL_STATE_SOURCES)
    wheel_speed_time_constant: float = param(
        0.1, 'time constant of the blend of reported speed and position differences [s] '
        '(core/wheel_state.py: removes the 12-bit speed quantization)', 0.005, 2.0,
        read_only=RO)
    position_wraps: bool = param(True, "the motors' position reply wraps at +-p_max (bgkatz "
                                 'and CubeMars firmware); false: it saturates', read_only=RO,
                                 name='can.mit.wrap')


@dataclass(frozen=True)
class LoopConfig:
    """The control loop's period and real-time options (docs/benchmarks.md)."""

    control_period: float = param(0.002, 'control period T_s [s] (the paper: 2 ms)', 0.0005,
                                  0.02, read_only=RO)
    realtime_priority: int = param(0, 'SCHED_FIFO priority of the control thread (0: leave the '
                                   'scheduler alone; needs rtprio rights)', 0, 98, read_only=RO)
    realtime_cpu: int = param(-1, 'CPU the control thread is pinned to (-1: no pinning)', -1,
                              1023, read_only=RO)
    lock_memory: bool = param(False, 'lock the process in RAM (mlockall, MCL_ONFAULT) so no '
                              'page fault stalls the loop; needs CAP_IPC_LOCK or a memlock '
                              'limit', read_only=RO)
    clock_source: str = param('wall', "what paces the control loop: 'wall' (the robot: every "
                              "control_period on CLOCK_MONOTONIC) or 'imu_stamp' (a simulator "
                              'in lockstep, sim_node lockstep: one tick per IMU sample, its '
                              'header stamp the time of every timeout; never on a robot: '
                              'only with can.interface %s)' % ', '.join(TEST_INTERFACES),
                              choices=CLOCK_SOURCES, read_only=RO)
    lockstep_wall_timeout: float = param(1.0, 'imu_stamp: while the motors are commanded, no '
                                         'IMU sample for this much wall time is FAULT '
                                         "imu_stale (above sim_node's lockstep_timeout, 0.5 s); "
                                         "the watchdog's limit there is this plus "
                                         'watchdog_timeout [s]', 0.1, 10.0, read_only=RO)


@dataclass(frozen=True)
class PublishConfig:
    """What balance_node publishes, how often, in which frames."""

    state_publish_rate: float = param(100.0, 'rate of ~/state [Hz] (decimated from the control '
                                      'loop; 0: off)', 0.0, 1000.0, read_only=RO)
    odom_publish_rate: float = param(50.0, 'rate of odom [Hz] (0: off)', 0.0, 1000.0,
                                     read_only=RO)
    diagnostics_rate: float = param(1.0, 'rate of /diagnostics [Hz]; a mode change publishes '
                                    'at once', 0.1, 10.0, read_only=RO)
    odom_frame_id: str = param('odom', 'frame of the odometry pose', read_only=RO)
    footprint_frame_id: str = param('base_footprint', 'frame on the floor under the wheel axle: '
                                    "the child of the odometry (its pose is the footprint's)",
                                    read_only=RO)
    base_frame_id: str = param('base_link', 'the body frame (pitched and raised over '
                               'base_footprint)', read_only=RO)
    enable_odom_tf: bool = param(True, 'publish odom -> base_footprint on /tf (false: another '
                                 'node does, e.g. a localization filter); base_footprint -> '
                                 'base_link is always published', read_only=RO)
    pose_covariance_diagonal: List[float] = param(
        [0.001, 0.001, 1.0e6, 1.0e6, 1.0e6, 0.01], 'odom pose covariance diagonal (x, y, z, '
        'roll, pitch, yaw)', 0.0, 1e12, read_only=RO, length=6)
    twist_covariance_diagonal: List[float] = param(
        [0.001, 0.001, 1.0e6, 1.0e6, 1.0e6, 0.01], 'odom twist covariance diagonal (x, y, z, '
        'roll, pitch, yaw)', 0.0, 1e12, read_only=RO, length=6)


@dataclass(frozen=True)
class BalanceConfig:
    """Everything balance_node is configured with (see the module docstring)."""

    model: RobotParams = section(RobotParams)
    imu: ImuConfig = section(ImuConfig)
    control: ControlConfig = section(ControlConfig)
    ida_pbc: IdaPbcGains = section(IdaPbcGains, 'ida_pbc')
    auto: AutoRules = section(AutoRules, 'auto')
    output_regulation: OutputRegulationConfig = section(OutputRegulationConfig,
                                                        'output_regulation')
    joints: JointsConfig = section(JointsConfig)
    leg: LegGeometry = section(LegGeometry, 'leg')
    safety: SafetyConfig = section(SafetyConfig)
    reference: ReferenceConfig = section(ReferenceConfig, 'reference')
    can: CanConfig = section(CanConfig, 'can')
    wheel_state: WheelStateConfig = section(WheelStateConfig)
    legs: LegsConfig = section(LegsConfig, 'legs')
    loop: LoopConfig = section(LoopConfig)
    publish: PublishConfig = section(PublishConfig)

    def problems(self) -> List[str]:
        """Rules across sections."""
        out = []
        m = self.model
        if m.height_min < m.height_max and not m.height_min <= self.control.height \
                <= m.height_max:
            out.append('height %.3f m outside height_min..height_max (%.3f..%.3f m)'
                       % (self.control.height, m.height_min, m.height_max))
        c = self.can   # each protocol judges its figures and its motors' IDs
        wheel, found = check_motors(c.protocol, c, (c.left_motor_id, c.right_motor_id))
        out += found + (check_motors(self.legs.protocol, self.legs, self.legs.motor_ids)[1]
                        if self.legs.driven else [])
        if wheel is not None and self.safety.max_wheel_torque > wheel.torque_limit:
            out.append("max_wheel_torque %.2f N m above the %s motors' limit %.2f N m (can.%s)"
                       % (self.safety.max_wheel_torque, c.protocol, wheel.torque_limit,
                          wheel.config_section))
        if self.loop.clock_source == 'imu_stamp' and self.can.interface not in TEST_INTERFACES:
            # The hips' bus (legs.can.channel) is opened with can.interface too.
            out.append('clock_source imu_stamp (lockstep with a simulator) needs a test bus, '
                       'can.interface %s, not %r: on a robot a silent IMU would stop the clock '
                       "and every timeout; use clock_source 'wall'"
                       % (' | '.join(TEST_INTERFACES), self.can.interface))
        if self.legs.driven:
            if set(self.legs.motor_ids) & {self.can.left_motor_id, self.can.right_motor_id} \
                    and not self.legs.channel:
                out.append('legs.motor_ids share a CAN ID with a wheel motor on one bus')
            if any(self.joints.leg_names):
                out.append('hip joint names (left_leg_front_joint ...) are for legs that '
                           'another driver reports; with legs.motor_ids the hips are ours')
            if self.loop.clock_source == 'imu_stamp' and self.legs.channel \
                    and self.legs.channel != self.can.channel \
                    and self.legs.command_divider != 1:
                out.append('clock_source imu_stamp with the hips on their own bus needs '
                           'legs.command_divider 1 (sim_node waits for every hip every tick '
                           'there; on one bus the wheels close a tick)')
        return out


#: The defaults, for code that needs one value (e.g. the fall angle of a test plant).
DEFAULTS = BalanceConfig()

#: Safety parameters that can only be tightened while the robot balances: name -> +1 where a
#: larger value is looser, -1 where a smaller one is.
TIGHTEN_ONLY = {
    'imu_timeout': 1, 'joint_state_timeout': 1, 'motor_timeout': 1, 'cmd_vel_timeout': 1,
    'fall_angle': 1, 'fall_roll_angle': 1, 'max_wheel_torque': 1, 'max_wheel_velocity': 1,
    'max_pitch_rate': 1, 'stamp_tolerance': 1, 'reference.max_velocity': 1,
    'reference.max_acceleration': 1, 'reference.max_yaw_rate': 1,
    'reference.max_yaw_acceleration': 1, 'lift_window': 1, 'lift_min_dv': 1, 'lift_ratio': 1,
    'lift_free_time': 1, 'lift_unloaded_time': 1, 'lift_min_load': -1,
    'lift_still_window': 1, 'lift_still_min_dv': 1, 'lift_still_ratio': -1,
    'response_window': 1, 'response_min_effect': 1, 'response_gain': -1, 'response_time': 1,
}


def loosening(cfg: BalanceConfig, changes) -> List[str]:
    """Return why ``changes`` {name: value} loosen a TIGHTEN_ONLY parameter of ``cfg``."""
    old = to_flat(cfg)
    out = []
    for name, value in changes.items():
        sign = TIGHTEN_ONLY.get(name)
        if sign is None or not isinstance(value, (int, float)) or isinstance(value, bool):
            continue
        if not sign * (value - old[name]) <= 0.0:   # looser, or NaN
            out.append('%s can only be tightened while the robot balances (%r -> %r)'
                       % (name, old[name], value))
    return out
