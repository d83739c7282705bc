"""
sim_node's configuration: every parameter once, with its default, meaning, unit and range.

``SimConfig`` is a tree of sections (core/schema.py), as balance_node's ``BalanceConfig``: the
node declares its parameters with descriptors from it (nodes/params.load), config/sim.yaml is
checked against it by the tests, and the simulated robot and its motors are built from it. The
prefixes give the ROS names of docs/simulation.md (``can.mit.t_max``, ``legs.motor_ids``,
``slope.angle``, ``fault.miswired_motor_id``). Every parameter is read-only: the scenario is set
at start. The wheels and the hips each name their protocol (``can.protocol``,
``legs.can.protocol``: any registered one) and its figures are balance_node's sections
(core/motor_config.py: ``can.mit``, ``can.lk``, ``can.dji``, ``legs.damiao`` ...), so both
sides build their codec the same way (``motor_protocol``); each motor is that codec's emulator,
with that model's limits. The firmware options under ``can.mit`` are the emulators' that take
them (sim/robot_motors.make_emulator). No MuJoCo here: a configuration is checked without it.
"""
from dataclasses import dataclass
import math
from typing import List

from .layout import HIP_TORQUE_LIMIT, LEG_JOINTS, WHEEL_TORQUE_LIMIT
from ..core.motor_config import (DjiConfig, HIP_PROTOCOL_NAMES, MitLimits, PROTOCOL_NAMES,
                                 sign_param)
from ..core.protocols import (CybergearConfig, DamiaoConfig, LkConfig, MotorProtocol,
                              protocol_for)
from ..core.protocols.emulation import TIMEOUT_ACTIONS
from ..core.protocols.mit import MitProtocol
from ..core.schema import param, section

RO = True
#: Values of ``initial_pose`` (RobotSim.reset).
INITIAL_POSES = ('folded', 'tail', 'pitch', 'stand')


@dataclass(frozen=True)
class SlopeConfig:
    """A ramp under one wheel (paper experiment 8)."""

    enabled: bool = param(False, 'put a ramp under one wheel (paper experiment 8)',
                          read_only=RO)
    start_x: float = param(1.0, 'x where the ramp leaves the floor [m]', -100.0, 100.0,
                           read_only=RO)
    length: float = param(1.2, 'ramp length [m]', 0.1, 10.0, read_only=RO)
    angle: float = param(math.radians(7.0), 'ramp angle [rad]', 0.0, 0.5, read_only=RO)
    side: str = param('left', 'wheel track of the ramp', read_only=RO,
                      choices=('left', 'right'))


@dataclass(frozen=True)
class MitFirmwareConfig:
    """The motors' firmware options (all motors whose emulator takes them; MIT's all)."""

    wrap: bool = param(True, 'MIT and DaMiao: reply fields beyond their range wrap around, as '
                       'the bgkatz and CubeMars firmware send them; false: clamped',
                       read_only=RO)
    command_timeout: float = param(0.0, 'all motors: no command for this long in motor mode '
                                   "fires the timeout [s] (0: each emulator's own default, "
                                   'none for all of them)', 0.0, 10.0, read_only=RO)
    timeout_action: str = param('zero', "what a timeout does: 'zero' (the command is zeroed, "
                                "as bgkatz CAN_TIMEOUT) or 'rest' (rest mode)", read_only=RO,
                                choices=TIMEOUT_ACTIONS)
    reply_temperature: bool = param(False, 'all motors: 8-byte replies with temperature and '
                                    'error code (newer CubeMars firmware)', read_only=RO)


@dataclass(frozen=True)
class SimCanConfig:
    """The wheel motors' bus, IDs and directions (the motors answer like the robot's)."""

    interface: str = param('virtual', 'python-can interface: virtual (one process), '
                           'udp_multicast (between processes) or socketcan', read_only=RO)
    channel: str = param('wheelleg_sim', 'python-can channel (udp_multicast: the group)',
                         read_only=RO)
    udp_port: int = param(43113, 'UDP port of the udp_multicast interface', 1, 65535,
                          read_only=RO)
    protocol: str = param('mit', 'wheel motor protocol: %s (its figures in can.<section>)'
                          % ' | '.join(PROTOCOL_NAMES), read_only=RO, choices=PROTOCOL_NAMES)
    left_motor_id: int = param(1, 'CAN ID of the left wheel motor', 1, 2047, read_only=RO)
    right_motor_id: int = param(2, 'CAN ID of the right wheel motor', 1, 2047, read_only=RO)
    left_direction: int = sign_param(1, '+1 when a positive torque of the left motor drives '
                                     'the wheel forward, else -1')
    right_direction: int = sign_param(-1, '+1 when a positive torque of the right motor '
                                      'drives the wheel forward, else -1')
    master_id: int = param(0, 'MIT motors: the standard ID they reply on', 0, 2047,
                           read_only=RO)
    mit: MitLimits = section(MitLimits, 'mit')
    firmware: MitFirmwareConfig = section(MitFirmwareConfig, 'mit')
    dji: DjiConfig = section(DjiConfig, 'dji')
    lk: LkConfig = section(LkConfig, 'lk')
    cybergear: CybergearConfig = section(CybergearConfig, 'cybergear')
    damiao: DamiaoConfig = section(DamiaoConfig, 'damiao')


@dataclass(frozen=True)
class LegsConfig:
    """The four hip motors on CAN: left front, left rear, right front, right rear."""

    motor_ids: List[int] = param([3, 4, 5, 6], 'CAN IDs of the hip motors: left front, left '
                                 'rear, right front, right rear', 1, 2047, read_only=RO,
                                 length=4)
    directions: List[int] = param([1, 1, 1, 1], 'per hip motor: +1 when a positive motor '
                                  'position is a positive FiveBarLeg joint angle, else -1', -1,
                                  1, read_only=RO, length=4)
    offsets: List[float] = param([0.0, 0.0, 0.0, 0.0], 'per hip motor: the joint angle [rad] '
                                 'at which it reads zero (q = direction p + offset)', -math.tau,
                                 math.tau, read_only=RO, length=4)
    can_channel: str = param('', "channel of a second CAN bus for the hip motors ('' = the "
                             "wheels' bus; same interface and udp_port)", read_only=RO,
                             name='legs.can.channel')
    gear_ratio: float = param(9.0, 'MIT hip motor gear ratio (what one rotor turn is at the '
                              "output: 2 pi / ratio; other protocols: their section's)", 1.0,
                              100.0, read_only=RO)
    power_up: bool = param(True, 'hip motors start as after a power-up: the reading is known '
                           'only modulo one rotor turn (homing needed); false: exact',
                           read_only=RO)
    protocol: str = param('mit', 'hip motor protocol: %s (its figures in legs.<section>)'
                          % ' | '.join(HIP_PROTOCOL_NAMES), read_only=RO,
                          choices=HIP_PROTOCOL_NAMES, name='legs.can.protocol')
    mit: MitLimits = section(MitLimits, 'mit')
    cybergear: CybergearConfig = section(CybergearConfig, 'cybergear')
    damiao: DamiaoConfig = section(DamiaoConfig, 'damiao')


@dataclass(frozen=True)
class FaultConfig:
    """Faults the simulated robot can be built with (bring-up checks)."""

    miswired_motor_id: int = param(0, 'the motor(s) with this CAN ID turn the other way than '
                                   'configured (bring-up check); 0: none', 0, 2047,
                                   read_only=RO)
    wrong_mode_motor_id: int = param(0, 'the motor(s) with this CAN ID start in control mode '
                                     'wrong_mode instead of the one the node commands (a '
                                     'DaMiao or CyberGear hip: bring-up check); 0: none', 0,
                                     2047, read_only=RO)
    wrong_mode: int = param(2, "that motor's mode register value (DaMiao CTRL_MODE, "
                            'CyberGear run_mode; 2: position-velocity, speed)', 0, 255,
                            read_only=RO)


@dataclass(frozen=True)
class HandConfig:
    """The builder's hand of the bring-up checks (sim/hand.py; the ``~/hand`` topic)."""

    kp: float = param(20.0, "the hand's stiffness [N m/rad]", 0.1, 1000.0, read_only=RO)
    kd: float = param(1.0, "the hand's damping [N m s/rad]", 0.0, 100.0, read_only=RO)
    max_torque: float = param(6.0, 'the most the hand pushes a joint with [N m]', 0.1, 50.0,
                              read_only=RO)


@dataclass(frozen=True)
class RobotBodyConfig:
    """
    The simulated robot's physical quantities (``robot.*``): defaults are sim/robot.xml's.

    RobotSim changes the MuJoCo model through mjSpec with the ones that differ from the defaults
    (docs/simulation.md, "A robot that is not the default"); identification fits them
    (docs/identification.md). Per wheel: wheel_mass, wheel_inertia, wheel_damping.
    """

    body_mass: float = param(11.0, 'the body without the legs and wheels [kg]', 1.0, 100.0,
                             read_only=RO)
    body_com: List[float] = param([0.0, 0.05], "the body's centre of mass [x, z] in base_link "
                                  '(x forward, z up from the hip midpoint) [m]', -0.5, 0.5,
                                  read_only=RO, length=2)
    body_inertia: float = param(0.0763, "the body's inertia about the pitch axis through its "
                                'centre of mass [kg m^2]', 0.001, 10.0, read_only=RO)
    wheel_mass: float = param(1.5, 'one wheel [kg]', 0.1, 20.0, read_only=RO)
    wheel_radius: float = param(0.1, 'wheel radius [m] (the contact geometry too)', 0.03, 0.3,
                                read_only=RO)
    wheel_inertia: float = param(0.0075, 'one wheel about its axle [kg m^2] (default: the '
                                 '1.5 kg, 0.1 m disc)', 1e-5, 1.0, read_only=RO)
    wheel_damping: float = param(0.0, "viscous friction of each wheel's bearing [N m s/rad]",
                                 0.0, 5.0, read_only=RO)
    motor_delay: float = param(0.0, "the motors' command latency: a torque takes effect this "
                               'long after it is commanded [s]', 0.0, 0.05, read_only=RO)

    def problems(self) -> List[str]:
        """Rules across fields: a wheel's inertia is at most its mass at the rim, m r^2."""
        rim = self.wheel_mass * self.wheel_radius ** 2
        if self.wheel_inertia > rim:
            return ['robot.wheel_inertia %.4g kg m^2 above wheel_mass wheel_radius^2 = %.4g kg '
                    'm^2 (all the mass at the rim)' % (self.wheel_inertia, rim)]
        return []


@dataclass(frozen=True)
class SimConfig:
    """Everything sim_node is configured with (see the module docstring)."""

    publish_rate: float = param(500.0, 'loop and imu/joint_states rate [Hz]', 10.0, 2000.0,
                                read_only=RO)
    publish_joint_states: bool = param(False, 'publish joint_states of the six motor joints '
                                       '(off: as on the robot, where nothing publishes them; '
                                       'balance_node publishes its own from the replies)',
                                       read_only=RO)
    ground_truth_rate: float = param(100.0, '~/ground_truth rate [Hz] (0: off)', 0.0, 1000.0,
                                     read_only=RO)
    lockstep: bool = param(False, 'step the physics once the motors in motor mode have their '
                           "commands of the tick (balance_node with clock_source 'imu_stamp'), "
                           'never faster than real time; imu stamped with the simulated time. '
                           'The closed loop is then the same on a loaded machine, only slower',
                           read_only=RO)
    lockstep_timeout: float = param(0.5, 'lockstep: the longest wait for the commands of a '
                                    'tick [s, wall clock]; then the physics steps without them '
                                    '(counted)', 0.001, 10.0, read_only=RO)
    imu_frame_id: str = param('imu_link', 'frame_id of imu', read_only=RO)
    imu_pitch_offset: float = param(math.radians(2.2), 'IMU pitch mounting offset d [rad]: the '
                                    'IMU reads theta + d (the paper: ~2.2 deg)', -0.5, 0.5,
                                    read_only=RO)
    initial_pose: str = param('folded', "'folded': as after power-up, hips limp, legs folded "
                              "onto their stops, resting on the tail; 'tail': resting on the "
                              'tail with the legs at height (as if the hips held them); '
                              "'pitch': wheels on the floor, body at initial_pitch, legs at "
                              "height (falls unless balanced at once); 'stand': on the bring-up "
                              'stand, body held at the tail pitch stand_lift above the floor, '
                              'wheels free, hips limp', read_only=RO, choices=INITIAL_POSES)
    stand_lift: float = param(0.05, 'initial_pose stand: how far the stand lifts the body above '
                              'its tail rest [m] (the wheels hang free)', 0.01, 0.5,
                              read_only=RO)
    initial_pitch: float = param(0.0, 'body pitch for initial_pose pitch [rad]', -1.5, 1.5,
                                 read_only=RO)
    height: float = param(0.37, "body height l [m] of the poses 'tail' and 'pitch'", 0.37,
                          0.70, read_only=RO)
    pushes: List[float] = param([], 'flat [start, duration, force_x, force_y, ...]: pushes on '
                                'the body [s, s, N, N] in world axes; empty: none',
                                read_only=RO, item=float)
    bumps: List[float] = param([], 'x positions of bumps across the floor [m]; empty: none',
                               read_only=RO, item=float)
    bump_height: float = param(0.02, 'height of the bumps [m]', 0.001, 0.1, read_only=RO)
    slope: SlopeConfig = section(SlopeConfig, 'slope')
    left_wheel_joint: str = param('left_wheel_joint', 'joint_states name of the left wheel',
                                  read_only=RO)
    right_wheel_joint: str = param('right_wheel_joint', 'joint_states name of the right '
                                   'wheel', read_only=RO)
    leg_joints: List[str] = param(list(LEG_JOINTS), 'joint_states names of the hips: left '
                                  'front, left rear, right front, right rear', read_only=RO,
                                  length=4)
    can: SimCanConfig = section(SimCanConfig, 'can')
    legs: LegsConfig = section(LegsConfig, 'legs')
    fault: FaultConfig = section(FaultConfig, 'fault')
    hand: HandConfig = section(HandConfig, 'hand')
    robot: RobotBodyConfig = section(RobotBodyConfig, 'robot')

    @property
    def second_bus(self) -> bool:
        """Return True when the hip motors are on a bus of their own."""
        return self.legs.can_channel not in ('', self.can.channel)

    @property
    def channels(self) -> List[str]:
        """Return the CAN channels: the wheels', then the hips' if they have their own."""
        return [self.can.channel] + ([self.legs.can_channel] if self.second_bus else [])

    @property
    def motor_ids(self) -> List[int]:
        """Return the CAN IDs of the motors: the wheels', then the hips'."""
        return [self.can.left_motor_id, self.can.right_motor_id] + list(self.legs.motor_ids)

    def problems(self) -> List[str]:
        """Rules across sections."""
        out = []
        if any(d not in (1, -1) for d in self.legs.directions):
            out.append('legs.directions entries must be 1 or -1')
        ids = self.motor_ids
        # Motors on one bus need different IDs; on two buses, per bus.
        groups = [ids[:2], ids[2:]] if self.second_bus else [ids]
        if any(len(set(g)) != len(g) for g in groups):
            out.append('the motors on a bus need different CAN IDs: %s' % ids)
        miswired = self.fault.miswired_motor_id
        if miswired and miswired not in ids:
            out.append('fault.miswired_motor_id %d is none of the motors %s' % (miswired, ids))
        out += self._wrong_mode_problems()
        if len(self.pushes) % 4:
            out.append('pushes needs groups of 4 [start, duration, force_x, force_y]')
        for name, owner, limit in (('can', self.can, WHEEL_TORQUE_LIMIT),
                                   ('legs', self.legs, HIP_TORQUE_LIMIT)):
            try:
                codec = motor_protocol(owner)
            except ValueError as e:
                out.append('%s.%s figures: %s' % (name, owner.protocol, e))
                continue
            if codec.torque_limit > limit:
                # The figure that sets it: the range (t_max) or the current (LK, the C620).
                field = 't_max' if hasattr(codec, 't_max') else 'current_limit'
                out.append("%s.%s.%s: the %s motors' torque limit %.1f N m above the model's "
                           'actuators (%.0f N m)' % (name, codec.config_section, field,
                                                     owner.protocol, codec.torque_limit, limit))
        return out

    def _wrong_mode_problems(self) -> List[str]:
        """fault.wrong_mode_motor_id: one of the motors, whose emulator has that mode."""
        motor_id = self.fault.wrong_mode_motor_id
        if not motor_id:
            return []
        ids = self.motor_ids
        owners = [owner for owner, on in ((self.can, ids[:2]), (self.legs, ids[2:]))
                  if motor_id in on]
        if not owners:
            return ['fault.wrong_mode_motor_id %d is none of the motors %s' % (motor_id, ids)]
        out = []
        for owner in owners:
            try:
                motor_protocol(owner).make_emulator(motor_id).set_control_mode(
                    self.fault.wrong_mode)
            except ValueError as e:   # its codec's figures are judged above
                out.append('fault.wrong_mode_motor_id %d (%s): %s'
                           % (motor_id, owner.protocol, e))
        return out


def mit_protocol(limits: MitLimits, master_id: int = 0) -> MitProtocol:
    """Return the MIT codec of a motor model's ranges, replies on ``master_id``."""
    return MitProtocol(**limits.codec_ranges(), master_id=master_id)


def motor_protocol(owner, master_id: int = 0) -> MotorProtocol:
    """
    Return the codec of a motor set (``can`` or ``legs``) from its protocol's section.

    As balance_node builds it (core/protocols protocol_for); MIT motors reply on master_id
    (``can.master_id``, a firmware option of the simulated ones).
    """
    if owner.protocol == MitProtocol.name:
        return mit_protocol(owner.mit, master_id)
    return protocol_for(owner.protocol, owner)
