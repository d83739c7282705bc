"""
bringup: each judgement on recorded data, the procedure on a virtual bus, and `bringup --sim`.

- The CAN interface checks read ``ip -details -json link show`` output. This machine has no
  SocketCAN (no ``can`` or ``vcan`` kernel module), so the CAN outputs are written in iproute2's
  format (the keys ip/iplink_can.c prints: ``restart_ms``, ``bittiming.bitrate``, ``state``,
  ``berr_counter``; the link keys ``flags``, ``operstate``, ``txqlen``, ``link_type`` as this
  machine's ``ip -details -json link show lo`` prints them, which is recorded verbatim below).
- The motor probe and the refusal run session.BringUp on python-can's virtual bus against the
  firmware emulators (sim/motor_emulator.MitMotorBank).
- `bringup --sim` runs the installed command's code against a sim_node process: without a
  fault every check passes; a miswired wheel or hip motor (``fault.miswired_motor_id``) is
  named with the exact fix, and the written config carries it.
"""
import json
import math
import os
import pathlib
import re
import subprocess
import sys
import threading
import time

import can
import pytest

from wheelleg_balance.bringup import imu_check, iplink, motor_checks as mc, robot_config
from wheelleg_balance.bringup.report import FAIL, INFO, PASS, Report, WARN
from wheelleg_balance.bringup.session import BringUp, Operator, Refused
from wheelleg_balance.core.attitude import quaternion_from_rpy, quaternion_multiply
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.core.schema import with_changes
from wheelleg_balance.nodes.can_io import CanIo
from wheelleg_balance.sim.motor_emulator import MitMotorBank
from wheelleg_balance.validation import child_env

REPO = pathlib.Path(__file__).resolve().parents[1]

# ---- the CAN interface ---------------------------------------------------------------------

#: `ip -details -json link show lo` on this machine (2026-12-01), verbatim.
LOOPBACK = ('[{"ifindex":1,"ifname":"lo","flags":["LOOPBACK","UP","LOWER_UP"],"mtu":65536,'
            '"qdisc":"noqueue","operstate":"UNKNOWN","linkmode":"DEFAULT","group":"default",'
            '"txqlen":1000,"link_type":"loopback","address":"00:00:00:00:00:00","broadcast":'
            '"00:00:00:00:00:00","promiscuity":0,"allmulti":0,"min_mtu":0,"max_mtu":0,'
            '"inet6_addr_gen_mode":"eui64","num_tx_queues":1,"num_rx_queues":1,"gso_max_size":'
            '65536,"gso_max_segs":65535,"tso_max_size":524280,"tso_max_segs":65535,'
            '"gro_max_size":65536}]')


def _can_link(up=True, bitrate=1000000, restart_ms=100, txqlen=1000, state='ERROR-ACTIVE'):
    data = {'ctrlmode_supported': ['LOOPBACK', 'LISTEN-ONLY', 'TRIPLE-SAMPLING', 'ONE-SHOT',
                                   'BERR-REPORTING'],
            'state': state, 'berr_counter': {'tx': 0, 'rx': 0}, 'restart_ms': restart_ms,
            'bittiming_const': {'name': 'gs_usb', 'tseg1': {'min': 1, 'max': 16},
                                'tseg2': {'min': 1, 'max': 8}, 'sjw': {'min': 1, 'max': 4},
                                'brp': {'min': 1, 'max': 1024}, 'brp_inc': 1},
            'clock': 48000000}
    if bitrate is not None:
        data['bittiming'] = {'bitrate': bitrate, 'sample_point': '0.875', 'tq': 20,
                             'prop_seg': 21, 'phase_seg1': 21, 'phase_seg2': 6, 'sjw': 1,
                             'brp': 1}
    link = {'ifindex': 4, 'ifname': 'can0',
            'flags': ['NOARP', 'UP', 'LOWER_UP', 'ECHO'] if up else ['NOARP', 'ECHO'],
            'mtu': 16, 'qdisc': 'pfifo_fast', 'operstate': 'UP' if up else 'DOWN',
            'linkmode': 'DEFAULT', 'group': 'default', 'txqlen': txqlen, 'link_type': 'can',
            'promiscuity': 0, 'allmulti': 0, 'min_mtu': 0, 'max_mtu': 0,
            'linkinfo': {'info_kind': 'can', 'info_data': data}, 'num_tx_queues': 1,
            'num_rx_queues': 1, 'gso_max_size': 65536, 'gso_max_segs': 65535}
    return json.dumps([link])


def test_a_well_set_interface_passes():
    checks = iplink.check_link(_can_link(), 'can0')
    assert [c.level for c in checks] == [PASS]
    assert 'up, 1000000 bit/s, restart-ms 100, txqueuelen 1000, ERROR-ACTIVE' in checks[0].text


def test_the_kernel_defaults_get_the_exact_missing_lines():
    # A new adapter: no bitrate, restart-ms 0, the 10-frame queue, down.
    checks = iplink.check_link(_can_link(up=False, bitrate=None, restart_ms=0, txqlen=10),
                               'can0')
    assert all(c.level == FAIL for c in checks)
    text = ' | '.join(c.text for c in checks)
    assert 'bitrate is not set' in text and 'restart-ms is 0' in text
    assert 'txqueuelen is 10' in text and 'is down' in text
    fixes = [f for c in checks for f in c.fix]
    assert fixes == ['sudo ip link set can0 down',
                     'sudo ip link set can0 type can bitrate 1000000 restart-ms 100',
                     'sudo ip link set can0 up', 'sudo ip link set can0 txqueuelen 1000']


def test_only_what_is_missing_is_printed():
    checks = iplink.check_link(_can_link(restart_ms=0), 'can0')
    assert len(checks) == 1 and checks[0].level == FAIL
    assert checks[0].fix[1] == 'sudo ip link set can0 type can bitrate 1000000 restart-ms 100'
    checks = iplink.check_link(_can_link(txqlen=100), 'can0')
    assert [c.fix for c in checks] == [['sudo ip link set can0 txqueuelen 1000']]
    checks = iplink.check_link(_can_link(bitrate=500000), 'can0')
    assert 'bitrate is 500000 bit/s' in checks[0].text


def test_a_bus_off_controller_is_named_with_its_likely_causes():
    checks = iplink.check_link(_can_link(state='BUS-OFF'), 'can0')
    assert [c.level for c in checks] == [FAIL]
    assert 'BUS-OFF' in checks[0].text and 'termination' in checks[0].text
    checks = iplink.check_link(_can_link(state='ERROR-WARNING', restart_ms=0), 'can0')
    assert [c.level for c in checks] == [FAIL, INFO]


def test_no_interface_a_loopback_and_a_vcan_are_told_apart():
    missing = iplink.check_link(None, 'can0')
    assert missing[0].level == FAIL and 'no such network interface' in missing[0].text
    assert 'sudo ip link set can0 txqueuelen 1000' in missing[0].fix
    assert iplink.check_link(LOOPBACK, 'lo')[0].text == 'is not a CAN interface (link type ' \
        'loopback)'
    vcan = json.loads(LOOPBACK)
    vcan[0].update(link_type='can', linkinfo={'info_kind': 'vcan'})
    assert iplink.check_link(json.dumps(vcan), 'vcan0')[0].level == WARN
    # The real command on this machine: no can0 here.
    assert iplink.ip_link_json('can_no_such_if') is None
    assert json.loads(iplink.ip_link_json('lo'))[0]['ifname'] == 'lo'


# ---- motors: pure judgements ---------------------------------------------------------------

CFG = with_changes(BalanceConfig(), {'legs.driven': True})
SLOTS = mc.motor_slots(CFG)


def _slot(key):
    return next(s for s in SLOTS if s.key == key)


def test_the_six_motors_and_their_parameters():
    assert [(s.key, s.motor_id, s.direction) for s in SLOTS] == [
        ('left_wheel', 1, 1), ('right_wheel', 2, -1), ('left_front', 3, 1),
        ('left_rear', 4, 1), ('right_front', 5, 1), ('right_rear', 6, 1)]
    assert _slot('right_wheel').direction_param == 'can.right_direction'
    assert _slot('right_rear').direction_param == 'legs.directions[3]'
    two = with_changes(CFG, {'legs.can.channel': 'can1'})
    assert mc.channels(two) == ['can0', 'can1']
    assert {s.bus for s in mc.motor_slots(two) if s.kind == 'hip'} == {1}


def test_a_wheel_turned_forward_checks_its_direction():
    right = _slot('right_wheel')   # direction -1: a forward turn reads negative
    check, changes = mc.wheel_check(right, {'right_wheel': -1.2, 'left_wheel': 0.1}, SLOTS)
    assert check.level == PASS and changes == {}
    check, changes = mc.wheel_check(right, {'right_wheel': 1.2}, SLOTS)
    assert check.level == FAIL and changes == {'can.right_direction': 1}
    assert check.fix == ['can.right_direction: 1']


def test_crossed_wheel_ids_and_a_wheel_that_did_not_turn():
    left = _slot('left_wheel')
    check, changes = mc.wheel_check(left, {'left_wheel': 0.01, 'right_wheel': -1.0}, SLOTS)
    assert check.level == FAIL and 'crossed' in check.text
    assert changes == {'can.left_motor_id': 2, 'can.right_motor_id': 1}
    check, changes = mc.wheel_check(left, {'left_wheel': 0.2, 'right_wheel': 0.0}, SLOTS)
    assert check.level == FAIL and 'no turn seen' in check.text and changes == {}


def test_a_leg_checks_directions_and_offsets():
    stop = {'left_front': -0.2, 'left_rear': -0.2}
    stretch = {'left_front': 0.25, 'left_rear': -0.2}   # the rear hip reads the other way
    offsets = [0.0] * 4
    checks, changes = mc.leg_checks(0, SLOTS, stop, stretch, [-0.2] * 4, offsets, 'set_zero')
    levels = {(c.item, c.level) for c in checks}
    assert ('left front hip (ID 3)', PASS) in levels
    assert ('left rear hip (ID 4)', FAIL) in levels
    assert changes['legs.directions'] == {1: -1}
    # With the corrected direction the rear hip's reading -0.2 at the stop means an offset of
    # -0.4 rad: not the configured 0.
    assert changes['legs.offsets'] == {1: -0.4}


def test_a_hip_powered_up_a_rotor_turn_away_is_named():
    turn = 2.0 * math.pi / 9.0
    stop = {'right_front': -0.2 - turn, 'right_rear': -0.2}
    stretch = {'right_front': 0.3, 'right_rear': 0.3}
    checks, changes = mc.leg_checks(1, SLOTS, stop, stretch, [-0.2] * 4, [0.0] * 4, 'set_zero')
    front = [c for c in checks if c.item == 'right front hip (ID 5)' and 'stop' in c.text][0]
    assert front.level == FAIL and '1.00 rotor turns' in front.text
    assert changes['legs.offsets'] == {2: round(turn, 4)}
    # Homing at the hard stops measures the offset at every start: a note, not a failure.
    checks, _ = mc.leg_checks(1, SLOTS, stop, stretch, [-0.2] * 4, [0.0] * 4, 'hard_stops')
    assert not [c for c in checks if c.level == FAIL]


def test_unwrapping_across_the_reply_range():
    u = mc.Unwrapper(MitProtocol(p_min=-12.5, p_max=12.5))
    for p in (12.0, 12.4, -12.4, -12.0):   # forward through +12.5 = -12.5
        u.update(p)
    assert u.value == pytest.approx(13.0)


# ---- the IMU -------------------------------------------------------------------------------

TAIL = math.radians(36.0)


def _samples(body_pitch, mount_rpy, n=20, orientation=True):
    q_wb = quaternion_from_rpy(0.0, body_pitch, 0.3)
    q_bi = quaternion_from_rpy(*mount_rpy)
    q_wi = quaternion_multiply(q_wb, q_bi)
    # Specific force: +g up, in IMU coordinates (the mounting's inverse of up in the body).
    from wheelleg_balance.core.attitude import ImuMounting, quaternion_conjugate, rotation_matrix
    r = rotation_matrix(quaternion_conjugate(q_wi))
    f = tuple(9.81 * r[i][2] for i in range(3))
    ImuMounting(mount_rpy)
    q = q_wi if orientation else (0.0, 0.0, 0.0, 0.0)
    return [imu_check.ImuSample(q, 0.0 if orientation else -1.0, (0.0, 0.0, 0.0), f)] * n


def test_the_imu_at_the_tail_rest_passes_with_its_mounting():
    pitch = TAIL + math.radians(2.2)   # d = 2.2 deg
    checks, changes = imu_check.imu_checks(_samples(pitch, (0, 0, math.pi)), (0, 0, math.pi),
                                           TAIL, math.radians(10.0))
    assert checks[0].level == PASS
    assert changes == {'tail_pitch': round(pitch, 4)}


@pytest.mark.parametrize('mount', [(0.0, 0.0, math.pi), (math.pi, 0.0, 0.0),
                                   (0.5 * math.pi, 0.0, 0.0), (0.0, 0.0, 0.5 * math.pi)],
                         ids=['yawed_180', 'upside_down', 'rolled_90', 'yawed_90'])
@pytest.mark.parametrize('orientation', [True, False], ids=['quaternion', 'gravity'])
def test_a_wrong_mounting_is_found_among_the_square_ones(mount, orientation):
    samples = _samples(TAIL, mount, orientation=orientation)
    checks, changes = imu_check.imu_checks(samples, (0.0, 0.0, 0.0), TAIL, math.radians(10.0))
    assert checks[-1].level == FAIL and 'mounted otherwise' in checks[-1].text
    found = changes['imu_mounting_rpy']
    # The suggestion is the mounting itself (the same rotation, whatever its rpy spelling).
    again, _ = imu_check.imu_checks(samples, found, TAIL, math.radians(10.0))
    assert again[0].level == PASS
    assert len(imu_check.square_mountings()) == 24


def test_no_imu_or_not_on_the_tail_fails():
    assert imu_check.imu_checks([], (0, 0, 0), TAIL, 0.17)[0][0].level == FAIL
    upright = _samples(0.0, (0, 0, 0))
    checks, changes = imu_check.imu_checks(upright, (0, 0, 0), TAIL, math.radians(10.0))
    assert checks[-1].level == FAIL and 'not the tail rest' in checks[-1].text
    assert changes == {}


# ---- the config file -----------------------------------------------------------------------

def test_the_filled_config_is_valid_and_reads_back(tmp_path):
    base = robot_config.build(robot_config.read_params(REPO / 'config' / 'balance.yaml'))
    cfg, _ = robot_config.filled_config(with_changes(base, {'legs.driven': True}), {
        'can.left_direction': -1, 'legs.offsets': {1: 0.6981}, 'tail_pitch': 0.65,
        'imu_mounting_rpy': [0.0, 0.0, math.pi]})
    path = robot_config.write_params(tmp_path / 'robot.yaml', cfg, ['checked', ''])
    assert path.read_text().startswith('# checked\n#\nbalance_node:')
    back = robot_config.build(robot_config.read_params(path))
    assert back == cfg
    assert back.can.left_direction == -1 and back.legs.offsets == [0.0, 0.6981, 0.0, 0.0]
    with pytest.raises(ValueError, match='tail_pitch'):
        robot_config.filled_config(base, {'tail_pitch': 5.0})


# ---- the procedure on a virtual bus --------------------------------------------------------

class Responder:
    """Firmware emulators answering on a virtual bus, in a thread."""

    def __init__(self, channel, bank):
        self.bus = can.Bus(interface='virtual', channel=channel)
        self.bank = bank
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stop.is_set():
            msg = self.bus.recv(timeout=0.01)
            if msg is None:
                continue
            for r in self.bank.handle(Frame(msg.arbitration_id, bytes(msg.data),
                                            msg.is_extended_id), time.monotonic()):
                self.bus.send(can.Message(arbitration_id=r.arbitration_id, data=r.data,
                                          is_extended_id=r.is_extended_id))

    def close(self):
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()


class NoHands(Operator):
    def ask(self, step, slots, text):
        raise AssertionError('no step by hand expected')


def _session(channel, lines, owners=lambda: []):
    cfg = with_changes(CFG, {'can.interface': 'virtual', 'can.channel': channel})
    io = CanIo(can.Bus(interface='virtual', channel=channel), send_timeout=0.01)
    return BringUp(cfg, [io], NoHands(), lambda t: [], Report(lines.append), owners=owners,
                   scan_ids=range(1, 13)), io


def test_a_motor_with_a_wrong_id_an_error_and_a_silent_one_are_named():
    channel = 'bringup_probe_%d' % os.getpid()
    bank = MitMotorBank((1, 2, 3, 4, 9), reply_temperature=True)   # ID 9 where 5 is expected
    bank.motor(2).set_error(1)
    bank.motor(3).set_temperature(61.0)
    motors = Responder(channel, bank)
    lines = []
    session, io = _session(channel, lines)
    try:
        session.find_motors()
        sent = bank.motor(1).frames
        session.exit_all()
        end = time.monotonic() + 2.0   # the responder answers in its own thread
        while bank.motor(1).frames < sent + 2 and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        io.close()
        motors.close()
    by_item = {c.item: c for c in session.report.checks}
    assert by_item['left wheel (ID 1)'].level == PASS
    assert 'temperature 25 degC, error 0 (no error)' in by_item['left wheel (ID 1)'].text
    assert by_item['right wheel (ID 2)'].level == FAIL
    assert 'error 1 (motor over-temperature)' in by_item['right wheel (ID 2)'].text
    assert by_item['left front hip (ID 3)'].level == WARN
    right_front = by_item['right front hip (ID 5)']
    assert right_front.level == FAIL and 'ID 9 answers' in right_front.text
    assert 'legs.motor_ids[2]: 9' in right_front.fix[0]
    assert [s.key for s in session.found] == ['left_wheel', 'right_wheel', 'left_front',
                                              'left_rear']
    # Entered motor mode and left it again: every motor that answered is in rest mode.
    assert not any(e.enabled for e in bank.emulators.values())
    assert bank.motor(1).last_decoded == 'exit'


def test_nothing_answering_lists_the_wiring_causes():
    channel = 'bringup_silent_%d' % os.getpid()
    lines = []
    session, io = _session(channel, lines)
    try:
        session.find_motors()
    finally:
        io.close()
    text = session.report.checks[0].text
    assert 'nothing answers' in text and 'termination' in text and 'protocol mit' in text


def test_refuses_beside_a_balance_node_or_motor_traffic():
    channel = 'bringup_owner_%d' % os.getpid()
    lines = []
    session, io = _session(channel, lines, owners=lambda: ['/balance_node'])
    with pytest.raises(Refused, match='/balance_node runs'):
        session.check_owner()
    io.close()
    # Someone else commanding the left wheel: MIT motors speak only when spoken to.
    other = can.Bus(interface='virtual', channel=channel)
    stop = threading.Event()

    def drive():
        while not stop.is_set():
            other.send(can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False))
            time.sleep(0.002)
    t = threading.Thread(target=drive, daemon=True)
    t.start()
    session, io = _session(channel, lines)
    try:
        with pytest.raises(Refused, match='a command to left wheel'):
            session.check_owner()
    finally:
        stop.set()
        t.join()
        other.shutdown()
        io.close()


# ---- bringup --sim -------------------------------------------------------------------------

def _bringup_sim(tmp_path, *params, robot=None):
    """Run bringup --sim with sim_node parameters (NAME=VALUE), on robot's params file."""
    out = tmp_path / 'robot.yaml'
    args = [sys.executable, '-m', 'wheelleg_balance.bringup.cli', '--sim', '--output', str(out)]
    if robot is not None:
        args += ['--sim-config', robot]
    for p in params:
        args += ['--sim-param', p]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=240, cwd=tmp_path,
                          env=child_env())
    return proc, out


def _levels(stdout):
    out = {}
    for line in stdout.splitlines():
        if line.startswith('['):
            out.setdefault(line.split(']', 1)[1].split(':', 1)[0].strip(), set()).add(line[1:5])
    return out


@pytest.mark.ros
@pytest.mark.slow
def test_bringup_sim_passes_on_a_well_wired_robot(tmp_path):
    proc, out = _bringup_sim(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert '[FAIL]' not in proc.stdout
    levels = _levels(proc.stdout)
    for item in ('left wheel (ID 1)', 'right wheel (ID 2)', 'left front hip (ID 3)',
                 'right rear hip (ID 6)', 'IMU (/imu)', 'bus'):
        assert levels[item] <= {'PASS', 'INFO'} and 'PASS' in levels[item], (item, proc.stdout)
    cfg = robot_config.build(robot_config.read_params(out))
    assert (cfg.can.left_direction, cfg.can.right_direction) == (1, -1)
    assert cfg.legs.directions == [1, 1, 1, 1] and cfg.legs.offsets == [0.0] * 4


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize('motor_id,item,param,fixed', [
    (1, 'left wheel (ID 1)', 'can.left_direction: -1', ('can', 'left_direction', -1)),
    (4, 'left rear hip (ID 4)', 'legs.directions[1]: -1', ('legs', 'directions', [1, -1, 1, 1])),
], ids=['wheel', 'hip'])
def test_bringup_sim_catches_a_miswired_motor(tmp_path, motor_id, item, param, fixed):
    proc, out = _bringup_sim(tmp_path, 'fault.miswired_motor_id=%d' % motor_id)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    fails = [line for line in proc.stdout.splitlines() if line.startswith('[FAIL]')]
    assert len(fails) == 1 and fails[0].startswith('[FAIL] %s:' % item), proc.stdout
    assert 'the direction is wrong' in fails[0]
    assert '       fix: %s' % param in proc.stdout
    cfg = robot_config.build(robot_config.read_params(out))
    section, name, value = fixed
    assert getattr(getattr(cfg, section), name) == value
    assert out.read_text().splitlines()[2].startswith('# FAIL %s' % item)


def _robot_file(robot):
    """Return the package's sim_node params file of another simulated robot (main_job's)."""
    from wheelleg_balance.validation.paper.main_job.params import config_dir
    return 'sim_%s.yaml' % robot, str(config_dir() / ('sim_%s.yaml' % robot))


@pytest.mark.ros
@pytest.mark.slow
def test_bringup_sim_passes_with_lk_wheels_and_damiao_hips(tmp_path):
    name, path = _robot_file('lk_damiao')
    proc, out = _bringup_sim(tmp_path, robot=path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert '[FAIL]' not in proc.stdout and name in proc.stdout.splitlines()[0]
    levels = _levels(proc.stdout)
    for item in ('left wheel (ID 1)', 'right rear hip (ID 6)', 'IMU (/imu)'):
        assert levels[item] <= {'PASS', 'INFO'} and 'PASS' in levels[item], (item, proc.stdout)
    assert '(ID 1): answers on' in proc.stdout and '(lk): position' in proc.stdout
    assert proc.stdout.count('(damiao): position') == 4
    # The written config speaks both protocols with the robot's figures.
    cfg = robot_config.build(robot_config.read_params(out))
    assert (cfg.can.protocol, cfg.legs.protocol) == ('lk', 'damiao')
    assert cfg.can.lk.torque_constant == 0.32 and cfg.safety.max_wheel_torque == 5.28


@pytest.mark.ros
@pytest.mark.slow
def test_bringup_sim_finds_a_cybergear_hip_in_the_wrong_mode(tmp_path):
    _, path = _robot_file('c620_cybergear')
    proc, out = _bringup_sim(tmp_path, 'fault.wrong_mode_motor_id=5', robot=path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    fails = [line for line in proc.stdout.splitlines() if line.startswith('[FAIL]')]
    assert len(fails) == 1 and fails[0].startswith('[FAIL] right front hip (ID 5):'), \
        proc.stdout
    assert 'in speed mode (run_mode = 2), not operation control: stop it (type 4) and write ' \
        'run_mode 0' in fails[0]
    assert proc.stdout.count('(cybergear): position') == 3   # the other hips
    cfg = robot_config.build(robot_config.read_params(out))
    assert (cfg.can.protocol, cfg.legs.protocol) == ('dji_c620', 'cybergear')


def test_a_wrong_mode_goes_on_a_motor_with_a_mode_register_only():
    from wheelleg_balance.bringup.sim import sim_params
    from wheelleg_balance.sim.config import SimConfig
    from wheelleg_balance.core.schema import check, from_flat
    flat = sim_params('239.1.2.3', 40001, {'legs.can.protocol': 'damiao',
                                           'fault.wrong_mode_motor_id': 4})
    assert check(from_flat(SimConfig, flat)) == []
    for wrong, words in (({'fault.wrong_mode_motor_id': 4}, 'motor 4 has no control mode'),
                         ({'fault.wrong_mode_motor_id': 7}, 'is none of the motors'),
                         ({'legs.can.protocol': 'damiao', 'fault.wrong_mode_motor_id': 4,
                           'fault.wrong_mode': 9}, 'DaMiao CTRL_MODE is one of [1, 2, 3, 4]')):
        with pytest.raises(ValueError, match=re.escape(words)):
            sim_params('239.1.2.3', 40001, wrong)


# ---- the simulator's side: the stand and the hand ------------------------------------------

def test_the_hand_pulls_to_its_target_within_its_torque():
    from wheelleg_balance.sim.hand import Hand
    hand = Hand(6, kp=20.0, kd=1.0, max_torque=6.0)
    q = [0.0, 0.5, 0.0, 0.0, 0.0, 0.0]
    hand.grab({1: 1.0, 2: -3.0, 7: 1.0}, q, {2: 4.0, 1: 100.0})
    assert hand.targets == {1: (1.5, 6.0), 2: (-3.0, 4.0)}   # index 7 is no joint
    tau = hand.torques(q, [0.0] * 6)
    assert tau == [0.0, 6.0, -4.0, 0.0, 0.0, 0.0]
    assert hand.torques([0.0, 1.5, -3.0, 0, 0, 0], [0.0, 2.0, 0, 0, 0, 0])[1] == -2.0
    hand.release()
    assert hand.torques(q, [0.0] * 6) == [0.0] * 6


def test_on_the_stand_the_wheels_turn_free_and_the_imu_reads_the_tail_rest():
    pytest.importorskip('mujoco')
    from wheelleg_balance.sim.robot_motors import default_specs, RobotMotors
    from wheelleg_balance.sim.robot_sim import RobotSim
    sim = RobotSim(legs='motors')
    rest = sim.tail_rest_pitch()
    sim.reset('stand', lift=0.05)
    motors = RobotMotors(sim, default_specs(), power_up=True)
    q0 = motors.joint_angles()
    assert q0[2:] == pytest.approx([-0.2] * 4, abs=0.01)   # powered up folded
    motors.hand.grab({0: 1.0}, q0, {0: 0.5})
    motors.step(1.5)
    gt = sim.ground_truth()
    assert gt['theta'] == pytest.approx(rest, abs=0.01)   # held at the tail pitch
    # Turned forward by well over MIN_WHEEL_TURN (the limp legs swing the wheel's leg a little).
    assert 0.6 < motors.joint_angles()[0] - q0[0] < 1.1
    # The motor reads the turn through its direction (the left motor: +1).
    assert motors.motor_state('left_wheel_joint')[0] == pytest.approx(
        motors.joint_angles()[0], abs=1e-3)


def test_the_builder_at_the_terminal_is_asked_and_no_terminal_refuses():
    from wheelleg_balance.bringup.session import ConsoleOperator
    said, asked = [], []
    ConsoleOperator(said.append, asked.append).ask('wheel_forward', SLOTS[:1], 'Turn it.')
    assert said == ['>>> Turn it.'] and asked == ['    press Enter when done > ']

    def no_terminal(prompt):
        raise EOFError
    with pytest.raises(Refused, match='no terminal'):
        ConsoleOperator(said.append, no_terminal).ask('wheel_forward', SLOTS[:1], 'Turn it.')
