"""
The motors' sections of balance_node's configuration: the wheels' bus and the hips.

``can.*`` and ``legs.*``, each with its protocol's own section (core/protocols/).

Split from core/config.py, which builds ``BalanceConfig`` from these sections and checks the
cross-field rules (one motor set's protocol against the other's, the torque limits).
"""
from dataclasses import dataclass
from typing import List

from .protocols import CybergearConfig, DamiaoConfig, impedance_protocols, LkConfig, PROTOCOLS
from .schema import LiveChoices, param, section

RO = True
#: Values of ``can.protocol`` and ``legs.can.protocol`` (those with impedance commands), read
#: from the protocol table at each check: a protocol registered at run time can be named.
PROTOCOL_NAMES = LiveChoices(lambda: tuple(PROTOCOLS))
HIP_PROTOCOL_NAMES = LiveChoices(impedance_protocols)


def sign_param(default: int, description: str):
    """Declare a read-only motor or joint direction: exactly -1 or +1."""
    # An integer range -1..1 with step 2 admits exactly -1 and +1.
    return param(default, description, -1, 1, read_only=RO, step=2)


@dataclass(frozen=True)
class MitLimits:
    """The MIT-mode motor model's ranges (they must match the firmware's build)."""

    p_max: float = param(12.5, 'MIT position range +-p_max [rad]', 0.1, 1000.0, read_only=RO)
    v_max: float = param(50.0, 'MIT velocity range +-v_max [rad/s]', 0.1, 1000.0, read_only=RO)
    kp_max: float = param(500.0, 'MIT kp range 0..kp_max [N m/rad]', 0.1, 10000.0,
                          read_only=RO)
    kd_max: float = param(5.0, 'MIT kd range 0..kd_max [N m s/rad]', 0.01, 1000.0,
                          read_only=RO)
    t_max: float = param(18.0, 'MIT torque range +-t_max [N m]', 0.1, 1000.0, read_only=RO)
    temp_derate: float = param(70.0, "motor temperature (the 8-byte reply's) from which its "
                               'torque limit falls linearly, to half at temp_max [deg C] (the '
                               "motor model's data sheet)", -40.0, 200.0, read_only=RO)
    temp_max: float = param(85.0, 'motor temperature at which balancing ends: the sit-down, '
                            'arming refused until it cools [deg C]', -40.0, 200.0,
                            read_only=RO)
    position_jump: float = param(0.3, 'a reply position this far off the extrapolation of the '
                                 'previous reply is a reboot: fault [rad] (a rotor turn of a '
                                 '9:1 gear is 0.70 rad)', 0.01, 10.0, read_only=RO)

    def codec_ranges(self) -> dict:
        """Keyword arguments of core/protocols/mit.MitProtocol for these ranges."""
        return {'p_min': -self.p_max, 'p_max': self.p_max, 'v_min': -self.v_max,
                'v_max': self.v_max, 'kp_max': self.kp_max, 'kd_max': self.kd_max,
                't_min': -self.t_max, 't_max': self.t_max}


@dataclass(frozen=True)
class DjiConfig:
    """DJI C620 + M3508 P19 figures (core/protocols/dji.py)."""

    torque_constant: float = param(0.3, 'dji_c620: output torque per ampere [N m/A] (M3508 '
                                   'P19)', 0.001, 100.0, read_only=RO)
    gear_ratio: float = param(3591.0 / 187.0, 'dji_c620: rotor turns per output turn', 0.01,
                              1000.0, read_only=RO)
    current_limit: float = param(20.0, 'dji_c620: current limit [A] (C620: 20 A)', 0.1, 20.0,
                                 read_only=RO)
    temp_derate: float = param(70.0, 'dji_c620: motor temperature from which the torque limit '
                               'falls linearly, to half at temp_max [deg C]', -40.0, 200.0,
                               read_only=RO)
    temp_max: float = param(85.0, 'dji_c620: motor temperature at which balancing ends [deg C]',
                            -40.0, 200.0, read_only=RO)


@dataclass(frozen=True)
class CanConfig:
    """The wheel motors' bus, protocol, IDs and directions."""

    interface: str = param('socketcan', 'python-can interface: socketcan on the robot, virtual '
                           '(one process) or udp_multicast (between processes) for tests, '
                           'socketcan_hub (SocketcanBus through a hub process) for benchmarks',
                           read_only=RO)
    channel: str = param('can0', 'python-can channel (udp_multicast: the group, e.g. '
                         "239.74.163.2; socketcan_hub: the hub's 127.0.0.1:PORT)", read_only=RO)
    udp_port: int = param(43113, 'UDP port of the udp_multicast interface (python-can default '
                          '43113)', 1, 65535, read_only=RO)
    protocol: str = param('mit', 'wheel motor protocol: %s' % ' | '.join(PROTOCOL_NAMES),
                          read_only=RO, choices=PROTOCOL_NAMES)
    left_motor_id: int = param(1, 'CAN ID of the left wheel motor', 0, 2047, read_only=RO)
    right_motor_id: int = param(2, 'CAN ID of the right wheel motor', 0, 2047, read_only=RO)
    left_direction: int = sign_param(1, '+1 when a positive torque of the left motor drives '
                                     'the wheel forward, else -1 (also applied to its '
                                     'feedback)')
    right_direction: int = sign_param(-1, '+1 when a positive torque of the right motor drives '
                                      'the wheel forward, else -1 (mirrored mounting)')
    send_timeout: float = param(0.0005, 'timeout of one bus.send [s]; a send that fails is a '
                                'fault', 0.0, 0.01, read_only=RO)
    raw_frames: bool = param(True, 'on SocketCAN, the loop reads and writes struct can_frame '
                             'on the socket python-can opened (half the CPU of its recv and '
                             "send); false: python-can's recv and send", read_only=RO)
    bitrate: int = param(1000000, "the bus's bit rate [bit/s] as ip link sets it (the load "
                         'in diagnostics is reckoned from it)', 10000, 1000000, read_only=RO)
    tx_queue_len: int = param(1000, "the interface's txqueuelen [frames] (ip link; SocketCAN's "
                              'default 10 is too short): a catch-up after a late tick sends '
                              'at most this many frames back to back', 1, 100000,
                              read_only=RO)
    mit: MitLimits = section(MitLimits, 'mit')
    dji: DjiConfig = section(DjiConfig, 'dji')
    lk: LkConfig = section(LkConfig, 'lk')
    cybergear: CybergearConfig = section(CybergearConfig, 'cybergear')
    damiao: DamiaoConfig = section(DamiaoConfig, 'damiao')

    def problems(self) -> List[str]:
        """Check that the two wheel motors have different IDs."""
        if self.left_motor_id == self.right_motor_id:
            return ['can.left_motor_id and can.right_motor_id must differ']
        return []


#: Values of ``legs.homing``.
HOMING_METHODS = ('set_zero', 'hard_stops')


@dataclass(frozen=True)
class LegsConfig:
    """The four hip motors that set the height (core/legs.py), when ``legs.driven``."""

    driven: bool = param(False, 'balance_node drives the four hip motors (false: the legs are '
                         'not driven, l comes from joint_states_in or the height parameter)',
                         read_only=RO)
    motor_ids: List[int] = param([3, 4, 5, 6], 'CAN IDs of the hip motors: left front, left '
                                 'rear, right front, right rear', 1, 2047, read_only=RO,
                                 length=4)
    directions: List[int] = param([1, 1, 1, 1], 'per hip motor: +1 when a positive motor '
                                  'position increases the joint angle q (FiveBarLeg '
                                  'convention), else -1', -1, 1, read_only=RO, step=2,
                                  length=4)
    offsets: List[float] = param([0.0, 0.0, 0.0, 0.0], 'per hip motor: the joint angle q '
                                 "[rad] at the motor's zero (homing: set_zero), or a first "
                                 'guess (hard_stops)', -10.0, 10.0, read_only=RO, length=4)
    kp: float = param(60.0, 'hip impedance stiffness [N m/rad]', 0.0, 500.0)
    kd: float = param(3.0, 'hip impedance damping [N m s/rad]', 0.0, 5.0)
    damping_kd: float = param(5.0, 'hip damping on disarm and faults: kp 0, this kd '
                              '[N m s/rad] (the body is lowered, not dropped)', 0.01, 5.0)
    damping_gravity: float = param(0.6, "share of the weight's static hip torque kept while "
                                   'damping (0: pure damping)', 0.0, 1.0)
    channel: str = param('', "CAN channel of the hips' bus ('' = the wheels' bus)",
                         read_only=RO, name='legs.can.channel')
    command_divider: int = param(2, 'command each leg every n-th tick while balancing, the '
                                 'legs taking turns (CAN budget: 2 = 250 Hz, two hip frames '
                                 'per tick; 1 = all four at 500 Hz)', 1, 10, read_only=RO)
    max_height_rate: float = param(0.1, 'limit of the rate of the height reference [m/s]',
                                   0.01, 1.0)
    max_height_accel: float = param(0.2, 'limit of the acceleration of the height reference '
                                    '[m/s^2]', 0.01, 5.0)
    roll_kp: float = param(0.5, 'roll levelling: differential leg length per rad of roll '
                           '[m/rad] (0: no levelling)', 0.0, 5.0)
    roll_ki: float = param(2.0, 'roll levelling: integral gain [m/(rad s)]', 0.0, 20.0)
    roll_kd: float = param(0.1, 'roll levelling: roll-rate gain [m s/rad] (damps the roll '
                           'swing after a drop; 0 left a limit cycle of +-25 deg off a 0.15 m '
                           'ramp in MuJoCo)', 0.0, 2.0)
    max_roll_dl: float = param(0.2, 'roll levelling: largest differential leg length [m]',
                               0.0, 0.33)
    homing: str = param('set_zero', 'how the hip angles are known before the first arm: '
                        'set_zero (the motors were zeroed in the documented pose, offsets '
                        'hold its angles) | hard_stops (driven gently to their stops)',
                        read_only=RO, choices=HOMING_METHODS)
    stop_angles: List[float] = param([-0.2, -0.2, -0.2, -0.2], "joint angle of each hip's "
                                     'hard stop [rad] (homing: hard_stops)', -3.2, 3.2,
                                     read_only=RO, length=4)
    homing_speed: float = param(0.3, 'joint speed of the homing ramp [rad/s]', 0.05, 2.0,
                                read_only=RO)
    homing_torque: float = param(3.0, 'torque towards the stop that says a hip is there '
                                 '[N m]', 0.5, 10.0, read_only=RO)
    joint_names: List[str] = param(['left_leg_front_joint', 'left_leg_rear_joint',
                                    'right_leg_front_joint', 'right_leg_rear_joint'],
                                   "joint_states names of the four hips (the URDF's)",
                                   read_only=RO, length=4)
    knee_names: List[str] = param(['left_front_knee', 'left_rear_knee', 'right_front_knee',
                                   'right_rear_knee'], 'joint_states names of the four passive '
                                  "knees (the URDF's), from the five-bar kinematics",
                                  read_only=RO, length=4)
    protocol: str = param('mit', 'hip motor protocol: %s (its figures in legs.<section>)'
                          % ' | '.join(HIP_PROTOCOL_NAMES), read_only=RO,
                          choices=HIP_PROTOCOL_NAMES, name='legs.can.protocol')
    mit: MitLimits = section(MitLimits, 'mit')
    cybergear: CybergearConfig = section(CybergearConfig, 'cybergear')
    damiao: DamiaoConfig = section(DamiaoConfig, 'damiao')

    def problems(self) -> List[str]:
        """Check that the four hips have different IDs."""
        if self.driven and len(set(self.motor_ids)) != 4:
            return ['legs.motor_ids needs four different CAN IDs']
        return []
