"""
The margins on an identified robot against the default configuration (``margins_report --config``).

``margins_report --config robot.yaml [--config fitted.yaml ...] [--identify-report
identify_report.json | --extra-delay S]`` builds the configuration from balance_node parameter
files (later files override earlier ones: the robot's own, then identify's fitted file) and
certifies every controller (the ``default`` gain set: what balance_node runs) in three cases:

- ``default``: the default configuration on its own model, no extra delay (docs/margins.md);
- ``default on fitted``: the default configuration's controllers on the fitted robot with its
  motor delay: what the robot has when nobody identified it;
- ``fitted``: the fitted configuration's controllers (built from the fitted model, as
  balance_node builds them) on the fitted robot with its motor delay;
- ``fitted, with I`` (with ``--identify-report``): the same on a plant whose pendulum has the
  inertia about its centre of mass the fit found beyond model (1)'s point mass (the report's
  ``lumped``: J_a - m l^2, averaged over the heights; core/model.py ``linearize``).

The motor delay is identify's ``robot.motor_delay`` (or ``--extra-delay``), put into the loop
as whole ticks of 2 ms rounded up (core/margins.py ``delayed``, ``delay_ticks``): the margins
are what is left beyond it. It writes DIR/margins_fitted.md and DIR/img/margins_fitted.png and
prints which minima changed (by more than CHANGE_DB or CHANGE_S, or certified or not).
"""
import json
import math
import os
import pathlib
from typing import Dict, List, Sequence, Tuple

from ...core.config import BalanceConfig
from ...core.margins import (certify, delay_ticks, height_grid, Margins,
                             REQUIRED_DELAY_MARGIN_S, REQUIRED_GAIN_MARGIN_DB)
from ...core.pipeline import CONTROLLER_NAMES
from ...optional import pyplot

CASES = ('default', 'default on fitted', 'fitted', 'fitted, with I')
#: A minimum that moved by more than this is reported as changed [dB], [s].
CHANGE_DB, CHANGE_S = 0.5, 0.0005

Results = Dict[Tuple[str, str], List[Margins]]


def configuration(paths: Sequence[str]) -> BalanceConfig:
    """Return the checked configuration of balance_node files applied in order (ValueError)."""
    from ...bringup.robot_config import build, read_params
    flat: Dict = {}
    for p in paths:
        flat.update(read_params(pathlib.Path(p)))
    return build(flat)


def report_delay(path: str) -> float:
    """Return identify_report.json's ``robot.motor_delay`` [s] (KeyError if not fitted)."""
    with open(path) as f:
        return float(json.load(f)['quantities']['robot.motor_delay']['value'])


def report_inertia(path: str) -> float:
    """Return the pendulum's inertia beyond m l^2 [kg m^2] of identify_report.json (mean)."""
    with open(path) as f:
        lumped = json.load(f)['lumped']
    return sum(h['inertia_about_axle'] - h['mass'] * h['l'] ** 2 for h in lumped) / len(lumped)


def run(cfg: BalanceConfig, extra_delay: float, step: float = 0.01,
        inertia: float = 0.0) -> Results:
    """Return the Margins of every controller in CASES (the last with ``inertia`` > 0 only)."""
    base = BalanceConfig()
    ticks = delay_ticks(extra_delay, cfg.loop.control_period)
    out: Results = {}
    for c in CONTROLLER_NAMES:
        out[(c, CASES[0])] = certify(c, 'default', height_grid(step, base.model), base)
        fitted_heights = height_grid(step, cfg.model)
        out[(c, CASES[1])] = certify(c, 'default', fitted_heights, base, ticks, cfg.model)
        out[(c, CASES[2])] = certify(c, 'default', fitted_heights, cfg, ticks)
        if inertia > 0.0:
            out[(c, CASES[3])] = certify(c, 'default', fitted_heights, cfg, ticks,
                                         inertia=inertia)
    return out


def summary(ms: List[Margins]) -> Dict[str, float]:
    """Return the minima over the heights of GM up, GM down [dB], DM [s], and certified."""
    stable = [m for m in ms if m.stable]

    def low(name):
        return min((getattr(m, name) for m in stable), default=math.nan)
    return {'gm_up_db': low('gain_margin_up_db'), 'gm_down_db': low('gain_margin_down_db'),
            'dm_s': low('delay_margin_s'),
            'certified': bool(ms) and all(not m.shortfalls() for m in ms)}


def changes(results: Results) -> List[str]:
    """Return one line per controller and margin whose minimum changed, default -> fitted."""
    out = []
    for c in CONTROLLER_NAMES:
        a, b = summary(results[(c, 'default')]), summary(results[(c, 'fitted')])
        for key, unit, scale, tol in (('gm_up_db', 'dB', 1.0, CHANGE_DB),
                                      ('gm_down_db', 'dB', 1.0, CHANGE_DB),
                                      ('dm_s', 'ms', 1e3, CHANGE_S)):
            if not abs(b[key] - a[key]) <= tol:   # NaN (unstable) counts as changed
                out.append('%s: min %s %.2f -> %.2f %s' % (
                    c, {'gm_up_db': 'GM up', 'gm_down_db': 'GM down', 'dm_s': 'DM'}[key],
                    scale * a[key], scale * b[key], unit))
        if a['certified'] != b['certified']:
            out.append('%s: %s' % (c, 'no longer certified' if a['certified']
                                   else 'certified now'))
    return out


def markdown(results: Results, cfg: BalanceConfig, extra_delay: float,
             inertia: float = 0.0) -> str:
    """Return margins_fitted.md: the three cases' minima per controller and the changes."""
    ticks = delay_ticks(extra_delay, cfg.loop.control_period)
    m = cfg.model
    out = ['# Margins on the fitted robot', '',
           'Generated by `margins_report --config`: model body_mass %.3f kg, wheel_mass %.3f '
           'kg, wheel_radius %.4f m; motor delay %.2f ms in the loop as %d tick(s) of %.0f ms; '
           'pendulum inertia beyond m l^2 %.4f kg m^2. '
           'Required: gain margin >= %.0f dB both ways, delay margin >= %.0f ms.'
           % (m.body_mass, m.wheel_mass, m.wheel_radius, 1e3 * extra_delay, ticks,
              1e3 * cfg.loop.control_period, inertia, REQUIRED_GAIN_MARGIN_DB,
              1e3 * REQUIRED_DELAY_MARGIN_S), '',
           '| controller | case | min GM up [dB] | min GM down [dB] | min DM [ms] | '
           'certified |', '|---|---|---|---|---|---|']
    for (c, case), ms in results.items():
        s = summary(ms)
        out.append('| %s | %s | %.2f | %.2f | %.2f | %s |' % (
            c, case, s['gm_up_db'], s['gm_down_db'], 1e3 * s['dm_s'],
            'yes' if s['certified'] else '**no**'))
    lines = changes(results)
    out += ['', 'Changed, default -> fitted: %s.' % ('; '.join(lines) if lines else 'nothing'),
            '', '![margins on the fitted robot](img/margins_fitted.png)', '']
    return '\n'.join(out)


def plot(results: Results, path: str) -> None:
    """Save the delay margin and the smaller gain margin against l per controller and case."""
    plt = pyplot('margins_report')
    fig, axes = plt.subplots(2, len(CONTROLLER_NAMES), sharex='col', figsize=(11.0, 5.5))
    styles = dict(zip(CASES, ('-', ':', '--', '-.')))
    for k, c in enumerate(CONTROLLER_NAMES):
        for case in [case for case in CASES if (c, case) in results]:
            ms = results[(c, case)]
            h = [m.l for m in ms]
            axes[0][k].plot(h, [min(m.gain_margin_up_db, m.gain_margin_down_db) for m in ms],
                            'C0' + styles[case], label=case)
            axes[1][k].plot(h, [1e3 * m.delay_margin_s for m in ms], 'C2' + styles[case],
                            label=case)
        axes[0][k].axhline(REQUIRED_GAIN_MARGIN_DB, color='r', ls=':', lw=0.8)
        axes[1][k].axhline(1e3 * REQUIRED_DELAY_MARGIN_S, color='r', ls=':', lw=0.8)
        axes[0][k].set_title(c)
        axes[1][k].set_xlabel('height l [m]')
        for ax in (axes[0][k], axes[1][k]):
            ax.grid(True, alpha=0.3)
            ax.set_ylim(bottom=0.0)
    axes[0][0].set_ylabel('smaller gain margin [dB]')
    axes[1][0].set_ylabel('delay margin [ms]')
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def report(cfg: BalanceConfig, extra_delay: float, folder: str, step: float,
           inertia: float = 0.0) -> Results:
    """Run, write DIR/margins_fitted.md and its figure, print the changes; return results."""
    results = run(cfg, extra_delay, step, inertia)
    os.makedirs(os.path.join(folder, 'img'), exist_ok=True)
    plot(results, os.path.join(folder, 'img', 'margins_fitted.png'))
    with open(os.path.join(folder, 'margins_fitted.md'), 'w') as f:
        f.write(markdown(results, cfg, extra_delay, inertia))
    for (c, case), ms in results.items():
        s = summary(ms)
        print('%-18s %-18s min GM up %.2f dB, down %.2f dB, DM %.2f ms: %s' % (
            c, case, s['gm_up_db'], s['gm_down_db'], 1e3 * s['dm_s'],
            'certified' if s['certified'] else 'NOT certified'))
    print('changed, default -> fitted: %s' % ('; '.join(changes(results)) or 'nothing'))
    print('wrote %s' % os.path.join(folder, 'margins_fitted.md'))
    return results
