"""
The control tick on every wheel-motor protocol (issue 31): arm, torque, disarm, the motor faults.

The fault suite's bench (validation/faults/bench.LoopBench: BalanceLoop on a virtual clock) with
the configured protocol's own emulated motors (bench.wheel_motors: core/protocols'
``make_emulator`` for each; MIT's with 8-byte replies, temperature and error code, as CubeMars
firmware sends them): what the tick sends is what the emulated firmware acts on, its replies are
what the tick reads. The motor faults on each protocol: a silent motor, error bits (every protocol
whose reply carries them, and LK by its state-1 read: not the C620's feedback), an
over-temperature, a reboot; and the second-commander check. Wheel speeds come from joint states;
max_wheel_torque 4 N m is within each model's limit.
"""
import math

import pytest
from wheelleg_balance.core.protocols.emulation import EmulatedMotors
from wheelleg_balance.core.protocols.mit import MitMotorEmulator
from wheelleg_balance.core.safety import Mode
import wheelleg_balance.validation.faults.bench as bench_module
from wheelleg_balance.validation.faults.bench import LoopBench, make_imu

PROTOCOLS = ('mit', 'dji_c620', 'lk', 'cybergear', 'damiao')
LIMIT = 4.0
#: The bench's own choice of motors (the fixture below sets the MIT motors' reply length).
BENCH_MOTORS = bench_module.wheel_motors


def wheel_motors(loop):
    """Return the bench's motors (each protocol's own), MIT's with 8-byte replies."""
    motors = BENCH_MOTORS(loop)
    for e in motors.emulators.values():
        if isinstance(e, MitMotorEmulator):
            e.reply_temperature = True   # CubeMars' 8-byte replies: temperature, error code
    return motors


@pytest.fixture
def make_bench(monkeypatch):
    """Return a maker of armed benches whose wheel motors speak ``protocol``."""
    monkeypatch.setattr(bench_module, 'wheel_motors', wheel_motors)

    def make(protocol, wheel_angle=0.0, **params):
        bench = LoopBench(**{'can.protocol': protocol, 'max_wheel_torque': LIMIT,
                             'wheel_state_source': 'joint_states', **params})
        bench.set_wheel_motion((wheel_angle, 0.0), (0.0, 0.0))   # before the first reply
        req = bench.arm_from_rest()
        assert req.success, req.message
        assert bench.mode == int(Mode.BALANCING)
        return bench
    return make


def test_the_bench_builds_each_protocols_own_motors():
    for protocol in PROTOCOLS:
        bench = LoopBench(**{'can.protocol': protocol, 'max_wheel_torque': LIMIT,
                             'wheel_state_source': 'joint_states'})
        assert isinstance(bench.motors, EmulatedMotors)
        assert bench.motors.protocol is bench.loop.protocol


def health_latency_ticks(bench) -> int:
    """Return the ticks until every wheel was asked once (health_interval; 0: no query)."""
    interval = bench.loop.protocol.health_interval
    ids = bench.loop.motors.ids
    return math.ceil(len(ids) * interval / bench.period - 1e-9) if interval else 0


def lean(bench, ticks=5):
    for _ in range(ticks):
        bench.feed(make_imu(0.3, 0.0))
        bench.tick()


def applied(bench):
    """Return the joint torques the emulated motors apply now [N m] (left, right)."""
    return [bench.motors.torque(i, bench.t) for i in bench.loop.motors.ids]


def no_torque(bench) -> bool:
    """Tell whether both motors give none: zero, or the zero command's code (one step)."""
    step = 2.0 * bench.loop.protocol.torque_limit / 4095   # the coarsest field: 12 bits
    return all(abs(tau) <= step for tau in applied(bench))


@pytest.mark.parametrize('protocol', PROTOCOLS)
def test_the_tick_drives_the_motors_and_disarms_them(make_bench, protocol):
    bench = make_bench(protocol)
    lean(bench)   # leaning forward: the torque saturates at max_wheel_torque
    assert bench.wheel_torques() == (pytest.approx(LIMIT), pytest.approx(LIMIT))
    # Both wheels forward at the shaft, the right motor mirrored by its direction (-1); one
    # code step of each protocol's torque field at most.
    assert applied(bench) == [pytest.approx(LIMIT, abs=0.01)] * 2
    bench.estop()
    bench.tick()
    assert bench.mode == int(Mode.DISARMED)
    assert applied(bench) == [0.0, 0.0]   # out of torque mode: nothing at all
    if bench.loop.protocol.enable_frames(bench.loop.motors.ids):   # the C620 has no mode
        assert not any(e.enabled for e in bench.motors.emulators.values())
    else:
        assert all(e.command.torque == 0.0 for e in bench.motors.emulators.values())


@pytest.mark.parametrize('protocol', PROTOCOLS)
def test_a_silent_motor_faults(make_bench, protocol):
    bench = make_bench(protocol)
    bench.motors.silent.add(bench.loop.motors.ids[0])
    for _ in range(100):   # 0.2 s
        bench.feed()
        bench.tick()
        if bench.mode == int(Mode.FAULT):
            break
    assert bench.mode == int(Mode.FAULT)
    assert no_torque(bench)


@pytest.mark.parametrize('protocol, code, reason', [
    ('mit', 1, 'motor over-temperature'), ('mit', 5, 'encoder fault'),
    ('cybergear', 0b000100, 'over-temperature'), ('cybergear', 0b000001, 'under-voltage'),
    ('damiao', 0xB, 'MOS over-temperature'), ('damiao', 0xA, 'over-current'),
    # LK's torque reply has no error bits: the tick's state-1 read (0x9A) brings them.
    ('lk', 0x08, 'over-temperature'), ('lk', 0x01, 'under-voltage')])
def test_a_motor_fault_faults_the_tick_with_the_protocols_reason(make_bench, protocol, code,
                                                                 reason):
    bench = make_bench(protocol)
    left = bench.loop.motors.ids[0]
    bench.motors.motor(left).set_error(code)
    # The motor answers with the fault, the next tick reads it; where the protocol asks for
    # it (health_interval), once the query to this motor has gone out.
    for _ in range(2 + health_latency_ticks(bench)):
        bench.feed()
        bench.tick()
        if bench.mode == int(Mode.FAULT):
            break
    assert bench.mode == int(Mode.FAULT)
    faults = bench.loop.supervisor.faults
    assert [f.code for f in faults] == ['motor_error'] and reason in faults[0].message
    assert no_torque(bench)


@pytest.mark.parametrize('protocol', PROTOCOLS)
def test_an_over_temperature_sits_down(make_bench, protocol):
    bench = make_bench(protocol, fall_angle=1.0)
    model = getattr(bench.config.can, bench.loop.protocol.config_section)
    bench.motors.motor(bench.loop.motors.ids[1]).set_temperature(model.temp_max + 1.0)
    events = []
    for _ in range(3):
        lean(bench, 1)
        events += bench.loop.last_result.events
    assert bench.mode == int(Mode.SITTING)
    assert any('deg C' in text and 'temp_max' in text for _, text in events), events


@pytest.mark.parametrize('protocol, angle, reason', [
    # MIT knows its angle modulo a rotor turn of its 9:1 gear after power-up (40 deg).
    ('mit', 5.0, 'position jumped'), ('mit', 0.3, 'position jumped'),
    # Both lose the turn count at power-up (CyberGear also its zero): 5 rad reads otherwise
    # (DaMiao: within +-pi, 5 - 2 pi; CyberGear: within a rotor turn of its 7.75:1 gear).
    ('cybergear', 5.0, ''), ('damiao', 5.0, 'position jumped'),
    # At 0.3 rad a DaMiao motor reads the same after power-up: no jump. Its replies say
    # "disabled" where they said "enabled": the reboot shows there.
    ('cybergear', 0.3, ''), ('damiao', 0.3, 'answered disabled while commanded')])
def test_a_reboot_faults(make_bench, protocol, angle, reason):
    bench = make_bench(protocol, wheel_angle=angle)
    left = bench.loop.motors.ids[0]
    bench.motors.motor(left).reboot(angle)
    for _ in range(3):
        bench.feed()
        bench.tick()
    assert bench.mode == int(Mode.FAULT)
    faults = bench.loop.supervisor.faults
    assert [f.code for f in faults] == ['motor_rebooted'] and reason in faults[0].message
    assert no_torque(bench)


@pytest.mark.parametrize('protocol', ('lk', 'dji_c620'))
def test_a_reboot_loses_nothing_the_tick_needs(make_bench, protocol):
    # LK's and the C620's single-turn encoders are absolute and the motor takes the next
    # torque command after power-up: the reading stays, the torque comes back at once (a
    # boot's silence is the liveness check's, test_a_silent_motor_faults).
    bench = make_bench(protocol, wheel_angle=3.0)
    left = bench.loop.motors.ids[0]
    lean(bench, 3)
    bench.motors.motor(left).reboot(3.0)
    assert applied(bench)[0] == 0.0
    lean(bench, 3)
    assert bench.mode == int(Mode.BALANCING)
    assert applied(bench)[0] == pytest.approx(LIMIT, abs=0.01)
    fb = bench.loop.motors.by_id[left].feedback
    span = bench.loop.protocol.position_span   # LK: a turn; the C620: a rotor turn
    assert fb.position == pytest.approx(3.0 % span, abs=1e-3) and math.isfinite(fb.velocity)


def _foreign_commands():
    """Per protocol: a command of another sender to wheel motor 1 (not one of ours)."""
    from wheelleg_balance.core.protocols import make_protocol
    mit, dji, lk, cg, dm = (make_protocol(n) for n in PROTOCOLS)
    return {'mit': mit.command_frame(1, 0.0, 0.0, 5.0, 0.1, 0.0),      # MIT on ID 1, kp 5
            'dji_c620': dji.torque_frames({3: 0.5})[0],                # 0x200: ESCs 1-4
            'lk': lk.torque_frames({1: 0.5})[0],                       # 0xA1 on 0x141
            'cybergear': cg.command_frame(1, 0.0, 0.0, 5.0, 0.1, 0.0),  # type 1, kp 5
            'damiao': dm.command_frame(1, 0.0, 0.0, 5.0, 0.1, 0.0)}     # MIT on ID 1


@pytest.mark.parametrize('protocol', PROTOCOLS)
def test_a_second_commander_faults_the_tick_and_its_replies_do_not(make_bench, protocol):
    bench = make_bench(protocol)
    for _ in range(25):   # the motors' own replies (and LK's run echo) are no commands
        bench.feed()
        bench.tick()
    assert bench.mode == int(Mode.BALANCING)
    bench.feed()
    bench.inputs.frames.append((bench.t + bench.period, _foreign_commands()[protocol]))
    bench.tick()
    assert bench.mode == int(Mode.FAULT)
    faults = bench.loop.supervisor.faults
    assert [f.code for f in faults] == ['input_conflict'] and 'another sender' in \
        faults[0].message
    assert no_torque(bench)


class MixedBench(LoopBench):
    """
    LoopBench with driven legs: wheels and hips each on their protocol's emulators, one bus.

    The hips (IDs 3..6) start at NOMINAL_LEGS with the configured offsets as their zero
    (``legs.homing: set_zero``: homed at once); the hips' frames go out after the wheels'.
    """

    def __init__(self, **params):
        super().__init__(**{'legs.driven': True, **params})
        loop = self.loop
        hips = loop.legs.controller.motors
        self.hip_ids = tuple(hips.motor_ids)
        for i, q, offset, d in zip(self.hip_ids, bench_module.NOMINAL_LEGS, hips.offsets,
                                   hips.directions):
            e = loop.legs.protocol.make_emulator(i, direction=d)
            e.zero = d * offset
            self.motors.emulators[i] = e
            self.motors.joints[i] = (q, 0.0)
        self.motors.ids = tuple(self.motors.emulators)

    def tick(self, replies=True):
        """Run one tick; the wheels' and the hips' frames reach the motors, replies come back."""
        self.t += self.period
        if replies:
            self.inputs.frames.extend((self.t, f) for f in self._replies)
        result = self.loop.tick(self.t, self.inputs)
        self.inputs.clear()
        self.sent = list(result.frames) + list(result.leg_frames)
        self._replies = [r for f in self.sent for r in self.motors.handle(f, self.t)]
        self.after_tick(result)
        return self.sent


@pytest.mark.parametrize('wheels, hips, hip_ids', [
    ('lk', 'damiao', None), ('lk', 'cybergear', None), ('cybergear', 'damiao', None),
    # A DaMiao reply's byte 0 is its ID and status (0x11: motor 1 enabled), which MIT hips
    # 17..20 read as their own ID: the wheels' replies must reach the wheels.
    ('damiao', 'mit', [17, 18, 19, 20])])
def test_mixed_robots_arm_hold_their_legs_and_disarm(make_bench, wheels, hips, hip_ids):
    ids = {} if hip_ids is None else {'legs.motor_ids': hip_ids}
    bench = MixedBench(**{'can.protocol': wheels, 'legs.can.protocol': hips,
                          'max_wheel_torque': LIMIT, 'wheel_state_source': 'joint_states',
                          **ids})
    req = bench.arm_from_rest()
    assert req.success, req.message
    sent = []
    for _ in range(50):   # 0.1 s balancing
        bench.feed()
        sent.append(bench.tick())
    assert bench.mode == int(Mode.BALANCING), bench.loop.supervisor.faults
    # legs.command_divider 2: the legs take turns, two hips a tick beside both wheels; LK
    # wheels ask one of them for its error bits (0x9A) every health_interval besides.
    protocol = bench.loop.protocol
    health = {f for i in bench.loop.motors.ids for f in protocol.health_frames(i)}
    queries = [sum(f in health for f in frames) for frames in sent]
    assert [len(frames) - q for frames, q in zip(sent, queries)] == [4] * len(sent)
    interval = protocol.health_interval
    assert sum(queries) == (round(50 * bench.period / interval) if interval else 0)
    limit = bench.loop.legs.protocol.torque_limit
    hip_torques = [bench.motors.torque(i, bench.t) for i in bench.hip_ids]
    assert all(0.0 < abs(tau) <= limit + 1e-9 for tau in hip_torques), hip_torques
    bench.estop()
    bench.tick()
    bench.tick()
    assert bench.mode == int(Mode.DISARMED)
    assert not any(e.enabled for e in bench.motors.emulators.values())
    assert len(bench.motors.ids) == 6
    assert all(bench.motors.torque(i, bench.t) == 0.0 for i in bench.motors.ids)


@pytest.mark.parametrize('protocol', ('cybergear', 'damiao'))
def test_a_disarm_s_disabled_replies_are_no_reboot(make_bench, protocol):
    bench = make_bench(protocol)
    bench.estop()
    for _ in range(5):
        bench.feed()
        bench.tick()
    assert bench.mode == int(Mode.DISARMED)
    assert not any(m.rebooted for m in bench.loop.motors.motors)
    assert not bench.loop.supervisor.faults
