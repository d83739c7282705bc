"""
balance_node under faults and bad input: each fault, its reaction, the time to zero torque.

The scenarios live in wheelleg_balance/validation/faults/ (the ``fault_report`` command runs
the same ones); docs/faults.md has the table of reactions and measured times. Most run the node
as on the robot: its 2 ms control loop, real DDS on localhost (own domain), a python-can
``virtual`` bus with two fake wheel motors (MIT, or the configured protocol's emulator);
torques are read off the bus as the motors' firmware acts on them. The SIGINT/SIGTERM tests
run the node as a process on ``udp_multicast``; the push test runs against sim_node (MuJoCo)
in this process; the field matrices, the controller switch and the latch test drive the
control tick itself (core/balance_loop.py) on a virtual clock.

Each test fails with the list of the scenario's checks that did not hold.
"""
import math
import threading
import time
import warnings

import pytest

# conftest.py isolates ROS (domain from the pid, localhost) and provides ``context``.
from wheelleg_balance.validation.faults.bench import (is_zero_torque, LoopBench, make_imu,
                                                      make_joints, MODE)
from wheelleg_balance.validation.faults.lockstep import scenario_controller_switch
from wheelleg_balance.validation.faults.matrices import FieldMatrix, MATRICES
from wheelleg_balance.validation.faults.outcome import Outcome
from wheelleg_balance.validation.faults.rig import (REACTION_TIME_CHECK, SITTING_TIME_CHECK,
                                                    Spinning, unique_namespace)
from wheelleg_balance.validation.faults.scenarios import PROTOCOL_FAULTS
from wheelleg_balance.validation.faults.suite import run_measured

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def matrices():
    """Return a FieldMatrix per parameter set of MATRICES (keyed by its sorted names)."""
    return {tuple(sorted(params)): FieldMatrix(LoopBench(**params))
            for _, _, params in MATRICES.values()}


def assert_handled(out: Outcome) -> Outcome:
    assert out.handled, '%s (%s): %s' % (out.name, out.expected, '; '.join(out.failures))
    return out


def scenario_test(name):
    """
    Return a test that runs fault scenario ``name`` and asserts it was handled.

    A failed run is run once more only for what the run itself attributes (``attributable``):
    - its only failed checks are reaction-time bounds with the reaction there, at most
      LATE_MARGIN past the bound: a scheduling stall of the loaded 2-core test machine can
      exceed the slack once (seen: 160.8 ms against 160 ms; SITTING 61.4 ms against 60);
    - or the machine kept tasks from the CPU before the fault came: CPU pressure at least
      CONTENDED_PRESSURE_PCT over the BEFORE_INJECTION seconds before the injection (the
      kernel's counters, validation/contention.py). Seen in CI: every tick 10 to 20 ms late
      for a minute, one tick's compute 75 ms (0.3 ms normally), the rig's 500 Hz IMU silent
      104 ms, so a FAULT nothing injected; a quiet run of this file stays below 41 %.
    A reaction that never came is never run again, nor any other failure, nor a failure of the
    second run. Every retry is counted in the run's closing summary (conftest.py), recorded as
    a warning and as the junit test-suite property ``<scenario>.retried`` (xunit2, as colcon
    writes it, has no per-test properties); the figures of every run likewise,
    ``<scenario>.figures``.
    """
    def test(context, record_testsuite_property, fault_retries):
        run_scenario(name, context, record_testsuite_property, fault_retries)
    return test


#: How far past its bound a reaction may come and still be run once more [s].
LATE_MARGIN = 0.010
#: CPU pressure [% of the window before the injection] from which a failed run is attributed
#: to the machine: quiet runs of this file measured 0..25 % in-process, 28..41 % with the node
#: as a subprocess (over whole runs, docs/faults.md).
CONTENDED_PRESSURE_PCT = 60.0


def missing_reaction(out):
    """Whether a reaction ``out`` required never came."""
    return any(elapsed is None for _, elapsed, _ in out.reactions)


def only_late(out):
    """Whether every failed check of ``out`` is a reaction that came, at most LATE_MARGIN late."""
    late = {text for text, elapsed, bound in out.reactions
            if elapsed is not None and bound < elapsed <= bound + LATE_MARGIN}
    return bool(out.failures) and all(f in late for f in out.failures)


def attributable(out):
    """Why a failed ``out`` may run once more ('' when it may not): see scenario_test."""
    if out.handled or missing_reaction(out):
        return ''
    if only_late(out):
        return 'the reaction came late by at most %.0f ms' % (1e3 * LATE_MARGIN)
    pressure = out.figures.get('cpu_pressure_before_pct')
    if pressure is not None and pressure >= CONTENDED_PRESSURE_PCT:
        return 'the machine was contended before the injection (CPU pressure %s %%)' % pressure
    return ''


def _outcome(checks=(), reactions=(), **figures):
    out = Outcome('x', 'fault', 'expected')
    for text, ok in checks:
        out.check(text, ok)
    for text, elapsed, bound in reactions:
        out.reaction(text, elapsed, bound)
    out.figures.update(figures)
    return out


def test_only_a_reaction_that_came_at_most_10_ms_late_is_run_once_more():
    zero, sit = REACTION_TIME_CHECK + ' 160 ms', SITTING_TIME_CHECK + ' 60 ms'
    assert attributable(_outcome(reactions=[(zero, 0.1608, 0.160)]))
    assert attributable(_outcome(checks=[('re-arm refused', True)],
                                 reactions=[(sit, 0.0614, 0.060)]))
    assert not attributable(_outcome(reactions=[(zero, 0.171, 0.160)]))     # 11 ms late
    assert not attributable(_outcome(reactions=[(zero, None, 0.160)]))      # never came
    assert not attributable(_outcome(checks=[('re-arm refused', False)],
                                     reactions=[(sit, 0.0614, 0.060)]))
    assert not attributable(_outcome(checks=[('~/state reports SITTING', False)]))
    assert not attributable(_outcome(reactions=[(zero, 0.1, 0.160)]))      # nothing failed


def test_contention_before_the_injection_alone_allows_a_rerun_and_never_a_missing_reaction():
    failed = [('still BALANCING', False)]
    assert attributable(_outcome(failed, cpu_pressure_before_pct=85.0))
    # The pressure over the whole run (the node's reaction included) does not count, nor
    # steal time, nor a quiet machine, nor an unknown pressure.
    assert not attributable(_outcome(failed, cpu_pressure_pct=99.0, cpu_steal_pct=35.0,
                                     cpu_pressure_before_pct=40.0))
    assert not attributable(_outcome(failed, cpu_pressure_before_pct=None))
    assert not attributable(_outcome(failed))
    never = _outcome(failed, [(REACTION_TIME_CHECK + ' 60 ms', None, 0.06)],
                     cpu_pressure_before_pct=99.0)
    assert not attributable(never)


def test_contention_figures_come_from_the_kernels_counters(tmp_path, monkeypatch):
    from wheelleg_balance.validation import contention
    pressure, stat = tmp_path / 'pressure', tmp_path / 'stat'
    monkeypatch.setattr(contention, 'PRESSURE', str(pressure))
    monkeypatch.setattr(contention, 'STAT', str(stat))
    clock = iter([100.0, 102.0])
    monkeypatch.setattr(contention.time, 'monotonic', lambda: next(clock))

    def counters(stall_us, steal, other):
        pressure.write_text('some avg10=1.00 avg60=0.50 avg300=0.10 total=%d\n'
                            'full avg10=0.00 avg60=0.00 avg300=0.00 total=0\n' % stall_us)
        # user nice system idle iowait irq softirq steal guest guest_nice
        stat.write_text('cpu  %d 0 0 0 0 0 0 %d 7 7\ncpu0 1 0 0 0 0 0 0 0 0 0\n' % (other, steal))
    counters(5_000_000, 100, 1000)
    window = contention.CpuContention()
    counters(6_500_000, 130, 1090)            # 1.5 s of 2 s stalled; 30 of 120 jiffies stolen
    assert window.figures() == {'cpu_pressure_pct': 75.0, 'cpu_steal_pct': 25.0}
    pressure.unlink()                          # a kernel without PSI
    monkeypatch.setattr(contention.time, 'monotonic', lambda: 104.0)
    assert window.figures()['cpu_pressure_pct'] is None


def test_the_contention_history_judges_the_window_before_the_injection(tmp_path, monkeypatch):
    from wheelleg_balance.validation import contention
    pressure = tmp_path / 'pressure'
    monkeypatch.setattr(contention, 'PRESSURE', str(pressure))
    now = [10.0]
    monkeypatch.setattr(contention.time, 'monotonic', lambda: now[0])

    def at(t, stall_us):
        now[0] = t
        pressure.write_text('some avg10=0 avg60=0 avg300=0 total=%d\n' % stall_us)
    history = contention.CpuHistory()   # not started: the test takes the readings itself
    at(10.0, 0)
    history._read()
    at(12.0, 200_000)                  # 10 % of 2 s
    history._read()
    at(14.0, 2_000_000)                # 90 % of the next 2 s (the injection at 14 s)
    history._read()
    at(16.0, 2_100_000)                # a quiet 5 % after it
    assert history.window(12.0, 14.0)['cpu_pressure_pct'] == 90.0
    assert history.window(10.0, 12.0)['cpu_pressure_pct'] == 10.0
    assert history.window(14.0, 16.0)['cpu_pressure_pct'] == 5.0


def run_scenario(name, context, record, retries):
    """Run scenario ``name``, once more only for what it attributes (see scenario_test)."""
    out = run_measured(name, context)
    why = attributable(out)
    retries.ran(name)
    if why:
        text = '%s: %s (%s; figures %s), run once more' % (
            name, why, '; '.join(out.failures), out.figures)
        record('%s.retried' % name, text)
        retries.retried(name, text)
        warnings.warn(text)
        out = run_measured(name, context)
    record('%s.figures' % name, out.figures)
    assert_handled(out)


def matrix_test(name):
    """Return a test that runs field matrix ``name`` of MATRICES (every case)."""
    kind, cases, params = MATRICES[name]

    def test(matrices):
        assert_handled(matrices[tuple(sorted(params))].outcome(name, kind, cases))
    return test


# ------------------------------------------------------------------------------ sensors

# And not before the timeout.
test_imu_silent_gives_zero_torque_within_imu_timeout = scenario_test('imu_silent')
test_imu_frozen_with_repeated_stamp_counts_as_stale = scenario_test('imu_frozen')
test_imu_nan_orientation_faults_at_the_next_tick = scenario_test('imu_nan')
test_imu_inf_pitch_rate_faults_at_the_next_tick = scenario_test('imu_rate_inf')
test_non_unit_quaternion_faults = scenario_test('quaternion_not_unit')
test_imu_non_finite_value_in_every_field = matrix_test('imu_fields_non_finite')
test_imu_absurd_finite_value_in_every_field = matrix_test('imu_fields_absurd')
test_wheel_velocity_nan_faults_at_the_next_tick = scenario_test('wheel_velocity_nan')
test_joint_states_non_finite_value_in_every_field = matrix_test('joint_fields_non_finite')
test_joint_states_absurd_finite_value_in_every_field = matrix_test('joint_fields_absurd')
test_wheel_joints_missing_is_stale_joint_states = scenario_test('wheel_joints_missing')
test_imu_stamped_ahead_of_the_clock_is_refused = scenario_test('imu_stamp_future')
test_imu_stamps_running_backwards_are_refused = scenario_test('imu_stamp_backwards')
test_leg_angles_out_of_five_bar_reach_fault = scenario_test('leg_out_of_reach')
test_leg_angles_bad_values_fault = matrix_test('leg_fields')

# ------------------------------------------------------------------------------ cmd_vel

test_cmd_vel_non_finite_dropped_and_absurd_limited = scenario_test('cmd_vel_invalid')
test_cmd_vel_bad_value_in_every_field = matrix_test('cmd_vel_fields')
test_cmd_vel_stamped_in_the_past_still_times_out = scenario_test('cmd_vel_stale')
test_cmd_vel_stamped_in_the_future_still_times_out = scenario_test('cmd_vel_future')
# A second publisher (nodes/input_guard.py): on a sensor a FAULT, on a command a refusal.
test_a_second_imu_publisher_faults_and_blocks_arming = scenario_test('second_imu_publisher')
test_a_second_cmd_vel_publisher_is_refused_while_balancing_goes_on = \
    scenario_test('second_cmd_vel_publisher')
test_joy_bad_value_in_every_axis_gives_a_bounded_command = scenario_test('joy_fields')

# ---------------------------------------------------------------------------------- CAN

test_silent_motor_gives_zero_torque_within_motor_timeout = scenario_test('motor_silent')
test_reply_from_unknown_id_does_not_keep_a_motor_alive = scenario_test('reply_unknown_id')
test_replies_from_a_stranger_are_ignored = scenario_test('stranger_replies')
test_full_tx_queue_faults_and_sends_only_zero_torque_after = scenario_test('can_tx_queue_full')
test_bus_off_faults_and_sends_only_zero_torque_after = scenario_test('can_bus_off')
test_error_frame_storm_does_not_stop_balancing = scenario_test('error_frame_storm')
test_motor_error_code_faults_with_the_reason = scenario_test('motor_error')
test_rebooted_motor_faults = scenario_test('motor_rebooted')
test_over_temperature_sits_down_and_refuses_to_arm = scenario_test('motor_over_temperature')


@pytest.mark.parametrize('name', ['%s_%s' % (fault, wheels)
                                  for wheels, faults in PROTOCOL_FAULTS.items()
                                  for fault in faults])
def test_motor_faults_on_the_other_wheel_protocols(context, record_testsuite_property,
                                                   fault_retries, name):
    """Run the motor faults and the second commander with LK, CyberGear and DaMiao wheels."""
    run_scenario(name, context, record_testsuite_property, fault_retries)


# ------------------------------------------------- at the robot's own timeouts (50 ms)

test_imu_silent_at_the_robot_timeouts = scenario_test('imu_silent_50ms')
test_imu_frozen_at_the_robot_timeouts = scenario_test('imu_frozen_50ms')
test_wheel_joints_missing_at_the_robot_timeouts = scenario_test('wheel_joints_missing_50ms')
test_silent_motor_at_the_robot_timeouts = scenario_test('motor_silent_50ms')

# --------------------------------------------------------------------------------- falls

test_imu_past_fall_angle_forward_faults_at_the_next_tick = scenario_test('fall_forward')
test_imu_past_fall_angle_backward_faults_at_the_next_tick = scenario_test('fall_backward')
test_push_past_fall_angle_on_sim_node_ends_at_rest_without_torque = \
    scenario_test('push_fall_sim_node')

# ---------------------------------------------------------------------- parameters, switch

test_bad_parameters_are_refused_and_nothing_changes = scenario_test('bad_parameters')
test_safety_parameters_only_tighten_while_balancing = scenario_test('loosen_while_balancing')


def _slow_node(context, seconds):
    """Return (node, started, ended): a node whose timer callback sleeps ``seconds``."""
    from rclpy.node import Node
    node = Node('slow_callback', namespace=unique_namespace(), context=context)
    started, ended = threading.Event(), threading.Event()

    def slow():
        if not started.is_set():
            started.set()
            time.sleep(seconds)
            ended.set()
    node.create_timer(0.01, slow)
    return node, started, ended


def test_the_rig_stops_spinning_only_after_a_running_callback_ends(context):
    """
    A callback longer than the old 2 s join: stop() waits for it, or says it could not.

    The old stop() (a 2 s join) returned during it, and the rig then destroyed the nodes
    under the running callback.
    """
    errors = []
    hook = threading.excepthook
    threading.excepthook = errors.append
    try:
        node, started, ended = _slow_node(context, 2.5)
        spinning = Spinning(context, (node,))
        assert started.wait(5.0)
        spinning.stop()
        assert ended.is_set()          # stop() returned after the callback, not during it
        node.destroy_node()
        node, started, ended = _slow_node(context, 1.5)
        spinning = Spinning(context, (node,))
        assert started.wait(5.0)
        with pytest.raises(RuntimeError, match='still in a callback'):
            spinning.stop(timeout=0.2)
        assert not ended.is_set()
        spinning.stop()                # the second call waits for it to end
        assert ended.is_set()
        node.destroy_node()
        time.sleep(0.1)
    finally:
        threading.excepthook = hook
    assert not errors, [str(e.exc_value) for e in errors]


def test_controller_switch_at_full_speed_is_bumpless(context):
    out = assert_handled(scenario_controller_switch(context))
    # The check can fail: without blending the switch to lqr jumps by far more than the bound.
    to_lqr = out.figures['to_lqr']
    assert to_lqr['unblended_nm'] > 5 * to_lqr['bound_nm']


# ---------------------------------------------------------------------------- recovery

test_recovery_only_by_explicit_rearm_while_on_the_tail = scenario_test('recovery_rearm')


LATCH_CAUSES = ('imu_stale', 'non_finite', 'fall', 'motor_silent', 'can_send')


@pytest.fixture(scope='module')
def auto_arm_bench():
    return LoopBench(auto_arm=True)


@pytest.mark.parametrize('cause', LATCH_CAUSES)
def test_fault_latches_until_rearm_even_with_auto_arm(auto_arm_bench, cause):
    """
    Latch each fault cause until an explicit re-arm, auto_arm on.

    After the fault, 10 s of healthy samples at the tail rest pitch: FAULT and zero torque
    throughout, then an explicit re-arm balances again.
    """
    bench = auto_arm_bench
    tail = math.radians(36.0)
    bench.feed()
    bench.rearm()
    for _ in range(10):
        bench.feed()
        bench.tick()
    if cause == 'imu_stale':
        bench.t += 0.2          # nothing arrives for 0.2 s
        bench.feed_joints(make_joints())
        frames = bench.tick()
    elif cause == 'non_finite':
        # A NaN pitch rate (a NaN orientation alone falls back to gravity: core/attitude.py).
        bench.feed(make_imu(0.02, math.nan))
        frames = bench.tick()
    elif cause == 'fall':
        bench.feed(make_imu(math.radians(50.0)))
        frames = bench.tick()
    elif cause == 'motor_silent':
        bench.t += 0.2
        bench.feed()
        frames = bench.tick(replies=False)
    else:
        bench.fail_with = 'CanOperationError: Failed to transmit: [Errno 105] No buffer space'
        bench.feed()
        frames = bench.tick()
        bench.fail_with = None
    assert bench.mode == MODE['FAULT']
    codes = {f.code for f in bench.loop.supervisor.faults}
    assert cause in codes, codes
    if cause != 'can_send':
        assert frames and all(is_zero_torque(f) for _, f in frames), frames
    for _ in range(5000):   # 10 s lying on the tail, every sensor and motor healthy
        bench.feed(make_imu(tail))
        frames = bench.tick()
        assert bench.mode == MODE['FAULT']
        assert len(frames) == 2 and all(is_zero_torque(f) for _, f in frames)
    req = bench.request(True)
    frames = bench.tick()
    assert req.success, req.message
    assert bench.mode == MODE['BALANCING']
    assert [f for _, f in frames[:2]] == ['enter', 'enter']


# ----------------------------------------------------------------------------- signals

@pytest.mark.parametrize('name', ['sigint_shutdown', 'sigterm_shutdown', 'sighup_shutdown',
                                  'sigquit_shutdown'])
def test_signal_sends_zero_torque_then_exit_frames(context, record_testsuite_property,
                                                   fault_retries, name):
    run_scenario(name, context, record_testsuite_property, fault_retries)


# The watchdog process (nodes/watchdog.py): a control process that stops for good or is killed.
test_stalled_control_process_is_killed_and_the_watchdog_zeroes_the_motors = \
    scenario_test('control_process_stalled')
test_killed_control_process_the_watchdog_zeroes_the_motors = \
    scenario_test('control_process_killed')
# SIGKILL of balance_node itself: its children see it die (PR_SET_PDEATHSIG, the link's EOF).
test_killed_balance_node_its_control_process_zeroes_the_motors_within_100_ms = \
    scenario_test('balance_node_killed')


def test_zero_applied_after_counts_from_the_sample_to_lasting_zero_torque():
    from wheelleg_balance.validation.faults.scenarios import _zero_applied_after
    truth = [(0.000, 3.0, -3.0), (0.002, 2.0, -2.0), (0.004, 0.0, 0.0), (0.006, 0.5, 0.0),
             (0.008, 0.0, 0.0), (0.010, 0.0, 0.0)]
    # Zero from 0.008 s on (the blip at 0.006 s restarts the count).
    assert _zero_applied_after(truth, 0.002) == pytest.approx(0.006)
    assert _zero_applied_after(truth, 0.009) == pytest.approx(0.001)
    assert _zero_applied_after(truth[:4], 0.0) is None
