"""
The paper's experiments in closed-loop simulation, side by side with the paper's figures.

``experiments [--output DIR] [--quick]`` runs, on the nonlinear model (1) with BalanceCore (the
code of balance_node; core/simulation.py):

1. start-up from the tail (+36 deg) at l = 0.37 m (paper Fig. 3): IDA-PBC (13) with Table I's
   gains, IDA-PBC with ``ida_pbc.TUNED_GAINS``, the linear controller u = k_x xi~ with the LQR
   k_x, and with Table I's k_x in working units (``lqr.table_i_force_gain``);
2. standing still with output regulation (Fig. 4): true IMU offset d = 2.2 deg, d_hat0 = 2.7 deg;
   IDA-PBC with and without the d_hat compensation alongside;
3. height 0.70 -> 0.52 -> 0.37 m while driving at 0.3 m/s, and back (Fig. 5);
4. rotating on the spot at 165 deg/s at l = 0.70 m (Fig. 6);
5. a robustness matrix: the start-up under +-20 % mass, one extra tick of delay, a 6 N m torque
   limit (configured in the controller, or a motor limit it does not know), sensor noise and
   the IMU offset, for each controller.

It writes ``experiments.json`` (per experiment and controller: overshoot_deg, settling_time_s,
peak_torque_nm, fell, and the experiment's own figures), ``comparison.md`` (also printed) and
paper-style PNG plots (panels a-d: theta, theta_dot, x_dot, u against time) into the output
folder. ``--quick`` shortens the runs for CI. The experiments, the paper's figures and the
targets are the ``model1`` entries of validation/paper/table.py; the metrics are those of
validation/paper/metrics.py.
"""
import argparse
import json
import math
import os
import platform
import sys
import time
from typing import Optional, Tuple

import numpy as np

from . import table
from .metrics import (drift, max_deviation, overshoot, peak_abs, SETTLING_BAND_DEG,
                      settling_band_note, settling_time, tracking_error, window)
from .table import D_HAT0, DEG, IMU_OFFSET, ROTATE_RATE_DPS
from .. import json_safe
from ...core import ida_pbc, lqr
from ...core.params import RobotParams, TABLE_I_IDA_PBC
from ...core.simulation import Scenario, SimResult, simulate, TAIL_ANGLE
from ...optional import missing, pyplot

P = RobotParams()

#: The paper's figures (Sec. V-C), for the comparison table.
PAPER = table.PAPER_FIGURES
#: Targets for standing still (issue 2): the limits of the table's model-(1) criteria.
TARGETS = table.BY_NAME['standing'].model1.limits()
#: Window of the final figures (mean speed, yaw rate) [s].
FINAL_WINDOW = 1.0

#: Sensor noise of the robustness matrix: pitch [rad], pitch rate [rad/s], wheel speed [rad/s].
SENSOR_NOISE = (0.2 * DEG, 0.02, 0.05)


def overshoot_deg(r: SimResult) -> float:
    """Largest excursion of the true theta past 0 away from the start side [deg] (0: none)."""
    if r.theta.size == 0:
        return 0.0
    return math.degrees(overshoot(r.theta, 0.0, 1.0 if r.scenario.theta0 >= 0.0 else -1.0))


def settling_time_s(r: SimResult, band_deg: float = SETTLING_BAND_DEG) -> Optional[float]:
    """Time [s] after which the true |theta| stays within band_deg; None if it fell or never."""
    if r.fell:
        return None
    return settling_time(r.t, r.theta, math.radians(band_deg))


def peak_torque_nm(r: SimResult) -> float:
    """Largest wheel torque magnitude applied to either wheel [N m]."""
    return peak_abs(r.tau_left, r.tau_right) if r.t.size else 0.0


def velocity_error(r: SimResult, t_from: float = 0.0) -> Tuple[float, float]:
    """Return (rms, max) of |x_dot - x_dot_ref| [m/s] over t >= t_from (true speed)."""
    sel = r.t >= t_from
    e = tracking_error(r.x_dot[sel], r.x_dot_ref[sel])
    return e.rms, e.max_abs


def run_metrics(r: SimResult) -> dict:
    """Return the figures every run reports (table.MODEL1_COMMON)."""
    return {
        'overshoot_deg': overshoot_deg(r),
        'settling_time_s': settling_time_s(r),
        'peak_torque_nm': peak_torque_nm(r),
        'fell': bool(r.fell),
        'fall_time_s': r.fall_time,
        'duration_s': float(r.t[-1] + r.scenario.dt) if r.t.size else 0.0,
        'cpu_time_s': r.cpu_time,
    }


def controllers() -> dict:
    """
    Return the controllers compared, as Scenario keyword arguments, by name.

    ida_pbc_table_i / ida_pbc_tuned: IDA-PBC (13) with Table I's / the tuned gains, fed
    theta~ - d_hat as balance_node runs it; ida_pbc_uncompensated / ida_pbc_tuned_uncompensated:
    the same on the raw IMU pitch theta~, as in the paper; lqr: the
    linear u = k_x xi~ with the LQR k_x(l); linear_table_i: the same law with Table I's k_x in
    force units; output_regulation: u = k_x xi_hat + k_d d_hat (9).
    """
    out = {'ida_pbc_table_i': {'controller': 'ida_pbc', 'ida_pbc_gains': TABLE_I_IDA_PBC}}
    tuned = getattr(ida_pbc, 'TUNED_GAINS', None)
    if tuned is not None:
        out['ida_pbc_tuned'] = {'controller': 'ida_pbc', 'ida_pbc_gains': tuned}
    out['ida_pbc_uncompensated'] = {'controller': 'ida_pbc', 'ida_pbc_gains': TABLE_I_IDA_PBC,
                                    'compensate_offset': False}
    if tuned is not None:
        out['ida_pbc_tuned_uncompensated'] = {'controller': 'ida_pbc', 'ida_pbc_gains': tuned,
                                              'compensate_offset': False}
    out['lqr'] = {'controller': 'lqr'}
    table_i = getattr(lqr, 'table_i_force_gain', None)
    if table_i is not None:
        out['linear_table_i'] = {'controller': 'lqr', 'linear_gain': table_i(P)}
    out['output_regulation'] = {'controller': 'output_regulation'}
    return out


def startup(quick: bool) -> tuple:
    """Experiment 1: start-up from the tail at l = 0.37 m. Returns (metrics, results)."""
    duration = 4.0 if quick else 10.0
    names = ['ida_pbc_table_i', 'ida_pbc_tuned', 'ida_pbc_uncompensated',
             'ida_pbc_tuned_uncompensated', 'lqr', 'linear_table_i']
    ctrl = controllers()
    metrics, results = {}, {}
    for name in names:
        if name not in ctrl:
            continue
        r = simulate(Scenario(name='startup/' + name, duration=duration, theta0=TAIL_ANGLE,
                              height=0.37, **ctrl[name]))
        m = run_metrics(r)
        m.update({'peak_speed_mps': peak_abs(r.x_dot),
                  'x_final_m': float(r.x[-1]), 'x_dot_final_mps': float(r.x_dot[-1])})
        metrics[name] = m
        results[name] = r
    return metrics, results


def standing_metrics(r) -> dict:
    """Standing-still figures: d_hat error, its convergence time, final speed and drift."""
    m = run_metrics(r)
    d = r.scenario.imu_offset
    err = r.d_hat - d
    i5 = min(int(round(TARGETS['d_hat_time_s'] / r.scenario.dt)), err.size - 1)
    last = window(r.t, r.t[-1] - FINAL_WINDOW + 0.5 * r.scenario.dt)
    m.update({
        'd_hat_error_deg': abs(math.degrees(err[-1])),
        'd_hat_error_5s_deg': abs(math.degrees(err[i5])),
        'd_hat_within_0p1deg_s': settling_time(r.t, err, TARGETS['d_hat_error_deg'] * DEG),
        'x_dot_final_mps': abs(float(np.mean(r.x_dot[last]))),
        'drift_m': drift(r.x),
        'max_excursion_m': max_deviation(r.x, r.x[0]),
    })
    return m


def standing_still(quick: bool) -> tuple:
    """Experiment 2: standing still, d = 2.2 deg, d_hat0 = 2.7 deg. Returns (metrics, results)."""
    duration = 20.0  # the targets are stated after 20 s; 20 s costs about a second
    variants = {
        'output_regulation': {'controller': 'output_regulation'},
        'output_regulation_noise': {'controller': 'output_regulation',
                                    'noise_std': SENSOR_NOISE, 'seed': 2},
        'ida_pbc_table_i': {'controller': 'ida_pbc'},
        'ida_pbc_uncompensated': {'controller': 'ida_pbc', 'compensate_offset': False},
    }
    metrics, results = {}, {}
    for name, kw in variants.items():
        if quick and not name.startswith('output_regulation'):
            continue
        r = simulate(Scenario(name='standing/' + name, duration=duration, theta0=0.0,
                              imu_offset=IMU_OFFSET, d_hat0=D_HAT0, height=0.37, **kw))
        metrics[name] = standing_metrics(r)
        results[name] = r
    return metrics, results


def height_change(quick: bool) -> tuple:
    """
    Experiment 3: 0.70 -> 0.52 -> 0.37 m driving at 0.3 m/s (and back up driving backward).

    Returns (metrics, results); velocity errors are over the whole run and after the first
    2 s (the start of the drive).
    """
    forward = ((0.0, 0.70), (3.0, 0.70), (4.0, 0.52), (6.0, 0.52), (7.0, 0.37))
    v_forward = ((0.0, 0.0), (1.0, 0.3), (9.0, 0.3), (10.0, 0.0))
    if quick:
        height, v_ref, duration = forward, v_forward, 10.0
    else:
        height = forward + ((11.0, 0.37), (12.0, 0.52), (14.0, 0.52), (15.0, 0.70))
        v_ref = ((0.0, 0.0), (1.0, 0.3), (9.0, 0.3), (10.0, -0.3), (16.0, -0.3), (17.0, 0.0))
        duration = 20.0
    ctrl = controllers()
    metrics, results = {}, {}
    for name in ('ida_pbc_table_i', 'ida_pbc_tuned', 'lqr', 'output_regulation'):
        if name not in ctrl or (quick and name not in ('ida_pbc_table_i', 'ida_pbc_tuned')):
            continue
        r = simulate(Scenario(name='height/' + name, duration=duration, theta0=0.0,
                              height=height, x_dot_ref=v_ref, **ctrl[name]))
        m = run_metrics(r)
        rms, peak = velocity_error(r, 0.0)
        rms2, peak2 = velocity_error(r, 2.0)
        m.update({'velocity_error_rms_mps': rms, 'velocity_error_max_mps': peak,
                  'velocity_error_rms_after_2s_mps': rms2,
                  'velocity_error_max_after_2s_mps': peak2,
                  'max_abs_theta_deg': math.degrees(max_deviation(r.theta))})
        metrics[name] = m
        results[name] = r
    return metrics, results


def rotating(quick: bool) -> tuple:
    """
    Experiment 4 of the paper (Fig. 6): turning on the spot at 165 deg/s at l = 0.70 m, IDA-PBC.

    Returns (metrics, results); yaw_rate_error_final_dps is the mean |error| over the last 1 s.
    """
    duration = 4.0 if quick else 8.0
    rate = ROTATE_RATE_DPS * DEG
    yaw_ref = ((0.0, 0.0), (1.0, rate))
    ctrl = controllers()
    metrics, results = {}, {}
    for name in ('ida_pbc_table_i', 'ida_pbc_tuned'):
        if name not in ctrl:
            continue
        r = simulate(Scenario(name='rotating/' + name, duration=duration, theta0=0.0,
                              height=0.70, yaw_rate_ref=yaw_ref, **ctrl[name]))
        m = run_metrics(r)
        last = window(r.t, r.t[-1] - FINAL_WINDOW + 0.5 * r.scenario.dt)
        m.update({
            'yaw_rate_final_dps': math.degrees(float(np.mean(r.yaw_rate[last]))),
            'yaw_rate_error_final_dps': math.degrees(
                tracking_error(r.yaw_rate[last], rate).mean_abs),
            'max_abs_theta_deg': math.degrees(max_deviation(r.theta)),
        })
        metrics[name] = m
        results[name] = r
    return metrics, results


#: Perturbations of the robustness matrix: name -> Scenario keyword arguments.
PERTURBATIONS = {
    'nominal': {},
    'mass_plus_20pct': {'mass_factor': 1.2},
    'mass_minus_20pct': {'mass_factor': 0.8},
    'delay_1_tick': {'delay_ticks': 1},
    'torque_limit_6nm': {'max_wheel_torque': 6.0},
    'motor_limit_6nm_unknown': {'motor_torque_limit': 6.0},
    'sensor_noise': {'noise_std': SENSOR_NOISE, 'seed': 1},
    'imu_offset_2p2deg': {'imu_offset': IMU_OFFSET, 'd_hat0': D_HAT0},
}


def robustness(quick: bool) -> tuple:
    """Experiment 5: the start-up under each perturbation, per controller."""
    duration = 4.0 if quick else 8.0
    ctrl = controllers()
    metrics, results = {}, {}
    for pert, pkw in PERTURBATIONS.items():
        metrics[pert], results[pert] = {}, {}
        for name, kw in ctrl.items():
            r = simulate(Scenario(name='robustness/%s/%s' % (pert, name), duration=duration,
                                  theta0=TAIL_ANGLE, height=0.37, **kw, **pkw))
            metrics[pert][name] = run_metrics(r)
            results[pert][name] = r
    return metrics, results


# ---------------------------------------------------------------- plots

#: Panels of the paper's Fig. 3-5: (label, series of a SimResult).
PANELS = (
    (r'(a) $\theta$ [deg]', lambda r: np.degrees(r.theta)),
    (r'(b) $\dot\theta$ [deg/s]', lambda r: np.degrees(r.theta_dot)),
    (r'(c) $\dot x$ [m/s]', lambda r: r.x_dot),
    (r'(d) $u$ [N]', lambda r: r.u),
)


def plot_runs(results: dict, path: str, title: str, panels=PANELS, extra=None) -> None:
    """Save a paper-style figure: one panel per series, one line per run (Agg backend)."""
    plt = pyplot()

    panels = list(panels) + list(extra or [])
    cols = 2
    rows = (len(panels) + 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(11, 3.0 * rows), sharex=True)
    axes = np.atleast_1d(axes).ravel()
    for ax, (label, series) in zip(axes, panels):
        for name, r in results.items():
            style = '--' if r.fell else '-'
            tag = name + (' (fell)' if r.fell else '')
            ax.plot(r.t, series(r), style, lw=1.2, label=tag)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    for ax in axes[max(0, len(panels) - cols):len(panels)]:
        ax.set_xlabel('t [s]')
    axes[0].legend(fontsize=8, loc='best')
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _fmt(v, digits=2):
    if v is None:
        return '-'
    if isinstance(v, bool):
        return 'yes' if v else 'no'
    if isinstance(v, float) and not math.isfinite(v):
        return '-'
    return ('%.' + str(digits) + 'f') % v


def _startup_md(rows: dict) -> list:
    lines = ['## 1. Start-up from the tail (36 deg, l = 0.37 m; paper Fig. 3)', '',
             '| controller | overshoot [deg] | paper | settling [s] | peak torque [N m] '
             '| peak speed [m/s] | x, x_dot at the end [m, m/s] | fell |',
             '|---|---|---|---|---|---|---|---|']
    for name, m in rows.items():
        paper = (PAPER['startup_overshoot_ida_pbc_deg'] if name.startswith('ida_pbc')
                 else PAPER['startup_overshoot_linear_deg'])
        lines.append('| %s | %s | %s | %s | %s | %s | %s, %s | %s |' % (
            name, _fmt(m['overshoot_deg']), _fmt(paper, 0), _fmt(m['settling_time_s']),
            _fmt(m['peak_torque_nm']), _fmt(m['peak_speed_mps']), _fmt(m['x_final_m']),
            _fmt(m['x_dot_final_mps']), _fmt(m['fell'])))
    return lines


def _standing_md(rows: dict) -> list:
    lines = ['## 2. Standing still (d = 2.2 deg, d_hat0 = 2.7 deg; paper Fig. 4)', '',
             '| controller | d_hat error 5 s [deg] | final [deg] | within 0.1 deg at [s] '
             '| x_dot last 1 s [mm/s] | drift [mm] | fell |', '|---|---|---|---|---|---|---|']
    for name, m in rows.items():
        lines.append('| %s | %s | %s | %s | %s | %s | %s |' % (
            name, _fmt(m['d_hat_error_5s_deg'], 3), _fmt(m['d_hat_error_deg'], 4),
            _fmt(m['d_hat_within_0p1deg_s']), _fmt(1e3 * m['x_dot_final_mps'], 3),
            _fmt(1e3 * m['drift_m'], 1), _fmt(m['fell'])))
    lines += ['', 'Targets: d_hat within %.1f deg in <= %.0f s, |x_dot| < %.0f mm/s, drift < '
              '%.0f mm. Paper: stands still on carpet (friction), d about 2.2 deg.' % (
                  TARGETS['d_hat_error_deg'], TARGETS['d_hat_time_s'],
                  1e3 * TARGETS['x_dot_final_mps'], 1e3 * TARGETS['drift_m'])]
    return lines


def _height_md(rows: dict) -> list:
    lines = ['## 3. Height 0.70 -> 0.52 -> 0.37 m at 0.3 m/s (paper Fig. 5)', '',
             '| controller | fell | max abs theta [deg] | velocity error rms / max [m/s] '
             '| after 2 s rms / max [m/s] | peak torque [N m] |', '|---|---|---|---|---|---|']
    for name, m in rows.items():
        lines.append('| %s | %s | %s | %s / %s | %s / %s | %s |' % (
            name, _fmt(m['fell']), _fmt(m['max_abs_theta_deg']),
            _fmt(m['velocity_error_rms_mps'], 3), _fmt(m['velocity_error_max_mps'], 3),
            _fmt(m['velocity_error_rms_after_2s_mps'], 3),
            _fmt(m['velocity_error_max_after_2s_mps'], 3), _fmt(m['peak_torque_nm'])))
    return lines + ['', 'Paper: the robot stays stable (no figure of merit given).']


def _rotating_md(rows: dict) -> list:
    lines = ['## 4. Rotating at 165 deg/s, l = 0.70 m (paper Fig. 6)', '',
             '| controller | fell | yaw rate last 1 s [deg/s] | max abs theta [deg] '
             '| peak torque [N m] |', '|---|---|---|---|---|']
    for name, m in rows.items():
        lines.append('| %s | %s | %s | %s | %s |' % (
            name, _fmt(m['fell']), _fmt(m['yaw_rate_final_dps'], 1),
            _fmt(m['max_abs_theta_deg']), _fmt(m['peak_torque_nm'])))
    return lines + ['', 'Paper: rotates smoothly at 165 deg/s; the yaw torque does not disturb '
                    'balance.']


def _robustness_md(rob: dict) -> list:
    names = list(next(iter(rob.values())).keys())
    lines = ['## 5. Robustness: start-up from the tail under perturbations', '',
             'Cell: survived (overshoot deg / settling s) or FELL at t s.', '',
             '| perturbation | ' + ' | '.join(names) + ' |',
             '|---|' + '---|' * len(names)]
    for pert, row in rob.items():
        cells = []
        for name in names:
            m = row[name]
            if m['fell']:
                cells.append('FELL at %s' % _fmt(m['fall_time_s']))
            else:
                cells.append('ok (%s / %s)' % (
                    _fmt(m['overshoot_deg'], 1), _fmt(m['settling_time_s'])))
        lines.append('| %s | %s |' % (pert, ' | '.join(cells)))
    return lines


#: Per experiments.json key: its runner and its section of comparison.md.
RUNS = {
    'startup': (startup, _startup_md),
    'standing_still': (standing_still, _standing_md),
    'height_change': (height_change, _height_md),
    'rotating': (rotating, _rotating_md),
    'robustness': (robustness, _robustness_md),
}


def comparison_markdown(data: dict) -> str:
    """Return the measured figures next to the paper's, as markdown."""
    lines = ['# Simulation vs. the paper', '',
             'Nonlinear model (1), RK4 4 x 0.5 ms, 2 ms zero-order hold, BalanceCore. '
             + settling_band_note()]
    for entry in table.for_runner('model1'):
        lines += [''] + RUNS[entry.model1_key][1](data[entry.model1_key])
    return '\n'.join(lines) + '\n'


def plot_all(figs: dict, output: str) -> None:
    """Write the paper-style plots of every experiment into ``output``."""
    fig = {e.model1_key: e.figure for e in table.for_runner('model1')}
    plot_runs(figs['startup'], os.path.join(output, 'startup.png'),
              'Start-up from the tail, l = 0.37 m (cf. paper %s)' % fig['startup'])
    plot_runs(figs['standing_still'], os.path.join(output, 'standing_still.png'),
              'Standing still, d = 2.2 deg, d_hat0 = 2.7 deg (cf. paper %s)'
              % fig['standing_still'],
              extra=[(r'(e) $\hat d$ [deg]', lambda r: np.degrees(r.d_hat)),
                     (r'(f) $x$ [m]', lambda r: r.x)])
    plot_runs(figs['height_change'], os.path.join(output, 'height_change.png'),
              'Height 0.70 -> 0.52 -> 0.37 m at 0.3 m/s (cf. paper %s)' % fig['height_change'],
              extra=[(r'(e) $l$ [m]', lambda r: r.l),
                     (r'(f) $\dot x - \dot x^*$ [m/s]', lambda r: r.x_dot - r.x_dot_ref)])
    plot_runs(figs['rotating'], os.path.join(output, 'rotating.png'),
              'Rotating at 165 deg/s, l = 0.70 m (cf. paper %s)' % fig['rotating'],
              extra=[(r'(e) yaw rate [deg/s]', lambda r: np.degrees(r.yaw_rate)),
                     (r'(f) $\tau_l, \tau_r$ [N m]',
                      lambda r: np.column_stack([r.tau_left, r.tau_right]))])
    for pert, res in figs['robustness'].items():
        plot_runs(res, os.path.join(output, 'robustness_%s.png' % pert),
                  'Start-up under perturbation: %s' % pert)


def run(output: str, quick: bool = False) -> dict:
    """Run every experiment, write JSON, markdown and plots into ``output``; return the data."""
    os.makedirs(output, exist_ok=True)
    cpu0 = time.process_time()
    data, figs = {}, {}
    for entry in table.for_runner('model1'):
        key = entry.model1_key
        data[key], figs[key] = RUNS[key][0](quick)
    sim_cpu = time.process_time() - cpu0
    plot_all(figs, output)
    data['meta'] = {
        'quick': quick,
        'python': platform.python_version(),
        'machine': platform.machine(),
        'simulation_cpu_s': sim_cpu,
        'total_cpu_s': time.process_time() - cpu0,
        'paper': PAPER,
        'targets': TARGETS,
        'settling_definition': settling_band_note(),
    }
    data = json_safe(data)
    with open(os.path.join(output, 'experiments.json'), 'w') as f:
        json.dump(data, f, indent=2, sort_keys=False)
    with open(os.path.join(output, 'comparison.md'), 'w') as f:
        f.write(comparison_markdown(data))
    return data


def main(argv=None) -> int:
    """Entry point of the ``experiments`` executable."""
    parser = argparse.ArgumentParser(
        prog='experiments',
        description="Run the paper's experiments in closed-loop simulation and compare.")
    parser.add_argument('--output', default=os.path.join('output', 'experiments'),
                        help='output folder (default: ./output/experiments)')
    parser.add_argument('--quick', action='store_true', help='short runs for CI')
    args = parser.parse_args(argv)
    absent = missing(('matplotlib',), 'experiments (its figures)')
    if absent:
        print('\n'.join(absent), file=sys.stderr)
        return 2
    output = os.path.abspath(args.output)
    data = run(output, args.quick)
    with open(os.path.join(output, 'comparison.md')) as f:
        sys.stdout.write(f.read())
    print('\nsimulation CPU time: %.1f s' % data['meta']['simulation_cpu_s'])
    print('output folder: %s' % output)
    return 0


if __name__ == '__main__':
    sys.exit(main())
