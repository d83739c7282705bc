"""
balance_node's processes: the lockstep clock's guards, the children's package, a failed start.

- ``clock_source: imu_stamp`` (a simulator in lockstep) runs only on a test bus, and there a
  dead IMU stops the ticks but not the safety: after ``lockstep_wall_timeout`` of wall time
  without a sample the loop faults imu_stale with zero torque; only ticks beat the watchdog's
  heartbeat, and the watchdog's limit there is that timeout plus ``watchdog_timeout``.
- The control process, the sensor intake and the watchdog import the package their parent
  runs, never a copy in the working directory (processes.py).
- A child that cannot start is one line (what, why, the fix) with which the node exits; its
  traceback only with WHEELLEG_BALANCE_TRACEBACK=1.

The node runs here as ``ros2 run`` starts it: a script whose own folder holds no package, the
package on PYTHONPATH (the one these tests import). SIGKILL of the node itself is a fault
scenario (test_faults.py ``balance_node_killed``).
"""
import math
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid

import can
from can.interfaces.virtual import VirtualBus
import pytest
from test_watchdog import FakeTime   # a helper of this folder: a clock moved by sleeping

import wheelleg_balance
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.schema import with_changes
from wheelleg_balance.core.sensors import ImuSample
from wheelleg_balance.nodes import control_link as L
from wheelleg_balance.nodes import watchdog as wd
from wheelleg_balance.nodes.control_process import make_runner
from wheelleg_balance.validation.faults import scenarios
from wheelleg_balance.validation.faults.bench import quaternion_pitch
from wheelleg_balance.validation.faults.doubles import FakeMotors, MOTOR_IDS, TORQUE_LSB
from wheelleg_balance.validation.faults.rig import wait_for

#: The folder the package of these tests comes from (the source tree or the install).
PACKAGE_PARENT = str(pathlib.Path(wheelleg_balance.__file__).resolve().parent.parent)
#: balance_node as its installed script runs it (sys.path[0] is not the working directory).
NODE = [sys.executable, '-P', '-c', 'import sys\nfrom wheelleg_balance.nodes.balance_node '
        'import main\nsys.exit(main())']
CHILD_MODULES = ('wheelleg_balance.nodes.control_process', 'wheelleg_balance.nodes.watchdog',
                 'wheelleg_balance.nodes.sensor_intake')
PERIOD_NS = 2_000_000
#: lockstep_wall_timeout's default [s] (test_config.py holds it there).
LOCKSTEP_WALL_TIMEOUT = 1.0


def _env(**extra):
    env = dict(os.environ, PYTHONUNBUFFERED='1', **extra)
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (PACKAGE_PARENT, os.environ.get('PYTHONPATH')) if p)
    env.pop('WHEELLEG_BALANCE_TRACEBACK', None)
    env.update(extra)
    return env


def _params(**params):
    out = ['--ros-args']
    for name, value in params.items():
        out += ['-p', '%s:=%s' % (name, value)]
    return out


def _own_lines(stderr: str):
    """Return the lines of stderr that are not ROS log records ('[WARN] [...]: ...')."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith('[')]


def _run_to_end(cwd, env=None, **params):
    proc = subprocess.run(NODE + _params(**params), cwd=cwd, env=env or _env(),
                          capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stderr


# ----------------------------------------------------------------- the lockstep clock

def test_balance_node_refuses_the_lockstep_clock_on_a_robot_bus_in_one_line(tmp_path):
    rc, err = _run_to_end(tmp_path, **{'can.interface': 'socketcan', 'can.channel': 'can0',
                                       'clock_source': 'imu_stamp'})
    lines = _own_lines(err)
    assert rc == 1 and lines and 'clock_source' in lines[-1], err
    assert len(lines) == 1 and lines[0].startswith('balance_node: '), err
    assert "'socketcan'" in lines[0] and 'Traceback' not in err, err


def _upright_sample(k: int, theta: float) -> ImuSample:
    """Sample k of a simulator in lockstep: stamped k periods after 1000 s, receipt time 0."""
    qx, qy, qz, qw = quaternion_pitch(theta)
    return ImuSample(0.0, 1000, k * PERIOD_NS, qx, qy, qz, qw, True, 0.0, 0.0, 0.0,
                     0.0, 0.0, 9.81)


def test_a_dead_imu_in_lockstep_faults_imu_stale_with_zero_torque_after_the_wall_timeout():
    """
    The simulator's IMU stops while the loop balances on its stamps: no tick, so no timeout.

    The motors keep their last torque, the heartbeat stays as the last tick wrote it (a
    watchdog that reads it sees the loop stalled), until lockstep_wall_timeout of wall time:
    then one tick, FAULT imu_stale, zero torque to both motors.
    """
    cfg = with_changes(BalanceConfig(), {'clock_source': 'imu_stamp',
                                         'can.interface': 'virtual'})
    limit = LOCKSTEP_WALL_TIMEOUT
    channel = 'wlb-lockstep-%s' % uuid.uuid4().hex
    motors = FakeMotors(can.Bus(interface='virtual', channel=channel))
    heartbeat = wd.Heartbeat()
    heartbeat.set_state(wd.WATCHING)   # as the watchdog process does once it watches
    ros_end, loop_end = L.socket_pair()
    intake_end, loop_sensor_end = L.socket_pair()
    runner = make_runner(cfg, VirtualBus(channel=channel), L.Link(loop_end),
                         L.Link(loop_sensor_end), realtime_options=False,
                         heartbeat=heartbeat)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    ros, sensors = L.Link(ros_end), L.Link(intake_end)
    theta = 0.03   # leaning 1.7 deg: the controller pushes
    try:
        for k in range(1, 601):   # as sim_node in lockstep: the next sample once ticked
            sensors.send_imu(_upright_sample(k, theta))
            assert wait_for(lambda: runner.ticks >= k, 5.0), k
            time.sleep(0.0005)     # the motors' replies to this tick, for the next one
            if k == 200:
                ros.send_object(L.ARM, (1, True))
        assert runner.loop.mode.name == 'BALANCING', runner.loop.supervisor.faults
        t_stop, mono_stop = time.time(), time.monotonic()
        pushing = [abs(tau) for m in MOTOR_IDS for tau in motors.torques(m, t_stop - 0.2)]
        assert pushing and min(pushing) > 0.1, pushing   # torque in the motors when it dies
        time.sleep(0.5 * limit)
        beat, flags = heartbeat.loop()
        # No tick, no beat: the heartbeat is the last tick's, and it says commanding.
        assert beat <= mono_stop and flags & wd.COMMANDING, (beat, mono_stop, flags)
        assert runner.loop.mode.name == 'BALANCING'
        assert motors.frames(MOTOR_IDS[0], t_stop + 0.01) == []   # no tick, no frame
        assert wait_for(lambda: runner.loop.mode.name == 'FAULT', 3.0)
        time.sleep(0.1)
        faults = runner.loop.supervisor.faults
        assert [f.code for f in faults] == ['imu_stale'], faults
        assert 'lockstep_wall_timeout' in faults[0].message, faults
        for m in MOTOR_IDS:
            frames = [(t, tau) for t, kind, tau in motors.frames(m, t_stop + 0.01)
                      if kind == 'torque']
            assert frames and all(abs(tau) <= TORQUE_LSB for _, tau in frames), frames
            # About lockstep_wall_timeout after the last tick (the loop looks every 20 ms).
            assert limit - 0.05 <= frames[0][0] - t_stop <= limit + 0.3, frames[0][0] - t_stop
        assert not heartbeat.loop()[1] & wd.COMMANDING   # the fault tick beat: not commanding
    finally:
        runner.stop()
        thread.join(5.0)
        ros.close()
        sensors.close()
        motors.close()
        heartbeat.close()
        os.close(heartbeat.fd)
    assert not thread.is_alive()


def test_in_lockstep_the_watchdog_waits_for_the_loops_guard_then_fires():
    """A slow simulator tick is no stall; a loop that hangs past its own guard is."""
    wall = BalanceConfig()
    lockstep = with_changes(wall, {'clock_source': 'imu_stamp', 'can.interface': 'virtual'})
    timeout = wall.safety.watchdog_timeout
    assert wd.stall_limit(wall) == timeout
    assert wd.stall_limit(lockstep) == pytest.approx(lockstep.loop.lockstep_wall_timeout
                                                     + timeout)
    hb = wd.Heartbeat()
    try:
        ft = FakeTime()
        fired = []
        dog = wd.Watchdog(hb, wd.stall_limit(lockstep), lambda: True,
                          lambda state, age: fired.append(state), clock=ft.clock,
                          sleep=ft.sleep)
        hb.beat(ft.t, True)
        ft.t += 0.5    # a lockstep tick 0.5 s apart (sim_node's lockstep_timeout)
        assert dog.check() and not fired
        ft.t += lockstep.loop.lockstep_wall_timeout - 0.5   # the loop's guard is due now
        assert dog.check() and not fired
        ft.t += timeout + 0.01   # it did not come: the loop hangs
        assert not dog.check() and fired == [wd.FIRED_STALL]
    finally:
        hb.close()
        os.close(hb.fd)


# ----------------------------------------------------------------- the children's package

def _environ(pid: int) -> dict:
    with open('/proc/%d/environ' % pid, 'rb') as f:
        pairs = [item.split(b'=', 1) for item in f.read().split(b'\0') if b'=' in item]
    return {k.decode(): v.decode() for k, v in pairs}


def _bus_params():
    pid = os.getpid()
    return {'can.interface': 'udp_multicast',
            'can.channel': '239.74.164.%d' % (1 + pid % 200),
            'can.udp_port': 44000 + pid % 900}


def test_every_child_runs_the_package_of_its_parent_not_a_copy_in_the_working_directory(
        tmp_path):
    """A copy of the package in the working directory that records who imports it."""
    copy = tmp_path / 'wheelleg_balance'
    shutil.copytree(pathlib.Path(wheelleg_balance.__file__).parent, copy,
                    ignore=shutil.ignore_patterns('__pycache__'))
    marker = tmp_path / 'imported_the_copy.txt'
    with open(copy / '__init__.py', 'a') as f:
        f.write('\nimport os as _os, sys as _sys\nwith open(%r, "a") as _f:\n'
                '    _f.write("%%d %%s\\n" %% (_os.getpid(), " ".join(_sys.argv)))\n'
                % str(marker))
    proc = subprocess.Popen(NODE + _params(**_bus_params()), cwd=tmp_path, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        started = wait_for(lambda: any('balance_node: controller' in line for line in lines)
                           or proc.poll() is not None, 60.0, step=0.05)
        assert started and proc.poll() is None, ''.join(lines)
        children = scenarios.children(proc.pid)
        modules = {m for argv in children.values() for m in argv if m in CHILD_MODULES}
        assert modules == set(CHILD_MODULES), children
        assert not marker.exists(), 'imported the copy: %s' % marker.read_text()
        for pid, argv in children.items():
            assert '-P' in argv[:argv.index('-m')], argv   # never the working directory
            first = _environ(pid)['PYTHONPATH'].split(os.pathsep)[0]
            assert pathlib.Path(first).resolve() == pathlib.Path(PACKAGE_PARENT), first
            assert os.readlink('/proc/%d/cwd' % pid) == str(tmp_path)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(5.0)
    assert proc.returncode == 0, ''.join(lines)
    assert not marker.exists(), 'imported the copy: %s' % marker.read_text()


# ------------------------------------------------------------------------ a failed start

def test_a_child_that_cannot_open_the_bus_is_one_line_and_the_node_exits_with_it(tmp_path):
    channel = 'wlbnocan%d' % (os.getpid() % 1000)
    bus = {'can.interface': 'socketcan', 'can.channel': channel}
    rc, err = _run_to_end(tmp_path, **bus)
    lines = _own_lines(err)
    assert rc == 1, err
    assert 'Traceback' not in err and '[ERROR]' not in err, err
    assert len(lines) == 1, err
    line = lines[0]
    # What failed, why (the OS's error), the fix.
    assert line.startswith('balance_node: cannot open the CAN bus socketcan:%s: ' % channel), line
    assert 'Error' in line and 'ip link' in line, line
    # The traceback when asked for; the line still closes the output.
    rc, err = _run_to_end(tmp_path, env=_env(WHEELLEG_BALANCE_TRACEBACK='1'), **bus)
    assert rc == 1 and 'Traceback' in err, err
    assert _own_lines(err)[-1] == line, err


def test_the_lockstep_guard_keeps_the_clock_moving_only_while_commanding():
    """Disarmed, a silent simulator is no fault: nothing to guard, no tick is made up."""
    cfg = with_changes(BalanceConfig(), {'clock_source': 'imu_stamp',
                                         'can.interface': 'virtual',
                                         'lockstep_wall_timeout': 0.1})
    ros_end, loop_end = L.socket_pair()
    intake_end, loop_sensor_end = L.socket_pair()
    runner = make_runner(cfg, VirtualBus(channel='wlb-%s' % uuid.uuid4().hex),
                         L.Link(loop_end), L.Link(loop_sensor_end), realtime_options=False)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    sensors = L.Link(intake_end)
    try:
        for k in range(1, 11):
            sensors.send_imu(_upright_sample(k, 0.0))
            assert wait_for(lambda: runner.ticks >= k, 5.0), k
        time.sleep(0.5)
        assert runner.ticks == 10 and runner.loop.mode.name == 'DISARMED'
        assert math.isclose(runner.now, 1000.02)
    finally:
        runner.stop()
        thread.join(5.0)
        L.Link(ros_end).close()
        sensors.close()
