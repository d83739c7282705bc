"""
The simulated wheel-legged robot: MuJoCo model robot.xml behind a small numpy API (no ROS).

Conventions (REP 103, docs/simulation.md): x forward, y left, z up; theta > 0 = body leans
forward (positive rotation about y). Wheel torques, angles and velocities here are *forward
positive* (a positive torque drives the wheel so that the robot rolls forward, i.e. about +y);
motor directions are the node's business. Wheel angles and velocities are measured *relative to
the leg* (the front shank that carries the wheel motor), as the motor encoders measure them;
leg joint angles are in core/kinematics.py FiveBarLeg's convention.

Scenario features: rest on the tail or start at a pitch, a piecewise-linear height schedule
(the four hip servos follow FiveBarLeg.inverse), pushes on the body (xfrc_applied for a
duration), bumps (capsules lying across the floor at given x) and a slope under the left wheel
(a box tilted by the slope angle). A test stand (a mocap weld) holds the body in a given pose.
"""
from dataclasses import dataclass
import math
import pathlib
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import mujoco
import numpy as np

from ..core.kinematics import FiveBarLeg

MODEL_PATH = pathlib.Path(__file__).with_name('robot.xml')

#: Wheel radius r_w [m] and track d_w [m] of robot.xml (Table I).
WHEEL_RADIUS = 0.1
WHEEL_SEPARATION = 0.47
#: Torque range of the wheel motors' actuators [N m] (the MIT limit of the AK80-9 class).
WHEEL_TORQUE_LIMIT = 18.0
#: How far the wheels sink into the floor at rest under the robot's weight [m] (soft contact).
CONTACT_DEPTH = 0.0003
#: Hip joints, in the order of ``leg_angles()``: left front, left rear, right front, right rear.
LEG_JOINTS = ('left_leg_front_joint', 'left_leg_rear_joint',
              'right_leg_front_joint', 'right_leg_rear_joint')
WHEEL_JOINTS = ('left_wheel_joint', 'right_wheel_joint')
#: Labels of ``ground_truth()`` values, in order.
GROUND_TRUTH_FIELDS = ('time', 'theta', 'theta_dot', 'x', 'y', 'x_dot', 'yaw', 'yaw_rate',
                       'roll', 'l', 'tau_left', 'tau_right')


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
    height: initial body height l [m] (COM above the wheel axle), used until the schedule says
    otherwise; height_schedule: [(t [s], l [m]), ...] piecewise-linear in simulated time, held
    before the first and after the last point; pushes: Push events; bumps: x positions [m] of
    bumps of height bump_height [m]; slope: a Slope or None; leg: the five-bar geometry that
    robot.xml is built with (FiveBarLeg defaults).
    """

    def __init__(self, d_offset: float = 0.0, height: float = 0.37,
                 height_schedule: Sequence[Tuple[float, float]] = (),
                 pushes: Iterable[Push] = (), bumps: Iterable[float] = (),
                 bump_height: float = 0.02, slope: Optional[Slope] = None,
                 leg: Optional[FiveBarLeg] = None):
        self.leg = leg or FiveBarLeg()
        self.model = self._build_model(list(bumps), bump_height, slope)
        self.data = mujoco.MjData(self.model)
        self.timestep = float(self.model.opt.timestep)
        m = self.model
        self._base = m.body('base_link').id
        self._wheels = [m.body(n).id for n in ('left_wheel', 'right_wheel')]
        self._tail_wheel = m.geom('tail_wheel').id
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
        self._wheel_act = [m.actuator(n).id for n in ('left_wheel', 'right_wheel')]
        self._leg_act = [m.actuator(n).id for n in
                         ('left_leg_front', 'left_leg_rear', 'right_leg_front',
                          'right_leg_rear')]
        self._sensor = {n: (m.sensor_adr[m.sensor(n).id], m.sensor_dim[m.sensor(n).id])
                        for n in ('imu_quat', 'imu_gyro', 'imu_accel')}
        self._vel6 = np.zeros(6)
        self.pushes: List[Push] = list(pushes)
        self.height_schedule: List[Tuple[float, float]] = sorted(
            (float(t), float(v)) for t, v in height_schedule)
        self.set_imu_offset(d_offset)
        self._height_target = float('nan')
        self.set_height(height)
        self.reset('tail')

    # ---- model ------------------------------------------------------------------------------

    @staticmethod
    def _build_model(bumps: List[float], bump_height: float,
                     slope: Optional[Slope]) -> mujoco.MjModel:
        spec = mujoco.MjSpec.from_file(str(MODEL_PATH))
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
        leg = self.leg
        q_f, q_r = leg.inverse(l)
        if q_f != q_f:
            raise ValueError("height %.3f m is out of the legs' reach" % l)
        a, h = leg.thigh, 0.5 * leg.hip_spacing
        xc, zc = leg.com_x, leg.com_height - l   # axle in the hip-midpoint frame
        kfx, kfz = h + a * math.cos(q_f), -a * math.sin(q_f)
        krx, krz = -h - a * math.cos(q_r), -a * math.sin(q_r)
        phi = math.atan2(-(zc - kfz), xc - kfx)     # front shank below the forward horizontal
        psi = math.atan2(-(zc - krz), -(xc - krx))  # rear shank below the backward horizontal
        return q_f, q_r, phi - q_f, psi - q_r

    def place(self, pitch: float, x: float = 0.0, yaw: float = 0.0) -> None:
        """
        Put the robot at rest with its wheels on the floor at x [m], pitched by pitch [rad].

        The legs are set closed at the height target of time 0; velocities are zero.
        """
        m, d = self.model, self.data
        d.qpos[:] = m.qpos0
        d.qvel[:] = 0.0
        d.qacc_warmstart[:] = 0.0
        d.xfrc_applied[:] = 0.0
        l0 = self.height_target(0.0)
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
        d.qpos[0:3] = np.array([x, 0.0, WHEEL_RADIUS - CONTACT_DEPTH]) - axle
        d.ctrl[:] = 0.0
        self._apply_height(l0)
        mujoco.mj_forward(m, d)

    def tail_rest_pitch(self) -> float:
        """
        Pitch [rad] at which the tail wheel touches the floor with both wheels down.

        Geometric, at the height target of time 0; the simulation state is left as it was.
        """
        d = self.data
        saved = (d.qpos.copy(), d.qvel.copy(), d.ctrl.copy(), d.xfrc_applied.copy(), d.time)
        lo, hi = 0.0, 1.5
        for _ in range(40):  # bisection on the tail wheel's lowest point
            mid = 0.5 * (lo + hi)
            self.place(mid)
            if self._tail_clearance() > 0.0:
                lo = mid
            else:
                hi = mid
        d.qpos[:], d.qvel[:], d.ctrl[:], d.xfrc_applied[:], d.time = saved
        mujoco.mj_forward(self.model, d)
        return 0.5 * (lo + hi)

    def _tail_clearance(self) -> float:
        d = self.data
        centre_z = d.geom_xpos[self._tail_wheel][2]
        radius = self.model.geom_size[self._tail_wheel][0]
        # The tail wheel's axis stays horizontal (pitch only): its rim reaches radius lower.
        return centre_z - radius

    def reset(self, pose: str = 'tail', pitch: float = 0.0, x: float = 0.0,
              settle: float = 0.3) -> None:
        """
        Restart at time 0 in a pose.

        'tail' rests on the tail (then ``settle`` s with zero torque); 'pitch' puts the wheels
        on the floor with the body at ``pitch`` [rad] (not settled). x: axle position [m].
        """
        self.release()
        if pose == 'tail':
            self.place(self.tail_rest_pitch() + 1e-3, x)
            self.data.time = 0.0
            n = int(round(settle / self.timestep))
            for _ in range(n):
                mujoco.mj_step(self.model, self.data)
        elif pose == 'pitch':
            self.place(pitch, x)
        else:
            raise ValueError("pose must be 'tail' or 'pitch'")
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
        """Command the body height l [m] (hip servos); a height schedule overrides it."""
        self._leg_pose(l)  # raises when out of reach
        self._height_target = float(l)
        self._apply_height(l)

    def height_target(self, t: float) -> float:
        """Commanded height [m] at simulated time t [s] (schedule, else the set height)."""
        sched = self.height_schedule
        if not sched:
            return self._height_target
        if t <= sched[0][0]:
            return sched[0][1]
        for (t0, l0), (t1, l1) in zip(sched, sched[1:]):
            if t < t1:
                return l0 + (l1 - l0) * (t - t0) / (t1 - t0)
        return sched[-1][1]

    def _apply_height(self, l: float) -> None:
        q_f, q_r = self.leg.inverse(l)
        if q_f != q_f:
            return  # out of reach: keep the last target
        ctrl = self.data.ctrl
        a = self._leg_act
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

    def step(self, tau_left: float, tau_right: float, dt: Optional[float] = None) -> None:
        """
        Advance dt [s] (rounded to whole physics steps, at least one) with the wheel torques.

        tau_left, tau_right: forward-positive wheel torques [N m], clamped to +-18 N m (a
        non-finite value gives zero). The height schedule and pushes are applied every step.
        """
        m, d = self.model, self.data
        n = 1 if dt is None else max(1, int(round(dt / self.timestep)))
        d.ctrl[self._wheel_act[0]] = _clamp_torque(tau_left)
        d.ctrl[self._wheel_act[1]] = _clamp_torque(tau_right)
        base_force = d.xfrc_applied[self._base]
        for _ in range(n):
            t = d.time
            if self.height_schedule:
                self._apply_height(self.height_target(t))
            if self.pushes:
                base_force[0:3] = self.push_force(t)
            mujoco.mj_step(m, d)

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

    def leg_angles(self) -> Tuple[float, float, float, float]:
        """Hip angles [rad] (FiveBarLeg convention) in LEG_JOINTS order."""
        q = self.data.qpos
        return tuple(float(q[i]) for i in self._leg_q)

    def leg_velocities(self) -> Tuple[float, float, float, float]:
        """Hip angular velocities [rad/s] in LEG_JOINTS order."""
        v = self.data.qvel
        return tuple(float(v[i]) for i in self._leg_v)

    def leg_torques(self) -> Tuple[float, float, float, float]:
        """Hip servo torques [N m] in LEG_JOINTS order."""
        f = self.data.actuator_force
        return tuple(float(f[i]) for i in self._leg_act)

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
        height above the axle midpoint, along the body z axis [m]; applied wheel torques.
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
        return {
            'time': float(d.time), 'theta': pitch, 'theta_dot': float(theta_dot),
            'x': float(axle[0]), 'y': float(axle[1]),
            'x_dot': float(lin[0] * math.cos(yaw) + lin[1] * math.sin(yaw)),
            'yaw': yaw, 'yaw_rate': yaw_rate, 'roll': roll, 'l': l,
            'tau_left': tau_l, 'tau_right': tau_r,
        }


def _clamp_torque(tau: float) -> float:
    if not -math.inf < tau < math.inf:
        return 0.0
    return min(max(float(tau), -WHEEL_TORQUE_LIMIT), WHEEL_TORQUE_LIMIT)
