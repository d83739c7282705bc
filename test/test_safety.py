"""Every transition of the safety supervisor, and the reference shaping of cmd_vel."""
import math

from hypothesis import given, settings, strategies as st
import pytest

from wheelleg_balance.core.rate_limiter import limit_rate
from wheelleg_balance.core.reference import ReferenceShaper
from wheelleg_balance.core.safety import (
    CAN_SEND, FALL, IMU_STALE, INTERNAL, JOINT_STATES_STALE, LOOP_STALL, Mode, MOTOR_SILENT,
    NON_FINITE, POSE, ROLL, SafetyLimits, SafetySupervisor, SensorSnapshot)

LIMITS = SafetyLimits(fall_angle=math.radians(45.0), imu_timeout=0.05,
                      joint_state_timeout=0.05, motor_timeout=0.05)
TAIL_REST = math.radians(36.0)


def fresh(now, theta=0.02):
    """Return samples that just arrived, robot near upright."""
    return SensorSnapshot(imu_time=now, joint_time=now, theta=theta, theta_dot=0.0,
                          wheel_vel_left=0.0, wheel_vel_right=0.0, l=0.37)


def replies(now):
    return {1: now, 2: now}


def codes(faults):
    return {f.code for f in faults}


def armed(now=10.0):
    sup = SafetySupervisor(LIMITS, motor_ids=(1, 2))
    ok, reason = sup.arm(now, fresh(now), {})
    assert ok, reason
    return sup


def test_starts_disarmed_without_torque():
    sup = SafetySupervisor(LIMITS)
    assert sup.mode is Mode.DISARMED
    assert not sup.torque_allowed
    assert sup.faults == ()


def test_disarmed_reports_conditions_but_stays_disarmed():
    sup = SafetySupervisor(LIMITS)
    mode = sup.update(1.0, SensorSnapshot(), {})
    assert mode is Mode.DISARMED
    assert codes(sup.conditions) == {IMU_STALE, JOINT_STATES_STALE}
    assert sup.faults == ()


def test_disarmed_does_not_judge_motors_that_are_not_commanded():
    sup = SafetySupervisor(LIMITS)
    sup.update(100.0, fresh(100.0), {})
    assert sup.conditions == ()


@pytest.mark.parametrize('theta', [0.0, math.radians(9.0), TAIL_REST, math.radians(44.9)])
def test_arm_accepted_upright_or_on_the_tail(theta):
    sup = SafetySupervisor(LIMITS)
    ok, reason = sup.arm(5.0, fresh(5.0, theta), {})
    assert ok, reason
    assert sup.mode is Mode.BALANCING and sup.torque_allowed


@pytest.mark.parametrize('theta,theta_dot,roll', [
    (-0.5, 0.0, 0.0),                    # leaning back: neither upright nor on the tail
    # between the upright window and the tail's
    (0.5 * (LIMITS.upright_pitch + LIMITS.tail_pitch - LIMITS.tail_tolerance), 0.0, 0.0),
    (0.0, 1.0, 0.0),                     # upright but swinging: not still
    (TAIL_REST, 0.0, math.radians(15.0)),  # on the tail but tipped sideways
])
def test_arm_refused_from_an_implausible_pose(theta, theta_dot, roll):
    sup = SafetySupervisor(LIMITS)
    s = fresh(5.0, theta)
    s.theta_dot, s.roll = theta_dot, roll
    ok, reason = sup.arm(5.0, s, {})
    assert not ok and 'pose' in reason
    assert codes(sup.conditions) == {POSE} and sup.mode is Mode.DISARMED


def test_a_robot_lying_on_its_side_is_a_fault_and_cannot_arm():
    """On its side the pitch reads 0: the roll tells (core/attitude.py)."""
    sup = armed(10.0)
    s = fresh(10.1)
    s.roll = math.radians(90.0)
    assert sup.update(10.1, s, replies(10.1)) is Mode.FAULT
    assert codes(sup.faults) == {ROLL}
    ok, reason = sup.arm(10.2, s, replies(10.2))
    assert not ok and 'fall_roll_angle' in reason


def test_homing_then_balancing_then_sitting_down():
    sup = SafetySupervisor(LIMITS)
    ok, reason = sup.start_homing(5.0, fresh(5.0, TAIL_REST), {})
    assert ok and sup.mode is Mode.HOMING and not sup.torque_allowed
    # The motors are commanded while homing: a silent one is a fault ...
    assert sup.update(5.04, fresh(5.04, TAIL_REST), replies(5.04)) is Mode.HOMING
    ok, reason = sup.arm(5.05, fresh(5.05, TAIL_REST), replies(5.05))
    assert ok and sup.mode is Mode.BALANCING
    assert sup.sit_down() and sup.mode is Mode.SITTING and sup.torque_allowed
    assert not sup.sit_down()
    # ... and while sitting down, as while balancing.
    assert sup.update(5.2, fresh(5.2), {1: 5.2}) is Mode.FAULT
    assert codes(sup.faults) == {MOTOR_SILENT}


def test_a_reported_fault_latches_while_commanding_only():
    sup = SafetySupervisor(LIMITS)
    assert sup.report_fault(1.0, LOOP_STALL, 'stalled') is Mode.DISARMED
    sup = armed(10.0)
    assert sup.report_fault(10.1, LOOP_STALL, 'loop stalled 80 ms') is Mode.FAULT
    assert codes(sup.faults) == {LOOP_STALL}


@pytest.mark.parametrize('snapshot,code', [
    (SensorSnapshot(joint_time=5.0, theta=0.0, theta_dot=0.0, wheel_vel_left=0.0,
                    wheel_vel_right=0.0, l=0.4), IMU_STALE),
    (SensorSnapshot(imu_time=4.9, joint_time=5.0, theta=0.0, theta_dot=0.0, wheel_vel_left=0.0,
                    wheel_vel_right=0.0, l=0.4), IMU_STALE),
    (SensorSnapshot(imu_time=5.0, joint_time=4.9, theta=0.0, theta_dot=0.0, wheel_vel_left=0.0,
                    wheel_vel_right=0.0, l=0.4), JOINT_STATES_STALE),
    (SensorSnapshot(imu_time=5.0, joint_time=5.0, theta=math.nan, theta_dot=0.0,
                    wheel_vel_left=0.0, wheel_vel_right=0.0, l=0.4), NON_FINITE),
    (SensorSnapshot(imu_time=5.0, joint_time=5.0, theta=0.0, theta_dot=0.0,
                    wheel_vel_left=math.inf, wheel_vel_right=0.0, l=0.4), NON_FINITE),
    (SensorSnapshot(imu_time=5.0, joint_time=5.0, theta=0.0, theta_dot=0.0, wheel_vel_left=0.0,
                    wheel_vel_right=0.0, l=math.nan), NON_FINITE),
    (SensorSnapshot(imu_time=5.0, joint_time=5.0, theta=-math.radians(46.0), theta_dot=0.0,
                    wheel_vel_left=0.0, wheel_vel_right=0.0, l=0.4), FALL),
])
def test_arm_refused_with_a_reason_while_a_condition_is_present(snapshot, code):
    sup = SafetySupervisor(LIMITS)
    ok, reason = sup.arm(5.0, snapshot, {})
    assert not ok
    assert reason.startswith('arming refused')
    assert codes(sup.conditions) == {code}
    assert sup.mode is Mode.DISARMED and not sup.torque_allowed


def test_sensor_timeouts():
    sup = armed(10.0)
    s = fresh(10.0)
    assert sup.update(10.049, s, replies(10.049)) is Mode.BALANCING
    assert sup.update(10.051, s, replies(10.051)) is Mode.FAULT
    assert codes(sup.faults) == {IMU_STALE, JOINT_STATES_STALE}


@pytest.mark.parametrize('change,code', [
    ({'imu_time': 10.0}, IMU_STALE),
    ({'joint_time': 10.0}, JOINT_STATES_STALE),
    ({'theta': math.nan}, NON_FINITE),
    ({'theta_dot': -math.inf}, NON_FINITE),
    ({'wheel_vel_right': math.nan}, NON_FINITE),
    ({'theta': math.radians(45.5)}, FALL),
    ({'theta': -math.radians(60.0)}, FALL),
])
def test_each_condition_while_balancing_is_a_fault(change, code):
    sup = armed(10.0)
    now = 10.2
    s = fresh(now)
    for name, value in change.items():
        setattr(s, name, value)
    assert sup.update(now, s, replies(now)) is Mode.FAULT
    assert not sup.torque_allowed
    assert codes(sup.faults) == {code}
    assert all(f.message for f in sup.faults)


def test_silent_motor_is_a_fault_after_motor_timeout_only():
    sup = armed(10.0)
    t = 10.0
    # Both motors answer every tick for a while.
    while t < 10.5:
        t += 0.002
        assert sup.update(t, fresh(t), replies(t)) is Mode.BALANCING
    last_right = t
    # Motor 2 goes quiet: still fine inside motor_timeout, a fault just after it.
    while t < last_right + 0.048:
        t += 0.002
        assert sup.update(t, fresh(t), {1: t, 2: last_right}) is Mode.BALANCING
    t = last_right + 0.052
    assert sup.update(t, fresh(t), {1: t, 2: last_right}) is Mode.FAULT
    (fault,) = sup.faults
    assert fault.code == MOTOR_SILENT and 'motor 2' in fault.message


def test_motor_that_never_answers_after_arm_is_a_fault():
    sup = armed(10.0)
    assert sup.update(10.04, fresh(10.04), {1: 10.04}) is Mode.BALANCING
    assert sup.update(10.06, fresh(10.06), {1: 10.06}) is Mode.FAULT
    assert codes(sup.faults) == {MOTOR_SILENT}


def test_can_send_failure_while_balancing_is_a_fault():
    sup = armed(10.0)
    assert sup.report_send(10.01, True) is Mode.BALANCING
    assert sup.report_send(10.012, False, 'Transmit buffer full') is Mode.FAULT
    (fault,) = sup.faults
    assert fault.code == CAN_SEND and 'Transmit buffer full' in fault.message


def test_fault_is_never_left_by_itself():
    sup = armed(10.0)
    sup.update(10.1, fresh(10.0), replies(10.1))  # IMU and joints stale
    assert sup.mode is Mode.FAULT
    first = sup.faults
    t = 10.1
    for _ in range(2000):  # 4 s of healthy ticks
        t += 0.002
        assert sup.update(t, fresh(t), replies(t)) is Mode.FAULT
        sup.report_send(t, True)
    assert sup.conditions == ()
    assert sup.faults == first  # the latched reason stays for the operator


def test_rearm_from_fault_refused_while_condition_present_then_accepted():
    sup = armed(10.0)
    sup.update(10.1, fresh(10.1, theta=1.0), replies(10.1))
    assert sup.mode is Mode.FAULT
    ok, reason = sup.arm(10.2, fresh(10.2, theta=1.0), replies(10.2))
    assert not ok and 'fall_angle' in reason
    assert sup.mode is Mode.FAULT
    ok, reason = sup.arm(10.3, fresh(10.3, theta=TAIL_REST), replies(10.3))
    assert ok, reason
    assert sup.mode is Mode.BALANCING and sup.faults == ()


def test_rearm_refused_while_a_motor_stays_silent_in_fault():
    sup = armed(10.0)
    sup.update(10.1, fresh(10.1), {1: 10.1})
    assert codes(sup.faults) == {MOTOR_SILENT}
    ok, reason = sup.arm(10.5, fresh(10.5), {1: 10.5})
    assert not ok and 'motor 2' in reason
    ok, reason = sup.arm(10.6, fresh(10.6), replies(10.6))
    assert ok, reason


def test_rearm_refused_while_the_last_send_failed():
    sup = armed(10.0)
    sup.report_send(10.1, False, 'bus off')
    assert sup.mode is Mode.FAULT
    ok, reason = sup.arm(10.2, fresh(10.2), replies(10.2))
    assert not ok and 'bus off' in reason
    sup.report_send(10.25, True)  # the zero-torque frames of FAULT go through again
    ok, reason = sup.arm(10.3, fresh(10.3), replies(10.3))
    assert ok, reason


def test_internal_error_is_a_fault_while_commanding_only():
    sup = SafetySupervisor(LIMITS)
    assert sup.report_internal_error(1.0, 'ZeroDivisionError') is Mode.DISARMED
    sup = armed(10.0)
    assert sup.report_internal_error(10.1, 'ZeroDivisionError') is Mode.FAULT
    assert codes(sup.faults) == {INTERNAL} and 'ZeroDivisionError' in sup.faults[0].message
    sup.report_internal_error(10.2, 'again')
    assert len(sup.faults) == 1


def test_send_failure_in_fault_adds_a_reason_once():
    sup = armed(10.0)
    sup.update(10.1, fresh(10.1, theta=math.nan), replies(10.1))
    sup.report_send(10.11, False, 'bus off')
    sup.report_send(10.12, False, 'bus off')
    assert [f.code for f in sup.faults] == [NON_FINITE, CAN_SEND]


@pytest.mark.parametrize('setup', ['balancing', 'fault'])
def test_disarm_from_any_mode(setup):
    sup = armed(10.0)
    if setup == 'fault':
        sup.update(10.1, fresh(10.1, theta=2.0), replies(10.1))
        assert sup.mode is Mode.FAULT
    sup.disarm()
    assert sup.mode is Mode.DISARMED and not sup.torque_allowed and sup.faults == ()
    # Motors are no longer commanded: their silence is not a condition any more.
    sup.update(20.0, fresh(20.0), {})
    assert sup.conditions == ()


def test_send_error_while_disarmed_does_not_block_arming():
    sup = SafetySupervisor(LIMITS)
    sup.report_send(1.0, False, 'exit frame lost')
    assert sup.mode is Mode.DISARMED
    ok, reason = sup.arm(1.1, fresh(1.1), {})
    assert ok, reason
    assert sup.update(1.102, fresh(1.102), replies(1.102)) is Mode.BALANCING


def test_arm_while_balancing_is_a_no_op():
    sup = armed(10.0)
    ok, reason = sup.arm(10.01, fresh(10.01, theta=2.0), replies(10.01))
    assert ok and sup.mode is Mode.BALANCING


# ----------------------------------------------------------------- reference shaping (cmd_vel)

def test_reference_ramps_at_the_acceleration_limit_and_saturates():
    shaper = ReferenceShaper(max_velocity=0.8, max_acceleration=1.0, max_yaw_rate=2.0,
                             max_yaw_acceleration=4.0, cmd_vel_timeout=0.5)
    dt = 0.002
    x, w = shaper.update(0.0, 0.0, 5.0, -5.0, dt)
    assert x == pytest.approx(1.0 * dt) and w == pytest.approx(-4.0 * dt)
    t = 0.0
    for _ in range(499):  # 1 s in total, command refreshed at 0 s every tick
        t += dt
        x, w = shaper.update(t, t, 5.0, -5.0, dt)
    assert x == pytest.approx(0.8)  # velocity limit
    assert w == pytest.approx(-2.0)
    assert not shaper.timed_out


def test_stale_cmd_vel_ramps_the_reference_to_zero():
    shaper = ReferenceShaper(max_velocity=1.0, max_acceleration=2.0, cmd_vel_timeout=0.5)
    dt = 0.002
    t = 0.0
    for _ in range(500):
        t += dt
        shaper.update(t, t, 0.6, 1.0, dt)
    assert shaper.x_dot_ref == pytest.approx(0.6)
    last_cmd = t
    history = []
    while t < last_cmd + 1.5:
        t += dt
        history.append(shaper.update(t, last_cmd, 0.6, 1.0, dt))
    xs = [h[0] for h in history]
    # Held while the command is fresh, then down to zero at the acceleration limit (0.3 s).
    fresh_ticks = int(0.5 / dt) - 1
    assert all(x == pytest.approx(0.6) for x in xs[:fresh_ticks])
    ramp = xs[fresh_ticks + 1:]
    assert all(b <= a for a, b in zip(ramp, ramp[1:]))
    assert max(a - b for a, b in zip(xs, xs[1:])) == pytest.approx(2.0 * dt)
    assert xs[-1] == 0.0 and history[-1][1] == 0.0
    assert shaper.timed_out


def test_no_command_yet_means_zero_and_reset_restarts_from_rest():
    shaper = ReferenceShaper()
    assert shaper.update(1.0, None, 1.0, 1.0, 0.002) == (0.0, 0.0)
    assert shaper.timed_out
    for k in range(100):
        shaper.update(1.0 + k * 0.002, 1.0, 1.0, 1.0, 0.002)
    assert shaper.x_dot_ref > 0.0
    shaper.reset()
    assert (shaper.x_dot_ref, shaper.yaw_rate_ref) == (0.0, 0.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.booleans()), min_size=1,
                max_size=60),
       st.floats(0.1, 2.0), st.floats(0.1, 5.0))
def test_reference_never_exceeds_its_limits(commands, v_max, a_max):
    shaper = ReferenceShaper(max_velocity=v_max, max_acceleration=a_max, max_yaw_rate=v_max,
                             max_yaw_acceleration=a_max, cmd_vel_timeout=0.5)
    dt = 0.002
    prev = (0.0, 0.0)
    for k, (x_cmd, w_cmd, stale) in enumerate(commands):
        now = k * dt
        ref = shaper.update(now, now - 1.0 if stale else now, x_cmd, w_cmd, dt)
        for r, p in zip(ref, prev):
            assert abs(r) <= v_max + 1e-12
            assert abs(r - p) <= a_max * dt + 1e-12
        prev = ref


def test_limit_rate():
    assert limit_rate(1.0, 0.0, 10.0, 0.01) == pytest.approx(0.1)
    assert limit_rate(-1.0, 0.0, 10.0, 0.01) == pytest.approx(-0.1)
    assert limit_rate(0.05, 0.0, 10.0, 0.01) == 0.05
