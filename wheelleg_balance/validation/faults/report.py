"""
fault_report: run the fault-injection suite against balance_node and summarize the reactions.

``fault_report [--only NAME,...] [--output FILE.json] [--list]`` runs the scenarios of
validation/faults/ (the ones test/test_faults.py asserts on; docs/faults.md describes them)
in this process: balance_node with its control loop in a thread, DDS on localhost in a domain
of its own, a python-can virtual bus with fake MIT motors, sim_node for the push, a subprocess for
SIGINT/SIGTERM. It prints one line per scenario (handled or not, time from fault to zero torque
on the bus, the checks that failed) and a summary: faults tried, handled, worst reaction time.
``--output`` also writes everything as JSON. Exit code 0 when every fault was handled, else 1.
"""
import argparse
import datetime
import json
import platform
import sys

from .suite import run_scenarios, SCENARIOS


def _ms(seconds) -> str:
    return '-' if seconds is None else '%.1f ms' % (1e3 * seconds)


def summarize(outcomes) -> dict:
    """Return the summary figures of a list of validation/faults/outcome.Outcome."""
    times = [(o.time_to_zero, o.name) for o in outcomes if o.time_to_zero is not None]
    worst = max(times) if times else (None, None)
    return {
        'tried': len(outcomes),
        'handled': sum(o.handled for o in outcomes),
        'not_handled': [o.name for o in outcomes if not o.handled],
        'worst_time_to_zero_s': worst[0],
        'worst_time_to_zero_scenario': worst[1],
    }


def main(argv=None) -> int:
    """Run the scenarios, print the table and the summary; exit 0 when all were handled."""
    parser = argparse.ArgumentParser(
        prog='fault_report', description='Run the fault-injection suite against balance_node.')
    parser.add_argument('--only', default='',
                        help='comma-separated scenario names (default: all; see --list)')
    parser.add_argument('--output', help='write the outcomes and the summary to this JSON file')
    parser.add_argument('--list', action='store_true', help='list the scenarios and exit')
    args = parser.parse_args(argv)
    if args.list:
        for name in SCENARIOS:
            print(name)
        return 0
    names = [n for n in args.only.split(',') if n] or list(SCENARIOS)
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        parser.error('unknown scenario(s): %s (see --list)' % ', '.join(unknown))

    print('%-26s %-8s %12s  %s' % ('scenario', 'handled', 'to zero', 'fault -> expected'))

    def progress(o):
        print('%-26s %-8s %12s  %s -> %s' % (o.name, 'yes' if o.handled else 'NO',
                                             _ms(o.time_to_zero), o.fault, o.expected),
              flush=True)
        for text in o.failures:
            print('%28s FAILED: %s' % ('', text), flush=True)

    outcomes = run_scenarios(names, progress=progress)
    summary = summarize(outcomes)
    print()
    print('faults tried: %d, handled: %d, worst time to zero torque: %s (%s)' % (
        summary['tried'], summary['handled'], _ms(summary['worst_time_to_zero_s']),
        summary['worst_time_to_zero_scenario']))
    if summary['not_handled']:
        print('not handled: %s' % ', '.join(summary['not_handled']))
    if args.output:
        report = {
            'date': datetime.datetime.now().isoformat(timespec='seconds'),
            'python': platform.python_version(), 'machine': platform.machine(),
            'summary': summary, 'outcomes': [o.as_dict() for o in outcomes],
        }
        with open(args.output, 'w') as f:
            json.dump(report, f, indent=2, default=str)
        print('written: %s' % args.output)
    return 0 if not summary['not_handled'] else 1


if __name__ == '__main__':
    sys.exit(main())
