"""
main_job's plots: each run in its paper figure's layout, and the start-ups overlaid (Fig. 3).

A panel is one quantity over time since the start of balancing, from sim_node's ground truth
and balance_node's ~/state (the estimate beside the truth where there is one). Matplotlib with
the Agg backend (optional.pyplot).
"""
import pathlib
from typing import Dict, List

import numpy as np

from .record import Trace
from .scenarios import BY_NAME, Scenario, STARTUP_PANELS
from ..table import DEG, IMU_OFFSET
from ....optional import pyplot


def _theta(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, np.degrees(tr.g['theta']), label=label or 'theta (true)')
    if single:
        ax.plot(tr.ts, np.degrees(tr.s['theta']), label='theta~ (IMU = theta + d)', alpha=0.6)
    return 'theta [deg]'


def _theta_dot(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, np.degrees(tr.g['theta_dot']), label=label or 'theta_dot (true)')
    return 'theta_dot [deg/s]'


def _x(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, tr.g['x'], label='x (true)')
    if single:
        ax.plot(tr.ts, tr.s['x'], label='x (odometry, 0 at arm)', alpha=0.6)
    for b in exp.sim.get('bumps', []):
        ax.axhline(b, color='k', lw=0.6, ls=':')
    return 'x [m]'


def _x_dot(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, tr.g['x_dot'], label=label or 'x_dot (true)')
    if single:
        ax.plot(tr.ts, tr.s['x_dot'], label='x_dot (odometry)', alpha=0.6)
        if exp.joy:
            ax.plot(tr.ts, tr.s['x_dot_ref'], 'k--', lw=1.0, label='x_dot* (shaped)')
    return 'x_dot [m/s]'


def _yaw_rate(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, np.degrees(tr.g['yaw_rate']), label='yaw rate (true)')
    ax.plot(tr.ts, np.degrees(tr.s['yaw_rate_ref']), 'k--', lw=1.0, label='yaw rate* (shaped)')
    return 'yaw rate [deg/s]'


def _u(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.ts, tr.s['u'], label=label or 'u (applied)')
    return 'u [N]'


def _torques(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, tr.g['tau_left'], label='tau left')
    ax.plot(tr.tg, tr.g['tau_right'], label='tau right')
    return 'wheel torque [N m]'


def _d_hat(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.ts, np.degrees(tr.s['d_hat']), label='d_hat')
    ax.axhline(IMU_OFFSET / DEG, color='k', lw=0.8, ls='--', label='d (sim)')
    return 'd [deg]'


def _l(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, tr.g['l'], label='l (true)')
    ax.plot(tr.ts, tr.s['l'], label='l (leg kinematics)', alpha=0.6)
    if 'l_ref' in tr.s:
        ax.plot(tr.ts, tr.s['l_ref'], 'k--', lw=1.0, label='l_ref (shaped cmd_height)')
    if tr.th.size:
        ax.step(tr.th, tr.h['height'], 'g:', where='post', lw=1.0, label='cmd_height')
    return 'l [m]'


def _roll(ax, tr: Trace, exp: Scenario, label: str, single: bool) -> str:
    ax.plot(tr.tg, np.degrees(tr.g['roll']), label='roll (true)')
    return 'roll [deg]'


#: Panel name -> drawer(ax, trace, scenario, label, single) returning the y label.
PANELS: Dict[str, object] = {
    'theta': _theta, 'theta_dot': _theta_dot, 'x': _x, 'x_dot': _x_dot, 'yaw_rate': _yaw_rate,
    'u': _u, 'torques': _torques, 'd_hat': _d_hat, 'l': _l, 'roll': _roll,
}


def _panel(ax, name: str, tr: Trace, exp: Scenario, label: str = '', single: bool = True):
    """Draw one panel of the paper's layout (single: one run, with its estimates)."""
    ax.set_ylabel(PANELS[name](ax, tr, exp, label, single))
    ax.grid(True)


def plot(exp: Scenario, tr: Trace, path: pathlib.Path, result: dict) -> None:
    """Plot the experiment in its paper figure's layout: panels (a), (b), ... over time."""
    plt = pyplot()
    n = len(exp.panels)
    fig, axes = plt.subplots(n, 1, sharex=True, figsize=(8, 1.9 * n + 0.8))
    for k, (ax, name) in enumerate(zip(axes, exp.panels)):
        _panel(ax, name, tr, exp)
        ax.set_title('(%s) %s' % ('abcdefgh'[k], name), loc='left', fontsize=9)
        ax.legend(loc='upper right', fontsize=7)
        for t, pname, value in exp.actions:
            ax.axvline(t, color='r', lw=0.6, ls=':')
        ax.axvline(tr.t_arm, color='grey', lw=0.6, ls='--')   # the arm: homing, raising
    axes[-1].set_xlabel('time since the start of balancing [s] (grey dashed: the arm)')
    axes[-1].set_xlim(tr.t_arm - 0.5, tr.duration)
    paper = " (cf. the paper's %s)" % exp.figure if exp.figure else ' (not in the paper)'
    fig.suptitle('%s%s: %s' % (exp.name, paper, 'passed' if result['passed'] else 'FAILED'),
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_startups(results: List[dict], path: pathlib.Path) -> bool:
    """Overlay the start-up runs as the paper's Fig. 3: theta, theta_dot, x_dot, u."""
    runs = [r for r in results if r.get('trace') is not None and
            BY_NAME[r['experiment']].kind == 'startup']
    if len(runs) < 2:
        return False
    plt = pyplot()
    panels = STARTUP_PANELS
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(8, 8.4))
    for r in runs:
        exp = BY_NAME[r['experiment']]
        label = '%s (%s)' % (exp.name, 'passed' if r['passed'] else 'FAILED')
        for ax, name in zip(axes, panels):
            _panel(ax, name, r['trace'], exp, label=label, single=False)
    for k, (ax, name) in enumerate(zip(axes, panels)):
        ax.set_title('(%s) %s' % ('abcd'[k], name), loc='left', fontsize=9)
        ax.legend(loc='upper right', fontsize=7)
    axes[0].set_ylim(-40, 60)
    axes[-1].set_xlabel('time since the start of balancing [s]')
    axes[-1].set_xlim(-0.5, max(r['trace'].duration for r in runs))
    fig.suptitle("Start-up from the tail, IDA-PBC vs linear (cf. the paper's Fig. 3)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return True
