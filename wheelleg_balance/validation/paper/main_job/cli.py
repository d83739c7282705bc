"""
main_job: the paper's experiments 1-8 (Sec. V-B) with the real processes against the sim robot.

The command line of ``main_job``: which experiments (``--only``, ``--list``; the main_job entries
of validation/paper/table.py), ``--short`` runs, the CAN group and port, the teleop file, the
retries of a run starved of CPU; then one run per experiment (main_job/orchestrate.py), the
overlaid start-ups, and the report (main_job/report.py). Exit code 0 when every experiment met
its criteria (a known finding is reported as failed but does not fail the job).
"""
import argparse
import os
import pathlib
import platform
import sys
import time
from typing import List

from .orchestrate import Progress, run_with_retries, RunSetup
from .params import config_dir, ROBOTS
from .plots import plot_startups
from .record import Recorder
from .report import write_report
from .scenarios import BY_NAME, SCENARIOS
from ....optional import missing


def parser() -> argparse.ArgumentParser:
    """Return main_job's argument parser."""
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    p.add_argument('--output', default='output/main_job_%s' % time.strftime('%Y%m%d_%H%M%S'),
                   help='folder for the report, plots, data and logs')
    p.add_argument('--only', default='', help='comma-separated experiments (%s)' % ', '.join(
        e.name for e in SCENARIOS))
    p.add_argument('--short', action='store_true',
                   help='shorter start-up and standing runs (CI)')
    p.add_argument('--list', action='store_true', help='list the experiments and exit')
    p.add_argument('--clock', choices=('lockstep', 'wall'), default='lockstep',
                   help="lockstep (default): sim_node steps on balance_node's commands and "
                   "balance_node ticks on sim_node's IMU stamps, the same closed loop on a "
                   'busy machine, only slower; wall: both in real time on their own clocks, '
                   'as on the robot (a loaded machine disturbs it)')
    p.add_argument('--retries', type=int, default=1,
                   help='with --clock wall: runs again a failed experiment whose sim_node '
                        'loop was starved of CPU, at most this many times (default 1)')
    p.add_argument('--teleop-config', default='',
                   help='teleop_node parameter file (default: config/teleop_xbox.yaml)')
    p.add_argument('--robot', default='', choices=[''] + list(ROBOTS),
                   help="the simulated robot's motors (default: six MIT motors); %s" % '; '.join(
                       '%s: %s' % kv for kv in ROBOTS.items()))
    p.add_argument('--can-group', default='', help='udp_multicast group of the CAN bus '
                   '(default: one of 239.74.0.0/16 from the process id)')
    p.add_argument('--udp-port', type=int, default=0,
                   help='udp_multicast port (default: from the process id)')
    return p


def _setup(args: argparse.Namespace) -> RunSetup:
    """Return the job's shared set-up; CAN group and port from the process id by default."""
    out = pathlib.Path(args.output).resolve()
    out.mkdir(parents=True, exist_ok=True)
    pid = os.getpid()
    return RunSetup(
        output=out, short=args.short, lockstep=args.clock == 'lockstep',
        can_group=args.can_group or '239.74.%d.%d' % ((pid >> 8) % 256, pid % 256 or 1),
        udp_port=args.udp_port or 40000 + pid % 20000,
        teleop_config=pathlib.Path(args.teleop_config) if args.teleop_config else
        config_dir() / 'teleop_xbox.yaml', robot=args.robot)


def main(argv=None) -> int:
    """Run the experiments; write plots, report.md and report.json into --output."""
    p = parser()
    args = p.parse_args(argv)
    if args.list:
        for e in SCENARIOS:
            print('%-17s %-8s %s' % (e.name, e.figure, e.title))
        return 0
    names = [n for n in args.only.split(',') if n]
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        p.error('no such experiment: %s (see --list)' % ', '.join(unknown))
    chosen = [e for e in SCENARIOS if not names or e.name in names]
    # Say before the first run, not minutes later, what the simulator and the figures lack.
    absent = missing(('mujoco', 'matplotlib'), 'main_job')
    if absent:
        print('\n'.join(absent), file=sys.stderr)
        return 2
    setup = _setup(args)
    out = setup.output
    # ROS isolation (main_job.sh sets these too); the node processes inherit them.
    pid = os.getpid()
    os.environ.setdefault('ROS_DOMAIN_ID', str(100 + pid % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    import rclpy
    log = Progress()
    log('%d experiment(s) into %s (ROS_DOMAIN_ID %s, CAN %s:%d)' % (
        len(chosen), out, os.environ['ROS_DOMAIN_ID'], setup.can_group, setup.udp_port))
    rclpy.init()
    rec = Recorder()
    results: List[dict] = []
    info = {'date': time.strftime('%Y-%m-%d %H:%M:%S'), 'platform': platform.platform(),
            'python': platform.python_version(), 'cpus': os.cpu_count() or 0,
            'ros_domain_id': os.environ['ROS_DOMAIN_ID'], 'can_group': setup.can_group,
            'udp_port': setup.udp_port, 'teleop_config': str(setup.teleop_config),
            'short': args.short, 'clock': args.clock, 'robot': args.robot or 'mit',
            'experiments_run': [e.name for e in chosen]}
    try:
        for exp in chosen:
            results.append(run_with_retries(exp, rec, setup, log, args.retries))
    finally:
        rec.close()
        rclpy.try_shutdown()
    if plot_startups(results, out / 'fig3_startup.png'):
        log('fig3_startup.png: the start-up runs overlaid')
    info['elapsed_s'] = time.monotonic() - log.t0
    info['passed'] = bool(results) and all(r['passed'] or r['known_finding'] for r in results)
    write_report(out, results, info)
    log('%s; report: %s' % ('passed' if info['passed'] else 'FAILED', out / 'report.md'))
    print(out, flush=True)
    return 0 if info['passed'] else 1


if __name__ == '__main__':
    sys.exit(main())
