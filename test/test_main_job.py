"""
main_job and joy_script: the scripted joystick, the judging of runs, and the CI end-to-end run.

The end-to-end test runs ``main_job --only startup,standing --short`` as it runs on a user's
machine: sim_node (MuJoCo) and balance_node as separate processes over ROS 2 (a ROS_DOMAIN_ID
of this run, localhost only) and CAN over udp_multicast (a group and port of this run). It then
checks the ground truth the simulator recorded, independently of main_job's own verdict: the
robot rises from its tail, stays in a pitch band and does not drift while standing.
"""
import csv
import json
import math
import os
import pathlib
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest
from wheelleg_balance.core.teleop import map_joy, TeleopConfig
from wheelleg_balance.tools import main_job
from wheelleg_balance.tools.joy_script import joy_arrays, JoyScript, load_mapping, PadMapping
import yaml

REPO = pathlib.Path(__file__).resolve().parents[1]
XBOX = REPO / 'config' / 'teleop_xbox.yaml'


def _teleop_config(path) -> TeleopConfig:
    p = yaml.safe_load(path.read_text())['teleop_node']['ros__parameters']
    return TeleopConfig(**{k.replace('.', '_'): v for k, v in p.items()
                           if k.replace('.', '_') in TeleopConfig.__dataclass_fields__})


# ------------------------------------------------------------------------------ joy_script

def test_pad_mapping_comes_from_the_teleop_config():
    pad = load_mapping(XBOX)
    p = yaml.safe_load(XBOX.read_text())['teleop_node']['ros__parameters']
    assert pad.axis_linear == p['axis_linear.x']
    assert pad.axis_yaw == p['axis_angular.yaw']
    assert pad.enable_button == p['enable_button']
    assert pad.turbo_button == p['enable_turbo_button']
    assert pad.rate == 20.0   # game_controller_node autorepeat_rate


def test_nested_parameter_names_are_read_too(tmp_path):
    f = tmp_path / 'pad.yaml'
    f.write_text(yaml.safe_dump({'teleop_node': {'ros__parameters': {
        'axis_linear': {'x': 4}, 'axis_angular': {'yaw': 0}, 'enable_button': 2,
        'enable_turbo_button': -1}}}))
    assert load_mapping(f) == PadMapping(axis_linear=4, axis_yaw=0, enable_button=2,
                                         turbo_button=-1, rate=20.0)


def test_script_holds_values_and_releases_the_pad():
    script = JoyScript.from_dict({'end': 6.0, 'steps': [
        {'t': 1.0, 'linear': 0.5}, {'t': 3.0, 'yaw': -1.0, 'turbo': True},
        {'t': 5.0, 'enable': False}]})
    assert not script.state(0.5).enable                      # before the first step
    s = script.state(2.0)
    assert (s.linear, s.yaw, s.turbo, s.enable) == (0.5, 0.0, False, True)
    s = script.state(4.0)                                    # linear carries over
    assert (s.linear, s.yaw, s.turbo, s.enable) == (0.5, -1.0, True, True)
    assert not script.state(5.5).enable
    assert script.state(6.0) == script.state(-1.0)           # released after the end


def test_joy_arrays_put_sticks_and_buttons_at_the_mapped_indices():
    pad = load_mapping(XBOX)
    state = JoyScript.from_dict({'end': 2.0, 'steps': [
        {'t': 0.0, 'linear': 0.64, 'yaw': -0.3, 'turbo': True}]}).state(1.0)
    axes, buttons = joy_arrays(state, pad)
    assert (len(axes), len(buttons)) == (6, 16)
    assert axes[pad.axis_linear] == 0.64 and axes[pad.axis_yaw] == -0.3
    assert sum(abs(a) for a in axes) == pytest.approx(0.94)
    assert buttons[pad.enable_button] == 1 and buttons[pad.turbo_button] == 1
    assert sum(buttons) == 2


@pytest.mark.parametrize('doc', [
    {'steps': [{'t': 2.0}, {'t': 1.0}]},                  # time going back
    {'steps': [{'t': 0.0, 'linear': 1.5}]},               # beyond full deflection
    {'steps': [{'t': 0.0, 'speed': 0.3}]},                # unknown key
    {'end': 1.0, 'steps': [{'t': 2.0}]},                  # end before the last step
])
def test_bad_scripts_are_refused(doc):
    with pytest.raises(ValueError):
        JoyScript.from_dict(doc)


@pytest.mark.parametrize('exp', [e for e in main_job.EXPERIMENTS if e.joy], ids=lambda e: e.name)
def test_scripted_sticks_give_the_intended_commands_through_teleop(exp):
    """main_job's physical steps -> deflections -> Joy -> core.teleop: the same v and w."""
    cfg = _teleop_config(XBOX)
    pad = load_mapping(XBOX)
    script = JoyScript.from_dict(main_job.joy_script_doc(exp, main_job.teleop_scales(XBOX)))
    for (t0, t1, v, w) in main_job._joy_segments(exp):
        axes, buttons = joy_arrays(script.state(0.5 * (t0 + t1)), pad)
        x_dot, yaw_rate = map_joy(axes, buttons, cfg)
        assert x_dot == pytest.approx(v, abs=1e-3)
        assert yaw_rate == pytest.approx(w, abs=1e-3)


@pytest.mark.ros
def test_joy_script_publishes_the_script_once_started(tmp_path):
    """The process: the released pad until ~/start, then the script at 20 Hz, then released."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Joy
    from std_srvs.srv import Trigger

    script = tmp_path / 'script.yaml'
    script.write_text(yaml.safe_dump({'end': 1.0, 'steps': [
        {'t': 0.0, 'linear': 0.5, 'yaw': -0.25, 'turbo': True}]}))
    domain = 1 + (os.getpid() * 11 + 5) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.Popen([sys.executable, '-m', 'wheelleg_balance.tools.joy_script',
                             '--config', str(XBOX), '--script', str(script), '--wait-start',
                             '--exit'], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    try:
        node = rclpy.create_node('joy_listener', context=ctx)
        got = []
        node.create_subscription(Joy, 'joy', lambda m: got.append(
            (list(m.axes), list(m.buttons))), 50)
        start = node.create_client(Trigger, 'joy_script/start')
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        deadline = time.monotonic() + 30.0
        while (len(got) < 3 or not start.service_is_ready()) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert len(got) >= 3, 'no Joy from joy_script'
        n_before = len(got)
        future = start.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=5.0)
        assert future.result().success
        while proc.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        for _ in range(10):
            executor.spin_once(timeout_sec=0.01)
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    assert proc.returncode == 0, proc.stdout.read()
    pad = load_mapping(XBOX)
    released = ([0.0] * 6, [0] * 16)
    assert all(g == released for g in got[:n_before])
    scripted = [g for g in got[n_before:] if g != released]
    expect_axes = [0.0] * 6
    expect_axes[pad.axis_linear], expect_axes[pad.axis_yaw] = 0.5, -0.25
    expect_buttons = [0] * 16
    expect_buttons[pad.enable_button] = expect_buttons[pad.turbo_button] = 1
    assert all(g == (expect_axes, expect_buttons) for g in scripted)
    assert 14 <= len(scripted) <= 22          # 1 s of script at 20 Hz
    assert got[-1] == released                # released after the end


# ------------------------------------------------------------------------------ judging

# sim_node's ground truth and balance_node's ~/state layouts (docs/simulation.md,
# docs/balance_node.md).
GT = ['time', 'theta', 'theta_dot', 'x', 'y', 'x_dot', 'yaw', 'yaw_rate', 'roll', 'l',
      'tau_left', 'tau_right']
ST = ['theta', 'theta_dot', 'x', 'x_dot', 'yaw_rate', 'd_hat', 'l', 'u', 'tau_left',
      'tau_right', 'controller', 'mode', 'x_dot_ref', 'yaw_rate_ref']


def _synthetic_run(theta_of_t, duration=4.0, fault_at=None):
    """Make a 100 Hz recording with the true pitch theta_of_t(t) [rad]; armed at t = 0."""
    gt, st = [], []
    for k in range(-50, int(duration * 100)):
        t = 0.01 * k
        th = theta_of_t(t)
        gt.append((t, 3.5 + t, th, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.37, 0.0, 0.0))
        mode = 0 if t < 0 else (2 if fault_at is not None and t >= fault_at else 1)
        st.append((t, th, 0.0, 0.0, 0.0, 0.0, 0.0, 0.37, 0.0, 0.0, 0.0, 0.0, mode, 0.0, 0.0))
    rec = SimpleNamespace(gt=gt, gt_labels=GT, state=st, state_labels=ST, cmd=[])
    return main_job.Trace(rec, 0.0, duration)


def _rise(t, overshoot=0.1):
    """36 deg decaying towards 0 with a dip of about ``overshoot`` rad below it."""
    if t < 0.0:
        return math.radians(36.0)
    return math.radians(36.0) * math.exp(-8.0 * t) - overshoot * math.sin(
        min(t, 0.6) * math.pi / 0.6) * (t < 0.6)


def test_a_clean_start_up_passes_and_its_overshoot_is_measured():
    res = main_job.evaluate(main_job.EXPERIMENT_BY_NAME['startup'], _synthetic_run(_rise), [])
    assert res['passed'], res['criteria']
    assert res['metrics']['overshoot_deg'] == pytest.approx(
        -math.degrees(min(_rise(0.01 * k) for k in range(400))), abs=0.05)


def test_a_start_up_that_falls_back_on_the_tail_fails():
    def back(t):
        return _rise(t) if t < 1.5 else math.radians(36.0)
    res = main_job.evaluate(main_job.EXPERIMENT_BY_NAME['startup'], _synthetic_run(back), [])
    failed = {c['name'] for c in res['criteria'] if not c['ok']}
    assert 'off the tail' in failed and not res['passed']


def test_a_fault_fails_even_if_the_pitch_looks_fine():
    res = main_job.evaluate(main_job.EXPERIMENT_BY_NAME['startup'],
                            _synthetic_run(_rise, fault_at=2.0), [])
    assert {c['name'] for c in res['criteria'] if not c['ok']} == {'stays up'}


def test_a_robot_that_never_rises_fails():
    res = main_job.evaluate(main_job.EXPERIMENT_BY_NAME['startup'],
                            _synthetic_run(lambda t: math.radians(36.0)), [])
    assert 'rises' in {c['name'] for c in res['criteria'] if not c['ok']}


def test_every_experiment_has_an_evaluator_and_stated_bounds():
    assert {e.kind for e in main_job.EXPERIMENTS} <= set(main_job.EVALUATORS)
    assert [e.figure for e in main_job.EXPERIMENTS if e.name != 'startup_lqr'] == [
        'Fig. %d' % n for n in (3, 3, 3, 4, 5, 6, 7, 8, 9, 10)]


# ------------------------------------------------------------------------------ end to end

def _read(path):
    with open(path) as f:
        rows = list(csv.reader(f))
    head = rows[0]
    return {name: [float(r[i]) for r in rows[1:]] for i, name in enumerate(head)}


def _arm_time(state):
    return next(t for t, m in zip(state['receipt_time'], state['mode']) if m == 1.0)


def _disarm_time(state):
    """Receipt time of the last state row in BALANCING: main_job disarms at the end of a run."""
    return max(t for t, m in zip(state['receipt_time'], state['mode']) if m == 1.0)


@pytest.mark.ros
@pytest.mark.slow
def test_start_up_and_standing_through_the_real_processes(tmp_path):
    pid = os.getpid()
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + (pid * 7) % 100),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    out = tmp_path / 'job'
    proc = subprocess.run(
        [sys.executable, '-m', 'wheelleg_balance.tools.main_job', '--only', 'startup,standing',
         '--short', '--output', str(out), '--can-group',
         '239.75.%d.%d' % ((pid >> 8) % 256, pid % 256 or 1), '--udp-port',
         str(30000 + pid % 10000)],
        env=env, cwd=str(REPO), capture_output=True, text=True, timeout=110)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    assert str(out) in proc.stdout.splitlines()[-1]          # prints the folder at the end
    report = json.loads((out / 'report.json').read_text())
    assert [e['experiment'] for e in report['experiments']] == ['startup', 'standing']
    assert report['passed'], log
    assert (out / 'report.md').exists() and (out / 'startup' / 'startup.png').exists()

    # From the simulator's ground truth, not from main_job's verdict.
    for name, standing in (('startup', 4.0), ('standing', 13.0)):
        gt = _read(out / name / 'ground_truth.csv')
        state = _read(out / name / 'state.csv')
        t_arm, t_disarm = _arm_time(state), _disarm_time(state)
        # While balancing only: after the disarm at the end the robot drops back onto its tail.
        rows = [(t - t_arm, math.degrees(th), x, v) for t, th, x, v in zip(
            gt['receipt_time'], gt['theta'], gt['x'], gt['x_dot']) if t_arm <= t <= t_disarm]
        t_end = rows[-1][0]
        assert t_end > standing - 0.5
        # Rises: from the tail (about 36 deg) to below 10 deg within 2 s.
        assert rows[0][1] > 30.0
        assert min(r[0] for r in rows if r[1] < 10.0) < 2.0
        risen = [r for r in rows if r[0] > 1.0]
        # Pitch band: after rising within 15 deg (the tail holds it at 36: never back on it),
        # and within 5 deg of upright once up (upright is within 1 deg of 0) until standing's
        # switch to output regulation at 3 s, which stops the robot from about 0.7 m/s.
        assert max(abs(r[1]) for r in risen) < 15.0
        t_up_end = 3.0 if name == 'standing' else math.inf
        assert max(abs(r[1]) for r in rows if 2.5 < r[0] < t_up_end) < 5.0
        if name == 'standing':
            # Output regulation from 3 s: no drift, stands still over the last 5 s.
            last = [r for r in rows if r[0] > t_end - 5.0]
            assert abs(last[-1][2] - last[0][2]) < 0.02
            assert abs(sum(r[3] for r in last) / len(last)) < 0.01
            assert max(abs(r[1]) for r in last) < 1.0
