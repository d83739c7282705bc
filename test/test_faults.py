"""
balance_node under faults and bad input: each fault, its reaction, the time to zero torque.

The scenarios live in wheelleg_balance/tools/fault_suite.py (the ``fault_report`` command runs
the same ones); docs/faults.md has the table of reactions and measured times. Most run the node
as on the robot: its own 2 ms control thread, real DDS on localhost (own domain), a python-can
``virtual`` bus with two fake MIT motors; torques are read off the bus and decoded with
MitProtocol. The SIGINT/SIGTERM tests run the node as a process on ``udp_multicast``; the push
test runs against sim_node (MuJoCo) in this process; the field matrices, the controller switch
and the latch test drive the node's callbacks and tick directly on a virtual clock.

Each test fails with the list of the scenario's checks that did not hold.
"""
import math

import pytest

# conftest.py isolates ROS (domain from the pid, localhost) and provides ``context``.
from wheelleg_balance.tools import fault_suite as fs

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def matrices(context):
    """Return a FieldMatrix by leg setting: False, no leg joints configured; True, leg joints."""
    with fs.Bench(context) as bench, fs.Bench(context, **fs.LEG_PARAMS) as leg_bench:
        yield {False: fs.FieldMatrix(bench), True: fs.FieldMatrix(leg_bench)}


def assert_handled(out: fs.Outcome) -> fs.Outcome:
    assert out.handled, '%s (%s): %s' % (out.name, out.expected, '; '.join(out.failures))
    return out


def scenario_test(name):
    """
    Return a test that runs fault_suite scenario ``name`` and asserts it was handled.

    A run whose only failed check is the reaction-time bound (the timeout + fs.SLACK) is run
    once more: a scheduling stall of the loaded 2-core test machine can exceed the slack once
    (seen: 160.8 ms against 160 ms). Every other check, and a reaction time that misses its
    bound twice, fails.
    """
    def test(context):
        out = fs.SCENARIOS[name](context)
        if not out.handled and all(f.startswith(fs.REACTION_TIME_CHECK) for f in out.failures):
            out = fs.SCENARIOS[name](context)
        assert_handled(out)
    return test


def matrix_test(name):
    """Return a test that runs field matrix ``name`` of fault_suite.MATRICES (every case)."""
    kind, cases, legs = fs.MATRICES[name]

    def test(matrices):
        assert_handled(matrices[legs].outcome(name, kind, cases))
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
test_leg_angles_out_of_five_bar_reach_fault = scenario_test('leg_out_of_reach')
test_leg_angles_bad_values_fault = matrix_test('leg_fields')

# ------------------------------------------------------------------------------ cmd_vel

test_cmd_vel_non_finite_dropped_and_absurd_limited = scenario_test('cmd_vel_invalid')
test_cmd_vel_bad_value_in_every_field = matrix_test('cmd_vel_fields')
test_cmd_vel_stamped_in_the_past_still_times_out = scenario_test('cmd_vel_stale')
test_cmd_vel_stamped_in_the_future_still_times_out = scenario_test('cmd_vel_future')
test_joy_bad_value_in_every_axis_gives_a_bounded_command = scenario_test('joy_fields')

# ---------------------------------------------------------------------------------- CAN

test_silent_motor_gives_zero_torque_within_motor_timeout = scenario_test('motor_silent')
test_reply_from_unknown_id_does_not_keep_a_motor_alive = scenario_test('reply_unknown_id')
test_replies_from_a_stranger_are_ignored = scenario_test('stranger_replies')
test_full_tx_queue_faults_and_sends_only_zero_torque_after = scenario_test('can_tx_queue_full')
test_bus_off_faults_and_sends_only_zero_torque_after = scenario_test('can_bus_off')
test_error_frame_storm_does_not_stop_balancing = scenario_test('error_frame_storm')

# --------------------------------------------------------------------------------- falls

test_imu_past_fall_angle_forward_faults_at_the_next_tick = scenario_test('fall_forward')
test_imu_past_fall_angle_backward_faults_at_the_next_tick = scenario_test('fall_backward')
test_push_past_fall_angle_on_sim_node_ends_at_rest_without_torque = \
    scenario_test('push_fall_sim_node')

# ---------------------------------------------------------------------- parameters, switch

test_bad_parameters_are_refused_and_nothing_changes = scenario_test('bad_parameters')


def test_controller_switch_at_full_speed_is_bumpless(context):
    out = assert_handled(fs.scenario_controller_switch(context))
    # The check can fail: without blending the switch to lqr jumps by far more than the bound.
    to_lqr = out.figures['to_lqr']
    assert to_lqr['unblended_nm'] > 5 * to_lqr['bound_nm']


# ---------------------------------------------------------------------------- recovery

test_recovery_only_by_explicit_rearm_while_on_the_tail = scenario_test('recovery_rearm')


LATCH_CAUSES = ('imu_stale', 'non_finite', 'fall', 'motor_silent', 'can_send')


@pytest.fixture(scope='module')
def auto_arm_bench(context):
    with fs.Bench(context, auto_arm=True) as bench:
        yield bench


@pytest.mark.parametrize('cause', LATCH_CAUSES)
def test_fault_latches_until_rearm_even_with_auto_arm(auto_arm_bench, cause):
    """
    Latch each fault cause until an explicit re-arm, auto_arm on.

    After the fault, 10 s of healthy samples at the tail rest pitch: FAULT and zero torque
    throughout, then an explicit re-arm balances again.
    """
    bench = auto_arm_bench
    tail = math.radians(36.0)
    with bench.virtual_time() as clock:
        bench.feed()
        bench.rearm()
        for _ in range(10):
            bench.feed()
            bench.tick()
        if cause == 'imu_stale':
            clock.t += 0.2          # nothing arrives for 0.2 s
            bench.node._on_joint_states(fs.make_joints())
            frames = bench.tick()
        elif cause == 'non_finite':
            bench.feed(fs.make_imu(math.nan))
            frames = bench.tick()
        elif cause == 'fall':
            bench.feed(fs.make_imu(math.radians(50.0)))
            frames = bench.tick()
        elif cause == 'motor_silent':
            clock.t += 0.2
            bench.feed()
            frames = bench.tick(replies=False)
        else:
            bench.bus.fail_with = fs.tx_queue_full()
            bench.feed()
            frames = bench.tick()
            bench.bus.fail_with = None
        assert bench.mode == fs.MODE['FAULT']
        codes = {f.code for f in bench.node.supervisor.faults}
        assert cause in codes, codes
        if cause != 'can_send':
            assert frames and all(fs.is_zero_torque(f) for _, f in frames), frames
        for _ in range(5000):   # 10 s lying on the tail, every sensor and motor healthy
            bench.feed(fs.make_imu(tail))
            frames = bench.tick()
            assert bench.mode == fs.MODE['FAULT']
            assert len(frames) == 2 and all(fs.is_zero_torque(f) for _, f in frames)
        req = bench.request(True)
        frames = bench.tick()
        assert req.success, req.message
        assert bench.mode == fs.MODE['BALANCING']
        assert [f for _, f in frames[:2]] == ['enter', 'enter']


# ----------------------------------------------------------------------------- signals

@pytest.mark.parametrize('name', ['sigint_shutdown', 'sigterm_shutdown'])
def test_signal_sends_zero_torque_then_exit_frames(context, name):
    assert_handled(fs.SCENARIOS[name](context))
