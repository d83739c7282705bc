"""
LK wheels' health query on the tick (issue 31): the state-1 read (0x9A) brings the error bits.

LK's torque reply (state-2 layout) has no error bits, so the tick asks one wheel at a time
with 0x9A every ``health_interval`` (core/protocols/lk.py). On the fault suite's bench with
LK's own emulated motors (a latched error switches the output off and shows in the 0x9A
reply): the fault within the documented latency, measured at every phase of the query's turn;
no false fault; frames per tick and the catch-up budget with the query's frame.
"""
import math

import pytest
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.motor_health import judge_motors
from wheelleg_balance.core.motors import MotorSet
from wheelleg_balance.core.protocols.lk import LkProtocol, READ_STATE1
from wheelleg_balance.core.safety import Mode
from wheelleg_balance.core.schema import from_flat
from wheelleg_balance.nodes.control_runner import ControlRunner
from wheelleg_balance.validation.faults.bench import LoopBench

LK = {'can.protocol': 'lk', 'max_wheel_torque': 4.0, 'wheel_state_source': 'joint_states'}


def armed(**params):
    bench = LoopBench(**{**LK, **params})
    assert bench.arm_from_rest().success
    assert bench.mode == int(Mode.BALANCING)
    return bench


def queries(bench):
    """Return the motor IDs the tick just asked with 0x9A."""
    return [f.arbitration_id - 0x140 for f in bench.sent if f.data[0] == READ_STATE1]


def documented_latency_ticks(bench) -> int:
    """docs/faults.md: each wheel asked every 2 health_interval, then two ticks to FAULT."""
    return math.ceil(2 * bench.loop.protocol.health_interval / bench.period - 1e-9) + 2


@pytest.mark.parametrize('side', (0, 1))
def test_a_latched_error_faults_within_the_documented_latency_at_every_phase(side):
    latencies = []
    for phase in range(12):   # every position in the query's turn (10 ticks) and beyond
        bench = armed()
        for _ in range(phase):
            bench.feed()
            bench.tick()
        motor_id = bench.loop.motors.ids[side]
        emulator = bench.motors.motor(motor_id)
        emulator.set_error(0x01)
        # The motor switches its output off at once (V2.35: the error state stops it).
        assert bench.motors.torque(motor_id, bench.t) == 0.0
        for n in range(1, 100):
            bench.feed()
            bench.tick()
            if bench.mode == int(Mode.FAULT):
                break
        latencies.append(n)
        faults = bench.loop.supervisor.faults
        assert [f.code for f in faults] == ['motor_error']
        name = bench.loop.motors.motors[side].name
        assert 'motor %d (%s)' % (motor_id, name) in faults[0].message
        assert 'under-voltage' in faults[0].message
    assert max(latencies) <= documented_latency_ticks(bench), latencies
    assert min(latencies) < max(latencies)   # the phase matters: the turn is measured


def test_a_healthy_lk_robot_balances_on_asking_each_wheel_in_turn():
    bench = armed()
    asked = []
    for _ in range(500):   # 1 s
        bench.feed()
        bench.tick()
        asked += queries(bench)
    assert bench.mode == int(Mode.BALANCING)
    assert bench.loop.arming.motor_problems == []
    ids = bench.loop.motors.ids
    per_motor = 1.0 / (2 * bench.loop.protocol.health_interval)   # 50 a second each
    assert [asked.count(i) for i in ids] == [pytest.approx(per_motor, abs=1)] * 2
    assert all(a != b for a, b in zip(asked, asked[1:]))   # in turn


def test_the_frames_of_a_tick_and_the_catch_up_budget_count_the_query():
    bench = armed()
    ids = bench.loop.motors.ids
    most = 0
    for _ in range(50):
        bench.feed()
        bench.tick()
        most = max(most, len(bench.sent))
    assert most == bench.loop.protocol.frames_per_tick(ids) == 3
    short = {**LK, 'can.tx_queue_len': 9}
    # Three frames a tick at most: two missed ticks and this one fill nine.
    assert ControlRunner.catch_up_limit(from_flat(BalanceConfig, short), False) == 2
    mit = from_flat(BalanceConfig, {'can.tx_queue_len': 9})
    assert ControlRunner.catch_up_limit(mit, False) == 3   # no query: two frames a tick


def test_the_default_mit_robot_sends_no_query_and_keeps_the_plain_torques():
    bench = LoopBench()
    actuation = bench.loop.actuation
    assert 'torques' not in vars(actuation)   # the class's method: no health code per tick
    assert bench.loop.motors._decode_health is None


def test_the_state1_reply_feeds_the_temperature_and_the_error_code():
    p = LkProtocol()
    motors = MotorSet(p, [('left_wheel', 1, 1), ('right_wheel', 2, -1)])
    motors.on_frame(0.0, p.encode_reply(1, 0xA1, 40, 0, 0.0, 0))
    assert motors.on_frame(0.001, p.encode_status(1, READ_STATE1, 90.0, 24.0, 0x08)) is None
    model = BalanceConfig().can.lk
    scale, hot, problems = judge_motors([(motors, model)], motors, lambda m: m.name)
    assert hot is not None and '90 deg C' in hot
    assert ('motor_error', 'left_wheel error 8: over-temperature') in problems
    # Another motor's reply, a torque reply: no health record.
    assert p.decode_health(p.encode_status(5, READ_STATE1, 30.0, 24.0, 0)) is not None
    motors.on_frame(0.002, p.encode_status(5, READ_STATE1, 30.0, 24.0, 0x01))
    assert motors.by_id[2].error == 0
    assert p.decode_health(p.encode_reply(1, 0xA1, 40, 0, 0.0, 0)) is None
