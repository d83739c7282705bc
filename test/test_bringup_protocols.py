"""
bringup on every motor protocol (issue 31): the motor set's protocol says every frame and reply.

session.BringUp runs on python-can's virtual bus against each protocol's emulated firmware in a
thread (each protocol's ``make_emulator``): wheels and hips of two protocols on one bus are found
and checked, a DaMiao or CyberGear motor in the wrong control mode is named with the fix and never
enabled, a motor's fault is told in its protocol's words, and a protocol defined in this module
(registered with ``register_protocol``, no package file changed) is named by ``can.protocol`` in a
params file as any other (the choices are read from the table when a value is checked) and runs
through the motor checks, the check by hand included, and on the control tick (the fault suite's
bench) through the motor faults: silent, error code, over-temperature.
"""
import math
import os
import pathlib
import struct
import subprocess
import sys
import threading
import time

import can
import pytest

from wheelleg_balance.bringup import robot_config
from wheelleg_balance.bringup.report import FAIL, PASS, Report
from wheelleg_balance.bringup.session import BringUp, Operator
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.protocols import make_protocol, protocol_for, PROTOCOLS, \
    register_protocol
from wheelleg_balance.core.protocols.base import Frame, MotorFeedback, MotorProtocol
from wheelleg_balance.core.protocols.emulation import EmulatedMotor, EmulatedMotors, \
    torque_only
from wheelleg_balance.core.schema import from_flat, to_flat, with_changes
from wheelleg_balance.nodes.can_io import CanIo

WHEELS = (1, 2)
HIPS = (3, 4, 5, 6)
LABELS = ['left wheel (ID 1)', 'right wheel (ID 2)', 'left front hip (ID 3)',
          'left rear hip (ID 4)', 'right front hip (ID 5)', 'right rear hip (ID 6)']


class Responder:
    """Emulated motors of any protocols ("banks") answering on a virtual bus, in a thread."""

    def __init__(self, channel, banks):
        self.bus = can.Bus(interface='virtual', channel=channel)
        self.banks = list(banks)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stop.is_set():
            msg = self.bus.recv(timeout=0.01)
            if msg is None:
                continue
            frame = Frame(msg.arbitration_id, bytes(msg.data), msg.is_extended_id)
            for bank in self.banks:
                for r in bank.handle(frame, time.monotonic()):
                    self.bus.send(can.Message(arbitration_id=r.arbitration_id, data=r.data,
                                              is_extended_id=r.is_extended_id))

    def close(self):
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()


class NoHands(Operator):
    def ask(self, step, slots, text):
        raise AssertionError('no step by hand expected')


def bank(name, ids, cfg_section):
    """Return emulated motors of protocol ``name`` with the configuration's codec."""
    # CubeMars' 8-byte MIT replies: temperature and error code.
    options = {'reply_temperature': True} if name == 'mit' else {}
    return EmulatedMotors(protocol_for(name, cfg_section), ids, **options)


def config(channel, wheels, hips=None):
    """Return a configuration with wheels (and hips, if given) of those protocols on a bus."""
    changes = {'can.interface': 'virtual', 'can.channel': channel, 'can.protocol': wheels,
               'wheel_state_source': 'joint_states', 'max_wheel_torque': 4.0}
    if hips is not None:
        changes.update({'legs.driven': True, 'legs.can.protocol': hips})
    return with_changes(BalanceConfig(), changes)


def run_find(cfg, banks, operator=None, by_hand=False):
    """Run find_motors (and by_hand) against ``banks``; return the session, the probes by item."""
    channel = cfg.can.channel
    motors = Responder(channel, banks)
    io = CanIo(can.Bus(interface='virtual', channel=channel), send_timeout=0.01)
    lines = []
    session = BringUp(cfg, [io], operator or NoHands(), lambda t: [], Report(lines.append),
                      scan_ids=range(1, 9), settle=0.1)
    try:
        session.find_motors()
        if by_hand:
            session.by_hand()
        session.exit_all()
        time.sleep(0.1)   # the responder answers in its own thread
    finally:
        io.close()
        motors.close()
    probes = {}
    for c in session.report.checks:   # each motor's first check: its probe
        probes.setdefault(c.item, c)
    return session, probes


def left_on(banks):
    """Return the IDs of motors left driven: in torque mode (the C620 from power-up: a current)."""
    return [e.motor_id for b in banks for e in b.emulators.values()
            if e.enabled and not (e.powered_enabled and e.command is not None
                                  and e.command.torque == 0.0)]


@pytest.mark.parametrize('wheels', ['lk', 'cybergear', 'damiao', 'dji_c620', 'mit'])
def test_wheels_of_each_protocol_are_found_and_checked(wheels):
    cfg = config('bringup_wheels_%s_%d' % (wheels, os.getpid()), wheels)
    banks = [bank(wheels, WHEELS, cfg.can)]
    session, checks = run_find(cfg, banks)
    for item in LABELS[:2]:
        assert checks[item].level == PASS, checks[item]
        assert '(%s)' % wheels in checks[item].text and 'temperature 25 degC' in \
            checks[item].text
    assert [s.key for s in session.found] == ['left_wheel', 'right_wheel']
    # Enabled, answered, disabled again: no motor left in its torque mode.
    assert left_on(banks) == []


@pytest.mark.parametrize('wheels, hips', [('lk', 'damiao'), ('dji_c620', 'cybergear'),
                                          ('cybergear', 'damiao'), ('damiao', 'cybergear'),
                                          ('mit', 'damiao')])
def test_wheels_and_hips_of_two_protocols_on_one_bus(wheels, hips):
    cfg = config('bringup_mixed_%s_%s_%d' % (wheels, hips, os.getpid()), wheels, hips)
    banks = [bank(wheels, WHEELS, cfg.can), bank(hips, HIPS, cfg.legs)]
    session, checks = run_find(cfg, banks)
    assert [checks[item].level for item in LABELS] == [PASS] * 6, \
        [checks[i].text for i in LABELS]
    assert all('(%s)' % hips in checks[item].text for item in LABELS[2:])
    assert len(session.found) == 6
    assert left_on(banks) == []


@pytest.mark.parametrize('hips, wrong, words', [
    ('damiao', {'control_mode': 2}, 'position-velocity mode (CTRL_MODE = 2), not MIT: write '
     'register 10 = 1'),
    ('cybergear', {'run_mode': 2}, 'speed mode (run_mode = 2), not operation control: stop '
     'it (type 4) and write run_mode 0')])
def test_a_hip_in_the_wrong_mode_is_named_with_the_fix_and_never_enabled(hips, wrong, words):
    cfg = config('bringup_mode_%s_%d' % (hips, os.getpid()), 'lk', hips)
    legs = bank(hips, HIPS, cfg.legs)
    wrong_one = legs.motor(5)
    for key, value in wrong.items():
        setattr(wrong_one, key, value)
    enables = []
    set_enabled = wrong_one.set_enabled
    wrong_one.set_enabled = lambda on, now: (enables.append(on), set_enabled(on, now))
    banks = [bank('lk', WHEELS, cfg.can), legs]
    session, checks = run_find(cfg, banks)
    right_front = checks['right front hip (ID 5)']
    assert right_front.level == FAIL and words in right_front.text, right_front.text
    assert [checks[item].level for item in LABELS if item != right_front.item] == [PASS] * 5
    assert 'right_front' not in [s.key for s in session.found]
    # Asked for its mode only: never enabled, never commanded.
    assert True not in enables and wrong_one.command is None and not wrong_one.enabled
    assert legs.motor(3).frames > 1


@pytest.mark.parametrize('wheels, code, words', [
    ('cybergear', 0b000100, 'error 4 (over-temperature)'),
    ('damiao', 0xA, 'error 10 (over-current)'), ('mit', 2, 'error 2 (over-current)')])
def test_a_motor_fault_is_told_in_its_protocols_words(wheels, code, words):
    # (LK's torque reply carries no error bits: its state-1 read, 0x9A, has them.)
    cfg = config('bringup_fault_%s_%d' % (wheels, os.getpid()), wheels)
    motors = bank(wheels, WHEELS, cfg.can)
    motors.motor(2).set_error(code)
    _, checks = run_find(cfg, [motors])
    right = checks['right wheel (ID 2)']
    assert right.level == FAIL and words in right.text, right.text
    assert checks['left wheel (ID 1)'].level == PASS


def test_a_silent_motor_and_a_wrong_id_on_a_cybergear_bus():
    cfg = config('bringup_scan_%d' % os.getpid(), 'cybergear')
    motors = bank('cybergear', (1, 7), cfg.can)   # the right wheel answers as ID 7
    _, checks = run_find(cfg, [motors])
    right = checks['right wheel (ID 2)']
    assert right.level == FAIL and 'ID 7 answers' in right.text
    assert right.fix[-1].endswith('can.right_motor_id: 7 if that motor is this one')


# ---- a protocol defined here ---------------------------------------------------------------

class _HereProtocol(MotorProtocol):
    """
    A protocol the package does not know: torque in mN m, a 4-byte reply, a mode register.

    To motor i on 0x600 + i: 1 byte enable (1) / disable (0), 2 bytes int16 torque [mN m];
    0x700 + i, no data: read the mode. Replies on 0x680 + i: int16 position [mrad], int8
    temperature [deg C], uint8 error; mode answers on 0x780 + i: one byte (0: torque mode).
    """

    name = 'bringup_test_here'
    torque_limit = 12.0   # [N m]: within the simulated wheels' actuators (sim/layout.py)

    def enable_frames(self, motor_ids):
        return [Frame(0x600 + i, b'\x01') for i in motor_ids]

    def disable_frames(self, motor_ids):
        return self.zero_torque_frames(motor_ids) + [Frame(0x600 + i, b'\x00')
                                                     for i in motor_ids]

    def torque_frames(self, torques):
        return [Frame(0x600 + i, struct.pack('<h', round(1e3 * max(-12.0, min(12.0, t)))
                                             if math.isfinite(t) else 0))
                for i, t in torques.items()]

    def zero_torque_frames(self, motor_ids):
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def decode_feedback(self, frame):
        if not 0x680 < frame.arbitration_id < 0x6FF or len(frame.data) != 4 \
                or frame.is_extended_id:
            return None
        position, temperature, error = struct.unpack('<hbB', frame.data)
        return MotorFeedback(frame.arbitration_id - 0x680, position / 1e3, 0.0, 0.0,
                             float(temperature), error)

    def command_motor_ids(self, frame):
        return (frame.arbitration_id - 0x600,) if 0x600 < frame.arbitration_id < 0x67F else ()

    def error_reason(self, code):
        return {1: 'the test motor is too hot'}.get(code, 'test code %d' % code)

    def mode_query_frames(self, motor_ids):
        return [Frame(0x700 + i, b'') for i in motor_ids]

    def mode_problem(self, frame):
        if not 0x780 < frame.arbitration_id < 0x7FF or len(frame.data) != 1:
            return None
        mode = frame.data[0]
        return frame.arbitration_id - 0x780, None if mode == 0 else (
            'in test mode %d: write 0 to its mode' % mode)

    def make_emulator(self, motor_id, **options):
        return _HereMotor(motor_id, self.torque_limit, **options)


class _HereMotor(EmulatedMotor):
    """_HereProtocol's motor: answers every frame on its IDs; ``mode`` its mode register."""

    mode = 0

    def handle(self, frame, q, q_dot, now):
        if frame.arbitration_id == 0x700 + self.motor_id:
            return Frame(0x780 + self.motor_id, bytes((self.mode,)))
        if frame.arbitration_id != 0x600 + self.motor_id:
            return None
        self.frames += 1
        if len(frame.data) == 1:
            self.set_enabled(frame.data[0] == 1, now)
        elif len(frame.data) == 2:
            self.set_command(torque_only(struct.unpack('<h', frame.data)[0] / 1e3), now)
        self.torque(q, q_dot, now)
        position = max(-32.0, min(32.0, self.position(q)))
        return Frame(0x680 + self.own_reply_id, struct.pack(
            '<hbB', round(1e3 * position), round(self.temperature), self.error))


class TurnWheels(Operator):
    """The builder's hands on emulated joints: each wheel turned forward by 1 rad."""

    def __init__(self, motors):
        self.motors = motors

    def ask(self, step, slots, text):
        assert step == 'wheel_forward'
        for s in slots:
            q, _ = self.motors.joints[s.motor_id]
            self.motors.joints[s.motor_id] = (q + 1.0, 0.0)


def test_the_configuration_names_a_protocol_once_it_is_registered(monkeypatch):
    flat = {'can.protocol': _HereProtocol.name}
    with pytest.raises(ValueError, match="unknown can.protocol 'bringup_test_here'"):
        from_flat(BalanceConfig, flat)
    monkeypatch.setitem(PROTOCOLS, _HereProtocol.name, None)
    register_protocol(_HereProtocol)
    assert from_flat(BalanceConfig, flat).can.protocol == _HereProtocol.name
    # Torque commands only (no command_frame): the hips cannot speak it.
    with pytest.raises(ValueError, match="unknown legs.can.protocol 'bringup_test_here'"):
        from_flat(BalanceConfig, {'legs.can.protocol': _HereProtocol.name})


@pytest.fixture
def here_protocol(monkeypatch):
    """Register _HereProtocol for the test (removed from the table again afterwards)."""
    monkeypatch.setitem(PROTOCOLS, _HereProtocol.name, None)
    register_protocol(_HereProtocol)
    return _HereProtocol.name


@pytest.fixture
def here_config(here_protocol, tmp_path):
    """Return a configuration whose wheels speak _HereProtocol, read from a params file."""
    flat = to_flat(config('bringup_here_%d' % os.getpid(), 'mit'))
    flat['can.protocol'] = here_protocol   # named as any package protocol is
    path = robot_config.write_params(tmp_path / 'here.yaml', robot_config.build(
        dict(flat)), ['the wheels on a protocol of test_bringup_protocols.py'])
    assert 'protocol: %s' % here_protocol in path.read_text()
    return robot_config.build(robot_config.read_params(path))


def test_a_protocol_defined_here_runs_through_the_motor_checks(here_config):
    motors = EmulatedMotors(make_protocol(_HereProtocol.name), WHEELS,
                            {1: here_config.can.left_direction,
                             2: here_config.can.right_direction})
    motors.motor(2).miswired = True    # turns the other way than configured
    motors.motor(2).set_temperature(61.0)
    session, checks = run_find(here_config, [motors], TurnWheels(motors), by_hand=True)
    left = checks['left wheel (ID 1)']
    assert left.level == PASS and '(bringup_test_here)' in left.text
    assert 'temperature 25 degC, error 0 (no error)' in left.text
    assert 'warm at rest' in checks['right wheel (ID 2)'].text
    turned = [c for c in session.report.checks if 'turned forward' in c.text]
    assert [c.level for c in turned] == [PASS, FAIL]
    assert session.changes == {'can.right_direction': 1}
    assert not any(e.enabled for e in motors.emulators.values())


def test_a_protocol_defined_here_names_its_mode_and_its_fault(here_config):
    motors = EmulatedMotors(make_protocol(_HereProtocol.name), WHEELS)
    motors.motor(1).mode = 3
    motors.motor(2).set_error(1)
    session, checks = run_find(here_config, [motors])
    assert 'in test mode 3: write 0 to its mode' in checks['left wheel (ID 1)'].text
    assert motors.motor(1).frames == 0   # only asked for its mode
    right = checks['right wheel (ID 2)']
    assert right.level == FAIL and 'error 1 (the test motor is too hot)' in right.text
    assert [s.key for s in session.found] == ['right_wheel']


# ---- the same protocol on the control tick: its motor faults ---------------------------------

def here_bench(cfg):
    """Return an armed fault-suite bench on ``cfg`` (wheels: _HereProtocol's emulated motors)."""
    from wheelleg_balance.validation.faults import bench as bench_module
    bench = bench_module.LoopBench(**to_flat(cfg))   # checked as balance_node checks it
    req = bench.arm_from_rest()
    assert req.success, req.message
    return bench


@pytest.mark.parametrize('fault, code', [('silent', 'motor_silent'), ('error', 'motor_error'),
                                         ('hot', None)])
def test_a_protocol_defined_here_runs_the_tick_and_its_motor_faults(here_config, fault, code):
    from wheelleg_balance.core.safety import Mode
    from wheelleg_balance.validation.faults.bench import make_imu
    bench = here_bench(here_config)
    assert isinstance(bench.motors, EmulatedMotors) and bench.mode == int(Mode.BALANCING)
    right = bench.motors.motor(2)
    if fault == 'silent':
        bench.motors.silent.add(2)
    elif fault == 'error':
        right.set_error(1)
    else:   # no section of its own: the figures default to the MIT section's temp_max
        right.set_temperature(here_config.can.mit.temp_max + 1.0)
    events = []
    for _ in range(100):   # 0.2 s, leaning: torque commanded
        bench.feed(make_imu(0.3, 0.0))
        bench.tick()
        events += bench.loop.last_result.events
        if bench.mode != int(Mode.BALANCING):
            break
    faults = bench.loop.supervisor.faults
    if code is None:
        assert bench.mode == int(Mode.SITTING)
        assert any('temp_max' in text for _, text in events), events
        return
    assert bench.mode == int(Mode.FAULT) and [f.code for f in faults] == [code]
    if code == 'motor_error':
        assert 'the test motor is too hot' in faults[0].message
    assert all(bench.motors.torque(i, bench.t) == 0.0 for i in WHEELS)


def test_a_hip_on_the_wheels_bus_is_found_there_in_its_own_protocol():
    wheels_bus, legs_bus = ('bringup_bus%d_%d' % (i, os.getpid()) for i in (0, 1))
    cfg = with_changes(config(wheels_bus, 'lk', 'damiao'), {'legs.can.channel': legs_bus})
    hips = bank('damiao', HIPS[:3], cfg.legs)
    astray = bank('damiao', HIPS[3:], cfg.legs)   # the right rear hip, wired to the wheels' bus
    responders = [Responder(wheels_bus, [bank('lk', WHEELS, cfg.can), astray]),
                  Responder(legs_bus, [hips])]
    ios = [CanIo(can.Bus(interface='virtual', channel=c), send_timeout=0.01)
           for c in (wheels_bus, legs_bus)]
    session = BringUp(cfg, ios, NoHands(), lambda t: [], Report(lambda line: None),
                      scan_ids=range(1, 9))
    try:
        session.find_motors()
        session.exit_all()
    finally:
        for x in ios + responders:
            x.close()
    checks = {c.item: c for c in session.report.checks}
    rear = checks['right rear hip (ID 6)']
    assert rear.level == FAIL and 'it answers on %s instead: wrong bus' % wheels_bus in rear.text
    fix = 'connect it to %s, or set legs.can.channel: %s' % (legs_bus, wheels_bus)
    assert rear.fix[0] == fix
    assert [checks[item].level for item in LABELS[:5]] == [PASS] * 5


@pytest.mark.ros
@pytest.mark.slow
def test_a_protocol_defined_here_passes_bringup_sim(tmp_path):
    # sim_node is another process: bring-up names the protocol (module:class, this module on
    # the children's path) and has sim_node load it too.
    from wheelleg_balance.validation import child_env
    env = child_env()
    env['PYTHONPATH'] = os.pathsep.join((env['PYTHONPATH'], str(pathlib.Path(__file__).parent)))
    out = tmp_path / 'robot.yaml'
    proc = subprocess.run(
        [sys.executable, '-m', 'wheelleg_balance.bringup.cli', '--sim', '--output', str(out),
         '--protocol', 'test_bringup_protocols:_HereProtocol',
         '--sim-param', 'can.protocol=%s' % _HereProtocol.name],
        capture_output=True, text=True, timeout=240, cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert '[FAIL]' not in proc.stdout
    assert proc.stdout.count('(%s): position' % _HereProtocol.name) == 2   # both wheels
    assert '[PASS] right wheel (ID 2): turned forward' in proc.stdout
    text = out.read_text()
    assert 'protocol: %s' % _HereProtocol.name in text
