"""
Least squares on model (1) plus the wheel inertia, damping and delay, phase by phase.

Each phase makes some quantities identifiable (docs/identification.md), and each fit takes
the earlier phases' results as known:

- ``fit_stand`` (the wheels free on the stand): per wheel I_w w_dot = tau(t - delay) - b w,
  with tau the commanded torque held over each tick (zero-order hold) and w the wheel speed:
  the wheel inertia I_w [kg m^2], the bearing damping b [N m s/rad] and the motor delay [s], by
  simulating that equation exactly against the measured speeds (scipy least_squares);
- ``fit_tail`` (resting on the tail, torque pulses): the IMU's forward specific force,
  integrated, against the wheels' speed gives the rolling radius r_w (with a bias and drift of
  the integral, which a tilted IMU gives); then (M_tot r_w^2 + 2 I_w) (w(t) - w(0)) =
  integral of (sum of tau(t - delay) - b sum of w) less a resistance (constant and in
  proportion to speed: the tail wheel's) gives the rolling mass M_tot = M + m; both only
  from samples after the wheels coasted COAST s (a driven tyre slips);
- ``fit_balance`` (balancing, x_dot* chirps at two or more heights): the pitch equation of
  the pendulum (everything but the wheels) about the axle,
      J_a theta_dd = S_wx g - S_wz x_dd - (sum of tau(t - delay) - b sum of w),
  where S_w is the pendulum's first moment of mass about the axle in world axes (model (1)'s
  m l [sin theta, cos theta]) and J_a its inertia about the axle (m l^2 + I_b), written
  through the body's mass m_b, centre of mass (c_x, c_z) in base_link, pitch inertia I_b and the
  IMU offset d (theta = theta~ - d) plus the known light parts (leg links at the hip angles
  recorded, the tail wheel: ``KnownParts``). At one height only m l and the angle between
  the IMU and the centre of mass are seen; the heights' different leg geometry separates the
  body's mass from its height and the IMU offset from the centre of mass's x.

Intervals are 95 % (1.96 standard errors from the Jacobian at the optimum and the residuals'
variance): they assume independent residuals, so they are a lower bound where the residuals
are model error, not noise. ``identify`` runs the three and returns the report
(``identify_report.json``'s shape): each quantity under its sim_node parameter name.
"""
from dataclasses import dataclass
import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.optimize import least_squares
from scipy.signal import lfilter, savgol_filter

from .records import IMU, JOINTS, Record, STATE
from ..core.kinematics import FiveBarLeg
from ..sim.layout import LEG_JOINTS, WHEEL_JOINTS

G = 9.81
#: 95 % of a normal distribution lies within this many standard deviations.
Z95 = 1.96
#: Substeps per tick of the stand's simulation of the wheel (exact between them).
SUBSTEPS = 4
#: Savitzky-Golay window [samples] and order of the balance phase's derivatives.
SG_WINDOW, SG_ORDER = 21, 3
#: The tail's fit uses samples after the wheels coasted this long [s] (no tyre slip).
COAST = 0.1
#: Balance samples with the height changing faster than this are left out [m/s].
STEADY_HEIGHT_RATE = 0.005


@dataclass(frozen=True)
class Series:
    """A phase's measured signal against the fit's prediction: curves (label, t, meas, pred)."""

    quantity: str
    unit: str
    curves: List[Tuple[str, np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class KnownParts:
    """
    The light parts of the pendulum the fit does not identify, as weighed and measured.

    leg_link_mass: each of the eight five-bar links [kg] (uniform rods); tail_mass [kg] and
    tail_position (x, z) [m] in base_link: the tail's wheel, rigid with the body (the sim's
    ``robot.body_mass`` leaves it out). Defaults: sim/robot.xml's.
    """

    leg_link_mass: float = 0.05
    tail_mass: float = 0.05
    tail_position: Tuple[float, float] = (0.284, -0.20)

    @property
    def legs_mass(self) -> float:
        """Return the eight links' mass [kg]."""
        return 8.0 * self.leg_link_mass


@dataclass
class Estimate:
    """A fitted quantity: value, 95 % interval half-width, unit."""

    value: object
    interval: object
    unit: str

    def as_dict(self) -> Dict:
        """Return the report's form: value, interval [lo, hi] (per element for a list)."""
        v, h = np.asarray(self.value, float), np.asarray(self.interval, float)
        lo, hi = (v - h).tolist(), (v + h).tolist()
        return {'value': v.tolist(), 'interval': [lo, hi], 'unit': self.unit}


def _intervals(result, n_params: int) -> np.ndarray:
    """95 % half-widths of least_squares parameters (see the module docstring)."""
    J = result.jac
    dof = max(1, J.shape[0] - n_params)
    s2 = 2.0 * result.cost / dof
    cov = np.linalg.pinv(J.T @ J) * s2
    return Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0))


def _linear(A: np.ndarray, y: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ordinary least squares y ~ A p: (p, 95 % half-widths, residuals)."""
    p, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ p
    dof = max(1, len(y) - A.shape[1])
    cov = np.linalg.pinv(A.T @ A) * float(res @ res) / dof
    return p, Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0)), res


def held_integral(t_cmd: np.ndarray, u_cmd: np.ndarray):
    """
    Return U(t): the integral [N m s] of a command held from each t_cmd to the next.

    Zero before the first command; the last one held a tick beyond. Piecewise linear, so
    exact by interpolation between the knots: U(t - delay) is the delayed command's integral.
    """
    period = float(np.median(np.diff(t_cmd)))
    knots = np.append(t_cmd, t_cmd[-1] + period)
    values = np.concatenate([[0.0], np.cumsum(u_cmd * np.diff(knots))])

    def integral(t: np.ndarray) -> np.ndarray:
        return np.interp(t, knots, values, left=0.0)
    return integral


def _wheel_columns(rec: Record) -> Tuple[np.ndarray, List[np.ndarray], List[np.ndarray]]:
    """Return t, [left, right] wheel speeds [rad/s], [left, right] commanded torques [N m]."""
    js, st = rec[JOINTS], rec[STATE]
    speeds = [js[n + '.velocity'] for n in WHEEL_JOINTS]
    torques = [st['tau_left'], st['tau_right']]
    return js.t, speeds, torques


def simulate_wheel(t: np.ndarray, w0: float, torque, inertia: float, damping: float,
                   delay: float) -> np.ndarray:
    """
    Return a free wheel's speed [rad/s] at times t (uniform ticks) from w0.

    I w_dot = tau(t - delay) - b w, exact for a torque held over each substep (its average
    there, from ``torque``, a held_integral).
    """
    period = float(np.median(np.diff(t)))
    h = period / SUBSTEPS
    grid = t[0] + h * np.arange((len(t) - 1) * SUBSTEPS)
    u = (torque(grid + h - delay) - torque(grid - delay)) / h
    if damping > 1e-9:
        a = math.exp(-damping * h / inertia)
        c = (1.0 - a) / damping
    else:
        a, c = 1.0, h / inertia
    w, _ = lfilter([c], [1.0, -a], u, zi=[a * w0])   # w[n]: the speed at grid[n] + h
    return np.concatenate([[w0], w[SUBSTEPS - 1::SUBSTEPS]])


def shank_angles(rec: Record, leg: FiveBarLeg) -> List[np.ndarray]:
    """
    Return the [left, right] front shanks' angles [rad] below base_link's forward horizontal.

    The shank carries the wheel's axle and its motor's stator (sim/robot.xml): on a stand with
    the hips unpowered it swings under the wheel's reaction, and the wheel's speed in space is
    the joint's speed plus the shank's rate. From the hip angles recorded and the five-bar's
    geometry (``FiveBarLeg.pose``); zeros without hip angles in the recording.
    """
    js = rec[JOINTS]
    out = []
    for side in ('left', 'right'):
        names = ['%s_leg_%s_joint.position' % (side, end) for end in ('front', 'rear')]
        if not all(n in js.columns for n in names):
            out.append(np.zeros_like(js.t))
            continue
        hips = [_polled(js.t, js[n]) for n in names]
        poses = np.array([leg.pose(f, r) for f, r in zip(*hips)])
        fx, fz, xc, zc = poses[:, 0], poses[:, 1], poses[:, 4], poses[:, 5]
        phi = np.unwrap(np.arctan2(-(zc - fz), xc - fx))   # _knee_angles' phi
        out.append(phi if np.all(np.isfinite(phi)) else np.zeros_like(js.t))
    return out


def _polled(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """
    Return a polled angle [rad] linear between its polls (the samples where it changed).

    Off balancing the hips are polled at 50 Hz while joint_states comes every tick: the held
    values would make the shank's rate a train of spikes.
    """
    knots = np.flatnonzero(np.concatenate([[True], np.diff(q) != 0.0]))
    knots = np.union1d(knots, [len(q) - 1])
    return np.interp(t, t[knots], q[knots])


def fit_stand(rec: Record, leg: Optional[FiveBarLeg] = None) -> Dict[str, Estimate]:
    """
    Fit I_w, b and the delay from the stand phase (see the module docstring).

    leg: the five-bar's geometry (None: FiveBarLeg's defaults, sim/robot.xml's). The wheel's
    speed in space is w + phi_dot (phi: its shank's angle, ``shank_angles``; the body is held):
    I_w (w + phi_dot)' = tau(t - delay) - b w, so the state simulated is w + phi_dot, driven by
    tau(t - delay) + b phi_dot.
    """
    t, speeds, torques = _wheel_columns(rec)
    st_t = rec[STATE].t
    phis = shank_angles(rec, leg if leg is not None else FiveBarLeg())
    rates = [np.gradient(phi, t) for phi in phis]
    spins = [w + r for w, r in zip(speeds, rates)]   # the wheels' speeds in space [rad/s]
    commands = [held_integral(st_t, u) for u in torques]

    def drive(command, phi, damping, delay):
        # The integral of tau(t - delay) + b phi_dot, at the simulation's shifted times.
        return lambda s: command(s) + damping * np.interp(s + delay, t, phi)

    def predict(p):
        inertia, damping, delay = p
        return [simulate_wheel(t, w[0], drive(u, phi, damping, delay), inertia, damping, delay)
                for w, u, phi in zip(spins, commands, phis)]

    def residuals(p):
        return np.concatenate([pred - w for pred, w in zip(predict(p), spins)])

    # A first guess from the first second: I = integral of tau / change of speed.
    w, u = spins[0], commands[0]
    k = min(len(t) - 1, int(round(1.0 / np.median(np.diff(t)))))
    guess = max(abs(u(np.array([t[k]]))[0] - u(np.array([t[0]]))[0]) / max(abs(w[k] - w[0]),
                                                                           1e-6), 1e-4)
    result = least_squares(residuals, [guess, 0.01, 0.002],
                           bounds=([1e-6, 0.0, -0.01], [1.0, 5.0, 0.05]),
                           x_scale=[guess, 0.01, 0.001])
    half = _intervals(result, 3)
    inertia, damping, delay = result.x
    curves = [('wheel %d' % k, t, w, pred)
              for k, (w, pred) in enumerate(zip(spins, predict(result.x)))]
    return {'_series': Series('wheel speed', 'rad/s', curves),
            'robot.wheel_inertia': Estimate(inertia, half[0], 'kg m^2'),
            'robot.wheel_damping': Estimate(damping, half[1], 'N m s/rad'),
            'robot.motor_delay': Estimate(delay, half[2], 's'),
            '_residual_rms': Estimate(float(np.sqrt(np.mean(result.fun ** 2))), 0.0, 'rad/s')}


def _forward_specific_force(imu) -> np.ndarray:
    """Return the IMU's specific force along the heading, in the horizontal plane [m/s^2]."""
    qx, qy, qz, qw = (imu[n] for n in ('qx', 'qy', 'qz', 'qw'))
    ax, ay, az = imu['ax'], imu['ay'], imu['az']
    # First two rows of the rotation matrix of (w, x, y, z): world = R imu.
    fx = (1 - 2 * (qy * qy + qz * qz)) * ax + 2 * (qx * qy - qw * qz) * ay \
        + 2 * (qx * qz + qw * qy) * az
    fy = 2 * (qx * qy + qw * qz) * ax + (1 - 2 * (qx * qx + qz * qz)) * ay \
        + 2 * (qy * qz - qw * qx) * az
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    return np.cos(yaw) * fx + np.sin(yaw) * fy


def fit_tail(rec: Record, stand: Dict[str, Estimate]) -> Dict[str, Estimate]:
    """Fit the rolling radius and the rolling mass M + m from the tail phase (module doc)."""
    imu = rec[IMU]
    t, speeds, torques = _wheel_columns(rec)
    pitch_rate = imu.at(t, 'wy')
    w_abs = 0.5 * (speeds[0] + speeds[1]) + pitch_rate
    v_imu = cumulative_trapezoid(np.interp(t, imu.t, _forward_specific_force(imu)), t,
                                 initial=0.0)
    tt = t - t[0]
    inertia = stand['robot.wheel_inertia'].value
    damping = stand['robot.wheel_damping'].value
    delay = stand['robot.motor_delay'].value
    st_t = rec[STATE].t
    # Only where the wheels have coasted for COAST s: a driven tyre slips (in MuJoCo's soft
    # contact as on a floor), so the speeds agree with the rolling only between the pulses.
    effort = held_integral(st_t, np.abs(torques[0]) + np.abs(torques[1]))
    coast = (effort(t - delay) - effort(t - delay - COAST)) < 1e-9
    coast &= tt > COAST
    (r, c0, c1), half_r, res_r = _linear(
        np.stack([w_abs - w_abs[0], np.ones_like(t), tt], axis=1)[coast], v_imu[coast])
    drive = sum(held_integral(st_t, u)(t - delay) for u in torques)
    drive = drive - drive[0]
    friction = damping * cumulative_trapezoid(speeds[0] + speeds[1], t, initial=0.0)
    # (M_tot r^2 + 2 I_w)(w(t) - w(0)) = drive - friction - a resistance c0 + c1 w, integrated:
    # constant (rolling, a slope) and in proportion to speed (the tail wheel's bearing).
    travel = cumulative_trapezoid(w_abs, t, initial=0.0)
    (j_eff, _, _), half_j, res_j = _linear(
        np.stack([w_abs - w_abs[0], tt, travel], axis=1)[coast], (drive - friction)[coast])
    m_tot = (j_eff - 2.0 * inertia) / r ** 2
    i_half = stand['robot.wheel_inertia'].interval
    m_half = math.sqrt((half_j[0] / r ** 2) ** 2 + (2.0 * i_half / r ** 2) ** 2
                       + (2.0 * m_tot / r * half_r[0]) ** 2)
    # Predicted: the rolling equation's left side from the fitted inertia, against the drive.
    measured = (drive - friction)[coast]
    curves = [('rolling', t[coast], measured, measured - res_j)]
    return {'_series': Series('drive less bearing friction, integrated', 'N m s', curves),
            'robot.wheel_radius': Estimate(r, half_r[0], 'm'),
            'rolling_mass': Estimate(m_tot, m_half, 'kg'),
            '_residual_rms': Estimate(float(np.sqrt(np.mean(res_j ** 2))), 0.0, 'N m s')}


class Pendulum:
    """
    The pendulum (all but the wheels) of a body (m_b, c_x, c_z, I_b) on legs at hip angles.

    leg: the five-bar geometry (balance_node's ``leg.*``); known: the light parts. ``moments``
    gives, per sample of hip angles, the first moment S (x, z) [kg m] and the inertia J_a
    [kg m^2] about the axle in base_link axes, and the mass [kg].
    """

    def __init__(self, leg: FiveBarLeg, known: KnownParts, q_front: np.ndarray,
                 q_rear: np.ndarray):
        h = 0.5 * leg.hip_spacing
        poses = np.array([leg.pose(f, r) for f, r in zip(q_front, q_rear)])
        fx, fz, rx, rz, xc, zc = poses.T
        self.axle = (xc, zc)
        m = known.leg_link_mass
        # Per side two links from each hip: thigh hip -> knee, shank knee -> axle.
        links = [((h, 0.0), (fx, fz)), ((fx, fz), (xc, zc)),
                 ((-h, 0.0), (rx, rz)), ((rx, rz), (xc, zc))]
        sx = sz = ja = 0.0
        for (x0, z0), (x1, z1) in links:
            mx, mz = 0.5 * (x0 + x1) - xc, 0.5 * (z0 + z1) - zc
            length2 = (x1 - x0) ** 2 + (z1 - z0) ** 2
            sx, sz = sx + 2 * m * mx, sz + 2 * m * mz   # both legs
            ja = ja + 2 * m * (mx * mx + mz * mz + length2 / 12.0)
        tx, tz = known.tail_position[0] - xc, known.tail_position[1] - zc
        self.known_mass = known.legs_mass + known.tail_mass
        self.known_s = (sx + known.tail_mass * tx, sz + known.tail_mass * tz)
        self.known_j = ja + known.tail_mass * (tx * tx + tz * tz)

    def moments(self, m_b: float, c_x: float, c_z: float, i_b: float):
        """Return (mass, S_x, S_z, J_a) of the pendulum per sample (module docstring)."""
        xc, zc = self.axle
        bx, bz = c_x - xc, c_z - zc
        s_x = self.known_s[0] + m_b * bx
        s_z = self.known_s[1] + m_b * bz
        j_a = self.known_j + i_b + m_b * (bx * bx + bz * bz)
        return m_b + self.known_mass, s_x, s_z, j_a


def _hips(js) -> Tuple[np.ndarray, np.ndarray]:
    """Return the hip angles (front, rear) [rad], the two legs' mean (they move together)."""
    q = [js[n + '.position'] for n in LEG_JOINTS]
    return 0.5 * (q[0] + q[2]), 0.5 * (q[1] + q[3])


def _smooth(x: np.ndarray, deriv: int, dt: float) -> np.ndarray:
    return savgol_filter(x, SG_WINDOW, SG_ORDER, deriv=deriv, delta=dt)


def fit_balance(rec: Record, stand: Dict[str, Estimate], tail: Dict[str, Estimate],
                leg: FiveBarLeg, known: KnownParts = KnownParts(),
                guess: Sequence[float] = (11.0, 0.0, 0.05, 0.08, 0.0, 0.0)) -> Dict[str, Estimate]:
    """
    Fit the body's mass, centre of mass, pitch inertia and the IMU offset (module doc).

    A sixth parameter is the IMU's time offset against the joint states [s] (a nuisance:
    balancing keeps J_a theta_dd and S_wz x_dd nearly opposite, so a fraction of a
    millisecond between the two streams scales both; MuJoCo's sensors, for one, lag the joint
    velocities by a physics step).
    """
    imu, js, st = rec[IMU], rec[JOINTS], rec[STATE]
    t = js.t
    dt = float(np.median(np.diff(t)))
    r = tail['robot.wheel_radius'].value
    damping, delay = stand['robot.wheel_damping'].value, stand['robot.motor_delay'].value
    w_rel = [js[n + '.velocity'] for n in WHEEL_JOINTS]
    # The torque acting over each tick (delayed), smoothed as the derivatives are.
    drive = np.zeros_like(t)
    for n in ('tau_left', 'tau_right'):
        u = held_integral(st.t, st[n])
        drive += (u(t + 0.5 * dt - delay) - u(t - 0.5 * dt - delay)) / dt
    tau_net = _smooth(drive - damping * (w_rel[0] + w_rel[1]), 0, dt)
    wheel_dd = _smooth(0.5 * (w_rel[0] + w_rel[1]), 1, dt)
    q_front, q_rear = _hips(js)
    l_state = st.at(t, 'l')
    l_rate = np.gradient(l_state, t)
    l_rate[~np.isfinite(l_rate)] = 0.0
    mode = np.round(st.at(t, 'mode'))
    keep = (mode == 1) & (np.abs(l_rate) < STEADY_HEIGHT_RATE) & np.isfinite(q_front)
    # Not within a smoothing window of the ends or of a gap in the recording.
    edges = np.concatenate([[0], np.flatnonzero(np.diff(t) > 1.5 * dt) + 1, [len(t)]])
    for e in edges:
        keep[max(0, e - SG_WINDOW):e + SG_WINDOW] = False
    pend = Pendulum(leg, known, q_front[keep], q_rear[keep])
    tau = tau_net[keep]
    scale = max(float(np.std(tau)), 1e-3)

    def imu_signals(shift):
        qx, qy, qz, qw = (imu.at(t + shift, n) for n in ('qx', 'qy', 'qz', 'qw'))
        theta_m = np.arcsin(np.clip(2.0 * (qw * qy - qz * qx), -1.0, 1.0))  # theta + d
        rate = imu.at(t + shift, 'wy')
        theta_dd = _smooth(rate, 1, dt)
        x_dd = r * (wheel_dd + theta_dd)
        return _smooth(theta_m, 0, dt)[keep], theta_dd[keep], x_dd[keep]

    def residuals(p):
        m_b, c_x, c_z, i_b, d, shift = p
        th, thdd, xdd = imu_signals(shift)
        _, s_x, s_z, j_a = pend.moments(m_b, c_x, c_z, i_b)
        phi = th - d
        c, s = np.cos(phi), np.sin(phi)
        s_wx = s_x * c + s_z * s
        s_wz = -s_x * s + s_z * c
        return (j_a * thdd - s_wx * G + s_wz * xdd + tau) / scale

    result = least_squares(residuals, list(guess), x_scale=[1.0, 0.01, 0.01, 0.01, 0.01, 0.001],
                           bounds=([0.1, -0.5, -0.5, 1e-4, -0.5, -0.02],
                                   [200.0, 0.5, 0.5, 10.0, 0.5, 0.02]))
    half = _intervals(result, 6)
    m_b, c_x, c_z, i_b, d, shift = result.x
    lumped = _lumped(pend, result.x, l_state[keep])
    predicted = tau - result.fun * scale   # what the pitch equation asks of the wheels
    return {'_series': Series('net wheel torque on the pendulum', 'N m',
                              [('pitch equation', t[keep], tau, predicted)]),
            'robot.body_mass': Estimate(m_b, half[0], 'kg'),
            'robot.body_com': Estimate([c_x, c_z], [half[1], half[2]], 'm'),
            'robot.body_inertia': Estimate(i_b, half[3], 'kg m^2'),
            'imu_pitch_offset': Estimate(d, half[4], 'rad'),
            'imu_time_offset': Estimate(shift, half[5], 's'),
            '_lumped': lumped,
            '_residual_rms': Estimate(float(np.sqrt(np.mean(result.fun ** 2))) * scale, 0.0,
                                      'N m')}


def _lumped(pend: Pendulum, p, l_state: np.ndarray) -> List[Dict[str, float]]:
    """
    Model (1)'s pendulum at each height balanced (the state's l, to the cm).

    mass [kg]; l: its centre of mass's distance from the axle [m]; com_angle: that line's
    angle from base_link's z axis, forward positive [rad]; inertia_about_axle J_a [kg m^2];
    the axle's place below and ahead of the hip midpoint [m].
    """
    mass, s_x, s_z, j_a = pend.moments(*p[:4])
    out = []
    for level in np.unique(np.round(l_state, 2)):
        sel = np.abs(l_state - level) < 0.005
        if not sel.any():
            continue
        sx, sz = float(np.mean(s_x[sel])), float(np.mean(s_z[sel]))
        out.append({'height_state': float(level), 'mass': float(mass),
                    'l': math.hypot(sx, sz) / mass, 'com_angle': math.atan2(sx, sz),
                    'inertia_about_axle': float(np.mean(j_a[sel])),
                    'axle_below_hips': float(-np.mean(pend.axle[1][sel])),
                    'axle_ahead_of_hips': float(np.mean(pend.axle[0][sel]))})
    return out


def identify(records: Dict[str, Record], leg: FiveBarLeg,
             known: KnownParts = KnownParts(), series: Optional[Dict[str, Series]] = None
             ) -> Dict:
    """
    Fit the phases recorded, in turn; return the report (identify_report.json's shape).

    ``stand`` is needed, ``tail`` needs it, ``balance`` both. ``quantities``: {sim_node
    parameter name: {value, interval, unit}}, with the balance phase the wheel mass (the rolling
    mass less the pendulum's); ``lumped``: model (1)'s pendulum at each height; ``residuals``:
    each fit's RMS residual; ``phases``: the phases fitted. series: filled with each phase's
    measured signal against the fit's prediction ({phase: Series}, for plots).
    """
    parts = {'stand': fit_stand(records['stand'], leg)}
    if 'tail' in records:
        parts['tail'] = fit_tail(records['tail'], parts['stand'])
    if 'balance' in records and 'tail' in parts:
        parts['balance'] = fit_balance(records['balance'], parts['stand'], parts['tail'], leg,
                                       known)
    if series is not None:
        series.update({k: v['_series'] for k, v in parts.items()})
    quantities = {}
    for part in parts.values():
        quantities.update({k: v for k, v in part.items() if not k.startswith('_')})
    report = {'phases': list(parts)}
    if 'balance' in parts:
        m_b, rolling = quantities['robot.body_mass'], quantities['rolling_mass']
        quantities['robot.wheel_mass'] = Estimate(
            0.5 * (rolling.value - m_b.value - known.legs_mass - known.tail_mass),
            0.5 * math.hypot(rolling.interval, m_b.interval), 'kg')
        report['lumped'] = parts['balance']['_lumped']
    report['quantities'] = {k: v.as_dict() for k, v in sorted(quantities.items())}
    report['known_parts'] = {'leg_link_mass': known.leg_link_mass,
                             'tail_mass': known.tail_mass,
                             'tail_position': list(known.tail_position)}
    report['residuals'] = {k: float(v['_residual_rms'].value) for k, v in parts.items()}
    return report
