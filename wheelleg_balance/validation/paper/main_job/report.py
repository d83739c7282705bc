"""
main_job's report: ``report.md`` and ``report.json`` of a job.

report.md holds the tables and figures, this run beside the paper; report.json everything: per
run the metrics, criteria, comparisons, notes and loop statistics. docs/main_job.md explains
both.
"""
import json
import pathlib
from typing import List

import numpy as np

from .evaluate import fmt
from .params import ROBOTS
from ..table import DEG, IMU_OFFSET


def timing_text(r: dict) -> str:
    """sim_node's loop statistics of a run, as a phrase."""
    st = r.get('sim_node_loop') or {}
    if not st:
        return 'no sim_node loop statistics'
    if 'lockstep_timeouts' in st and r.get('clock') == 'lockstep':
        # Lateness only slows a lockstep run down; what could disturb it is a step taken
        # without its commands.
        return 'sim_node in lockstep: %d ticks at %.2f x real time, %d lockstep timeouts' % (
            st['ticks'], st['real_time_factor'], st['lockstep_timeouts'])
    return 'sim_node late on %.0f %% of %d ticks, %d resyncs' % (
        100.0 * st['late_share'], st['ticks'], st['resyncs'])


def _row(*cells) -> str:
    """Return a markdown table row; '|' inside a cell is escaped."""
    return '| %s |' % ' | '.join(str(c).replace('|', '\\|') for c in cells)


def verdict(r: dict) -> str:
    """Return a run's verdict in words (known findings marked)."""
    if r['passed']:
        return 'passed' + (' (known finding did not show)' if r['known_finding'] else '')
    return 'FAILED (known finding)' if r['known_finding'] else '**FAILED**'


def _head(results: List[dict], info: dict) -> List[str]:
    """Return the report's introduction and summary table (lines)."""
    lines = [
        '# main_job report', '',
        '%s; %s; Python %s; %d CPUs; %.0f s in all.' % (
            info['date'], info['platform'], info['python'], info['cpus'], info['elapsed_s']),
        '', 'balance_node against sim_node (MuJoCo) as separate processes: ROS 2 on localhost '
        '(ROS_DOMAIN_ID %s), CAN over udp_multicast (%s port %d), %s (wheel states '
        "from the wheel motors' replies, the four hips driven by balance_node); the driving "
        'experiments through teleop_node (%s) fed by a scripted joystick (joy_script), the '
        'height through its buttons and cmd_height. Each run starts folded on the tail as after '
        'power-up: armed, balance_node homes the hips, raises the legs and stands up. IMU '
        "offset d = %.1f deg in the simulated IMU. Figures from sim_node's ground truth unless "
        "marked, time 0 = the start of balancing. The paper's figures are not in the "
        'repository (only its text, Sec. V-C): the "paper" column quotes what its text reports '
        'about each figure.' % (
            info['ros_domain_id'], info['can_group'], info['udp_port'],
            ROBOTS.get(info.get('robot', ''), 'six MIT motors'),
            info['teleop_config'], IMU_OFFSET / DEG), '',
        '## Summary', '',
        '| experiment | paper | result | criteria met | headline: this run (paper) '
        '| wall time [s] |',
        '|---|---|---|---|---|---|']
    for r in results:
        ok = sum(c['ok'] for c in r['criteria'])
        head = '%s: %s (%s)' % (r['compare'][0][0], r['compare'][0][2], r['compare'][0][1]) \
            if r['compare'] else '-'
        lines.append(_row(r['experiment'], r['figure'], verdict(r),
                          '%d / %d' % (ok, len(r['criteria'])), head,
                          '%.0f' % r.get('wall_s', 0.0)))
    return lines + ['', 'Job verdict: **%s** (known findings do not fail the job).' % (
        'passed' if info['passed'] else 'FAILED'), '']


def _section(r: dict, has_fig3: bool) -> List[str]:
    """Return one run's section: verdict, paper beside this run, criteria, figure, timing."""
    lines = ['## %s: %s' % (r['experiment'], r['title']), '']
    lines.append('Result: %s. Controller at arming: `%s`%s; from the arm to balancing '
                 '(homing, raising the legs): %s s.' % (
                     verdict(r), r['controller'], ''.join(
                         ', `%s` = %s' % (k, fmt(v, '%.4g'))
                         for k, v in r['balance_overrides'].items()),
                     fmt(r['metrics'].get('t_homing_s'))))
    if r['known_finding']:
        lines.append('Known finding: %s.' % r['known_finding'])
    lines.append('')
    lines += ['| quantity | paper (%s) | this run |' % r['figure'], '|---|---|---|']
    lines.append(_row('what happens', r['paper'], 'see the criteria'))
    for q, p, o in r['compare']:
        lines.append(_row(q, p, o))
    lines += ['', '| criterion | bound | measured | met |', '|---|---|---|---|']
    for c in r['criteria']:
        lines.append(_row(c['name'], c['bound'], c['value'], 'yes' if c['ok'] else '**no**'))
    lines.append('')
    if r.get('joystick'):
        lines += ['Joystick script (teleop_node turns it into cmd_vel):', '']
        lines += ['    ' + j for j in r['joystick']]
        lines.append('')
    if r.get('figure_file'):
        lines += ['![%s](%s)' % (r['experiment'], r['figure_file']), '']
    if r['experiment'] == 'startup_lqr_soft' and has_fig3:
        lines += ["All start-up runs overlaid, as the paper's Fig. 3:", '',
                  '![fig3](fig3_startup.png)', '']
    lines.append('- real time: %s%s; balance_node: %s.' % (
        timing_text(r), ', sim time %.2f s behind the wall clock' % r['sim_lag_s']
        if r.get('sim_lag_s', 0.0) > 0.2 and r.get('clock') != 'lockstep' else '', ', '.join(
            '%s %s' % kv for kv in sorted(r.get('balance_node_loop', {}).items())) or '-'))
    if r.get('can_bus_load'):
        load = r['can_bus_load']
        lines.append('- CAN budget: %s wheels; the loads balance_node reported (median, max '
                     'of its statuses): %s.' % (load.get('protocol', '-'), ', '.join(
                         '%s %.1f %%' % (k.replace('_pct', ''), v)
                         for k, v in sorted(load.items()) if k.endswith('_pct')) or '-'))
    for d in r.get('discarded_attempts', []):
        lines.append('- an earlier attempt was discarded: %s' % d)
    for n in r['notes']:
        lines.append('- note: %s' % n)
    for f in r.get('after_stop', []):
        lines.append('- after the scripted ~/stop (expected, not counted): balance_node: %s' % f)
    lines.append('')
    return lines


def write_report(out: pathlib.Path, results: List[dict], info: dict) -> None:
    """report.md (tables and figures, ours beside the paper's) and report.json (everything)."""
    has_fig3 = (out / 'fig3_startup.png').exists()
    lines = _head(results, info)
    for r in results:
        lines += _section(r, has_fig3)
    (out / 'report.md').write_text('\n'.join(lines))
    doc = dict(info, experiments=[{k: v for k, v in r.items() if k != 'trace'}
                                  for r in results])
    (out / 'report.json').write_text(json.dumps(doc, indent=1, default=_json_default))


def _json_default(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)
