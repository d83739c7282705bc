"""
main_job's judging of one run: metrics from the recordings, criteria met, the paper beside it.

``evaluate`` returns a run's result: its metrics (named and defined in the table,
validation/paper/table.py, computed with validation/paper/metrics.py), the criteria with their
bounds (table) and measured values, and the side-by-side rows (the table's quantities and paper
quotes, this run's values). Times are seconds since the start of balancing (the robot armed on
its tail, the hips homed and the legs raised); angles from the ground truth in degrees unless
named otherwise.
"""
import math
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from .params import joy_segments, sim_time
from .record import Trace
from .scenarios import Scenario
from ..metrics import (drift, first_index, first_time, max_deviation, mean_or_none, overshoot,
                       peak_abs, rest_point, settling_time, tracking_error, TrackingError,
                       zero_crossings)
from ..table import CONTACT_WINDOW_S, D_HAT0, DEG, IMU_OFFSET, Judging, \
    KICK_AFTER_S, KICK_EARLIEST_S, KICK_RECOVERY_BAND_DEG, MAIN_JOB_COMMON, PAPER_YAW_GAIN, \
    REST_SPEED, STANDING_HOLD_S

#: balance_node's ~/state mode while balancing.
MODE_BALANCING = 1
#: Window of the figures at rest of the standing run [s].
REST_WINDOW = 5.0
#: |roll| beyond which a wheel is on the ramp [deg].
ROLL_ON_RAMP_DEG = 1.0
#: |roll| within which the body is level again after the drop [deg].
LEVEL_AGAIN_DEG = 2.0
G = 9.81
#: balance_node's ~/state mode at rest, and while it sits down (core/safety.Mode).
MODE_DISARMED = 0
MODE_SITTING = 4
#: How long before a scripted disarm its sit-down may already show in ~/state [s].
DISARM_SLACK = 0.05


def judge(judging: Judging, name: str, value, ok: bool, cause: str = '') -> dict:
    """Return a criterion's result: the table's name and bound, the measured value, met or not."""
    c = judging.criterion(name)
    return {'name': c.name, 'bound': c.unmet[cause] if cause else c.bound, 'value': value,
            'ok': bool(ok)}


def fmt(v, spec='%.2f') -> str:
    """Format a figure for a table: '-' for None, yes/no for a bool."""
    if v is None:
        return '-'
    if isinstance(v, (bool, np.bool_)):
        return 'yes' if v else 'no'
    if isinstance(v, (float, np.floating)):
        return spec % v
    return str(v)


def common(tr: Trace, m: dict, crit: List[dict], until: float = math.inf) -> float:
    """
    Rising and staying up, from the ground truth; returns the time it rose [s].

    rises: the true pitch is below 10 deg within 2 s of the start of balancing; stays up:
    balance_node stays in BALANCING and |theta| < 45 deg (its fall angle) to the end, or to
    ``until`` (a scripted disarm); tail: after rising the pitch never goes back above 30 deg
    (the tail holds the body at 36 deg and more).
    """
    rises = MAIN_JOB_COMMON.criterion('rises').limits
    theta = tr.deg('theta')
    m['t_homing_s'] = -tr.t_arm
    after = (tr.tg >= 0.0) & (tr.tg < until)
    t_rise = first_time(tr.tg, after & (theta < rises['theta_deg']))
    m['theta_start_deg'] = float(theta[after][0]) if after.any() else None
    m['t_rise_s'] = t_rise
    crit.append(judge(MAIN_JOB_COMMON, 'rises', fmt(t_rise, '%.2f s'),
                      t_rise is not None and t_rise <= rises['t_s']))
    risen = (tr.tg >= (t_rise if t_rise is not None else math.inf)) & (tr.tg < until)
    late = (tr.ts >= 0.05) & (tr.ts < until)
    mode = tr.s['mode'][late]
    # The scripted disarm's sit-down may show in samples just before ``until``: the actions'
    # clock starts when main_job sees balancing, the recording's at the first BALANCING sample
    # (a run had SITTING at 4.9995 s for a disarm at 5.0 s). Only SITTING is excused there.
    disarming = (tr.ts[late] >= until - DISARM_SLACK) & (mode == MODE_SITTING)
    t_fault = first_time(tr.ts[late], (mode != MODE_BALANCING) & ~disarming)
    max_abs = max_deviation(theta[risen]) if risen.any() else None
    m['t_fault_s'] = t_fault
    m['max_abs_theta_after_rise_deg'] = max_abs
    fall = MAIN_JOB_COMMON.criterion('stays up').limits['fall_deg']
    crit.append(judge(MAIN_JOB_COMMON, 'stays up',
                      'fault at %.2f s' % t_fault if t_fault is not None else
                      fmt(max_abs, 'max %.1f deg'),
                      t_fault is None and max_abs is not None and max_abs < fall))
    max_after = float(np.max(theta[risen])) if risen.any() else None
    m['max_theta_after_rise_deg'] = max_after
    tail = MAIN_JOB_COMMON.criterion('off the tail').limits['tail_deg']
    crit.append(judge(MAIN_JOB_COMMON, 'off the tail', fmt(max_after, 'max %.1f deg'),
                      max_after is not None and max_after < tail))
    m['peak_wheel_torque_nm'] = peak_abs(tr.g['tau_left'][after], tr.g['tau_right'][after])
    m['peak_abs_x_dot'] = peak_abs(tr.g['x_dot'][after])
    return t_rise if t_rise is not None else 0.0


def rest(tr: Trace) -> Tuple[Optional[float], Optional[float]]:
    """
    Return (rest_time_s, rest_distance_m) of a start-up, from the ground truth.

    At rest: from when the true |x_dot| stays below REST_SPEED to the end of the run (None,
    None if it is still faster at the end); the distance from the axle's x at arming.
    """
    after = tr.tg >= 0.0
    return rest_point(tr.tg[after], tr.g['x_dot'][after], tr.g['x'][after], REST_SPEED)


def eval_startup(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    Judge a start-up: overshoot, settling, and when and where it came to rest.

    Overshoot [deg]: how far the pitch went past its final value; settling within 2 deg.
    """
    lim = exp.judging.criterion('settles').limits
    theta = tr.deg('theta')
    t_end = tr.tg[-1]
    final = mean_or_none(theta[tr.win(t_end - 1.0, t_end + 1.0)])
    after = tr.tg >= 0.0
    m['theta_final_deg'] = final
    m['overshoot_deg'] = overshoot(theta[after], final)
    settle = settling_time(tr.tg, theta - final, lim['band_deg'], since=0.0, edge='outside')
    m['settle_s'] = settle
    m['rest_time_s'], m['rest_distance_m'] = rest(tr)
    cmp['rest_time'] = fmt(m['rest_time_s'], '%.2f') if m['rest_time_s'] is not None else \
        'still moving at %.2f s' % t_end
    cmp['rest_distance'] = fmt(m['rest_distance_m'], '%.2f')
    crit.append(judge(exp.judging, 'settles', '%.2f s' % settle, settle <= lim['settle_s']))
    up = all(c['ok'] for c in crit if c['name'] in ('stays up', 'off the tail'))
    cmp['overshoot'] = '%.1f' % m['overshoot_deg'] if up else 'none: it fell (%s)' % next(
        c['value'] for c in crit if c['name'] == 'stays up')
    cmp['theta_start'] = fmt(m['theta_start_deg'], '%.1f')
    cmp['settle'] = '%.2f' % settle
    cmp['peak_torque'] = '%.1f' % m['peak_wheel_torque_nm']


def eval_standing(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    d_hat against the measured pitch at rest, drift and speed over the last 5 s.

    At rest the observer's d_hat must equal the IMU pitch theta~ = theta + d: then the
    compensated pitch theta~ - d_hat is 0, the equilibrium of (9). In MuJoCo the true upright
    equilibrium is not exactly theta = 0 (the legs' mass sits off the body axis), so d_hat
    settles at d + theta_eq rather than at d itself; both are shown.
    """
    j = exp.judging
    t_end = tr.tg[-1]
    last = tr.win(t_end - REST_WINDOW, t_end + 1.0)
    st_last = tr.ts >= tr.ts[-1] - REST_WINDOW
    d_hat = float(np.degrees(np.mean(tr.s['d_hat'][st_last])))
    theta_meas = float(np.degrees(np.mean(tr.s['theta'][st_last])))
    theta_eq = float(np.mean(tr.deg('theta')[last]))
    x = tr.g['x'][last]
    m.update(d_hat_deg=d_hat, theta_meas_deg=theta_meas, theta_eq_deg=theta_eq,
             d_deg=IMU_OFFSET / DEG, d_hat0_deg=D_HAT0 / DEG,
             drift_last5_m=drift(x),
             drift_20s_m=drift(tr.g['x'][tr.win(t_end - STANDING_HOLD_S, t_end + 1.0)]),
             span_last5_m=float(np.ptp(x)),
             x_dot_mean_last5=float(np.mean(tr.g['x_dot'][last])))
    m['d_hat_within_0p1_deg_from_s'] = settling_time(
        tr.ts, np.degrees(tr.s['d_hat']) - d_hat, 0.1, since=0.0, edge='outside')
    err = abs(d_hat - theta_meas)
    crit.append(judge(j, 'd_hat found', '%.3f deg' % err,
                      err <= j.criterion('d_hat found').limits['err_deg']))
    crit.append(judge(j, 'no drift', '%.1f mm' % (1e3 * m['drift_last5_m']),
                      m['drift_last5_m'] <= j.criterion('no drift').limits['drift_m']))
    crit.append(judge(j, 'holds its spot', '%.1f mm' % (1e3 * m['drift_20s_m']),
                      m['drift_20s_m'] <= j.criterion('holds its spot').limits['drift_20s_m']))
    still = j.criterion('stands still').limits['x_dot_mps']
    crit.append(judge(j, 'stands still', '%.1f mm/s' % (1e3 * m['x_dot_mean_last5']),
                      abs(m['x_dot_mean_last5']) < still))
    cmp['d_hat'] = '%.2f (d = %.1f, true upright pitch %.2f)' % (
        d_hat, IMU_OFFSET / DEG, theta_eq)
    cmp['d_hat0'] = '%.1f' % (D_HAT0 / DEG)
    cmp['d_hat_time'] = '%.2f' % m['d_hat_within_0p1_deg_from_s']
    cmp['x_dot'] = '%.1f' % (1e3 * m['x_dot_mean_last5'])
    cmp['drift'] = '%.1f' % (1e3 * m['drift_last5_m'])


def _tracking(tr: Trace, t0: float, t1: float) -> Tuple[TrackingError, TrackingError]:
    """Errors of x_dot against x_dot* [m/s] and of the yaw rate against yaw rate* [rad/s]."""
    w = tr.win(t0, t1)
    return (tracking_error(tr.g['x_dot'][w], tr.state_on_gt('x_dot_ref')[w]),
            tracking_error(tr.g['yaw_rate'][w], tr.state_on_gt('yaw_rate_ref')[w]))


def eval_height(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    Drives both ways through the heights and stays level; velocity tracking is reported.

    IDA-PBC's velocity loop is slow with Table I's gains (about 3 s time constant,
    docs/ida_pbc.md), so the criterion asks for the commanded direction at half the commanded
    speed over the last 3 s of each drive; the tracking error is reported beside it.
    """
    j = exp.judging
    drives = j.criterion('drives both ways').limits
    span = drives['window_s']
    segs = [s for s in joy_segments(exp) if s[2] != 0.0]
    _height_tracking(exp, tr, m, crit, cmp, segs[-1][1])
    errs = [_tracking(tr, t1 - span, t1)[0].mean_abs for t0, t1, v, w in segs]
    speeds = [mean_or_none(tr.g['x_dot'][tr.win(t1 - span, t1)]) for t0, t1, v, w in segs]
    asked = [v for t0, t1, v, w in segs]
    drive = tr.win(segs[0][0], segs[-1][1])
    theta = tr.deg('theta')
    eq = mean_or_none(theta[tr.win(segs[0][0] - 1.0, segs[0][0])])
    l_drive = tr.g['l'][drive]
    m.update(x_dot_error_last3_mps=errs, x_dot_last3_mps=speeds, x_dot_asked_mps=asked,
             theta_eq_deg=eq, max_theta_dev_driving_deg=max_deviation(theta[drive], eq),
             l_max=float(np.max(l_drive)), l_min=float(np.min(l_drive)))
    speeds_text = ', '.join('%.2f (asked %+.2f)' % (v, a) for v, a in zip(speeds, asked))
    crit.append(judge(j, 'drives both ways', speeds_text,
                      all(v * a > 0.0 and abs(v) >= drives['share'] * abs(a)
                          for v, a in zip(speeds, asked))))
    crit.append(judge(j, 'level while driving', 'max %.2f deg' % m['max_theta_dev_driving_deg'],
                      m['max_theta_dev_driving_deg'] <
                      j.criterion('level while driving').limits['theta_dev_deg']))
    heights = j.criterion('heights').limits
    crit.append(judge(j, 'heights', '%.3f..%.3f m' % (m['l_min'], m['l_max']),
                      m['l_max'] > heights['l_max_above_m'] and
                      m['l_min'] < heights['l_min_below_m']))
    cmp['heights'] = '%.2f..%.2f' % (m['l_max'], m['l_min'])
    cmp['speeds'] = speeds_text
    cmp['errors'] = ', '.join('%.3f' % e for e in errs)
    cmp['pitch'] = '%.2f' % m['max_theta_dev_driving_deg']


def _height_tracking(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict,
                     t_end: float) -> None:
    """Judge the rms of the true height minus balance_node's shaped command from the 1st press."""
    presses = exp.height_presses
    w = tr.win(presses[0][0], t_end)
    err = tracking_error(tr.g['l'][w], tr.state_on_gt('l_ref')[w])
    m.update(height_tracking_rms_m=err.rms, height_tracking_max_m=err.max_abs,
             height_presses=[h for _, h in presses])
    bound = exp.judging.criterion('tracks the height').limits['rms_m']
    crit.append(judge(exp.judging, 'tracks the height', '%.4f m (max %.3f)' % (
        err.rms, err.max_abs), err.rms <= bound))
    cmp['tracking'] = '%.4f (max %.3f)' % (err.rms, err.max_abs)


def eval_rotate(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """Yaw rate reached with the paper's loop and with the default (PI); balance unaffected."""
    j = exp.judging
    (t_on, t_off) = [(s[0], s[1]) for s in joy_segments(exp) if s[3] != 0.0][0]
    t_gain = exp.actions[0][0]
    yaw = np.degrees(tr.g['yaw_rate'])
    r1 = mean_or_none(yaw[tr.win(t_gain - 2.0, t_gain)])
    r2 = mean_or_none(yaw[tr.win(t_off - 3.0, t_off)])
    rate = j.criterion('165 deg/s').limits
    error_pct = None if r2 is None else 100.0 * abs(r2 - rate['rate_dps']) / abs(
        rate['rate_dps'])
    theta = tr.deg('theta')
    eq = mean_or_none(theta[tr.win(t_on - 1.0, t_on)])
    spin = tr.win(t_on, t_off)
    m.update(yaw_rate_paper_gain_degps=r1, yaw_rate_pi_degps=r2, yaw_rate_error_pct=error_pct,
             theta_eq_deg=eq,
             max_theta_dev_deg=max_deviation(theta[spin], eq),
             max_abs_x_dot_spin=peak_abs(tr.g['x_dot'][spin]),
             # IDA-PBC is still slowing down from the start-up when the rotation begins.
             abs_x_dot_at_start=float(abs(np.interp(t_on, tr.tg, tr.g['x_dot']))),
             peak_torque_spin_nm=peak_abs(tr.g['tau_left'][spin], tr.g['tau_right'][spin]))
    crit.append(judge(j, '165 deg/s', '%.1f deg/s (%.1f %% off)' % (r2, error_pct),
                      error_pct is not None and error_pct <= rate['tol_pct']))
    calm = j.criterion('balance unaffected').limits
    crit.append(judge(j, 'balance unaffected', '%.2f deg; %.3f m/s (%.3f at the start)' % (
        m['max_theta_dev_deg'], m['max_abs_x_dot_spin'], m['abs_x_dot_at_start']),
        m['max_theta_dev_deg'] < calm['theta_dev_deg'] and
        m['max_abs_x_dot_spin'] < m['abs_x_dot_at_start'] + calm['x_dot_margin_mps']))
    cmp['yaw_rate'] = "%.1f with the paper's gain %.1f; %.1f with the default PI loop" % (
        r1, PAPER_YAW_GAIN, r2)
    cmp['pitch'] = 'max deviation %.2f deg' % m['max_theta_dev_deg']
    cmp['torques'] = 'peak %.2f N m (the step at the live gain change)' % (
        m['peak_torque_spin_nm'])


def eval_s_turn(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    Tracking of x_dot* and yaw rate* during the turns, and the oscillation about them.

    Oscillation: the standard deviation of (signal - reference) over the turns, which leaves
    out a steady offset (the yaw-rate loop is proportional only) and keeps what swings.
    """
    j = exp.judging
    turns = [s for s in joy_segments(exp) if s[3] != 0.0]
    t0, t1 = turns[0][0], turns[-1][1]
    ex, ey = _tracking(tr, t0, t1)
    w = tr.win(t0, t1)
    m.update(x_dot_error_mean=ex.mean_abs, yaw_rate_error_mean=ey.mean_abs,
             x_dot_oscillation=ex.std, yaw_rate_oscillation=ey.std,
             yaw_rate_peak_degps=peak_abs(np.degrees(tr.g['yaw_rate'][w])))
    crit.append(judge(j, 'tracks x_dot*', '%.3f m/s' % ex.mean_abs,
                      ex.mean_abs < j.criterion('tracks x_dot*').limits['mean_abs_mps']))
    crit.append(judge(j, 'tracks yaw rate*', '%.3f rad/s' % ey.mean_abs,
                      ey.mean_abs < j.criterion('tracks yaw rate*').limits['mean_abs_radps']))
    cmp['x_dot_osc'] = '%.3f' % m['x_dot_oscillation']
    cmp['yaw_osc'] = '%.1f' % math.degrees(m['yaw_rate_oscillation'])
    cmp['turns'] = 'peak %.0f deg/s' % m['yaw_rate_peak_degps']


def _settled_after(tr: Trace, t_from: float, t_to: float, before: float) -> float:
    """Largest |theta - before| [deg] in [t_from, t_to); nan when the window is empty."""
    late = tr.deg('theta')[tr.win(t_from, t_to)]
    return max_deviation(late, before) if late.size else math.nan


def eval_bumps(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    When the axle passes each bump; the pitch and speed excursions; settled after the last.

    The wheel's front meets a bump r_w = 0.1 m before the axle is over it.
    """
    j = exp.judging
    bumps = list(exp.sim['bumps'])
    x = tr.g['x']
    drives = [s for s in joy_segments(exp) if s[2] != 0.0]
    t_drive, t_stop = drives[0][0], drives[-1][1]
    times = [first_time(tr.tg, (tr.tg >= 0.0) & (x >= b)) for b in bumps]
    m.update(bump_x_m=bumps, t_bumps_s=times, x_end_m=float(x[-1]),
             t_bumps_after_drive_s=[t - t_drive if t is not None else None for t in times])
    crit.append(judge(j, 'crosses both bumps', 'x = %.2f m' % x[-1],
                      x[-1] > bumps[-1] + j.criterion('crosses both bumps').limits['beyond_m']))
    if any(t is None for t in times):
        crit.append(judge(j, 'settles after the bumps', 'not reached', False, cause='bumps'))
        return
    settles = j.criterion('settles after the bumps').limits
    theta = tr.deg('theta')
    before = mean_or_none(theta[tr.win(times[0] - 1.5, times[0] - 0.5)])
    near = tr.win(times[0] - 0.5, times[-1] + 1.0)
    worst = _settled_after(tr, times[-1] + settles['after_s'], t_stop, before)
    m.update(theta_before_deg=before,
             bump_pitch_peak_dev_deg=max_deviation(theta[near], before),
             x_dot_range_bumps=[float(np.min(tr.g['x_dot'][near])),
                                float(np.max(tr.g['x_dot'][near]))],
             x_dot_before=float(np.interp(times[0] - 0.5, tr.tg, tr.g['x_dot'])),
             theta_after_bumps_dev_deg=worst)
    crit.append(judge(j, 'settles after the bumps', fmt(worst, '%.2f deg'),
                      worst < settles['dev_deg']))
    cmp['t_bumps'] = ', '.join('%.2f' % t for t in m['t_bumps_after_drive_s'])
    cmp['pitch'] = '%.1f' % m['bump_pitch_peak_dev_deg']
    cmp['x_dot'] = '%.2f..%.2f (%.2f before)' % (
        m['x_dot_range_bumps'][0], m['x_dot_range_bumps'][1], m['x_dot_before'])


def _recovery(tr: Trace, t_kick: float, t_next: float, before: float,
              band_deg: float) -> Optional[float]:
    """
    Time from the kick until |theta - before| stays within band_deg up to t_next [s].

    None: no window, or still outside the band when the next kick comes.
    """
    idx = tr.win(t_kick, t_next)
    settled = settling_time(tr.tg[idx], tr.deg('theta')[idx] - before, band_deg, since=t_kick)
    return None if settled is None else settled - t_kick


def eval_push(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    Per kick: the pitch excursion, how much of it is left 1.5 s later, and the recovery time.

    The paper's run (push_paper, IDA-PBC): the pitch does not come all the way back while
    IDA-PBC's slow velocity loop is still braking the speed the kick gave (a lean of about 1 deg
    per 0.17 m/s^2), so "returns quickly" is judged as: 1.5 s after the kick, |theta -
    theta_before| is below half its peak. The default configuration's (push): every kick at
    most 3 deg, back within 1 deg of theta_before within 1 s (kick_recovery_s).
    """
    j = exp.judging
    names = [c.name for c in j.criteria]
    # The kicks run on sim time (main_job/params.sim_time); balancing may start later or
    # earlier than planned: each kick is mapped back through the recorded clock.
    kicks = [tr.sim_to_rel(sim_time(p[0])) for p in exp.pushes]
    m['kick_times_s'] = kicks
    if kicks[0] < KICK_EARLIEST_S:   # in the start-up: no settled pitch to judge it by
        for name in names:
            crit.append(judge(j, name, 'first kick at %.2f s' % kicks[0], False, cause='late'))
        return
    ends = kicks[1:] + [float(tr.tg[-1])]
    theta = tr.deg('theta')
    peaks, lefts, recoveries = [], [], []
    for t, t_next in zip(kicks, ends):
        before = mean_or_none(theta[tr.win(t - 0.5, t)])
        peaks.append(max_deviation(theta[tr.win(t, t_next)], before))
        lefts.append(_settled_after(tr, t + KICK_AFTER_S, t_next, before))
        recoveries.append(_recovery(tr, t, t_next, before, KICK_RECOVERY_BAND_DEG))
    x_dot = tr.g['x_dot'][tr.win(kicks[0], tr.tg[-1])]
    crossings = zero_crossings(x_dot)
    m.update(kick_times_s=kicks, kick_pitch_peak_deg=peaks, kick_pitch_after_1p5s_deg=lefts,
             kick_recovery_s=recoveries,
             x_dot_zero_crossings=crossings, peak_abs_x_dot_kicks=peak_abs(x_dot),
             theta_eq_deg=mean_or_none(theta[tr.win(kicks[0] - 1.0, kicks[0])]),
             theta_meas_eq_deg=float(np.degrees(np.mean(tr.s['theta'][
                 (tr.ts >= kicks[0] - 1.0) & (tr.ts < kicks[0])]))))
    if 'recovers from each kick' in names:
        share = j.criterion('recovers from each kick').limits['share']
        crit.append(judge(j, 'recovers from each kick', ', '.join(
            '%.1f of %.1f deg' % (lf, pk) for lf, pk in zip(lefts, peaks)),
            all(lf < share * pk for lf, pk in zip(lefts, peaks))))
    if 'kick pitch' in names:
        bound = j.criterion('kick pitch').limits['peak_deg']
        crit.append(judge(j, 'kick pitch', ', '.join('%.2f deg' % pk for pk in peaks),
                          all(pk <= bound for pk in peaks)))
    if 'kick recovery' in names:
        bound = j.criterion('kick recovery').limits['recovery_s']
        crit.append(judge(j, 'kick recovery', ', '.join(fmt(r, '%.2f s') for r in recoveries),
                          all(r is not None and r <= bound for r in recoveries)))
    cmp['reversals'] = '%d for %d kicks' % (crossings, len(kicks))
    cmp['pitch'] = ', '.join('%.1f' % pk for pk in peaks)
    cmp['recovery'] = ', '.join(fmt(r) for r in recoveries)
    cmp['theta_eq'] = '%.2f (true %.2f)' % (m['theta_meas_eq_deg'], m['theta_eq_deg'])
    cmp['x_dot'] = '%.2f' % m['peak_abs_x_dot_kicks']


def eval_slope(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """Roll on the ramp, heading kept, pitch back to its value before the ramp after the drop."""
    j = exp.judging
    roll = tr.deg('roll')
    theta = tr.deg('theta')
    after = tr.tg >= 0.0
    on = first_index(after & (np.abs(roll) > ROLL_ON_RAMP_DEG))
    m['max_roll_deg'] = peak_abs(roll[after])
    crit.append(judge(j, 'climbs the ramp', '%.1f deg' % m['max_roll_deg'],
                      m['max_roll_deg'] > j.criterion('climbs the ramp').limits['roll_deg']))
    if on is None:
        crit.append(judge(j, 'settles after the drop', 'never', False, cause='ramp'))
        return
    settles = j.criterion('settles after the drop').limits
    t_on = float(tr.tg[on])
    i_max = int(np.argmax(np.abs(roll) * after))
    t_off = first_time(tr.tg, (tr.tg > tr.tg[i_max]) & (np.abs(roll) < ROLL_ON_RAMP_DEG))
    before = mean_or_none(theta[tr.win(t_on - 1.0, t_on)])
    m.update(t_ramp_s=t_on, t_drop_s=t_off, theta_before_deg=before,
             heading_change_deg=float(np.degrees(tr.g['yaw'][i_max] - tr.g['yaw'][on])),
             x_dot_at_ramp=float(tr.g['x_dot'][on]))
    if t_off is not None:
        worst = _settled_after(tr, t_off + settles['after_s'], tr.tg[-1] + 1.0, before)
        m['theta_after_drop_dev_deg'] = worst
        crit.append(judge(j, 'settles after the drop', '%.2f deg' % worst,
                          not math.isnan(worst) and worst < settles['dev_deg']))
    else:
        crit.append(judge(j, 'settles after the drop', 'still on the ramp', False,
                          cause='down'))
    cmp['roll'] = '%.1f' % m['max_roll_deg']
    cmp['x_dot'] = '%.2f' % m['x_dot_at_ramp']
    cmp['heading'] = '%.1f' % m['heading_change_deg']
    cmp['pitch'] = fmt(m.get('theta_after_drop_dev_deg'), 'within %.2f deg')


def _ramp(exp: Scenario) -> Tuple[float, float, float]:
    """(x of the foot, x of the top [m], height of the top [m]) of the scenario's ramp."""
    sl = exp.sim
    a, length, x0 = sl['slope.angle'], sl['slope.length'], sl['slope.start_x']
    return x0, x0 + length * math.cos(a), length * math.sin(a)


def eval_slope_levelled(exp: Scenario, tr: Trace, m: dict, crit: List[dict],
                        cmp: dict) -> None:
    """
    Roll while the wheel climbs (the axle over the ramp), the drop off its top, pitch after it.

    With levelling the roll stays small, so the ramp is found from where the axle is (the ramp
    lies along x), not from the roll. The wheel is down the fall time of the ramp's height
    after the axle passes the top (0.15 m: 0.17 s).
    """
    j = exp.judging
    x_foot, x_top, h_top = _ramp(exp)
    x, roll, theta = tr.g['x'], tr.deg('roll'), tr.deg('theta')
    after = tr.tg >= 0.0
    m['max_roll_deg'] = peak_abs(roll[after])
    t_on = first_time(tr.tg, after & (x >= x_foot))
    t_top = first_time(tr.tg, after & (x >= x_top))
    m.update(t_ramp_s=t_on, t_top_s=t_top)
    if t_on is None:
        for name in ('level on the ramp', 'settles after the drop'):
            crit.append(judge(j, name, 'never', False, cause='ramp'))
        return
    on = after & (x >= x_foot) & (x < x_top)
    m['max_roll_on_ramp_deg'] = peak_abs(roll[on])
    m['x_dot_at_ramp'] = float(np.interp(t_on, tr.tg, tr.g['x_dot']))
    crit.append(judge(j, 'level on the ramp', '%.2f deg' % m['max_roll_on_ramp_deg'],
                      m['max_roll_on_ramp_deg'] <= j.criterion('level on the ramp').limits[
                          'roll_deg']))
    before = mean_or_none(theta[tr.win(t_on - 1.0, t_on)])
    m['theta_before_deg'] = before
    cmp['roll'] = '%.2f' % m['max_roll_on_ramp_deg']
    cmp['x_dot'] = '%.2f' % m['x_dot_at_ramp']
    if t_top is None:
        crit.append(judge(j, 'settles after the drop', 'still on the ramp', False,
                          cause='down'))
        return
    dropped = tr.tg >= t_top
    t_down = t_top + math.sqrt(2.0 * h_top / G)
    settles = j.criterion('settles after the drop').limits
    worst = _settled_after(tr, t_down + settles['after_s'], tr.tg[-1] + 1.0, before)
    tilted = np.flatnonzero(dropped & (np.abs(roll) > LEVEL_AGAIN_DEG))
    m.update(t_down_s=t_down, drop_roll_peak_deg=peak_abs(roll[dropped]),
             drop_roll_back_s=float(tr.tg[tilted[-1]] - t_top) if tilted.size else 0.0,
             drop_pitch_peak_deg=max_deviation(theta[dropped], before),
             theta_after_drop_dev_deg=worst)
    crit.append(judge(j, 'settles after the drop', fmt(worst, '%.2f deg'),
                      not math.isnan(worst) and worst < settles['dev_deg']))
    cmp['drop'] = '%.1f; %.2f s' % (m['drop_roll_peak_deg'], m['drop_roll_back_s'])
    cmp['pitch'] = fmt(worst, 'within %.2f deg')


def first_contact(tr: Trace, t_from: float,
                  t_to: float) -> Tuple[Optional[str], Optional[float], Optional[float]]:
    """
    Return (what, when [s], |pitch rate| [rad/s]) of the first floor contact in [t_from, t_to).

    what: 'tail' or 'body' (the tail wheel or the body box, sim_node's contact fields); the
    rate is the largest |true theta_dot| over CONTACT_WINDOW_S up to the first contact sample
    (the ground truth comes at 100 Hz). (None, None, None) when nothing touches.
    """
    w = tr.win(t_from, t_to)
    touching = w & ((tr.g['tail_contact'] > 0.5) | (tr.g['body_contact'] > 0.5))
    i = first_index(touching)
    if i is None:
        return None, None, None
    t_c = float(tr.tg[i])
    near = w & (tr.tg >= t_c - CONTACT_WINDOW_S) & (tr.tg <= t_c)
    what = 'tail' if tr.g['tail_contact'][i] > 0.5 else 'body'
    return what, t_c, peak_abs(tr.g['theta_dot'][near])


def eval_sit_down(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """
    Judge the sit-down after the disarm; beside it, after a re-arm, an uncontrolled torque cut.

    Contact: the first sample with the tail or the body on the floor after the disarm (the
    robot stands on its wheels until then); travel: the largest distance from where it was
    at the disarm (at the cut) until the re-arm (the end).
    """
    j = exp.judging
    t_dis = next(t for t, name, value in exp.actions if name == 'arm' and not value)
    t_rearm = next((t for t, name, value in exp.actions if name == 'arm' and value),
                   tr.tg[-1] + 1.0)
    t_stop = next((t for t, name, value in exp.actions if name == 'stop'), None)
    m.update(t_disarm_s=t_dis, t_stop_s=t_stop)
    x = tr.g['x']
    x_dis = float(np.interp(t_dis, tr.tg, x))
    seq = tr.win(t_dis, t_rearm)
    what, t_c, rate = first_contact(tr, t_dis, t_rearm)
    m.update(sit_down_contact=what, sit_down_contact_s=None if t_c is None else t_c - t_dis,
             sit_down_contact_rate_radps=rate,
             sit_down_travel_m=max_deviation(x[seq], x_dis))
    rest = (tr.ts >= t_dis) & (tr.ts < t_rearm) & (tr.s['mode'] == MODE_DISARMED)
    t_rest = first_time(tr.ts, rest)
    m['sit_down_time_s'] = None if t_rest is None else t_rest - t_dis
    late = tr.win(t_rearm - 0.5, t_rearm)
    m['rest_pitch_deg'] = mean_or_none(tr.deg('theta')[late])
    if what is None:
        crit.append(judge(j, 'onto the tail', 'no contact', False, cause='none'))
        crit.append(judge(j, 'gentle contact', 'no contact', False, cause='none'))
    else:
        crit.append(judge(j, 'onto the tail', what, what == 'tail'))
        crit.append(judge(j, 'gentle contact', '%.2f rad/s' % rate,
                          what == 'tail' and
                          rate <= j.criterion('gentle contact').limits['rate_radps']))
    crit.append(judge(j, 'short travel', '%.2f m' % m['sit_down_travel_m'],
                      m['sit_down_travel_m'] <= j.criterion('short travel').limits['travel_m']))
    crit.append(judge(j, 'rests', fmt(m['sit_down_time_s'], '%.2f s'),
                      t_rest is not None and
                      t_rest - t_dis <= j.criterion('rests').limits['time_s']))
    cut = (None, None, None)
    if t_stop is not None:
        cut = first_contact(tr, t_stop, tr.tg[-1] + 1.0)
        after = tr.tg >= t_stop
        m.update(cut_contact=cut[0], cut_contact_rate_radps=cut[2],
                 cut_travel_m=max_deviation(x[after], float(np.interp(t_stop, tr.tg, x)))
                 if after.any() else None)
    cmp['contact'] = '%s / %s' % (what or 'none', cut[0] or 'none')
    cmp['rate'] = '%s / %s' % (fmt(rate), fmt(cut[2]))
    cmp['travel'] = '%s / %s' % (fmt(m['sit_down_travel_m']), fmt(m.get('cut_travel_m')))


def _crossing(t: np.ndarray, v: np.ndarray, level: float, rising: bool) -> Optional[float]:
    """Return the first time [s] v crosses ``level`` upwards (rising) or downwards, else None."""
    hit = first_index(v >= level if rising else v <= level)
    if hit is None:
        return None
    if hit == 0:
        return float(t[0])
    # Linear between the samples on both sides of the crossing (100 Hz ground truth).
    v0, v1, t0, t1 = v[hit - 1], v[hit], t[hit - 1], t[hit]
    return float(t0 + (level - v0) / (v1 - v0) * (t1 - t0))


def step_response(t: np.ndarray, v: np.ndarray, start: float, target: float) \
        -> Tuple[Optional[float], float]:
    """
    Return (10-90 % time [s], overshoot [%]) of v(t) going from ``start`` to ``target``.

    The 10 % and 90 % levels lie on the way from start to target; overshoot: how far v goes
    past the target, in % of the step, at least 0.
    """
    step = target - start
    rising = step > 0.0
    t10 = _crossing(t, v, start + 0.1 * step, rising)
    t90 = _crossing(t, v, start + 0.9 * step, rising)
    beyond = (np.max(v) - target) if rising else (target - np.min(v))
    return (None if t10 is None or t90 is None else t90 - t10,
            max(0.0, 100.0 * float(beyond) / abs(step)))


def eval_velocity_step(exp: Scenario, tr: Trace, m: dict, crit: List[dict], cmp: dict) -> None:
    """Judge the step up's rise time and overshoot and the pitch peak; report the step down."""
    j = exp.judging
    segs = joy_segments(exp)
    t_up = next(s[0] for s in segs if s[2] > 0.0)
    t_down = next(s[0] for s in segs if s[0] > t_up and s[2] == 0.0)
    target = next(s[2] for s in segs if s[0] == t_up)
    x_dot, theta = tr.g['x_dot'], tr.deg('theta')
    before = mean_or_none(x_dot[tr.win(t_up - 0.5, t_up)])
    at_down = mean_or_none(x_dot[tr.win(t_down - 0.5, t_down)])
    theta_before = mean_or_none(theta[tr.win(t_up - 0.5, t_up)])
    up, down = tr.win(t_up, t_down), tr.win(t_down, tr.tg[-1])
    rise, overshoot_pct = step_response(tr.tg[up], x_dot[up], before, target)
    fall, undershoot_pct = step_response(tr.tg[down], x_dot[down], at_down, 0.0)
    pitch = max_deviation(theta[tr.win(t_up, tr.tg[-1])], theta_before)
    m.update(step_times_s=[t_up, t_down], velocity_before_mps=before,
             velocity_rise_time_s=rise, velocity_overshoot_pct=overshoot_pct,
             velocity_step_pitch_peak_deg=pitch, velocity_at_step_down_mps=at_down,
             velocity_fall_time_s=fall, velocity_undershoot_pct=undershoot_pct)
    lim = j.limits()
    crit.append(judge(j, 'rise time', '%s s (from %.3f m/s)' % (fmt(rise), before),
                      rise is not None and rise <= lim['rise_s']))
    crit.append(judge(j, 'overshoot', '%.1f %%' % overshoot_pct,
                      overshoot_pct <= lim['overshoot_pct']))
    crit.append(judge(j, 'pitch', '%.2f deg' % pitch, pitch <= lim['pitch_deg']))
    cmp['rise'] = '%s / %s' % (fmt(rise), fmt(fall))
    cmp['overshoot'] = '%.1f / %.1f' % (overshoot_pct, undershoot_pct)
    cmp['pitch'] = '%.2f' % pitch


EVALUATORS: Dict[str, Callable] = {
    'startup': eval_startup, 'standing': eval_standing, 'height': eval_height,
    'rotate': eval_rotate, 's_turn': eval_s_turn, 'bumps': eval_bumps, 'push': eval_push,
    'slope': eval_slope, 'slope_levelled': eval_slope_levelled, 'sit_down': eval_sit_down,
    'velocity_step': eval_velocity_step,
}


def evaluate(exp: Scenario, tr: Optional[Trace], notes: List[str]) -> dict:
    """Return the experiment's metrics, criteria (each with its bound) and comparisons."""
    res = {'experiment': exp.name, 'title': exp.title, 'figure': exp.figure,
           'paper': exp.paper, 'controller': exp.controller, 'balance_overrides': exp.balance,
           'known_finding': exp.known_finding, 'notes': list(notes), 'metrics': {},
           'criteria': [], 'compare': [], 'passed': False}
    if tr is None or tr.tg.size == 0 or tr.ts.size == 0:
        res['criteria'].append(judge(MAIN_JOB_COMMON, 'ran', 'no data', False))
        return res
    m, crit, cmp = res['metrics'], res['criteria'], {}
    common(tr, m, crit, exp.balancing_until if exp.balancing_until is not None else math.inf)
    try:
        EVALUATORS[exp.kind](exp, tr, m, crit, cmp)
    except (ValueError, IndexError, TypeError) as exc:   # e.g. a fall cut the run short
        crit.append(judge(MAIN_JOB_COMMON, 'evaluated', 'failed: %s' % exc, False))
    res['compare'] = [(c.quantity, c.paper, cmp[c.key]) for c in exp.judging.compare
                      if c.key in cmp]
    res['passed'] = bool(all(c['ok'] for c in crit) and not notes)
    return res
