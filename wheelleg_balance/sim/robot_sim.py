"""
The simulated wheel-legged robot: MuJoCo model robot.xml behind a small numpy API (no ROS).

Conventions (REP 103, docs/simulation.md): x forward, y left, z up; theta > 0 = body leans
forward (positive rotation about y). Wheel torques, angles and velocities here are *forward
positive* (a positive torque drives the wheel so that the robot rolls forward, i.e. about +y);
motor directions are the node's business. Wheel angles and velocities are measured *relative to
the leg* (the front shank that carries the wheel motor), as the motor encoders measure them;
leg joint angles are in core/kinematics.py FiveBarLeg's convention.

The hips: ``legs='motors'`` drives them by torque (the hip motors' torques are an input of
``step``, in FiveBarLeg's convention: positive increases q, the thigh down), as MIT motor
emulators do for sim_node (sim/robot_motors.py): what the robot has. ``legs='servo'`` (the
default) holds the legs at a set height with built-in position servos through
FiveBarLeg.inverse: for plants whose host drives only the wheels (the fault suite's
validation/faults/plants.py MujocoPlant, the URDF check), and the settling of the 'tail' pose.

Scenario features: rest on the tail or start at a pitch, pushes on the body (xfrc_applied for a
duration), bumps (capsules lying across the floor at given x) and a slope under the left wheel
(a box tilted by the slope angle). A test stand (a mocap weld) holds the body in a given pose.
"""
from dataclasses import dataclass
import math
import pathlib
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from .config import RobotBodyConfig
from .layout import HIP_TORQUE_LIMIT, LEG_JOINTS, LEG_MODES, WHEEL_JOINTS, WHEEL_TORQUE_LIMIT
from .variant import apply_body, CommandDelay
from ..core.kinematics import FiveBarLeg
from ..optional import require

# Only the simulator needs MuJoCo (not a run-time dependency of the robot): say so if absent.
mujoco = require('mujoco', 'the simulated robot (sim_node, main_job, the fault suite)')

MODEL_PATH = pathlib.Path(__file__).with_name('robot.xml')

#: Wheel radius r_w [m] and track d_w [m] of robot.xml (Table I): the default robot's.
WHEEL_RADIUS = 0.1
WHEEL_SEPARATION = 0.47
#: Actuator groups of robot.xml: hip torque motors and the transitional hip servos.
_HIP_MOTOR_GROUP, _HIP_SERVO_GROUP = 2, 1
#: How far the wheels sink into the floor at rest under the robot's weight [m] (soft contact).
CONTACT_DEPTH = 0.0003
#: Labels of ``ground_truth()`` values, in order.
GROUND_TRUTH_FIELDS = ('time', 'theta', 'theta_dot', 'x', 'y', 'x_dot', 'yaw', 'yaw_rate',
                       'roll', 'l', 'tau_left', 'tau_right', 'tail_contact', 'body_contact')


@dataclass(frozen=True)
class Push:
    """A force [N] in world axes on the body's centre of mass from ``start`` for ``duration``."""

    start: float
    duration: float
    force_x: float
    force_y: float = 0.0
    force_z: float = 0.0


@dataclass(frozen=True)
class Slope:
    """
    A ramp under one wheel (the paper's experiment 8: 1.2 m long, 7 deg).

    start_x: where the ramp leaves the floor [m]; length: along the ramp [m]; angle [rad];
    side: 'left' or 'right' wheel track; width [m] across y. The ramp ends in a drop.
    """

    start_x: float = 1.0
    length: float = 1.2
    angle: float = math.radians(7.0)
    side: str = 'left'
    width: float = 0.2


def _quat_pitch(pitch: float, yaw: float = 0.0) -> np.ndarray:
    """Return the MuJoCo quaternion (w, x, y, z) of R_z(yaw) R_y(pitch)."""
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    return np.array([cy * cp, -sy * sp, cy * sp, sy * cp])


def euler_zyx(w: float, x: float, y: float, z: float) -> Tuple[float, float, float]:
    """(roll, pitch, yaw) [rad] of a unit quaternion, z-y'-x'' (yaw-pitch-roll) Euler angles."""
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


class RobotSim:
    """
    The MuJoCo robot with the scenario around it (see the module docstring).

    d_offset: IMU pitch mounting offset d [rad] (the IMU reads theta~ = theta + d);
    height: initial body height l [m] (COM above the wheel axle; with legs='servo' the servos'
    height); pushes: Push events; bumps: x positions [m] of bumps of height bump_height [m];
    slope: a Slope or None; leg: the five-bar geometry that robot.xml is built with
    (FiveBarLeg defaults); legs: 'servo' (default) or 'motors' (LEG_MODES); body: the robot's
    physical quantities (sim_node's ``robot.*``, sim/config.RobotBodyConfig; None: robot.xml's),
    among them the motors' command latency (sim/variant.py).
    """

    def __init__(self, d_offset: float = 0.0, height: float = 0.37,
                 pushes: Iterable[Push] = (), bumps: Iterable[float] = (),
                 bump_height: float = 0.02, slope: Optional[Slope] = None,
                 leg: Optional[FiveBarLeg] = None, legs: str = 'servo',
                 body: Optional[RobotBodyConfig] = None):
        if legs not in LEG_MODES:
            raise ValueError('legs must be one of %s' % ', '.join(LEG_MODES))
        self.legs = legs
        self.leg = leg or FiveBarLeg()
        self.body = body if body is not None else RobotBodyConfig()
        #: Wheel radius r_w [m] of this robot.
        self.wheel_radius = float(self.body.wheel_radius)
        self.model = self._build_model(list(bumps), bump_height, slope, self.body)
        self.data = mujoco.MjData(self.model)
        self.timestep = float(self.model.opt.timestep)
        # The commands of the six motors (wheels, hips) and their latency (None: none).
        self._commanded = [0.0] * 6
        self._delay = CommandDelay(self.body.motor_delay, self.timestep, 6) \
            if self.body.motor_delay > 0.0 else None
        m = self.model
        self._base = m.body('base_link').id
        self._wheels = [m.body(n).id for n in ('left_wheel', 'right_wheel')]
        self._tail_wheel = m.geom('tail_wheel').id
        self._body_geom = m.geom('body').id
        self._imu_site = m.site('imu').id
        self._stand_eq = m.equality('stand').id
        self._stand_mocap = m.body_mocapid[m.body('stand').id]
        self._wheel_q = [m.jnt_qposadr[m.joint(n).id] for n in WHEEL_JOINTS]
        self._wheel_v = [m.jnt_dofadr[m.joint(n).id] for n in WHEEL_JOINTS]
        self._leg_q = [m.jnt_qposadr[m.joint(n).id] for n in LEG_JOINTS]
        self._leg_v = [m.jnt_dofadr[m.joint(n).id] for n in LEG_JOINTS]
        self._knee_q = [m.jnt_qposadr[m.joint(n).id] for n in
                        ('left_front_knee', 'left_rear_knee', 'right_front_knee',
                         'right_rear_knee')]
        self._motor_q = [int(i) for i in self._wheel_q + self._leg_q]
        self._motor_v = [int(i) for i in self._wheel_v + self._leg_v]
        self._wheel_act = [m.actuator(n).id for n in ('left_wheel', 'right_wheel')]
        hips = ('left_leg_front', 'left_leg_rear', 'right_leg_front', 'right_leg_rear')
        self._leg_act = [m.actuator(n).id for n in hips]
        self._servo_act = [m.actuator(n + '_servo').id for n in hips]
        self._sensor = {n: (m.sensor_adr[m.sensor(n).id], m.sensor_dim[m.sensor(n).id])
                        for n in ('imu_quat', 'imu_gyro', 'imu_accel')}
        self._vel6 = np.zeros(6)
        self.pushes: List[Push] = list(pushes)
        self.set_imu_offset(d_offset)
        self._use_servos(legs == 'servo')
        self._height_target = float('nan')
        self.set_height(height)
        self.reset('tail')

    # ---- model ------------------------------------------------------------------------------

    @staticmethod
    def _build_model(bumps: List[float], bump_height: float, slope: Optional[Slope],
                     body: RobotBodyConfig) -> mujoco.MjModel:
        spec = mujoco.MjSpec.from_file(str(MODEL_PATH))
        apply_body(spec, body)
        for i, x in enumerate(bumps):
            # A capsule across the floor, half buried: it sticks out bump_height.
            g = spec.worldbody.add_geom()
            g.name = 'bump_%d' % i
            g.type = mujoco.mjtGeom.mjGEOM_CAPSULE
            g.fromto = [x, -1.0, 0.0, x, 1.0, 0.0]
            g.size = [bump_height, 0.0, 0.0]
            g.contype, g.conaffinity, g.condim = 1, 1, 3
        if slope is not None:
            if slope.side not in ('left', 'right'):
                raise ValueError("slope side must be 'left' or 'right'")
            thickness = 0.1
            a = slope.angle
            # Rotation R_y(-a) makes +x rise; the top face starts on the floor at start_x.
            rx, rz = math.cos(a), math.sin(a)
            half = 0.5 * slope.length
            cx = slope.start_x + half * rx + 0.5 * thickness * rz
            cz = half * rz - 0.5 * thickness * rx
            y = 0.5 * WHEEL_SEPARATION * (1.0 if slope.side == 'left' else -1.0)
            g = spec.worldbody.add_geom()
            g.name = 'slope'
            g.type = mujoco.mjtGeom.mjGEOM_BOX
            g.size = [half, 0.5 * slope.width, 0.5 * thickness]
            g.pos = [cx, y, cz]
            g.quat = _quat_pitch(-a)
            g.contype, g.conaffinity, g.condim = 1, 1, 3
        return spec.compile()

    def _use_servos(self, on: bool) -> None:
        """Drive the hips by the transitional servos (on) or by the hip torque motors (off)."""
        off = _HIP_MOTOR_GROUP if on else _HIP_SERVO_GROUP
        self.model.opt.disableactuator = 1 << off

    def set_imu_offset(self, d_offset: float) -> None:
        """Mount the IMU pitched by d [rad] about the body y axis: it reads theta + d."""
        self.d_offset = float(d_offset)
        self.model.site_quat[self._imu_site] = _quat_pitch(self.d_offset)
        # The compiler marked the site as sharing the body's frame; make it read site_quat.
        self.model.site_sameframe[self._imu_site] = 0
        if hasattr(self, 'data'):
            mujoco.mj_forward(self.model, self.data)

    # ---- pose -------------------------------------------------------------------------------

    def _leg_pose(self, l: float) -> Tuple[float, float, float, float]:
        """(q_front, q_rear, front knee, rear knee) [rad] of a leg closed at height l [m]."""
        q_f, q_r = self.leg.inverse(l)
        if q_f != q_f:
            raise ValueError("height %.3f m is out of the legs' reach" % l)
        return (q_f, q_r) + self.leg.knee_angles(q_f, q_r)

    def place(self, pitch: float, x: float = 0.0, yaw: float = 0.0) -> None:
        """
        Put the robot at rest with its wheels on the floor at x [m], pitched by pitch [rad].

        The legs are set closed at the set height (``set_height``); velocities are zero.
        """
        m, d = self.model, self.data
        d.qpos[:] = m.qpos0
        d.qvel[:] = 0.0
        d.qacc_warmstart[:] = 0.0
        d.xfrc_applied[:] = 0.0
        d.qfrc_applied[:] = 0.0
        l0 = self._height_target
        q_f, q_r, k_f, k_r = self._leg_pose(l0)
        for side in (0, 2):
            d.qpos[self._leg_q[side]] = q_f
            d.qpos[self._leg_q[side + 1]] = q_r
            d.qpos[self._knee_q[side]] = k_f
            d.qpos[self._knee_q[side + 1]] = k_r
        d.qpos[3:7] = _quat_pitch(pitch, yaw)
        d.qpos[0:3] = 0.0
        mujoco.mj_kinematics(m, d)
        axle = 0.5 * (d.xpos[self._wheels[0]] + d.xpos[self._wheels[1]])
        # Sink the wheels by their resting depth in the soft contact: no drop at the start.
        d.qpos[0:3] = np.array([x, 0.0, self.wheel_radius - CONTACT_DEPTH]) - axle
        d.ctrl[:] = 0.0
        self._apply_height(l0)
        mujoco.mj_forward(m, d)

    def tail_rest_pitch(self) -> float:
        """
        Pitch [rad] at which the tail wheel touches the floor with both wheels down.

        Geometric, at the set height; the simulation state is left as it was.
        """
        d = self.data
        saved = (d.qpos.copy(), d.qvel.copy(), d.ctrl.copy(), d.xfrc_applied.copy(), d.time)
        lo, hi = 0.0, 1.5
        for _ in range(40):  # bisection on the tail wheel's lowest point
            mid = 0.5 * (lo + hi)
            self.place(mid)
            if self.tail_clearance() > 0.0:
                lo = mid
            else:
                hi = mid
        d.qpos[:], d.qvel[:], d.ctrl[:], d.xfrc_applied[:], d.time = saved
        mujoco.mj_forward(self.model, d)
        return 0.5 * (lo + hi)

    def tail_clearance(self) -> float:
        """Height [m] of the tail wheel's rim above the floor (<= 0: touching it)."""
        d = self.data
        centre_z = d.geom_xpos[self._tail_wheel][2]
        radius = self.model.geom_size[self._tail_wheel][0]
        # The tail wheel's axis stays horizontal (pitch only): its rim reaches radius lower.
        return centre_z - radius

    def reset(self, pose: str = 'tail', pitch: float = 0.0, x: float = 0.0,
              settle: float = 0.3, lift: float = 0.05) -> None:
        """
        Restart at time 0 in a pose.

        'tail' rests on the tail (then ``settle`` s with zero torque); 'pitch' puts the wheels
        on the floor with the body at ``pitch`` [rad] (not settled); 'folded' (legs='motors'):
        the robot as after power-up, hips limp, legs folded down to their lower stops and the
        body resting on its tail (``settle`` s with every motor off); 'stand' (legs='motors'):
        the bring-up stand, the body held at the tail rest's pitch ``lift`` [m] above it, wheels
        free, the legs folded at their lower stops while it settles (powered up folded) and
        hanging limp from time 0. x: axle position [m].
        With legs='motors' the settling holds the legs at the initial height with the servos
        (as if the hip motors had held them): time 0 starts settled, hip torques zero.
        """
        self.release()
        self._commanded = [0.0] * 6
        if self._delay is not None:
            self._delay.clear()
        if pose == 'tail':
            self.place(self.tail_rest_pitch() + 1e-3, x)
            self.data.time = 0.0
            n = int(round(settle / self.timestep))
            self._use_servos(True)
            for _ in range(n):
                mujoco.mj_step(self.model, self.data)
            self._use_servos(self.legs == 'servo')
        elif pose == 'pitch':
            self.place(pitch, x)
        elif pose == 'folded':
            if self.legs != 'motors':
                raise ValueError("pose 'folded' needs legs='motors' (the servos hold the legs)")
            target = self._height_target
            q = self.leg.q_min + 1e-3
            self._height_target = self.leg.height(q, q)
            self.place(self.tail_rest_pitch() + 1e-3, x)
            self._height_target = target
            self.data.time = 0.0
            for _ in range(int(round(max(settle, 0.5) / self.timestep))):
                self.step(0.0, 0.0, self.timestep, (0.0, 0.0, 0.0, 0.0))
        elif pose == 'stand':
            if self.legs != 'motors':
                raise ValueError("pose 'stand' needs legs='motors' (the hips hang limp)")
            # Held at the pitch of the tail rest at the initial height (what balance_node arms
            # from, tail_pitch), the legs folded under it.
            rest = self.tail_rest_pitch() + 1e-3
            target = self._height_target
            q = self.leg.q_min + 1e-3
            self._height_target = self.leg.height(q, q)
            self.place(rest, x)            # the servos' targets: the legs folded
            self._height_target = target
            self.hold(rest, float(self.data.qpos[2]) + lift, x)
            self.data.time = 0.0
            self._use_servos(True)
            for _ in range(int(round(settle / self.timestep))):
                mujoco.mj_step(self.model, self.data)
            self._use_servos(False)
        else:
            raise ValueError("pose must be 'tail', 'pitch', 'folded' or 'stand'")
        self.data.time = 0.0

    # ---- test stand -------------------------------------------------------------------------

    def hold(self, pitch: float = 0.0, z: Optional[float] = None, x: float = 0.0) -> None:
        """
        Weld the body to a stand: pitched by pitch [rad], base_link origin at (x, 0, z).

        z defaults to the height at which the wheels just touch the floor.
        """
        d = self.data
        if z is None:
            self.place(pitch, x)
            z = float(d.qpos[2])
        d.mocap_pos[self._stand_mocap] = (x, 0.0, z)
        d.mocap_quat[self._stand_mocap] = _quat_pitch(pitch)
        d.qpos[0:3] = (x, 0.0, z)
        d.qpos[3:7] = _quat_pitch(pitch)
        d.eq_active[self._stand_eq] = 1
        mujoco.mj_forward(self.model, d)

    def release(self) -> None:
        """Take the body off the stand."""
        self.data.eq_active[self._stand_eq] = 0

    # ---- stepping ---------------------------------------------------------------------------

    @property
    def time(self) -> float:
        """Return the simulated time [s] since the last reset."""
        return float(self.data.time)

    def set_height(self, l: float) -> None:
        """Set the body height l [m]: the servos' target, or with legs='motors' the initial one."""
        self._leg_pose(l)  # raises when out of reach
        self._height_target = float(l)
        self._apply_height(l)

    def _apply_height(self, l: float) -> None:
        q_f, q_r = self.leg.inverse(l)
        if q_f != q_f:
            return  # out of reach: keep the last target
        ctrl = self.data.ctrl
        a = self._servo_act
        ctrl[a[0]] = ctrl[a[2]] = q_f
        ctrl[a[1]] = ctrl[a[3]] = q_r

    def push_force(self, t: float) -> Tuple[float, float, float]:
        """Sum of the pushes acting at simulated time t [s] (world axes) [N]."""
        fx = fy = fz = 0.0
        for p in self.pushes:
            if p.start <= t < p.start + p.duration:
                fx += p.force_x
                fy += p.force_y
                fz += p.force_z
        return fx, fy, fz

    def step(self, tau_left: float, tau_right: float, dt: Optional[float] = None,
             hip_torques: Optional[Sequence[float]] = None) -> None:
        """
        Advance dt [s] (rounded to whole physics steps, at least one) with the motor torques.

        tau_left, tau_right: forward-positive wheel torques [N m], clamped to +-18 N m (a
        non-finite value gives zero). hip_torques (legs='motors'): the four hip torques [N m]
        in LEG_JOINTS order and FiveBarLeg's convention, clamped to +-HIP_TORQUE_LIMIT; None
        keeps the last ones; ignored with legs='servo'. The torques are held over dt: for a
        motor's impedance law evaluated at every physics step, step one timestep at a time
        (sim/robot_motors.py does). Pushes are applied every step. With a motor delay the
        torques act that much later (sim/variant.CommandDelay).
        """
        m, d = self.model, self.data
        n = 1 if dt is None else max(1, int(round(dt / self.timestep)))
        cmd = self._commanded
        cmd[0] = _clamp_torque(tau_left)
        cmd[1] = _clamp_torque(tau_right)
        motors = self._wheel_act
        if self.legs == 'motors':
            motors = self._wheel_act + self._leg_act
            if hip_torques is not None:
                cmd[2:] = [_clamp_torque(tau, HIP_TORQUE_LIMIT) for tau in hip_torques]
        if self._delay is None:
            d.ctrl[motors[0]], d.ctrl[motors[1]] = cmd[0], cmd[1]
            if hip_torques is not None and self.legs == 'motors':
                for a, tau in zip(self._leg_act, cmd[2:]):
                    d.ctrl[a] = tau
        base_force = d.xfrc_applied[self._base]
        for _ in range(n):
            if self._delay is not None:
                for a, tau in zip(motors, self._delay.push(cmd)):
                    d.ctrl[a] = tau
            if self.pushes:
                base_force[0:3] = self.push_force(d.time)
            mujoco.mj_step(m, d)

    def apply_joint_torques(self, torques: Sequence[float]) -> None:
        """
        Apply external torques [N m] to the six motor joints (WHEEL_JOINTS, then LEG_JOINTS).

        A hand's, not a motor's (sim/hand.py): held until changed, not shown as motor torques.
        """
        f = self.data.qfrc_applied
        for i, tau in zip(self._motor_v, torques):
            f[i] = tau if -math.inf < tau < math.inf else 0.0

    # ---- readings ---------------------------------------------------------------------------

    def _sensor_value(self, name: str) -> np.ndarray:
        adr, dim = self._sensor[name]
        return self.data.sensordata[adr:adr + dim]

    def imu(self) -> Tuple[Tuple[float, float, float, float], Tuple[float, float, float],
                           Tuple[float, float, float]]:
        """
        Read the IMU: (orientation, angular velocity, linear acceleration).

        Orientation (x, y, z, w) of the IMU frame in the world; angular velocity [rad/s] and
        specific force (acceleration minus gravity, +9.81 up at rest) [m/s^2] in the IMU frame,
        which is the body frame pitched by d_offset.
        """
        w, x, y, z = (float(v) for v in self._sensor_value('imu_quat'))
        gyro = tuple(float(v) for v in self._sensor_value('imu_gyro'))
        accel = tuple(float(v) for v in self._sensor_value('imu_accel'))
        return (x, y, z, w), gyro, accel

    def wheel_angles(self) -> Tuple[float, float]:
        """(left, right) wheel angles relative to the leg [rad], forward positive."""
        q = self.data.qpos
        return float(q[self._wheel_q[0]]), float(q[self._wheel_q[1]])

    def wheel_velocities(self) -> Tuple[float, float]:
        """(left, right) wheel angular velocities relative to the leg [rad/s], forward positive."""
        v = self.data.qvel
        return float(v[self._wheel_v[0]]), float(v[self._wheel_v[1]])

    def wheel_torques(self) -> Tuple[float, float]:
        """(left, right) wheel torques being applied [N m], forward positive."""
        c = self.data.ctrl
        return float(c[self._wheel_act[0]]), float(c[self._wheel_act[1]])

    def motor_joints(self) -> Tuple[List[float], List[float], float]:
        """
        Return (angles, velocities, time) of the six motor joints at once, for the emulators.

        WHEEL_JOINTS then LEG_JOINTS, in the conventions of wheel_angles and leg_angles [rad,
        rad/s]; time [s].
        """
        d = self.data
        q, v = d.qpos.tolist(), d.qvel.tolist()   # faster than fancy indexing, per step
        return [q[i] for i in self._motor_q], [v[i] for i in self._motor_v], d.time

    def leg_angles(self) -> Tuple[float, float, float, float]:
        """Hip angles [rad] (FiveBarLeg convention) in LEG_JOINTS order."""
        q = self.data.qpos
        return tuple(float(q[i]) for i in self._leg_q)

    def leg_velocities(self) -> Tuple[float, float, float, float]:
        """Hip angular velocities [rad/s] in LEG_JOINTS order."""
        v = self.data.qvel
        return tuple(float(v[i]) for i in self._leg_v)

    def leg_torques(self) -> Tuple[float, float, float, float]:
        """Hip torques being applied [N m] in LEG_JOINTS order (the motors', or the servos')."""
        if self.legs == 'motors':
            c = self.data.ctrl
            return tuple(float(c[i]) for i in self._leg_act)
        f = self.data.actuator_force
        return tuple(float(f[i]) for i in self._servo_act)

    def pendulum(self) -> Dict[str, float]:
        """
        Mass properties of the present pose, for comparing with the paper's model (1).

        Everything but the wheels is the pendulum: mass [kg]; l, its centre of mass's distance
        from the axle midpoint [m]; offset, the angle of that line from the body z axis [rad]
        (theta of the pendulum = body pitch + offset); inertia about its centre of mass, about
        y [kg m^2]. Wheels: wheel_mass [kg] and wheel_inertia about the axle [kg m^2], both
        wheels together.
        """
        m, d = self.model, self.data
        wheels = set(self._wheels)
        bodies = [b for b in range(1, m.nbody) if b not in wheels and m.body_mocapid[b] < 0]
        mass = float(sum(m.body_mass[b] for b in bodies))
        com = sum(m.body_mass[b] * d.xipos[b] for b in bodies) / mass
        inertia = 0.0
        for b in bodies:
            rot = d.ximat[b].reshape(3, 3)
            i_world = rot @ np.diag(m.body_inertia[b]) @ rot.T
            r = d.xipos[b] - com
            inertia += i_world[1, 1] + m.body_mass[b] * (r[0] ** 2 + r[2] ** 2)
        axle = 0.5 * (d.xpos[self._wheels[0]] + d.xpos[self._wheels[1]])
        v = com - axle
        roll, pitch, yaw = euler_zyx(*d.xquat[self._base])
        wheel_inertia = 0.0
        for b in self._wheels:   # about the axle (the wheel joint's axis)
            rot = d.ximat[b].reshape(3, 3)
            wheel_inertia += float((rot @ np.diag(m.body_inertia[b]) @ rot.T)[1, 1])
        return {'mass': mass, 'l': float(math.hypot(v[0], v[2])),
                'offset': math.atan2(v[0], v[2]) - pitch, 'inertia': float(inertia),
                'wheel_mass': float(sum(m.body_mass[b] for b in self._wheels)),
                'wheel_inertia': wheel_inertia}

    def ground_truth(self) -> Dict[str, float]:
        """
        Return the true state for reports (GROUND_TRUTH_FIELDS).

        theta: body pitch [rad] (what an IMU without offset reads) and theta_dot its rate;
        x, y: world position of the wheel-axle midpoint [m]; x_dot: its speed along the heading
        [m/s]; yaw, yaw_rate [rad, rad/s] (positive turns left); roll [rad]; l: the body COM's
        height above the axle midpoint, along the body z axis [m]; applied wheel torques;
        tail_contact, body_contact: 1.0 while the tail wheel, the body box touches the floor or
        the terrain, else 0.0 (only they and the wheels can touch the world).
        """
        m, d = self.model, self.data
        roll, pitch, yaw = euler_zyx(*d.xquat[self._base])
        v = self._vel6
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, self._base, v, 1)
        wy, wz = v[1], v[2]  # body-frame angular velocity
        theta_dot = wy * math.cos(roll) - wz * math.sin(roll)
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, self._base, v, 0)
        yaw_rate = float(v[2])
        lin = np.zeros(3)
        for b in self._wheels:
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, v, 0)
            lin += 0.5 * v[3:6]
        axle = 0.5 * (d.xpos[self._wheels[0]] + d.xpos[self._wheels[1]])
        rot = d.xmat[self._base].reshape(3, 3)
        l = float((rot.T @ (d.xipos[self._base] - axle))[2])
        tau_l, tau_r = self.wheel_torques()
        tail = body = 0.0
        for c in d.contact[:d.ncon]:
            if self._tail_wheel in (c.geom1, c.geom2):
                tail = 1.0
            elif self._body_geom in (c.geom1, c.geom2):
                body = 1.0
        return {
            'time': float(d.time), 'theta': pitch, 'theta_dot': float(theta_dot),
            'x': float(axle[0]), 'y': float(axle[1]),
            'x_dot': float(lin[0] * math.cos(yaw) + lin[1] * math.sin(yaw)),
            'yaw': yaw, 'yaw_rate': yaw_rate, 'roll': roll, 'l': l,
            'tau_left': tau_l, 'tau_right': tau_r, 'tail_contact': tail, 'body_contact': body,
        }


def _clamp_torque(tau: float, limit: float = WHEEL_TORQUE_LIMIT) -> float:
    if not -math.inf < tau < math.inf:
        return 0.0
    return min(max(float(tau), -limit), limit)
