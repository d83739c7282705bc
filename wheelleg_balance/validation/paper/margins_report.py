"""
margins_report: the stability margins of every controller over the height range, as docs.

``margins_report [--docs DIR] [--step M]`` runs core/margins.py ``certify`` for every controller
(ida_pbc, output_regulation, lqr) at every gain set (default, table_i) on heights every
``--step`` [m] (default 5 mm) from height_min to height_max, and writes

- the tables into DIR/margins.md (default ./docs/margins.md, so run it from the repository's
  root), between the lines ``<!-- margins_report: begin -->`` and ``<!-- margins_report: end
  -->``; the text around them is kept (a file without the markers gets them appended);
- one figure per controller, DIR/img/margins_<controller>.png: gain margins up and down and
  the delay margin against l, both gain sets, with the 6 dB and 10 ms limits drawn.

It prints one line per controller and gain set. Exit code 0 when every case meets the required
margins at every height, 1 otherwise (the docs are written either way), 2 without matplotlib.

``margins_report --config FILE [--config FILE ...] [--identify-report FILE | --extra-delay S]
[--docs DIR]`` certifies an identified robot instead (margins_fitted.py: its configuration and
its motor delay against the default configuration; DIR defaults to the current folder then).
"""
import argparse
import datetime
import math
import os
import platform
import sys
from typing import Dict, List, Sequence, Tuple

import numpy as np
import scipy

from ...core.margins import (certify, GAIN_SETS, height_grid, Margins,
                             REQUIRED_DELAY_MARGIN_S, REQUIRED_GAIN_MARGIN_DB)
from ...core.pipeline import CONTROLLER_NAMES
from ...optional import missing, pyplot

BEGIN = '<!-- margins_report: begin -->'
END = '<!-- margins_report: end -->'
#: Spacing of the table rows [m] (the minima are taken over every height computed).
ROW_STEP = 0.05

Results = Dict[Tuple[str, str], List[Margins]]


def run(heights: Sequence[float]) -> Results:
    """Return certify's Margins for every (controller, gain set) at ``heights`` [m]."""
    return {(c, g): certify(c, g, heights) for c in CONTROLLER_NAMES for g in GAIN_SETS}


def _same(a: List[Margins], b: List[Margins]) -> bool:
    """Return True when two runs gave the same margins (e.g. default gains equal to Table I's)."""
    def key(m):
        return (m.stable, m.gain_margin_up_db, m.gain_margin_down_db, m.delay_margin_s)
    return [key(m) for m in a] == [key(m) for m in b]


def _fmt(v: float, scale: float = 1.0, digits: int = 2) -> str:
    if v != v:
        return 'n/a'
    if math.isinf(v):
        return 'inf'
    return '%.*f' % (digits, scale * v)


def minima(ms: List[Margins]) -> Dict[str, Tuple[float, float]]:
    """Return {margin name: (smallest value over the heights, the l [m] where it occurs)}."""
    out = {}
    for name in ('gain_margin_up_db', 'gain_margin_down_db', 'phase_margin_deg',
                 'delay_margin_s'):
        vals = [(abs(getattr(m, name)) if name == 'phase_margin_deg' else getattr(m, name), m.l)
                for m in ms if m.stable]
        out[name] = min(vals) if vals else (math.nan, math.nan)
    return out


def _ranges(ls: List[float], step: float) -> str:
    """Group heights [m] into 'a..b' ranges of neighbours ``step`` apart."""
    if not ls:
        return ''
    parts, start, prev = [], ls[0], ls[0]
    for h in ls[1:]:
        if h - prev > 1.5 * step:
            parts.append((start, prev))
            start = h
        prev = h
    parts.append((start, prev))
    return ', '.join('%.3f' % a if a == b else '%.3f..%.3f' % (a, b) for a, b in parts)


def shortfall_text(ms: List[Margins], step: float) -> str:
    """Return where and by how much a run falls short of the requirements ('' if nowhere)."""
    gm, dm = REQUIRED_GAIN_MARGIN_DB, REQUIRED_DELAY_MARGIN_S
    checks = (
        ('unstable', lambda m: not m.stable, None, ''),
        ('gain margin up < %.0f dB' % gm, lambda m: not m.gain_margin_up_db >= gm,
         'gain_margin_up_db', 'dB'),
        ('gain margin down < %.0f dB' % gm, lambda m: not m.gain_margin_down_db >= gm,
         'gain_margin_down_db', 'dB'),
        ('delay margin < %.0f ms' % (1e3 * dm), lambda m: not m.delay_margin_s >= dm,
         'delay_margin_s', 'ms'),
        ('delay margin not confirmed by extra ticks', lambda m: not m.delay_confirmed,
         None, ''))
    out = []
    for text, fails, name, unit in checks:
        bad = [m for m in ms if fails(m)]
        if not bad or (text != 'unstable' and all(not m.stable for m in bad)):
            continue
        bad = [m for m in bad if m.stable or text == 'unstable']
        where = '%s at l = %s m' % (text, _ranges([m.l for m in bad], step))
        if name is not None:
            scale = 1e3 if unit == 'ms' else 1.0
            vals = [scale * getattr(m, name) for m in bad]
            where += ' (%.2f..%.2f %s)' % (min(vals), max(vals), unit)
        out.append(where)
    return '; '.join(out)


def _table_rows(ms: List[Margins]) -> List[Margins]:
    """Rows every ROW_STEP from the first height, plus the last height."""
    first = ms[0].l
    rows = [m for m in ms
            if abs((m.l - first) / ROW_STEP - round((m.l - first) / ROW_STEP)) < 1e-6]
    if rows[-1] is not ms[-1]:
        rows.append(ms[-1])
    return rows


def markdown(results: Results, heights: Sequence[float]) -> str:
    """Return the generated part of docs/margins.md (between the markers, markers excluded)."""
    step = float(heights[1] - heights[0]) if len(heights) > 1 else 0.0
    out = ['', 'Generated by `margins_report` on %s: %d heights every %.1f mm from %.3f to '
           '%.3f m; Python %s, numpy %s, scipy %s, %s %s, %d CPUs.'
           % (datetime.date.today().isoformat(), len(heights), 1e3 * step, heights[0],
              heights[-1], platform.python_version(), np.__version__, scipy.__version__,
              platform.system(), platform.machine(), os.cpu_count() or 0),
           '', 'Required: stable, gain margin >= %.0f dB up and down, delay margin >= %.0f ms. '
           'Minima over all heights, the height where each occurs in brackets (phase margin: '
           'smallest |PM|).' % (REQUIRED_GAIN_MARGIN_DB, 1e3 * REQUIRED_DELAY_MARGIN_S), '',
           '| controller | gains | stable everywhere | min GM up [dB] | min GM down [dB] | '
           'min PM [deg] | min DM [ms] | certified |',
           '|---|---|---|---|---|---|---|---|']
    for (c, g), ms in results.items():
        mn = minima(ms)
        ok = all(not m.shortfalls() for m in ms)
        cells = ['%s (%.3f)' % (_fmt(v, scale), l) for (v, l), scale in zip(
            mn.values(), (1.0, 1.0, 1.0, 1e3))]
        out.append('| %s | %s | %s | %s | %s |' % (
            c, g, 'yes' if all(m.stable for m in ms) else '**no**', ' | '.join(cells),
            'yes' if ok else '**no**'))
    for c in CONTROLLER_NAMES:
        out += ['', '### %s' % c, '', '![%s margins](img/margins_%s.png)' % (c, c)]
        shown: List[str] = []
        for g in GAIN_SETS:
            ms = results[(c, g)]
            if any(_same(ms, results[(c, g0)]) for g0 in shown):
                continue   # e.g. a default that is Table I's: one table
            shown.append(g)
            same = [g2 for g2 in GAIN_SETS if g2 != g and _same(ms, results[(c, g2)])]
            out += ['', '**%s gains**' % ' = '.join([g] + same)]
            short = shortfall_text(ms, step)
            out += ['', 'Falls short: %s.' % short if short else 'Meets every requirement.', '',
                    '| l [m] | stable | spectral radius | GM up [dB] | GM down [dB] | PM [deg] '
                    '| DM [ms] | w_c [rad/s] | extra ticks stable |',
                    '|---|---|---|---|---|---|---|---|---|']
            for m in _table_rows(ms):
                out.append('| %.3f | %s | %.7f | %s | %s | %s | %s | %s | %d |' % (
                    m.l, 'yes' if m.stable else '**no**', m.spectral_radius,
                    _fmt(m.gain_margin_up_db), _fmt(m.gain_margin_down_db),
                    _fmt(m.phase_margin_deg, digits=1), _fmt(m.delay_margin_s, 1e3),
                    _fmt(m.crossover_rad_s, digits=1), m.delay_ticks))
    out.append('')
    return '\n'.join(out)


def plot(controller: str, results: Results, path: str) -> None:
    """Save gain margins up/down and the delay margin against l for both gain sets (Agg)."""
    plt = pyplot('margins_report')
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(7.0, 6.0))
    styles = {'default': '-', 'table_i': '--'}
    drawn: List[Tuple[str, List[Margins]]] = []
    for g in GAIN_SETS:
        ms = results[(controller, g)]
        for i, (g0, ms0) in enumerate(drawn):
            if _same(ms, ms0):
                drawn[i] = ('%s = %s' % (g0, g), ms0)
                break
        else:
            drawn.append((g, ms))
    for label, ms in drawn:
        ls = styles.get(label.split(' ')[0], '-')
        h = [m.l for m in ms]
        ax1.plot(h, [m.gain_margin_up_db for m in ms], 'C0' + ls, label='up, %s' % label)
        ax1.plot(h, [m.gain_margin_down_db for m in ms], 'C1' + ls, label='down, %s' % label)
        ax2.plot(h, [1e3 * m.delay_margin_s for m in ms], 'C2' + ls, label=label)
    ax1.axhline(REQUIRED_GAIN_MARGIN_DB, color='r', ls=':',
                label='required %.0f dB' % REQUIRED_GAIN_MARGIN_DB)
    ax2.axhline(1e3 * REQUIRED_DELAY_MARGIN_S, color='r', ls=':',
                label='required %.0f ms' % (1e3 * REQUIRED_DELAY_MARGIN_S))
    ax1.set_ylabel('gain margin [dB]')
    ax2.set_ylabel('delay margin [ms]')
    ax2.set_xlabel('height l [m]')
    ax1.set_ylim(bottom=0.0)
    ax2.set_ylim(bottom=0.0)
    ax1.set_title('%s: 2 ms loop, one tick of delay, broken at the wheel torque' % controller)
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc='best')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_doc(path: str, block: str) -> None:
    """Replace the text between the markers of ``path`` with ``block`` (append if absent)."""
    text = ''
    if os.path.exists(path):
        with open(path) as f:
            text = f.read()
    if BEGIN in text and END in text and text.index(BEGIN) < text.index(END):
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
    else:
        head = text if text else '# Stability margins\n\n'
        if not head.endswith('\n'):
            head += '\n'
        tail = '\n'
    with open(path, 'w') as f:
        f.write(head + BEGIN + '\n' + block + END + tail)


def _fitted(args, step: float) -> int:
    """``--config``: the identified robot against the default configuration (exit code)."""
    from . import margins_fitted
    try:
        cfg = margins_fitted.configuration(args.config)
        extra, inertia = args.extra_delay or 0.0, 0.0
        if args.identify_report:
            extra = margins_fitted.report_delay(args.identify_report)
            inertia = margins_fitted.report_inertia(args.identify_report)
    except (ValueError, KeyError, OSError) as e:
        print('margins_report: %s' % e, file=sys.stderr)
        return 1
    if not 0.0 <= extra < 1.0:
        print('margins_report: extra delay %g s outside [0, 1) s' % extra, file=sys.stderr)
        return 1
    results = margins_fitted.report(cfg, extra, args.docs or '.', step, max(inertia, 0.0))
    fitted = [ms for (c, case), ms in results.items() if case.startswith('fitted')]
    return 0 if all(not m.shortfalls() for ms in fitted for m in ms) else 1


def main(argv=None) -> int:
    """Entry point of the ``margins_report`` executable."""
    parser = argparse.ArgumentParser(
        prog='margins_report',
        description="Certify every controller's stability margins over the height range.")
    parser.add_argument('--docs', default=None,
                        help='docs folder: writes margins.md and img/margins_*.png (default: '
                        './docs, i.e. run from the repository root)')
    parser.add_argument('--step', type=float, default=None,
                        help='height step [m] (default 0.005; 0.01 with --config)')
    parser.add_argument('--config', action='append', default=[], metavar='FILE.yaml',
                        help="balance_node parameter files, in order (the robot's, then "
                        "identify's fitted.yaml): certify that robot against the default "
                        'configuration (writes DIR/margins_fitted.md; DIR default: .)')
    delay = parser.add_mutually_exclusive_group()
    delay.add_argument('--identify-report', metavar='FILE.json',
                       help="with --config: identify's report; its robot.motor_delay is "
                       'extra loop delay')
    delay.add_argument('--extra-delay', type=float, default=None, metavar='S',
                       help='with --config: extra loop delay [s] (the motor delay)')
    args = parser.parse_args(argv)
    step = args.step if args.step is not None else (0.01 if args.config else 0.005)
    if not 0.0 < step <= 0.33:
        parser.error('--step must be in (0, 0.33] m')
    if not args.config and (args.identify_report or args.extra_delay is not None):
        parser.error('--identify-report and --extra-delay go with --config')
    absent = missing(('matplotlib',), 'margins_report (its figures)')
    if absent:
        print('\n'.join(absent), file=sys.stderr)
        return 2
    if args.config:
        return _fitted(args, step)
    args.step = step
    args.docs = args.docs or 'docs'
    heights = height_grid(args.step)
    results = run(heights)
    img = os.path.join(args.docs, 'img')
    os.makedirs(img, exist_ok=True)
    for c in CONTROLLER_NAMES:
        plot(c, results, os.path.join(img, 'margins_%s.png' % c))
    write_doc(os.path.join(args.docs, 'margins.md'), markdown(results, heights))
    ok = True
    for (c, g), ms in results.items():
        mn = minima(ms)
        short = shortfall_text(ms, args.step)
        ok = ok and not short
        print('%-18s %-8s min GM up %s dB, down %s dB, DM %s ms: %s' % (
            c, g, _fmt(mn['gain_margin_up_db'][0]), _fmt(mn['gain_margin_down_db'][0]),
            _fmt(mn['delay_margin_s'][0], 1e3), short or 'certified'))
    print('wrote %s and %s/margins_*.png' % (os.path.join(args.docs, 'margins.md'), img))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
