"""
identify: the robot's model from the three phases, as a report and a balance_node file.

``identify --sim [--sim-params FILE.yaml] [--output DIR] [--short]`` plays the phases on the
MuJoCo robot in-process (excite.py; FILE.yaml is a sim_node parameter file whose ``robot.*``
and ``imu_pitch_offset`` give the variant, default: the default robot) and fits them; it writes
into DIR (default ``./identify``) the recordings (``recordings/<phase>.mcap``, when the mcap
packages are there), ``identify_report.json`` (with the simulator's own values beside the
fitted ones), ``fitted.yaml`` (balance_node parameters, loaded after the robot's own file) and
``identify_<phase>.png`` (measured against predicted, and the residual). ``--short``: shorter
phases (the tests; the targets are not met that way).

``identify --recording DIR_OR_MCAP --config robot.yaml --output fitted.yaml`` fits MCAP
recordings offline: a folder's ``*.mcap`` files, or one file, each named after its phase
(``stand*.mcap``, ``tail*.mcap``, ``balance*.mcap``); or ``--window PHASE=START:END`` (s of
log time since the file's first message, repeatable) to take the phases out of one recording.
The leg geometry is the config's (``leg.*``). The report and the plots go beside the output.

``identify --phase stand|tail|balance --config robot.yaml --output fitted.yaml`` on a robot:
asks the running balance_node (``--node``) to play the phase (its excitation mode,
``~/excite/<phase>``, core/excitation.py; docs/identification.md), records it into
``recordings/<phase>.mcap`` beside the output (live.py) and fits the phases recorded there:
with all three, the fitted file; else the report and the phases missing (exit code 1).
balance_node must publish ~/state at the control rate (``state_publish_rate: 500``).
Exit code 0 when fitted, 1 when a phase is missing or a fit fails (with the reason), 2 for
missing packages.
"""
import argparse
from dataclasses import asdict
import json
import os
import pathlib
import sys
import time
from typing import Dict, List, Optional, Tuple

import numpy as np

from . import excite, fit, study
from .params import balance_params, params_yaml
from .records import PHASES, read_mcap, Record, STATE, write_mcap
from ..core.kinematics import FiveBarLeg
from ..core.schema import from_flat
from ..optional import MissingDependency, pyplot
from ..sim.config import RobotBodyConfig, SimConfig

#: The --short phases: stand and tail durations [s], the balance's heights [m], settle, sweep [s].
SHORT = {'stand': 1.5, 'tail': 2.0, 'heights': (0.37, 0.55), 'settle': 0.5, 'sweep': 2.0}


def sim_variant(path: Optional[str]) -> Tuple[RobotBodyConfig, float]:
    """Return (robot.*, imu_pitch_offset [rad]) of a sim_node parameter file (None: defaults)."""
    flat: Dict = {}
    if path:
        from ..bringup.robot_config import read_params
        flat = read_params(pathlib.Path(path), 'sim_node')
    body = from_flat(RobotBodyConfig, {k[len('robot.'):]: v for k, v in flat.items()
                                       if k.startswith('robot.')})
    d = float(flat.get('imu_pitch_offset', SimConfig().imu_pitch_offset))
    return body, d


def play(body: RobotBodyConfig, d: float, short: bool) -> Dict[str, Record]:
    """Return the three phases' Records played on the variant (``--short``: SHORT)."""
    if not short:
        return excite.play_all(body, d)
    return {'stand': excite.play_stand(body, d, SHORT['stand']),
            'tail': excite.play_tail(body, d, SHORT['tail']),
            'balance': excite.play_balance(body, d, SHORT['heights'], settle=SHORT['settle'],
                                           sweep=SHORT['sweep'])}


def recordings(source: str, windows: List[str]) -> Dict[str, Record]:
    """Return the phases' Records of an MCAP file or folder (module docstring; ValueError)."""
    path = pathlib.Path(source)
    if windows:
        if not path.is_file():
            raise ValueError('--window needs one MCAP file, not %s' % path)
        out = {}
        for w in windows:
            phase, _, span = w.partition('=')
            start, _, end = span.partition(':')
            if phase not in PHASES or not start or not end:
                raise ValueError('--window %r: PHASE=START:END, PHASE one of %s'
                                 % (w, ', '.join(PHASES)))
            out[phase] = read_mcap(path, phase, float(start), float(end))
        return out
    files = sorted(path.glob('*.mcap')) if path.is_dir() else [path]
    out = {}
    for f in files:
        phase = next((p for p in PHASES if f.name.startswith(p)), None)
        if phase is None:
            raise ValueError('%s: the name does not start with a phase (%s)'
                             % (f, ', '.join(PHASES)))
        if phase in out:
            raise ValueError('two recordings of the %s phase in %s' % (phase, path))
        out[phase] = read_mcap(f, phase)
    if not out:
        raise ValueError('no .mcap file in %s' % path)
    return out


def leg_of(config: Optional[str]) -> FiveBarLeg:
    """Return the leg geometry of a balance_node parameter file (None: the default's)."""
    if not config:
        return FiveBarLeg()
    from ..bringup.robot_config import build, read_params
    from ..core.sensing import five_bar
    return five_bar(build(read_params(pathlib.Path(config))))


def plot(phase: str, series: fit.Series, path: str) -> None:
    """Write one phase's measured against predicted (top) and the residual (bottom)."""
    plt = pyplot('identify (its plots)')
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True,
                             gridspec_kw={'height_ratios': [3, 1]})
    for label, t, measured, predicted in series.curves:
        # Break the lines where samples were left out (the gaps between runs, the pulses).
        gaps = np.flatnonzero(np.diff(t) > 1.5 * np.median(np.diff(t))) + 1
        t0, measured, predicted = (np.insert(np.asarray(x, float), gaps, np.nan)
                                   for x in (t - t[0], measured, predicted))
        line, = axes[0].plot(t0, measured, lw=0.8, label='%s measured' % label)
        axes[0].plot(t0, predicted, '--', lw=0.8, color=line.get_color(),
                     label='%s predicted' % label)
        axes[1].plot(t0, measured - predicted, lw=0.6, color=line.get_color())
    axes[0].set_ylabel('%s [%s]' % (series.quantity, series.unit))
    axes[0].set_title('identify, %s phase: measured against the fit' % phase)
    axes[0].legend(fontsize=7, loc='upper right')
    axes[1].set_ylabel('residual [%s]' % series.unit)
    axes[1].set_xlabel('time in the recording [s] (samples the fit used)')
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(report: Dict, series: Dict[str, fit.Series], folder: str,
                  fitted_path: str) -> List[str]:
    """Write the report, the fitted file (three phases) and the plots; return the paths."""
    os.makedirs(folder, exist_ok=True)
    written = []
    report_path = os.path.join(folder, 'identify_report.json')
    with open(report_path, 'w') as f:
        json.dump(report, f, indent=2)
    written.append(report_path)
    if 'lumped' in report:
        pathlib.Path(fitted_path).write_text(params_yaml(balance_params(report)))
        written.append(fitted_path)
    for phase, s in series.items():
        path = os.path.join(folder, 'identify_%s.png' % phase)
        plot(phase, s, path)
        written.append(path)
    return written


def print_table(report: Dict, comparison: Optional[Dict] = None) -> None:
    """Print each quantity: value, 95 % interval (and the simulator's value, the error)."""
    marks = {True: 'within target', False: 'OUTSIDE target', None: 'no target'}
    for name, q in report['quantities'].items():
        value, (lo, hi) = q['value'], q['interval']
        if isinstance(value, list):   # body_com: x, z
            rows = [('%s.%s' % (name, a), v, l, h) for a, v, l, h in zip('xz', value, lo, hi)]
        else:
            rows = [(name, value, lo, hi)]
        for key, v, l, h in rows:
            line = '%-22s %-11.5g [%.5g, %.5g] %s' % (key, v, l, h, q['unit'])
            c = (comparison or {}).get(key)
            if c is not None:
                line += '   simulator %.5g: %s' % (c['true'], marks[c['ok']])
            print(line)
    print('residuals (RMS): %s' % ', '.join('%s %.3g' % kv for kv in report['residuals'].items()))


def record_live(phase: str, node: str, folder: str) -> str:
    """Play ``phase`` on the running balance_node, write ``folder/<phase>.mcap``; return folder."""
    from .live import record_phase
    rec = record_phase(phase, node)
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, phase + '.mcap')
    write_mcap(path, rec)
    print('identify: %s recorded (%.1f s) into %s' % (phase, rec[STATE].t[-1] - rec[STATE].t[0],
                                                      path))
    return folder


def main(argv=None) -> int:
    """Entry point of the ``identify`` executable."""
    parser = argparse.ArgumentParser(
        prog='identify', description='Fit the robot model (model (1) plus the wheel inertia, '
        'damping and motor delay) from the stand, tail and balance phases.',
        epilog='On a robot, --phase asks the running balance_node to play a phase '
        '(~/excite/<phase>; state_publish_rate: 500), records it into the recordings folder '
        'beside --output and fits the phases there once all three are (docs/identification.md).')
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument('--sim', action='store_true',
                        help='play the phases on the MuJoCo robot in-process, then fit')
    source.add_argument('--recording', metavar='DIR_OR_MCAP',
                        help='fit MCAP recordings: a folder or a file named after its phase')
    source.add_argument('--phase', choices=PHASES,
                        help='on a robot: play this phase on the running balance_node, record '
                        'it beside --output (recordings/<phase>.mcap), fit what is there')
    parser.add_argument('--node', default='/balance_node',
                        help='--phase: the balance_node to ask (default /balance_node)')
    parser.add_argument('--sim-params', metavar='FILE.yaml',
                        help='--sim: a sim_node parameter file (robot.*, imu_pitch_offset)')
    parser.add_argument('--short', action='store_true', help='--sim: short phases (tests)')
    parser.add_argument('--config', metavar='ROBOT.yaml',
                        help="--recording: the robot's balance_node file (its leg geometry)")
    parser.add_argument('--window', action='append', default=[], metavar='PHASE=START:END',
                        help='--recording: a phase as a span of one file [s since its start]')
    parser.add_argument('--output', help='--sim: the output folder (default ./identify); '
                        '--recording: the fitted balance_node file (default ./fitted.yaml)')
    args = parser.parse_args(argv)
    if args.sim and (args.config or args.window):
        parser.error('--config and --window go with --recording')
    if not args.sim and (args.sim_params or args.short):
        parser.error('--sim-params and --short go with --sim')
    start = time.monotonic()
    comparison = None
    try:
        if args.sim:
            folder = args.output or 'identify'
            fitted_path = os.path.join(folder, 'fitted.yaml')
            body, d = sim_variant(args.sim_params)
            records = play(body, d, args.short)
            leg = FiveBarLeg()
        else:
            fitted_path = args.output or 'fitted.yaml'
            folder = os.path.dirname(os.path.abspath(fitted_path))
            source = args.recording
            if args.phase:
                source = record_live(args.phase, args.node, os.path.join(folder, 'recordings'))
            records = recordings(source, args.window)
            leg = leg_of(args.config)
        if 'stand' not in records:
            print('identify: no stand phase: every fit needs it', file=sys.stderr)
            return 1
        series: Dict[str, fit.Series] = {}
        report = fit.identify(records, leg, series=series)
        if args.sim:
            comparison = study.compare(report, body, d)
            report['simulator'] = comparison
            report['sim_variant'] = {'robot': asdict(body), 'imu_pitch_offset': d}
            try:
                os.makedirs(os.path.join(folder, 'recordings'), exist_ok=True)
                for phase, rec in records.items():
                    write_mcap(os.path.join(folder, 'recordings', phase + '.mcap'), rec)
            except (MissingDependency, ImportError) as e:
                print('identify: recordings not written (%s)' % e, file=sys.stderr)
        report['seconds'] = time.monotonic() - start
        written = write_outputs(report, series, folder, fitted_path)
    except MissingDependency as e:
        print('identify: %s' % e, file=sys.stderr)
        return 2
    except (ValueError, KeyError, RuntimeError, OSError) as e:   # live.PhaseError too
        print('identify: %s' % e, file=sys.stderr)
        return 1
    print_table(report, comparison)
    print('phases fitted: %s (%.0f s)' % (', '.join(report['phases']), report['seconds']))
    print('wrote %s' % ', '.join(written))
    if 'lumped' not in report:
        print('identify: no fitted file: it needs the three phases (%s missing)'
              % ', '.join(p for p in PHASES if p not in report['phases']), file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
