"""
The watchdog (nodes/watchdog.py): its decision on a fake clock, the heartbeat, the stop frames.

The whole reaction, a balance_node process whose control process is stopped or killed while it
balances, measured on the bus, is in test_faults.py (control_process_stalled / _killed).
"""
import os
import threading
import time
import uuid

from can.interfaces.virtual import VirtualBus
import pytest

from wheelleg_balance.core.balance_loop import all_stop_frames, BalanceLoop
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.core.schema import with_changes
from wheelleg_balance.nodes import watchdog as wd

TIMEOUT = 0.1


class FakeTime:
    """A clock that only moves when the watchdog sleeps."""

    def __init__(self):
        self.t = 100.0

    def clock(self):
        return self.t

    def sleep(self, dt):
        self.t += dt


@pytest.fixture
def heartbeat():
    hb = wd.Heartbeat()
    yield hb
    hb.close()
    os.close(hb.fd)


def make_dog(hb, ft, alive=lambda: True):
    fired = []
    dog = wd.Watchdog(hb, TIMEOUT, alive, lambda state, age: fired.append((state, age)),
                      clock=ft.clock, sleep=ft.sleep)
    return dog, fired


def test_a_commanding_loop_that_stops_beating_is_fired_at_the_timeout_not_before(heartbeat):
    ft = FakeTime()
    dog, fired = make_dog(heartbeat, ft)
    heartbeat.beat(ft.t, True)
    ft.t += 0.099
    assert dog.check() and not fired
    ft.t += 0.002
    assert not dog.check()
    assert [s for s, _ in fired] == [wd.FIRED_STALL]
    assert fired[0][1] == pytest.approx(0.102)   # the age, after the confirming read
    assert heartbeat.describe()['fired'] and heartbeat.state()[0] == wd.FIRED_STALL


def test_a_stale_heartbeat_of_a_loop_that_commands_nothing_is_left_alone(heartbeat):
    ft = FakeTime()
    dog, fired = make_dog(heartbeat, ft)
    heartbeat.beat(ft.t, False)   # DISARMED or FAULT: the motors hold no torque of ours
    ft.t += 10.0
    assert dog.check() and not fired


def test_a_beat_between_the_two_reads_keeps_it_quiet(heartbeat):
    """The confirming read: a stale time seen once (a torn read, a late beat) does not fire."""
    ft = FakeTime()
    fired = []

    def sleep(dt):
        ft.t += dt
        heartbeat.beat(ft.t, True)   # the loop beats during the confirmation
    dog = wd.Watchdog(heartbeat, TIMEOUT, lambda: True, lambda s, a: fired.append(s),
                      clock=ft.clock, sleep=sleep)
    heartbeat.beat(ft.t, True)
    ft.t += 0.2
    assert dog.check() and not fired


@pytest.mark.parametrize('commanding,state', [(True, wd.FIRED_DIED), (False, wd.ENDED_CLEAN)])
def test_a_dead_control_process_is_fired_on_only_if_it_was_commanding(
        heartbeat, commanding, state):
    ft = FakeTime()
    dog, fired = make_dog(heartbeat, ft, alive=lambda: False)
    heartbeat.beat(ft.t, commanding)
    assert not dog.check()
    assert [s for s, _ in fired] == ([state] if commanding else [])
    assert heartbeat.state()[0] == state


def test_a_loop_that_ended_with_its_stop_frames_needs_no_watchdog(heartbeat):
    ft = FakeTime()
    dog, fired = make_dog(heartbeat, ft, alive=lambda: False)
    heartbeat.beat(ft.t, True)
    heartbeat.end()
    ft.t += 1.0
    assert not dog.check() and not fired
    assert heartbeat.state()[0] == wd.ENDED_CLEAN


@pytest.mark.parametrize('ends', [True, False])
def test_on_its_own_stop_it_gives_the_loop_the_timeout_to_end(heartbeat, ends):
    """balance_node ends: the loop gets one timeout for its own stop frames, else it fires."""
    ft = FakeTime()
    fired = []
    polls = []

    def sleep(dt):
        ft.t += dt
        polls.append(ft.t)
        if not (ends and len(polls) >= 5):
            heartbeat.beat(ft.t, True)   # still balancing, beating on time
        elif len(polls) == 5:
            heartbeat.end()
    dog = wd.Watchdog(heartbeat, TIMEOUT, lambda: True, lambda s, a: fired.append(s),
                      clock=ft.clock, sleep=sleep)
    heartbeat.beat(ft.t, True)
    dog.run(lambda: len(polls) >= 2)
    if ends:
        assert fired == [] and heartbeat.state()[0] == wd.ENDED_CLEAN
    else:
        assert fired == [wd.FIRED_STALL]
        assert polls[-1] - polls[1] == pytest.approx(TIMEOUT, abs=TIMEOUT / 10 + 1e-9)


def test_the_heartbeat_is_shared_through_its_fd(heartbeat):
    """The control process and the watchdog map the same memfd (inherited by fd number)."""
    other = wd.Heartbeat(os.dup(heartbeat.fd))
    try:
        heartbeat.beat(12.5, True)
        assert other.loop() == (12.5, wd.COMMANDING)
        other.set_state(wd.FIRED_STALL, 0.25)
        assert heartbeat.describe() == {'state': wd.FIRED_STALL, 'fired': True,
                                        'stall': 0.25, 'text': wd.STATE_TEXT[wd.FIRED_STALL]}
    finally:
        other.close()
        os.close(other.fd)


def test_diagnostics_read_a_closed_heartbeat_as_closed_not_an_exception():
    """balance_node's diagnostics timer may run while shutdown() unmaps the heartbeat (CI)."""
    hb = wd.Heartbeat()
    hb.set_state(wd.WATCHING)
    assert hb.describe()['state'] == wd.WATCHING
    hb.close()
    os.close(hb.fd)
    out = hb.describe()
    assert out['state'] == wd.CLOSED and not out['fired'] and out['text'] == wd.STATE_TEXT[
        wd.CLOSED]


@pytest.mark.parametrize('legs', [False, True])
def test_the_watchdog_stops_every_motor_as_the_loop_does(legs):
    """all_stop_frames: zero torque then exit for each wheel (and hip) motor, as the loop's."""
    cfg = BalanceConfig()
    if legs:
        cfg = with_changes(cfg, {'legs.driven': True})   # hips 3..6 by default
    wheels, hips = all_stop_frames(cfg)
    assert (wheels, hips) == BalanceLoop(cfg).stop_frames()
    mit = MitProtocol()
    ids = [cfg.can.left_motor_id, cfg.can.right_motor_id]
    for frames, motor_ids in ((wheels, ids), (hips, [3, 4, 5, 6] if legs else [])):
        assert sorted({f.arbitration_id for f in frames}) == sorted(motor_ids)
        for i in motor_ids:
            seq = [mit.decode_command(f) for f in frames if f.arbitration_id == i]
            assert seq[-1] == 'exit' and len(seq) >= 2   # zero torque first, exit last
            assert all(c.torque == pytest.approx(0.0, abs=0.01) for c in seq[:-1])


def test_the_control_runner_beats_commanding_while_armed_and_ends_the_heartbeat(heartbeat):
    """The ControlRunner beats at each pass: commanding while BALANCING, then ENDED."""
    from wheelleg_balance.nodes import control_link as L
    from wheelleg_balance.nodes.control_runner import ControlRunner
    from wheelleg_balance.nodes.sensor_intake import imu_sample
    from wheelleg_balance.validation.faults.bench import make_imu
    from wheelleg_balance.validation.faults.doubles import FakeMotors

    channel = 'wlb-%s' % uuid.uuid4().hex
    motors = FakeMotors(VirtualBus(channel=channel))
    ros_end, loop_end = L.socket_pair()
    runner = ControlRunner(BalanceConfig(), VirtualBus(channel=channel), L.Link(loop_end),
                           realtime_options=False, heartbeat=heartbeat)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    ros = L.Link(ros_end)
    try:
        deadline = time.monotonic() + 5.0
        while heartbeat.loop()[0] == 0.0 and time.monotonic() < deadline:
            time.sleep(0.01)
        t, flags = heartbeat.loop()
        assert flags == 0 and abs(time.monotonic() - t) < 1.0   # beating, DISARMED
        ros.send_object(L.ARM, (7, True))   # before the watchdog watches: refused
        for _ in range(20):
            ros.send_imu(imu_sample(make_imu(0.0), time.monotonic()))
            time.sleep(0.002)
        early = [p for tag, p in ros.receive() if tag == L.ARM_REPLY]
        assert early and early[0][:2] == (7, False) and 'watchdog' in early[0][2], early
        heartbeat.set_state(wd.WATCHING)   # the watchdog's part: arming waits for it
        replies = []
        for k in range(150):
            ros.send_imu(imu_sample(make_imu(0.0), time.monotonic()))
            if k == 20:
                ros.send_object(L.ARM, (1, True))
            replies += [p for tag, p in ros.receive() if tag == L.ARM_REPLY]
            time.sleep(0.002)
        assert replies and replies[0][1], replies
        assert heartbeat.loop()[1] == wd.COMMANDING   # BALANCING
        assert time.monotonic() - heartbeat.loop()[0] < 0.5
    finally:
        runner.stop()
        thread.join(5.0)
        ros.close()
        motors.close()
    assert heartbeat.loop()[1] == wd.ENDED   # after the stop frames


def test_the_tick_neither_auto_arms_nor_arms_while_unguarded():
    """TickInputs.guarded False (the watchdog not yet watching): auto_arm waits, ~/arm refused."""
    from wheelleg_balance.validation.faults.bench import LoopBench, MODE
    bench = LoopBench(auto_arm=True)
    bench.inputs.guarded = False
    for _ in range(100):
        bench.feed()
        bench.tick()
    assert bench.mode == MODE['DISARMED']
    bench.inputs.guarded = True
    bench.feed()
    bench.tick()
    assert bench.mode == MODE['BALANCING']   # auto_arm, once guarded

    bench = LoopBench()
    bench.inputs.guarded = False
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert not req.success and 'watchdog' in req.message
    assert bench.mode == MODE['DISARMED']


def test_a_gap_before_arming_is_no_loop_stall_but_one_while_balancing_is():
    """
    A tick long after the previous one: harmless before arming (no torque of ours was held).

    In lockstep with auto_arm the first ticks come in a burst once the loop runs: the tick that
    armed saw a 1.1 s gap and faulted `loop_stall` at once (the sim-files test beside a CPU hog).
    """
    from wheelleg_balance.validation.faults.bench import LoopBench, MODE
    bench = LoopBench()
    bench.feed()
    bench.estop()
    bench.tick()                      # stop frames: the motors answer at the next tick
    bench.t += 1.1                    # the loop did not run for 1.1 s, then arms at once
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert req.success and bench.mode == MODE['BALANCING'], bench.safety_values()['faults']
    bench.feed()
    bench.tick()
    bench.t += 1.1                    # now a stall while balancing: FAULT loop_stall
    bench.feed()
    bench.tick()
    assert bench.mode == MODE['FAULT']
    assert 'loop_stall' in [c for c, _ in bench.safety_values()['faults']]


class _Running:
    """A stand-in for the watchdog's process that runs until told it has exited."""

    returncode = None

    def poll(self):
        return self.returncode


def test_balance_node_waits_until_the_watchdog_has_started_even_if_it_fired_already():
    """CI, 2026-12-06: the loop armed and was killed before the shell polled: not a failure."""
    dog = wd.WatchdogProcess(TIMEOUT)
    dog.process = _Running()
    try:
        for state in (wd.WATCHING, wd.FIRED_DIED, wd.FIRED_STALL, wd.ENDED_CLEAN):
            dog.heartbeat.set_state(state)
            dog.wait(time.monotonic() + 1.0)   # returns: it has started
        dog.heartbeat.set_state(wd.STARTING)
        with pytest.raises(RuntimeError, match='did not start'):
            dog.wait(time.monotonic() + 0.05)   # still starting when the time is up
        dog.process.returncode = 1
        with pytest.raises(RuntimeError, match=r'exit code 1'):
            dog.wait(time.monotonic() + 5.0)    # its process ended while starting
    finally:
        dog.heartbeat.close()
