"""
main_job's orchestration: start the processes of one run, arm, play the timeline, stop, judge.

Per run, fresh ``python -m`` processes: sim_node and balance_node with the parameter files of
main_job/params.py, and for the driving runs teleop_node fed by the joystick script. The robot
is armed at sim time ``ARM_AT`` once every node is up; balance_node homes the hips, raises the
legs on the tail and starts balancing: that is time 0, when the joystick script starts, and
the scenario's actions (parameter changes, disarm, re-arm, ~/stop) come at their times from
it; the run ends with the disarm. A failed run whose sim_node loop was starved of CPU (its own
late ticks, resyncs or lag behind the wall clock) is run once more (``run_with_retries``), and
the report names that stall.
"""
from dataclasses import dataclass
import math
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import time
from typing import Callable, Dict, List, Optional, Tuple

import yaml

from .evaluate import evaluate
from .params import balance_params, joy_script_doc, sim_params, teleop_scales, write_params
from .plots import plot
from .record import Recorder, Trace
from .report import timing_text, verdict
from .scenarios import ARM_AT, Scenario
from ..joy_script import describe, JoyScript
from ... import child_env
from ....processes import end_process

#: A run whose sim_node loop was this late (share of ticks) or resynced this often, or whose
#: sim time fell this far behind the wall clock [s] (one stall that long: balance_node controls
#: a frozen robot on old samples meanwhile), was starved of CPU: a failed run like that is run
#: once more (``--retries``), and the report names the stall (sim_node's own counts) and keeps
#: the failed attempt. Nothing else is retried: sim_node publishes UDP-only (nodes/dds.py), so
#: a sensor that goes silent while sim_node keeps time is balance_node's failure, not the
#: machine's (it used to count as starved too, when DDS stalls of sim_node were common).
DISTURBED_LATE_SHARE = 0.10
DISTURBED_RESYNCS = 5
DISTURBED_SIM_LAG = 0.1
#: A run's scenario may take this many times its duration of wall time (lockstep on a loaded
#: machine runs slower than real time), plus 10 s; then it ends with a note.
PLAY_WALL_FACTOR = 8.0
#: The run goes on this long past its duration [s of sim time] before the final disarm, so that
#: the recordings up to the duration all come from before it.
PLAY_MARGIN = 0.2
#: How long the nodes may take to come up, balance_node to accept the arm, and the homing and
#: raising of the legs to end in BALANCING [s] (wall clock; about 3 s of sim time).
STARTUP_TIMEOUT = 40.0
ARM_TIMEOUT = 5.0
BALANCING_TIMEOUT = 20.0
#: balance_node's ~/state modes (core/safety.py Mode).
MODE_BALANCING, MODE_FAULT = 1.0, 2.0
#: The nodes, in the order they are stopped.
STOP_ORDER = ('joy_script', 'teleop_node', 'balance_node', 'sim_node')


class Progress:
    """One line per step, with the time since the job started."""

    def __init__(self):
        self.t0 = time.monotonic()

    def __call__(self, text: str) -> None:
        print('[main_job %6.1f s] %s' % (time.monotonic() - self.t0, text), flush=True)


@dataclass
class RunSetup:
    """What every experiment of one job shares."""

    output: pathlib.Path
    can_group: str
    udp_port: int
    teleop_config: pathlib.Path
    short: bool = False
    #: sim_node and balance_node in lockstep (sim_node ``lockstep``, balance_node
    #: ``clock_source: imu_stamp``) rather than each on the wall clock.
    lockstep: bool = True
    #: The simulated robot's motors (params.ROBOTS; '': six MIT motors).
    robot: str = ''


def _start(args: List[str], log: pathlib.Path) -> subprocess.Popen:
    with open(log, 'w') as out:
        return subprocess.Popen([sys.executable, '-m'] + args, stdout=out,
                                stderr=subprocess.STDOUT,
                                env=child_env(dict(os.environ, PYTHONUNBUFFERED='1')))


def start_nodes(exp: Scenario, folder: pathlib.Path,
                setup: RunSetup) -> Tuple[Dict[str, subprocess.Popen], List[str]]:
    """Write the parameter files and start the run's nodes; returns them and the joystick lines."""
    write_params(folder / 'sim.yaml', 'sim_node',
                 sim_params(setup.can_group, setup.udp_port, exp, setup.lockstep, setup.robot))
    write_params(folder / 'balance.yaml', 'balance_node',
                 balance_params(setup.can_group, setup.udp_port, exp, setup.lockstep,
                                setup.robot))
    procs = {
        'sim_node': _start(['wheelleg_balance.nodes.sim_node', '--ros-args', '--params-file',
                            str(folder / 'sim.yaml')], folder / 'sim_node.log'),
        'balance_node': _start(['wheelleg_balance.nodes.balance_node', '--ros-args',
                                '--params-file', str(folder / 'balance.yaml')],
                               folder / 'balance_node.log'),
    }
    joy_lines: List[str] = []
    if exp.joy:
        teleop_yaml = folder / 'teleop.yaml'
        shutil.copyfile(setup.teleop_config, teleop_yaml)
        doc = joy_script_doc(exp, teleop_scales(teleop_yaml))
        (folder / 'joy_script.yaml').write_text(yaml.safe_dump(doc, sort_keys=False))
        joy_lines = describe(JoyScript.from_dict(doc))
        # In lockstep the pad and teleop_node's limits run on sim_node's /clock.
        sim_clock = ['-p', 'use_sim_time:=true'] if setup.lockstep else []
        procs['teleop_node'] = _start(['wheelleg_balance.nodes.teleop_node', '--ros-args',
                                       '--params-file', str(teleop_yaml)] + sim_clock,
                                      folder / 'teleop_node.log')
        procs['joy_script'] = _start(['wheelleg_balance.validation.paper.joy_script',
                                      '--config', str(teleop_yaml), '--script',
                                      str(folder / 'joy_script.yaml'), '--wait-start',
                                      '--ros-args'] + sim_clock,
                                     folder / 'joy_script.log')
    return procs, joy_lines


def _exited(procs: Dict[str, subprocess.Popen]) -> List[str]:
    return [n for n, p in procs.items() if p.poll() is not None]


def arm_when_ready(exp: Scenario, rec: Recorder, procs: Dict[str, subprocess.Popen],
                   log: Callable[[str], None],
                   notes: List[str]) -> Tuple[Optional[float], Optional[float]]:
    """
    Arm at ARM_AT s of sim time once every node is up; start the joystick at BALANCING.

    Returns the wall times of the arm and of the start of balancing (None when it did not
    happen; ``notes`` says why).
    """
    end = time.monotonic() + STARTUP_TIMEOUT
    while time.monotonic() < end and not _exited(procs):
        sim_t = rec.sim_time()
        ready = sim_t is not None and sim_t >= ARM_AT and rec.state
        if ready and exp.joy:
            ready = rec.start_client.service_is_ready() and \
                rec.node.count_publishers('cmd_vel') > 0
        if ready:
            break
        time.sleep(0.005)
    else:
        gone = _exited(procs)
        notes.append('%s exited before arming' % ', '.join(gone) if gone else
                     'nodes did not come up within %.0f s' % STARTUP_TIMEOUT)
        return None, None
    give_up = time.monotonic() + ARM_TIMEOUT
    while True:   # balance_node refuses to arm until every sensor is fresh
        resp = rec.arm(True)
        if (resp is not None and resp.success) or time.monotonic() > give_up:
            break
        time.sleep(0.1)
    if resp is None or not resp.success:
        notes.append('arm refused: %s' % (resp.message if resp else 'no answer'))
        return None, None
    t_arm = time.monotonic()
    log('%s: armed at sim time %.2f s (%s): %s'
        % (exp.name, rec.sim_time(), exp.controller, resp.message))
    t_bal = wait_balancing(rec, procs, t_arm, notes)
    if t_bal is None:
        return t_arm, None
    log('%s: balancing at sim time %.2f s, %.2f s after the arm' % (
        exp.name, rec.sim_time(), t_bal - t_arm))
    if exp.joy:
        r = rec.start_joystick()
        if r is None or not r.success:
            notes.append('joystick script did not start')
    return t_arm, t_bal


def wait_balancing(rec: Recorder, procs: Dict[str, subprocess.Popen], since: float,
                   notes: List[str]) -> Optional[float]:
    """Return the receipt time of the first BALANCING ~/state after ``since`` (None: none)."""
    end = time.monotonic() + BALANCING_TIMEOUT
    k = 0
    while time.monotonic() < end and not _exited(procs):
        rows = rec.state
        if 'mode' in rec.state_labels:
            i = 1 + rec.state_labels.index('mode')
            for row in rows[k:]:
                if row[0] >= since and row[i] == MODE_BALANCING:
                    return row[0]
                if row[0] >= since and row[i] == MODE_FAULT:
                    notes.append('balance_node faulted before balancing: %s' % (
                        '; '.join(rec.faults) or 'no reason seen'))
                    return None
            k = len(rows)
        time.sleep(0.005)
    notes.append('not balancing %.0f s after the arm' % BALANCING_TIMEOUT)
    return None


def act(rec: Recorder, name: str, value) -> Tuple[bool, str]:
    """Do one scenario action on balance_node; returns (done, what)."""
    if name == 'arm':
        r = rec.arm(bool(value))
        return (r is not None and r.success,
                '%s: %s' % ('arm' if value else 'disarm', r.message if r else 'no answer'))
    if name == 'stop':
        r = rec.stop()
        return r is not None and r.success, '~/stop: %s' % (r.message if r else 'no answer')
    r = rec.set_param(name, value)
    return r is not None and r.results[0].successful, '%s := %s' % (name, value)


def play(exp: Scenario, rec: Recorder, procs: Dict[str, subprocess.Popen], duration: float,
         log: Callable[[str], None], notes: List[str]) -> Dict[str, float]:
    """
    Do the scenario's actions at their times until ``duration`` after time 0 (now).

    The times are sim_node's (its ground truth), which is the wall clock's in a real-time run
    and slower in lockstep on a loaded machine. Returns {action: the wall time it was done}.
    """
    pending = sorted(exp.actions, key=lambda a: a[0])
    done: Dict[str, float] = {}
    start = rec.sim_time() or 0.0
    wall_end = time.monotonic() + PLAY_WALL_FACTOR * duration + 10.0
    while time.monotonic() < wall_end:
        now = (rec.sim_time() or start) - start
        if now >= duration + PLAY_MARGIN:
            break
        while pending and now >= pending[0][0]:
            t, name, value = pending.pop(0)
            done.setdefault(name, time.monotonic())
            ok, what = act(rec, name, value)
            log('%s: t = %.1f s: %s%s' % (exp.name, now, what, '' if ok else ' FAILED'))
            if not ok:
                notes.append('%s failed' % what)
        gone = _exited(procs)
        if gone:
            notes.append('%s exited during the run' % ', '.join(gone))
            break
        time.sleep(0.01)
    else:
        notes.append('sim time stood still: %.0f s of the run in %.0f s of wall time' % (
            (rec.sim_time() or start) - start, PLAY_WALL_FACTOR * duration + 10.0))
    return done


def sim_stats(log: pathlib.Path) -> Dict[str, float]:
    """
    sim_node's loop statistics from its last log line.

    ticks, late ticks, resyncs, late_share; and where printed the real-time factor (simulated
    over wall time) and the lockstep timeouts (ticks that stepped without their commands).
    """
    text = log.read_text(errors='replace')
    found = re.search(r'stopped after (\d+) ticks \((\d+) late, (\d+) resyncs\)', text)
    if not found:
        return {}
    ticks, late, resyncs = (int(v) for v in found.groups())
    out = {'ticks': ticks, 'late_ticks': late, 'resyncs': resyncs,
           'late_share': late / ticks if ticks else 0.0}
    more = re.search(r'real-time factor ([0-9.]+|nan), (\d+) lockstep timeouts', text)
    if more:
        out['real_time_factor'] = float(more.group(1))
        out['lockstep_timeouts'] = int(more.group(2))
    return out


def timing_disturbed(sim_loop: Dict[str, float], lag: float) -> bool:
    """Return True when sim_node's own loop was starved of CPU (see DISTURBED_LATE_SHARE)."""
    return bool(sim_loop.get('late_share', 0.0) > DISTURBED_LATE_SHARE or
                sim_loop.get('resyncs', 0) >= DISTURBED_RESYNCS or lag > DISTURBED_SIM_LAG)


def run_experiment(exp: Scenario, rec: Recorder, setup: RunSetup, log: Progress) -> dict:
    """Run one experiment; returns its result (see ``evaluate``) with the recordings."""
    folder = setup.output / exp.name
    folder.mkdir(parents=True, exist_ok=True)
    duration = exp.duration_for(setup.short)
    rec.clear()
    mcap = rec.start_mcap(folder / ('%s.mcap' % exp.name))   # every topic, for the viewers
    wall0 = time.monotonic()
    procs, joy_lines = start_nodes(exp, folder, setup)
    log('%s: started %s' % (exp.name, ', '.join(procs)))
    notes: List[str] = []
    t_arm = t_bal = None
    done: Dict[str, float] = {}
    try:
        t_arm, t_bal = arm_when_ready(exp, rec, procs, log, notes)
        if t_bal is not None:
            done = play(exp, rec, procs, duration, log, notes)
        if t_arm is not None:
            rec.arm(False)
    finally:
        for name in STOP_ORDER:
            if name in procs:
                end_process(procs[name], signal.SIGINT, 5.0)
        rec.stop_mcap()
    # After a scripted ~/stop the robot falls as it must (a torque cut): its faults then are
    # reported, not counted against the run.
    t_stop = done.get('stop', math.inf)
    faults = [f for f in rec.faults if rec.fault_times.get(f, -math.inf) < t_stop]
    notes += ['balance_node: %s' % f for f in faults]
    for name, p in procs.items():
        if p.returncode not in (0, -signal.SIGINT):
            notes.append('%s exit code %s (see %s.log)' % (name, p.returncode, name))
    rec.save_csv(folder)
    trace = Trace(rec, t_bal, duration, t_arm) if t_bal is not None and rec.gt and \
        rec.state else None
    result = evaluate(exp, trace, notes)
    result['duration_s'] = duration
    result['wall_s'] = time.monotonic() - wall0
    result['joystick'] = joy_lines
    result['folder'] = exp.name
    result['mcap_file'] = '%s/%s.mcap' % (exp.name, exp.name) if mcap is not None else None
    result['sim_node_loop'] = sim_stats(folder / 'sim_node.log')
    result['clock'] = 'lockstep' if setup.lockstep else 'wall'
    result['balance_node_loop'] = dict(rec.loop)
    result['can_bus_load'] = rec.bus_load_summary()
    lag = trace.sim_lag() if trace is not None else 0.0
    result['after_stop'] = [f for f in rec.faults if f not in faults]
    # In lockstep a slow machine only slows the run (sim_lag, late ticks); a step without its
    # commands is the one disturbance, and it is reported.
    result['timing_disturbed'] = \
        result['sim_node_loop'].get('lockstep_timeouts', 0) > 0 if setup.lockstep else \
        timing_disturbed(result['sim_node_loop'], lag)
    if trace is not None:
        result['sim_lag_s'] = lag
        plot(exp, trace, folder / ('%s.png' % exp.name), result)
        result['figure_file'] = '%s/%s.png' % (exp.name, exp.name)
    result['trace'] = trace
    return result


def run_with_retries(exp: Scenario, rec: Recorder, setup: RunSetup, log: Progress,
                     retries: int) -> dict:
    """Run an experiment; again (at most ``retries`` times) while it fails starved of CPU."""
    discarded = []
    while True:
        r = run_experiment(exp, rec, setup, log)
        failed = [c['name'] for c in r['criteria'] if not c['ok']]
        log('%s: %s in %.0f s%s%s' % (
            exp.name, verdict(r), r['wall_s'],
            ' (not met: %s)' % ', '.join(failed) if failed else '',
            '; %s' % timing_text(r) if r['timing_disturbed'] else ''))
        for n in r['notes']:
            log('%s: note: %s' % (exp.name, n))
        if r['passed'] or not r['timing_disturbed'] or len(discarded) >= retries or \
                setup.lockstep:   # in lockstep a slow machine only slows the run down
            break
        discarded.append('failed (%s) with %s, sim time up to %.2f s behind the wall clock'
                         % (', '.join(failed), timing_text(r), r.get('sim_lag_s', 0.0)))
        log('%s: the CPU was too busy for a real-time run: running it again' % exp.name)
    r['discarded_attempts'] = discarded
    return r
