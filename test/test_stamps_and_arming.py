"""
IMU header stamps that run backwards or ahead of the clock, and the arming rules of auto_arm.

On the fault suite's bench (validation/faults/bench.LoopBench: the control tick on a virtual
clock, its frames to emulated MIT wheel motors). A refused sample is not used: the IMU goes
stale after ``imu_timeout`` (FAULT imu_stale) as if the driver had stopped.
"""
import math

from wheelleg_balance.core.protocols.mit import ENTER_MOTOR_MODE
from wheelleg_balance.core.safety import Mode
from wheelleg_balance.nodes.sensor_intake import imu_sample
from wheelleg_balance.validation.faults.bench import LoopBench, make_imu

ENOBUFS = 'Failed to transmit: [Errno 105] No buffer space available'
CLOCK0 = 1.7e9   # the node's ROS clock at the bench's start [s]


def stamped(bench, stamp: float, clock_offset: float = 0.0, theta: float = 0.02):
    """Feed one IMU sample stamped ``stamp`` [s], received when the node's clock reads ..."""
    msg = make_imu(theta)
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9))
    clock = CLOCK0 + (bench.t - 1000.0) + clock_offset
    bench.inputs.imu.append(imu_sample(msg, bench.t, clock))


def node_clock(bench) -> float:
    return CLOCK0 + (bench.t - 1000.0)


def armed(**params) -> LoopBench:
    bench = LoopBench(**params)
    for _ in range(12):   # resting motors answer the exit frames sent every 20 ms
        stamped(bench, node_clock(bench))
        bench.tick()
    req = bench.request(True)
    stamped(bench, node_clock(bench))
    bench.tick()
    assert req.success, req.message
    for _ in range(5):
        stamped(bench, node_clock(bench))
        bench.tick()
    assert bench.mode == int(Mode.BALANCING)
    return bench


def run_for(bench, seconds, feed):
    for _ in range(int(round(seconds / bench.period))):
        feed()
        bench.tick()


def test_a_stamp_ahead_of_the_clock_beyond_the_tolerance_is_refused_and_goes_stale():
    bench = armed()
    tol = bench.config.safety.stamp_tolerance
    # Within the tolerance (a clock a little ahead): used, still balancing.
    run_for(bench, 0.2, lambda: stamped(bench, node_clock(bench) + 0.5 * tol))
    assert bench.mode == int(Mode.BALANCING)
    assert bench.loop.imu.refused_stamps == 0
    # A driver whose clock runs 1 s ahead: every sample refused, stale after imu_timeout.
    t0 = bench.t
    run_for(bench, 0.2, lambda: stamped(bench, node_clock(bench) + 1.0))
    assert bench.mode == int(Mode.FAULT)
    assert [f.code for f in bench.loop.supervisor.faults] == ['imu_stale']
    fault_t = bench.loop.supervisor.faults[0].time
    assert fault_t - t0 <= bench.config.safety.imu_timeout + 2 * bench.period
    assert bench.loop.imu.refused_stamps >= 50
    assert 'ahead of our clock' in bench.safety_values()['refused_imu_reason']


def test_a_stamp_running_backwards_is_refused():
    bench = armed()
    newest = node_clock(bench)
    stamped(bench, newest)
    bench.tick()
    t0 = bench.t
    # The driver restarted with an older clock: its samples go back 5 s.
    run_for(bench, 0.2, lambda: stamped(bench, newest - 5.0 + (bench.t - t0)))
    assert bench.mode == int(Mode.FAULT)
    assert [f.code for f in bench.loop.supervisor.faults] == ['imu_stale']
    assert 'backwards' in bench.safety_values()['refused_imu_reason']


def test_unstamped_samples_and_an_unknown_clock_are_not_judged():
    bench = armed()
    msg = make_imu(0.02)   # stamp 0: an unstamped driver

    def feed():
        bench.inputs.imu.append(imu_sample(msg, bench.t))
    run_for(bench, 0.3, feed)
    assert bench.mode == int(Mode.BALANCING) and bench.loop.imu.refused_stamps == 0
    # No clock at receipt (NaN): a future stamp cannot be judged, a backwards one still is.
    stamped(bench, node_clock(bench) + 100.0, clock_offset=math.nan)
    bench.tick()
    assert bench.loop.imu.refused_stamps == 0


def test_the_tolerance_is_a_parameter():
    bench = armed(stamp_tolerance=2.0)
    run_for(bench, 0.2, lambda: stamped(bench, node_clock(bench) + 1.0))
    assert bench.mode == int(Mode.BALANCING)


# ---------------------------------------------------------------------------- auto_arm

def healthy(bench, seconds):
    run_for(bench, seconds, lambda: bench.feed())


def test_auto_arm_arms_once_and_never_after_an_operator_disarm():
    bench = LoopBench(auto_arm=True)
    healthy(bench, 0.1)
    assert bench.mode == int(Mode.BALANCING)
    req = bench.request(False)
    bench.feed()
    bench.tick()
    assert req.success and bench.mode == int(Mode.SITTING)
    # (the bench's robot does not move: a second disarm ends the sit-down at once)
    bench.request(False)
    bench.feed()
    bench.tick()
    assert bench.mode == int(Mode.DISARMED)
    # Healthy samples for 2 s: no second arm by itself.
    healthy(bench, 2.0)
    assert bench.mode == int(Mode.DISARMED)


def test_auto_arm_waits_for_steady_ticks_after_a_gap():
    """
    After a gap beyond the sensor timeouts auto_arm waits AUTO_ARM_STEADY of steady ticks.

    In lockstep the first samples can come as a burst of old stamps: the tick that armed on one
    of them was followed by one 0.38 s of stamps later, and the motors counted as silent since
    the arm (FAULT, the sim-files test). Ticks on fresh samples after the gap: no arm at once.
    """
    from wheelleg_balance.core.balance_loop import AUTO_ARM_STEADY
    bench = LoopBench(auto_arm=True)
    bench.feed()
    bench.tick()
    assert bench.mode == int(Mode.DISARMED)   # not yet steady for AUTO_ARM_STEADY
    bench.t += 0.38                           # then a gap beyond imu_timeout (fresh samples)
    steady = int(round(AUTO_ARM_STEADY / bench.period))
    modes = []
    for _ in range(steady + 5):
        bench.feed()
        bench.tick()
        modes.append(bench.mode)
    assert set(modes[:steady]) == {int(Mode.DISARMED)}, modes
    assert bench.mode == int(Mode.BALANCING)
    assert int(Mode.FAULT) not in modes


def test_auto_arm_does_not_retry_after_its_enter_motor_mode_send_failed():
    bench = LoopBench(auto_arm=True)
    tick, attempts = bench.loop.tick, []

    def failing_first_enter(now, inputs):
        # The send of the tick that carries the first enter-motor-mode frames fails.
        result = tick(now, inputs)
        enter = any(f.data == ENTER_MOTOR_MODE for f in result.frames)
        bench.fail_with = ENOBUFS if enter and not attempts else None
        attempts.extend([now] if enter else [])
        return result
    bench.loop.tick = failing_first_enter
    modes = []
    for _ in range(int(round(2.0 / bench.period))):
        bench.feed()
        bench.tick()
        modes.append(bench.mode)
    assert len(attempts) == 1   # auto_arm tried once
    assert int(Mode.BALANCING) not in modes
    assert bench.mode == int(Mode.FAULT)
    assert [f.code for f in bench.loop.supervisor.faults] == ['can_send']
