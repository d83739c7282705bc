"""
The planned rise's figures on model (1): its plan, the start-up beside IDA-PBC's, the errors.

``python -m wheelleg_balance.validation.paper.rise_report --output DIR`` runs, on model (1) with
BalanceCore (core/simulation.py; ``controller: auto``, 12 N m, 2 ms), the start-up from the tail
at height_min with the planned rise (core/rise.py) and with IDA-PBC rising
(``auto.planned_rise`` false), for body mass -30/0/+30 % (the plant's; the controller keeps
the nominal) and IMU offset d = -3/0/+2.2/+3 deg (d_hat0 = 0). It prints the table of
docs/motions.md (overshoot past 0 of the true pitch, at rest, distance to rest, peak torque)
and saves ``rise_startup.png`` (the nominal start-up, both rises, paper-style panels) and
``rise_plan.png`` (the plan: pitch, speed, force) into DIR.
"""
import argparse
from dataclasses import replace
import math
import os

import numpy as np

from .experiments import overshoot_deg, plot_runs
from .metrics import rest_point
from .table import REST_SPEED
from ...core import rise
from ...core.params import RobotParams
from ...core.simulation import _build_core, Scenario, simulate
from ...optional import pyplot

MASS_FACTORS = (0.7, 1.0, 1.3)
OFFSETS_DEG = (-3.0, 0.0, 2.2, 3.0)


def start_up(planned: bool, mass_factor: float = 1.0, d_deg: float = 0.0,
             duration: float = 8.0):
    """Return the closed-loop run of one start-up from the tail (module docstring)."""
    sc = Scenario(name='planned rise' if planned else 'IDA-PBC rise', controller='auto',
                  duration=duration, mass_factor=mass_factor, imu_offset=math.radians(d_deg))
    core = _build_core(sc)
    core.set_auto_rules(replace(core.config.auto, planned_rise=planned))
    return simulate(sc, core)


def row(r) -> dict:
    """Return a run's figures: overshoot [deg], at rest [s], distance [m], peak torque [N m]."""
    t_rest, distance = rest_point(r.t, r.x_dot, r.x, REST_SPEED)
    return {'overshoot_deg': overshoot_deg(r), 'rest_time_s': t_rest,
            'rest_distance_m': distance, 'fell': bool(r.fell),
            'peak_torque_nm': float(np.max(np.abs(np.r_[r.tau_left, r.tau_right])))}


def table_lines() -> list:
    """Return the markdown table of every start-up (module docstring)."""
    def cell(v, spec='%.2f'):
        return '-' if v is None else spec % v
    lines = ['| rise | body mass | d [deg] | overshoot [deg] | at rest [s] | to rest [m] | '
             'peak torque [N m] |', '|---|---|---|---|---|---|---|']
    for planned in (True, False):
        for mf in MASS_FACTORS:
            for d in OFFSETS_DEG:
                m = row(start_up(planned, mf, d))
                lines.append('| %s | %+.0f %% | %+.1f | %s | %s | %s | %.1f |' % (
                    'planned' if planned else 'IDA-PBC', (mf - 1.0) * 100.0, d,
                    'FELL' if m['fell'] else cell(m['overshoot_deg']),
                    cell(m['rest_time_s']), cell(m['rest_distance_m']), m['peak_torque_nm']))
    return lines


def plot_plan(path: str) -> None:
    """Save the default plan: pitch [deg], speed [m/s] and force [N] against time."""
    p = RobotParams()
    table = rise.rise_table(p, rise.RiseSpec(l=p.height_min))
    plt = pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    lift = table[rise.on_tail_rows(table), 0]
    for ax, col, label in zip(axes, (1, 4, 5), ('theta [deg]', 'x_dot [m/s]', 'u_ff [N]')):
        ax.plot(table[:, 0], np.degrees(table[:, col]) if col == 1 else table[:, col])
        ax.axvline(lift, color='k', lw=0.8, ls=':')
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel('t [s] (dotted: lift-off from the tail)')
    fig.suptitle('The planned rise at l = %.2f m' % p.height_min)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    """Print the table; save the figures into --output."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--output', default='rise_report')
    args = ap.parse_args(argv)
    os.makedirs(args.output, exist_ok=True)
    print('\n'.join(table_lines()))
    runs = {'planned rise': start_up(True, duration=3.0),
            'IDA-PBC rise': start_up(False, duration=3.0)}
    plot_runs(runs, os.path.join(args.output, 'rise_startup.png'),
              'Start-up from the tail, l = 0.37 m, model (1)')
    plot_plan(os.path.join(args.output, 'rise_plan.png'))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
