"""
What goes into a control tick and what comes out of it, defined once (no rclpy, no CAN here).

``TickInputs`` is what arrived since the last tick, ``TickResult`` what the tick produced
(core/balance_loop.py). The **state frame** is what the control process sends the ROS side
after a tick (nodes/control_link.py carries it, nodes/balance_node.py publishes it): the
``LoopState`` values in ``STATE_FIELDS`` order (what ~/state publishes, the tick's time [s]
last), then the odometry in ``ODOM_FIELDS`` order, then the publication flags. ``state_frame``
builds one and the index constants below read one, so the layout is written down here only.
"""
from dataclasses import dataclass, field, fields
import math
from typing import Any, Dict, List, NamedTuple, Optional, Tuple

from .protocols.base import Frame
from .sensors import ImuSample, JointSample


class CmdVel(NamedTuple):
    """The newest cmd_vel: receipt time [s], x_dot* [m/s], yaw rate* [rad/s, + turns left]."""

    t: float
    x_dot: float
    yaw_rate: float


class CmdHeight(NamedTuple):
    """The newest cmd_height: receipt time [s], the height l* [m]."""

    t: float
    height: float


@dataclass
class TickInputs:
    """
    What arrived since the last tick (the caller fills it and clears it after the tick).

    imu, joints: samples in arrival order; frames: (monotonic receipt time [s], Frame) of the
    CAN bus (both buses when the legs have their own: each motor set takes its own IDs);
    cmd_vel, cmd_height: the newest command or None; arm: True / False for an operator's arm /
    disarm request, None for none; estop: an emergency stop (zero torque and exit motor mode at
    once, no sit-down); params: parameter changes {name: value}, already validated.
    guarded: a state, not an event (``clear`` leaves it): False while what guards the process
    (balance_node's watchdog, nodes/watchdog.py) is not watching: arming is refused and
    auto_arm waits. conflicts: a state too, {input: why}: inputs with a publisher that is not
    the robot's own (balance_node's graph check, nodes/input_guard.py). A conflict on a sensor
    ('imu', 'joint_states') refuses arming and is a FAULT while commanding; one on a command
    ('cmd_vel', 'cmd_height') drops that command (counted as rejected): it then times out.
    imu_silent: why the caller's own clock found the IMU silent where the tick's time cannot
    (on IMU stamps, lockstep: no sample for ``lockstep_wall_timeout`` of wall time, so no
    tick's time moved): FAULT imu_stale with it while commanding; '' none (an event).
    excite: an identification phase to play (core/excitation.py: 'stand', 'tail', 'balance'),
    answered like an arm request; '' none.
    """

    imu: List[ImuSample] = field(default_factory=list)
    joints: List[JointSample] = field(default_factory=list)
    frames: List[Tuple[float, Frame]] = field(default_factory=list)
    cmd_vel: Optional[CmdVel] = None
    cmd_height: Optional[CmdHeight] = None
    arm: Optional[bool] = None
    estop: bool = False
    params: Dict[str, Any] = field(default_factory=dict)
    guarded: bool = True
    conflicts: Dict[str, str] = field(default_factory=dict)
    imu_silent: str = ''
    excite: str = ''

    def clear(self) -> None:
        """Empty every input (the lists are reused)."""
        self.imu.clear()
        self.joints.clear()
        self.frames.clear()
        self.cmd_vel = None
        self.cmd_height = None
        self.arm = None
        self.estop = False
        self.params = {}
        self.imu_silent = ''
        self.excite = ''


@dataclass
class LoopState:
    """
    What ~/state publishes (docs/interface.md), one value per field, in this order.

    theta: IMU pitch theta~ [rad]; theta_dot [rad/s]; x: travel since arming [m]; x_dot [m/s];
    yaw_rate [rad/s]; d_hat: IMU offset estimate [rad]; l: height used [m]; u: force applied
    [N]; tau_left, tau_right: wheel torques commanded [N m]; controller: index into
    CONTROLLER_NAMES of the active controller; mode: core/safety.Mode the commands were made in;
    x_dot_ref, yaw_rate_ref: the shaped references [m/s, rad/s]; roll [rad]; l_ref: the shaped
    height reference [m]; l_target: the commanded height [m]; excitation: the identification
    phase running (core/excitation.py PHASE_INDEX: 1 stand, 2 tail, 3 balance; 0 none); time:
    the tick's time [s], on the loop's clock in the tick and the state frame, and on ~/state
    the ROS time of the tick (its joint_states' stamp; nodes/state_publisher.py): the fit of an
    identification phase reads it, not the receipt times, which stretch when a simulator lags.
    """

    theta: float = math.nan
    theta_dot: float = math.nan
    x: float = 0.0
    x_dot: float = 0.0
    yaw_rate: float = 0.0
    d_hat: float = 0.0
    l: float = math.nan
    u: float = 0.0
    tau_left: float = 0.0
    tau_right: float = 0.0
    controller: float = 0.0
    mode: float = 0.0
    x_dot_ref: float = 0.0
    yaw_rate_ref: float = 0.0
    roll: float = math.nan
    l_ref: float = math.nan
    l_target: float = math.nan
    excitation: float = 0.0
    time: float = math.nan

    def values(self) -> List[float]:
        """Return the fields' values in STATE_FIELDS order."""
        return [float(getattr(self, name)) for name in STATE_FIELDS]


#: The names of ~/state's values, in order.
STATE_FIELDS = tuple(f.name for f in fields(LoopState))


@dataclass
class Odom:
    """The planar odometry: pose (x, y [m], yaw [rad]) and twist (x_dot [m/s], yaw rate)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    x_dot: float = 0.0
    yaw_rate: float = 0.0


@dataclass
class TickResult:
    """
    What one tick produced (the loop reuses one instance).

    frames: to send on the wheels' bus now, in order; leg_frames: the hips' (on the legs' bus,
    or after ``frames`` on the one bus); state, odom: to publish; joints: (position, velocity,
    effort) per name of ``BalanceLoop.joint_names`` (NaN where unknown); arm_reply: (success,
    message) of an arm/disarm request, known once ``report_send`` has seen the frames go out;
    events: (level, text) lines to log ('info', 'warn', 'error').
    """

    frames: List[Frame] = field(default_factory=list)
    leg_frames: List[Frame] = field(default_factory=list)
    state: LoopState = field(default_factory=LoopState)
    odom: Odom = field(default_factory=Odom)
    joints: Tuple[List[float], List[float], List[float]] = ([], [], [])
    arm_reply: Optional[Tuple[bool, str]] = None
    events: List[Tuple[str, str]] = field(default_factory=list)


#: The odometry's values in the state frame, after the state's.
ODOM_FIELDS = ('x', 'y', 'yaw', 'x_dot', 'yaw_rate')
#: Every value of the state frame by name, in order.
FRAME_FIELDS = STATE_FIELDS + tuple('odom_' + name for name in ODOM_FIELDS) + ('flags',)
#: Where the parts of a state frame stand: the state (with the tick's time), the odometry,
#: the flags.
N_STATE = len(STATE_FIELDS)
ODOM = slice(N_STATE, N_STATE + len(ODOM_FIELDS))
TIME = STATE_FIELDS.index('time')
FLAGS = N_STATE + len(ODOM_FIELDS)
#: The index of the mode in a state frame (and in ~/state).
MODE = STATE_FIELDS.index('mode')
#: Flags of a state frame: which topics the ROS side publishes from it.
PUBLISH_STATE = 1
PUBLISH_ODOM = 2


def state_frame(state: LoopState, odom: Odom, flags: int) -> List[float]:
    """Return the state frame of a tick: the state (with its time), the odometry, the flags."""
    return state.values() + [odom.x, odom.y, odom.yaw, odom.x_dot, odom.yaw_rate, float(flags)]
