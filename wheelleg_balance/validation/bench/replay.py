"""
The replay: the tick's inputs recorded at one commit, fed tick by tick to another tick.

Recording (``record``, the ``record`` command below; MuJoCo needed): validation/lockstep.py's
Lockstep (BalanceLoop against the MuJoCo robot and its emulated MIT motors) goes through
scripted phases that cover the tick's modes and parts, and for every tick the recording keeps
what the tick got (``TickInputs``: IMU samples, CAN frames with their receipt times, cmd_vel,
cmd_height, arm, estop, parameter changes, guarded, conflicts, imu_silent; the error handed to
``report_send``) and what it produced (frames and leg frames as (ID, bytes, extended), the
``LoopState`` values, the odometry, the events, the arm reply), with the configuration, the
commit and the OpenBLAS kernel (``blas_cores``). Two runs (``RUNS``): ``six`` (the simulated
robot's six motors after power-up, legs driven) and ``wheels`` (the default robot: legs not
driven, two wheel motors). The file: msgpack, columns, xz (data/, about 0.95 MB).

Replaying (``Replay``) needs nothing but BalanceLoop: a fresh loop built from the recorded
configuration gets the recorded inputs through its public calls alone (``BalanceLoop(cfg)``,
``tick(now, inputs)``, ``report_send(now, error)``), so it replays the tick of any tree with
that interface, an older one too (inputs it does not know are dropped, ``Replay.dropped``).
``differences`` compares a tick's outputs with the recorded ones within ``Tolerance``:
frames equal, or MIT command frames within one code per field; state and odometry values
equal or within float noise (the wheel torques and the force within one torque code of the
wheel codec); events and arm replies equal. test/test_replay.py holds the tick to it.

Counting (``count``; the benchmark's ``replay`` part): the instructions of ``BalanceLoop.tick``
alone over a window of the recording (``BENCH_WINDOW``: 1000 ticks of the six motors balancing
and driving, 600 straight on, 400 turning), by valgrind's callgrind collecting only inside
``operator.call`` (``--toggle-collect``), through which the replay calls the tick in the window
and nowhere else (the tick itself never calls it): the replay's own work, the ticks before the
window and the interpreter's start are not counted (callgrind_control switches the
instrumentation on at the window), and no motor is emulated (their replies are recorded).
``--mode time`` times the same ticks with ``time.perf_counter_ns`` instead. The child that
replays is this file run as a script on another tree's package (``--tree DIR``): it imports
nothing of the package at module level for that reason.

    python -m wheelleg_balance.validation.bench.replay record [--output FILE]
    python -P .../replay.py compare [--tree DIR] [--file FILE]
    python -P .../replay.py count [--tree DIR] [--file FILE] [--mode callgrind|time]
"""
import argparse
import dataclasses
import datetime
import importlib
import json
import lzma
import math
import operator
import os
import subprocess
import sys
import time
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

#: The recording in the package: inputs and outputs of every tick, recorded at 0714d2b.
RECORDING = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'data',
                         'tick_replay_0714d2b.msgpack.xz')
FORMAT = 1
#: The benchmark's window: (run, first tick's label, ticks): the six motors balancing and
#: driving (forward, then turning), from the first cmd_vel of the drive on.
BENCH_WINDOW = ('six', 'drive', 1000)
#: ImuSample's fields, in order (all stored as float64: the ints and the bool are exact).
IMU_FIELDS = ('t', 'stamp_sec', 'stamp_nanosec', 'qx', 'qy', 'qz', 'qw', 'orientation_valid',
              'wx', 'wy', 'wz', 'ax', 'ay', 'az', 'clock')
ODOM_FIELDS = ('x', 'y', 'yaw', 'x_dot', 'yaw_rate')
#: Mantissa bits kept of the recorded state and odometry (relative rounding 2^-36 = 1.5e-11,
#: far below Tolerance's 1e-9); the inputs are kept whole.
OUTPUT_BITS = 36
#: The C function the tick is called through in the counted window (callgrind toggles on it).
TOGGLE = '_operator_call'


# ------------------------------------------------------------------------------ the format

def _pack_floats(rows, width: int, bits: int = 52) -> bytes:
    """
    Pack float64 rows of ``width`` values into bytes that compress.

    Column by column, each value's 64 bits minus the previous value's (as integers), the
    bytes of each place together.

    bits: the mantissa bits kept (52: all; fewer for recorded outputs, which are compared
    within a tolerance above the rounding: 36 bits is 1.5e-11 relative).
    """
    a = np.array(rows, dtype='<f8').reshape(-1, width).T.copy()
    u = a.view('<i8')
    if bits < 52:
        u &= np.int64(-(1 << (52 - bits)))
    d = u.copy()
    d[:, 1:] -= u[:, :-1]
    return d.view(np.uint8).reshape(width, -1, 8).transpose(0, 2, 1).tobytes()


def _unpack_floats(blob: bytes, width: int) -> np.ndarray:
    b = np.frombuffer(blob, np.uint8)
    n = b.size // (8 * width)
    d = b.reshape(width, 8, n).transpose(0, 2, 1).copy().view('<i8').reshape(width, n)
    return np.cumsum(d, axis=1, dtype='<i8').view('<f8').T


def _pack_frames(rows) -> Dict[str, bytes]:
    """Frames [(tick, time or None, bus, id, data, extended)] as columns."""
    cols = list(zip(*rows)) if rows else [()] * 6
    out = {'tick': np.asarray(cols[0], '<i4').tobytes(),
           'bus': bytes(cols[2]), 'id': np.asarray(cols[3], '<u4').tobytes(),
           'len': bytes(len(d) for d in cols[4]), 'data': b''.join(cols[4]),
           'ext': bytes(int(e) for e in cols[5])}
    if rows and rows[0][1] is not None:
        out['time'] = _pack_floats(cols[1], 1)
    return out


def _unpack_frames(d: Dict[str, bytes]):
    ticks = np.frombuffer(d['tick'], '<i4').tolist()
    ids = np.frombuffer(d['id'], '<u4').tolist()
    times = _unpack_floats(d['time'], 1)[:, 0].tolist() if 'time' in d else [None] * len(ids)
    data, at = [], 0
    for n in d['len']:
        data.append(d['data'][at:at + n])
        at += n
    return list(zip(ticks, times, d['bus'], ids, data, (bool(e) for e in d['ext'])))


class Tick(NamedTuple):
    """One recorded tick: its inputs, the send error, the outputs (``expected``)."""

    now: float
    imu: List[tuple]
    frames: List[Tuple[float, int, bytes, bool]]
    cmd_vel: Optional[tuple]
    cmd_height: Optional[tuple]
    arm: Optional[bool]
    estop: bool
    params: Dict[str, Any]
    guarded: bool
    conflicts: Dict[str, str]
    imu_silent: str
    send_error: Optional[str]
    expected: 'Outputs'


class Outputs(NamedTuple):
    """What a tick produced (after report_send): frames as (id, data, extended)."""

    frames: List[Tuple[int, bytes, bool]]
    leg_frames: List[Tuple[int, bytes, bool]]
    state: List[float]
    odom: List[float]
    events: List[Tuple[str, str]]
    arm_reply: Optional[Tuple[bool, str]]


def outputs_of(result) -> Outputs:
    """Read a TickResult (after report_send) into plain values."""
    return Outputs([(f.arbitration_id, bytes(f.data), bool(f.is_extended_id))
                    for f in result.frames],
                   [(f.arbitration_id, bytes(f.data), bool(f.is_extended_id))
                    for f in result.leg_frames],
                   [float(v) for v in result.state.values()],
                   [float(getattr(result.odom, n)) for n in ODOM_FIELDS],
                   [(str(a), str(b)) for a, b in result.events],
                   None if result.arm_reply is None else (bool(result.arm_reply[0]),
                                                          str(result.arm_reply[1])))


def encode_run(ticks: Sequence[Tick], info: Dict[str, Any]) -> Dict[str, Any]:
    """One run's ticks as columns (dense per tick, sparse for the rare inputs and outputs)."""
    n = len(ticks)
    run = dict(info, ticks=n, now=_pack_floats([t.now for t in ticks], 1))
    imu = [(k, s) for k, t in enumerate(ticks) for s in t.imu]
    run['imu_tick'] = np.asarray([k for k, _ in imu], '<i4').tobytes()
    run['imu'] = _pack_floats([[float(v) for v in s] for _, s in imu], len(IMU_FIELDS))
    run['frames_in'] = _pack_frames([(k, t, 0, i, d, e) for k, tk in enumerate(ticks)
                                     for t, i, d, e in tk.frames])
    run['frames_out'] = _pack_frames(
        [(k, None, bus, i, d, e) for k, tk in enumerate(ticks)
         for bus, frames in enumerate((tk.expected.frames, tk.expected.leg_frames))
         for i, d, e in frames])
    run['state'] = _pack_floats([t.expected.state for t in ticks], len(ticks[0].expected.state),
                                OUTPUT_BITS)
    run['odom'] = _pack_floats([t.expected.odom for t in ticks], len(ODOM_FIELDS), OUTPUT_BITS)
    sparse = {name: [] for name in ('cmd_vel', 'cmd_height', 'arm', 'estop', 'params',
                                    'guarded', 'conflicts', 'imu_silent', 'send_error',
                                    'events', 'arm_reply')}
    guarded, conflicts = True, {}
    for k, t in enumerate(ticks):
        for name, value in (('cmd_vel', t.cmd_vel), ('cmd_height', t.cmd_height),
                            ('arm', t.arm), ('send_error', t.send_error),
                            ('arm_reply', t.expected.arm_reply)):
            if value is not None:
                sparse[name].append([k, value])
        for name, value in (('estop', t.estop), ('params', t.params),
                            ('imu_silent', t.imu_silent), ('events', t.expected.events)):
            if value:
                sparse[name].append([k, value])
        if t.guarded != guarded:   # states: stored where they change
            guarded = t.guarded
            sparse['guarded'].append([k, guarded])
        if t.conflicts != conflicts:
            conflicts = t.conflicts
            sparse['conflicts'].append([k, conflicts])
    run.update(sparse)
    return run


def decode_run(run: Dict[str, Any]) -> List[Tick]:
    """Return a run's ticks (the inverse of ``encode_run``)."""
    n = run['ticks']
    now = _unpack_floats(run['now'], 1)[:, 0].tolist()
    imu: List[List[tuple]] = [[] for _ in range(n)]
    values = _unpack_floats(run['imu'], len(IMU_FIELDS)).tolist()
    for k, row in zip(np.frombuffer(run['imu_tick'], '<i4').tolist(), values):
        row[1], row[2], row[7] = int(row[1]), int(row[2]), bool(row[7])
        imu[k].append(tuple(row))
    frames: List[list] = [[] for _ in range(n)]
    for k, t, _, i, d, e in _unpack_frames(run['frames_in']):
        frames[k].append((t, i, d, e))
    out: List[Tuple[list, list]] = [([], []) for _ in range(n)]
    for k, _, bus, i, d, e in _unpack_frames(run['frames_out']):
        out[k][bus].append((i, d, e))
    state = _unpack_floats(run['state'], len(run['state_fields'])).tolist()
    odom = _unpack_floats(run['odom'], len(ODOM_FIELDS)).tolist()

    def sparse(name, default=None, convert=lambda v: v):
        col = [default] * n
        for k, v in run[name]:
            col[k] = convert(v)
        return col

    def states(name, first):
        col, value, changes = [], first, dict(run[name])
        for k in range(n):
            value = changes.get(k, value)
            col.append(value)
        return col

    cmd_vel, cmd_height = sparse('cmd_vel', convert=tuple), sparse('cmd_height', convert=tuple)
    arm, estop, params = sparse('arm'), sparse('estop', False), sparse('params', {})
    imu_silent, send_error = sparse('imu_silent', ''), sparse('send_error')
    events = sparse('events', [], lambda v: [tuple(e) for e in v])
    arm_reply = sparse('arm_reply', convert=tuple)
    guarded, conflicts = states('guarded', True), states('conflicts', {})
    return [Tick(now[k], imu[k], frames[k], cmd_vel[k], cmd_height[k], arm[k], estop[k],
                 params[k], guarded[k], conflicts[k], imu_silent[k], send_error[k],
                 Outputs(out[k][0], out[k][1], state[k], odom[k], events[k], arm_reply[k]))
            for k in range(n)]


def load(path: str = RECORDING) -> Dict[str, Any]:
    """Read a recording: {'commit', 'recorded', 'runs': {name: run}, ...}."""
    msgpack = importlib.import_module('msgpack')   # a test dependency: imported when used
    with lzma.open(path, 'rb') as f:
        rec = msgpack.unpackb(f.read(), raw=False, strict_map_key=False)
    if rec.get('format') != FORMAT:
        raise ValueError('%s: replay format %r, this reader reads %d'
                         % (path, rec.get('format'), FORMAT))
    return rec


def save(rec: Dict[str, Any], path: str) -> int:
    """Write a recording (msgpack, xz); return its size [bytes]."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    msgpack = importlib.import_module('msgpack')
    with lzma.open(path, 'wb', preset=9 | lzma.PRESET_EXTREME) as f:
        f.write(msgpack.packb(rec, use_bin_type=True))
    return os.path.getsize(path)


def blas_cores() -> List[str]:
    """
    Return the kernels (core names) of the OpenBLAS libraries numpy and scipy loaded here.

    The observer's gains are solved at start (pole placement, scipy): the kernel OpenBLAS picks
    for the CPU changes them by about 1e-9 (Haswell against SkylakeX: 3e-9), which a replay
    carries into d_hat and, thousands of ticks on, into a decision taken a tick earlier. A
    replay equals its recording on the recording's kernels (``OPENBLAS_CORETYPE`` sets them).
    """
    import ctypes
    importlib.import_module('numpy')
    importlib.import_module('scipy.linalg')
    try:
        with open('/proc/self/maps') as f:
            paths = sorted({line.split()[-1] for line in f if 'openblas' in line.lower()
                            and line.split()[-1].startswith('/')})
    except OSError:
        return []
    cores = set()
    for path in paths:
        lib = ctypes.CDLL(path)
        for name in ('scipy_openblas_get_corename64_', 'scipy_openblas_get_corename',
                     'openblas_get_corename64_', 'openblas_get_corename'):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                cores.add(fn().decode())
                break
    return sorted(cores)


# ------------------------------------------------------------------------------ replaying

def tick_api() -> Dict[str, Any]:
    """Return the classes of the importable tree's tick (older trees: TickInputs elsewhere)."""
    api = {}
    loop = importlib.import_module('wheelleg_balance.core.balance_loop')
    try:
        io = importlib.import_module('wheelleg_balance.core.tick_io')
    except ImportError:
        io = loop
    api['BalanceLoop'] = loop.BalanceLoop
    for name in ('TickInputs', 'CmdVel', 'CmdHeight'):
        api[name] = getattr(io, name, None) or getattr(loop, name)
    api['ImuSample'] = importlib.import_module('wheelleg_balance.core.sensors').ImuSample
    api['Frame'] = importlib.import_module('wheelleg_balance.core.protocols.base').Frame
    schema = importlib.import_module('wheelleg_balance.core.schema')
    api['from_flat'], api['spec_by_name'] = schema.from_flat, schema.spec_by_name
    api['BalanceConfig'] = importlib.import_module('wheelleg_balance.core.config').BalanceConfig
    api['MitProtocol'] = importlib.import_module('wheelleg_balance.core.protocols.mit') \
        .MitProtocol
    return api


class Replay:
    """
    One recorded run, ready to feed to a fresh BalanceLoop of the importable tree.

    config: the recorded configuration (flat), without the names this tree does not know
    (``dropped`` lists them, with the TickInputs fields this tree's tick does not take and
    that the run sets).
    """

    def __init__(self, run: Dict[str, Any], api: Optional[Dict[str, Any]] = None,
                 config: Optional[Dict[str, Any]] = None):
        self.api = api = api or tick_api()
        self.run = run
        self.ticks = decode_run(run)
        known = api['spec_by_name'](api['BalanceConfig'])
        flat = run['config'] if config is None else config
        self.config = {k: v for k, v in flat.items() if k in known}
        self.dropped = sorted(set(flat) - set(known))
        fields = {f.name for f in dataclasses.fields(api['TickInputs'])}
        used = {'imu', 'joints', 'frames', 'cmd_vel', 'cmd_height', 'arm', 'estop', 'params',
                'guarded', 'conflicts', 'imu_silent'}
        self.fields = used & fields
        self.dropped += sorted(name for name in used - fields
                               if any(getattr(t, name, None) for t in self.ticks))
        self._built: Optional[list] = None

    def cfg(self):
        """Return the recorded configuration as this tree's BalanceConfig."""
        return self.api['from_flat'](self.api['BalanceConfig'], self.config)

    def loop(self):
        """Return a fresh BalanceLoop of the recorded configuration."""
        return self.api['BalanceLoop'](self.cfg())

    def _inputs(self, t: Tick):
        api = self.api
        frame, imu = api['Frame'], api['ImuSample']
        values = {'imu': [imu(*s) for s in t.imu], 'joints': [],
                  'frames': [(at, frame(i, d, e)) for at, i, d, e in t.frames],
                  'cmd_vel': None if t.cmd_vel is None else api['CmdVel'](*t.cmd_vel),
                  'cmd_height': None if t.cmd_height is None
                  else api['CmdHeight'](*t.cmd_height),
                  'arm': t.arm, 'estop': t.estop, 'params': dict(t.params),
                  'guarded': t.guarded, 'conflicts': dict(t.conflicts),
                  'imu_silent': t.imu_silent}
        return api['TickInputs'](**{k: v for k, v in values.items() if k in self.fields})

    def inputs(self) -> list:
        """Return every tick's TickInputs, built once (the benchmark's window reuses them)."""
        if self._built is None:
            self._built = [self._inputs(t) for t in self.ticks]
        return self._built

    def index(self, label: str) -> int:
        """Return the tick of a label the recording set ('drive', ...)."""
        return self.run['labels'][label]

    def outputs(self, loop=None, stop: Optional[int] = None):
        """Yield (k, Tick, Outputs) of every tick replayed into ``loop`` (a fresh one)."""
        loop = loop if loop is not None else self.loop()
        for k, t in enumerate(self.ticks[:stop]):
            result = loop.tick(t.now, self._inputs(t))   # fresh: nothing a tick kept changes
            loop.report_send(t.now, t.send_error)
            yield k, t, outputs_of(result)


# ----------------------------------------------------------------------------- comparing

@dataclasses.dataclass
class Tolerance:
    """
    How far a replayed tick may be from the recorded one.

    Frames: bytes equal, or, for an MIT command frame, every field within ``codes`` codes
    (position 16 bits, velocity, kp, kd, torque 12 bits: a float's last bit can round a value
    to the next code). State and odometry values: NaN where the recording has NaN, else
    within ``abs_tol`` + ``rel_tol`` |recorded| (float noise of a reordered sum); the wheel
    torques and the force u within one torque code of the wheel codec too (``torque_code``
    [N m], ``force_code`` [N]), the resolution they are sent at. Events and arm replies equal.
    """

    codes: int = 1
    abs_tol: float = 1e-9
    rel_tol: float = 1e-9
    torque_code: float = 0.0
    force_code: float = 0.0


def tolerance_for(config: Dict[str, Any]) -> Tolerance:
    """Return the Tolerance of a run: one wheel torque code from the recorded configuration."""
    if config.get('can.protocol', 'mit') == 'mit':
        code = 2.0 * config['can.mit.t_max'] / 4095.0
    else:
        code = 0.0
    radius = config.get('wheel_radius')
    # u = 2 tau / r_w (Sec. V-A's split, both wheels): one code of each.
    return Tolerance(torque_code=code, force_code=2.0 * code / radius if radius else 0.0)


class _Frame(NamedTuple):
    """A frame as decode_command reads one (the tree's Frame has these fields first)."""

    arbitration_id: int
    data: bytes
    is_extended_id: bool = False


#: Per MitProtocol class: a codec whose ranges are the codes themselves.
_CODECS: Dict[type, Any] = {}


def mit_codes(frame: Tuple[int, bytes, bool], mit_protocol) -> Optional[Tuple[int, ...]]:
    """Return an MIT command frame's five codes (decode_command), None for anything else."""
    codec = _CODECS.get(mit_protocol)
    if codec is None:   # decode_command of this codec returns the codes as floats
        codec = _CODECS[mit_protocol] = mit_protocol(
            p_min=0.0, p_max=65535.0, v_min=0.0, v_max=4095.0, kp_max=4095.0, kd_max=4095.0,
            t_min=0.0, t_max=4095.0)
    i, data, ext = frame
    cmd = None if ext else codec.decode_command(_Frame(i, data))
    if cmd is None or isinstance(cmd, str):
        return None
    return tuple(int(round(v)) for v in cmd[1:])


def frames_differ(want, got, tol: Tolerance, mit_protocol) -> Optional[str]:
    """Return why two frame lists differ beyond ``tol`` (None: they agree)."""
    if len(want) != len(got):
        return '%d frames, recorded %d: %s vs %s' % (len(got), len(want), _ids(got), _ids(want))
    for a, b in zip(want, got):
        if a == b:
            continue
        if a[0] != b[0] or a[2] != b[2]:
            return 'frame to %s, recorded %s' % (b[0], a[0])
        ca, cb = mit_codes(a, mit_protocol), mit_codes(b, mit_protocol)
        if ca is None or cb is None:
            return 'frame to %d: %s, recorded %s' % (a[0], b[1].hex(), a[1].hex())
        far = [k for k, (x, y) in enumerate(zip(ca, cb)) if abs(x - y) > tol.codes]
        if far:
            return 'frame to %d: codes %s, recorded %s' % (a[0], cb, ca)
    return None


def _ids(frames) -> str:
    return ','.join(str(f[0]) for f in frames)


def values_differ(names: Sequence[str], want: Sequence[float], got: Sequence[float],
                  tol: Tolerance) -> List[str]:
    """Return the values beyond ``tol`` as 'name got (recorded want)'."""
    out = []
    for name, a, b in zip(names, want, got):
        if a == b or (math.isnan(a) and math.isnan(b)):
            continue
        limit = tol.abs_tol + tol.rel_tol * abs(a) if math.isfinite(a) else 0.0
        if name in ('tau_left', 'tau_right'):
            limit = max(limit, tol.torque_code)
        elif name == 'u':
            limit = max(limit, tol.force_code)
        if not abs(a - b) <= limit:
            out.append('%s %r (recorded %r)' % (name, b, a))
    return out


def differences(want: Outputs, got: Outputs, tol: Tolerance, state_fields: Sequence[str],
                mit_protocol) -> List[str]:
    """Return how a replayed tick's outputs differ from the recorded ones ([]: the same)."""
    out = []
    for name, a, b in (('frames', want.frames, got.frames),
                       ('leg_frames', want.leg_frames, got.leg_frames)):
        why = frames_differ(a, b, tol, mit_protocol)
        if why:
            out.append('%s: %s' % (name, why))
    out += values_differ(state_fields, want.state, got.state, tol)
    out += ['odom ' + d for d in values_differ(ODOM_FIELDS, want.odom, got.odom, tol)]
    if list(want.events) != list(got.events):
        out.append('events %r (recorded %r)' % (got.events, want.events))
    if want.arm_reply != got.arm_reply:
        out.append('arm_reply %r (recorded %r)' % (got.arm_reply, want.arm_reply))
    return out


def compare(replay: Replay, loop=None, tol: Optional[Tolerance] = None,
            limit: int = 10) -> List[str]:
    """Replay a run into a fresh loop; the first ``limit`` ticks that differ, one line each."""
    run = replay.run
    tol = tol or tolerance_for(run['config'])
    mit = replay.api['MitProtocol']
    out = []
    for k, t, got in replay.outputs(loop):
        diff = differences(t.expected, got, tol, run['state_fields'], mit)
        if diff:
            out.append('%s tick %d (t %.3f s, mode %s): %s' % (
                run['name'], k, t.now, t.expected.state[run['state_fields'].index('mode')],
                '; '.join(diff)))
            if len(out) >= limit:
                break
    return out


# ------------------------------------------------------------------------------ recording

class _Recorder:
    """Wraps a Lockstep's loop: keeps every tick's inputs and outputs; can cut the IMU."""

    def __init__(self, ls):
        self.loop = ls.loop
        self._tick, self._send = ls.loop.tick, ls.loop.report_send
        ls.loop.tick, ls.loop.report_send = self.tick, self.report_send
        self.ticks: List[Tick] = []
        self.imu_gap = False   # drop the IMU's samples (a driver that stopped)
        self._pending = self._result = None

    def tick(self, now, inputs):
        if self.imu_gap:
            inputs.imu.clear()
        self._pending = (now, [tuple(s) for s in inputs.imu],
                         [(t, f.arbitration_id, bytes(f.data), bool(f.is_extended_id))
                          for t, f in inputs.frames],
                         None if inputs.cmd_vel is None else tuple(inputs.cmd_vel),
                         None if inputs.cmd_height is None else tuple(inputs.cmd_height),
                         inputs.arm, bool(inputs.estop), dict(inputs.params),
                         bool(inputs.guarded), dict(inputs.conflicts), inputs.imu_silent)
        assert not inputs.joints, 'the lockstep has no joint states'
        self._result = self._tick(now, inputs)
        return self._result

    def report_send(self, now, error):
        self._send(now, error)   # it completes the result's arm_reply
        self.ticks.append(Tick(*self._pending, error, outputs_of(self._result)))


def _until_mode(ls, mode: int, limit: float) -> None:
    ls.run(limit, until=lambda: ls.mode == mode)
    if ls.mode != mode:
        raise RuntimeError('mode %d not reached in %.1f s: %s' % (mode, limit, ls.events[-3:]))


def _drive(ls, seconds: float, x_dot: float, yaw_rate: float) -> None:
    """cmd_vel at teleop_node's 50 Hz for ``seconds``."""
    for k in range(int(round(seconds / ls.period))):
        if k % 10 == 0:
            ls.command(x_dot, yaw_rate)
        ls.tick()


def _six(ls, rec: _Recorder, labels: Dict[str, int]) -> None:
    """Legs driven: power-up, arm, drive, height, controller switch, sit-down, a fault."""
    disarmed, balancing, fault, homing, sitting = 0, 1, 2, 3, 4   # core/safety.Mode
    ls.run(0.5)                                   # power-up: disarmed, resting polls
    ls.arm(True)                                  # homing, raising on the tail, rising
    _until_mode(ls, homing, 0.1)
    _until_mode(ls, balancing, 12.0)
    ls.run(0.5)
    labels['drive'] = len(rec.ticks)
    _drive(ls, 1.2, 0.4, 0.0)                     # forward
    _drive(ls, 1.2, 0.4, 0.8)                     # a left turn while driving
    _drive(ls, 0.4, 0.0, 0.0)
    labels['height'] = len(rec.ticks)
    ls.command_height(0.50)
    ls.run(1.0)
    labels['switch'] = len(rec.ticks)
    ls.inputs.params = {'controller': 'output_regulation'}
    ls.run(0.6)
    labels['disarm'] = len(rec.ticks)
    ls.arm(False)                                 # sit-down, then disarmed
    _until_mode(ls, sitting, 0.1)
    _until_mode(ls, disarmed, 6.0)
    ls.run(0.3)
    labels['fault'] = len(rec.ticks)
    ls.arm(True)                                  # the legs are homed: raising
    ls.run(0.3)
    ls.silent.add(ls.cfg.legs.motor_ids[0])       # a hip's replies lost
    _until_mode(ls, fault, 1.0)
    ls.run(0.1)
    ls.arm(True)                                  # re-arm refused: the hip is silent
    ls.run(0.2)
    ls.silent.clear()
    ls.run(0.2)
    ls.arm(False)
    ls.run(0.2)


def _wheels(ls, rec: _Recorder, labels: Dict[str, int]) -> None:
    """Legs not driven: unguarded arm, conflicts, rise, drive, an IMU gap, imu_silent, estop."""
    balancing, fault = 1, 2
    ls.inputs.guarded = False                     # the watchdog not watching yet
    ls.run(0.2)
    ls.arm(True)                                  # refused: not guarded
    ls.run(0.1)
    ls.inputs.guarded = True
    ls.inputs.conflicts = {'cmd_vel': 'cmd_vel: a second publisher (test)'}
    ls.run(0.1)
    ls.arm(True)                                  # rising from the tail
    _until_mode(ls, balancing, 0.1)
    ls.run(1.0)
    labels['drive'] = len(rec.ticks)
    _drive(ls, 0.3, 0.4, 0.0)                     # dropped: the conflict
    ls.inputs.conflicts = {}
    _drive(ls, 1.0, 0.3, -0.6)
    _drive(ls, 0.2, 0.0, 0.0)
    labels['imu_gap'] = len(rec.ticks)
    rec.imu_gap = True                            # FAULT imu_stale
    _until_mode(ls, fault, 1.0)
    ls.arm(True)                                  # re-arm refused: no IMU
    ls.run(0.05)
    rec.imu_gap = False
    ls.run(0.4)
    ls.arm(True)                                  # refused: fallen
    ls.run(0.05)
    ls.inputs.imu_silent = 'no IMU sample for 0.25 s of wall time (replay recording)'
    ls.run(0.05)
    ls.inputs.estop = True
    ls.run(0.1)


#: The recorded runs: name -> (balance_node parameters, Lockstep's power_up, the script). The
#: six motors after power-up: the hips know their angles only modulo a rotor turn and home at
#: their hard stops.
RUNS = {'six': ({'legs.homing': 'hard_stops'}, True, _six),
        'wheels': ({'legs.driven': False}, False, _wheels)}


def _git(*args) -> str:
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        return subprocess.run(['git', '-C', here] + list(args), capture_output=True,
                              text=True, timeout=30).stdout.strip()
    except OSError:
        return ''


def record(path: str = RECORDING) -> Dict[str, Any]:
    """Record every run of ``RUNS`` with this tree's tick; write ``path``; a summary."""
    from ..lockstep import Lockstep
    from ...core.balance_loop import STATE_FIELDS
    from ...core.schema import to_flat
    rec = {'format': FORMAT, 'commit': _git('rev-parse', 'HEAD'),
           'dirty': [line for line in _git('status', '--porcelain').splitlines()
                     if not line.endswith('replay.py')],
           'recorded': datetime.datetime.now().isoformat(timespec='seconds'),
           'blas_cores': blas_cores(),
           'recorder': 'wheelleg_balance.validation.bench.replay', 'runs': {}}
    summary = {}
    for name, (params, power_up, script) in RUNS.items():
        ls = Lockstep(params, imu_offset=math.radians(2.2), power_up=power_up)
        recorder, labels = _Recorder(ls), {}
        script(ls, recorder, labels)
        flat = {k: list(v) if isinstance(v, tuple) else v for k, v in to_flat(ls.cfg).items()}
        info = {'name': name, 'node_params': params, 'power_up': power_up, 'config': flat,
                'labels': labels,
                'state_fields': list(STATE_FIELDS), 'imu_offset': math.radians(2.2)}
        rec['runs'][name] = encode_run(recorder.ticks, info)
        modes = sorted({int(t.expected.state[STATE_FIELDS.index('mode')])
                        for t in recorder.ticks})
        summary[name] = {'ticks': len(recorder.ticks), 'modes': modes, 'labels': labels,
                         'events': [e for t in recorder.ticks for e in t.expected.events],
                         'arm_replies': [t.expected.arm_reply for t in recorder.ticks
                                         if t.expected.arm_reply]}
    summary['bytes'] = save(rec, path)
    return summary


# ------------------------------------------------------------------------------- counting

def bench_ticks(replay: Replay, window: Tuple[str, str, int] = BENCH_WINDOW):
    """Return (first, stop) ticks of the benchmark's window in this run."""
    first = replay.index(window[1])
    return first, first + window[2]


def run_window(replay: Replay, mode: str, window=BENCH_WINDOW, repeat: int = 1,
               before_window=None) -> Dict[str, Any]:
    """
    Replay up to the window's end; the window's ticks called through ``operator.call``.

    mode 'callgrind': nothing measured here (callgrind counts inside operator.call); 'time':
    each window tick timed (perf_counter_ns), ``repeat`` replays, the fastest median kept.
    before_window: called once just before the window (callgrind_control). Returns what the
    window's ticks did: modes, moving, their outputs' agreement with the recording.
    """
    first, stop = bench_ticks(replay, window)
    run = replay.run
    fields = run['state_fields']
    mode_at = fields.index('mode')
    tol, mit = tolerance_for(run['config']), replay.api['MitProtocol']
    medians, means = [], []
    for _ in range(repeat):
        loop = replay.loop()
        tick, send, call = loop.tick, loop.report_send, operator.call
        ticks, inputs = replay.ticks, replay.inputs()
        for k in range(first):
            t = ticks[k]
            tick(t.now, inputs[k])
            send(t.now, t.send_error)
        if before_window is not None:
            before_window()
            before_window = None
        clock = time.perf_counter_ns
        spent = [0] * (stop - first)
        modes, agree, moving, unlike = set(), 0, 0, []
        for k in range(first, stop):
            t = ticks[k]
            t0 = clock()
            result = call(tick, t.now, inputs[k])
            spent[k - first] = clock() - t0
            send(t.now, t.send_error)
            got = outputs_of(result)
            modes.add(int(got.state[mode_at]))
            diff = differences(t.expected, got, tol, fields, mit)
            agree += not diff
            if diff and len(unlike) < 3:
                unlike.append('tick %d: %s' % (k, '; '.join(diff)))
            moving += abs(got.odom[3]) > 0.05
        medians.append(float(np.median(spent)) / 1e3)
        means.append(float(np.mean(spent)) / 1e3)
    best = int(np.argmin(medians))
    return {'first': first, 'ticks': stop - first, 'modes': sorted(modes),
            'as_recorded_share': agree / (stop - first),
            'moving_share': moving / (stop - first), 'dropped': replay.dropped,
            'first_differences': unlike,
            'wall_median_us': medians[best], 'wall_mean_us': means[best],
            'repeat': repeat}


def instrument_now() -> None:
    """Switch callgrind's instrumentation on in this process (callgrind_control, vgdb)."""
    proc = subprocess.run(['callgrind_control', '-i', 'on', str(os.getpid())],
                          capture_output=True, text=True, timeout=120)
    if proc.returncode != 0 or 'PID %d' % os.getpid() not in proc.stdout:
        raise RuntimeError('callgrind_control -i on failed: %s' % (proc.stdout + proc.stderr))


def callgrind_total(path: str) -> int:
    """Return the instructions (Ir) a callgrind output file counted ('totals:' / 'summary:')."""
    total = None
    with open(path) as f:
        for line in f:
            if line.startswith('totals:') or (total is None and line.startswith('summary:')):
                total = int(line.split()[1])
    if total is None:
        raise ValueError('%s has no totals line' % path)
    return total


def count(tree: Optional[str] = None, path: str = RECORDING, mode: str = 'callgrind',
          window=BENCH_WINDOW, workdir: Optional[str] = None, repeat: int = 3,
          python: str = sys.executable, timeout: float = 1800.0) -> Dict[str, Any]:
    """
    Count (callgrind) or time the window's ticks of a tree's BalanceLoop, in a child process.

    tree: a source tree (the folder with its wheelleg_balance); None: this one. Returns the
    child's figures; with callgrind 'instructions_per_tick' ([Ir] of the tick alone).
    Raises RuntimeError when the child fails, FileNotFoundError without valgrind.
    """
    import shutil
    import tempfile
    valgrind = shutil.which('valgrind')
    if mode == 'callgrind' and valgrind is None:
        raise FileNotFoundError('valgrind not found')
    tree = os.path.abspath(tree) if tree else os.path.dirname(os.path.dirname(os.path.dirname(
        os.path.dirname(os.path.abspath(__file__)))))
    own = workdir is None
    workdir = workdir or tempfile.mkdtemp(prefix='wlb_replay_')
    out = os.path.join(workdir, 'replay_%d.json' % os.getpid())
    cmd = [python, '-P', os.path.abspath(__file__), 'run', '--tree', tree, '--file', path,
           '--mode', mode, '--window', ','.join(map(str, window)), '--output', out,
           '--repeat', str(repeat if mode == 'time' else 1)]
    env = dict(os.environ, PYTHONHASHSEED='0')   # the tree goes first on its path (_child)
    grind = os.path.join(workdir, 'callgrind.out.%d' % os.getpid())
    if mode == 'callgrind':
        # Without instrumentation up to the window (callgrind_control switches it on there):
        # the same count, the replay before the window about 5 times faster.
        late = shutil.which('callgrind_control') is not None
        # Children traced (a Python that re-executes itself at start, as a ROS wheels venv
        # does, stays counted), but not callgrind_control's.
        cmd = [valgrind, '--tool=callgrind', '--collect-atstart=no',
               '--trace-children=yes', '--trace-children-skip=*callgrind_control*,*perl*,*vgdb*',
               '--instr-atstart=%s' % ('no' if late else 'yes'),
               '--toggle-collect=' + TOGGLE, '--callgrind-out-file=' + grind] + cmd + \
            (['--instrument-at-window'] if late else [])
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError('replay of %s failed (%d): %s' % (
                tree, proc.returncode, (proc.stderr or proc.stdout).strip()[-2000:]))
        with open(out) as f:
            result = json.load(f)
        result['tree'] = tree
        if mode == 'callgrind':
            total = callgrind_total(grind)
            if total == 0:
                raise RuntimeError('callgrind counted nothing in %s: no symbol for it in this '
                                   'Python (stripped?)' % TOGGLE)
            result['instructions'] = total
            result['instructions_per_tick'] = total / result['ticks']
    finally:
        if own:
            shutil.rmtree(workdir, ignore_errors=True)
    return result


# ------------------------------------------------------------------- the benchmark's part

#: The target (issue 30): this tree's tick at most this share of the before tree's instructions.
TARGET_RATIO = 0.35


def tree_label(tree: Optional[str]) -> str:
    """Name a source tree by its commit ('0714d2b', '0714d2b+changes'), else its folder."""
    folder = tree or os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
        os.path.abspath(__file__)))))

    def git(*args):
        try:
            return subprocess.run(['git', '-C', folder] + list(args), capture_output=True,
                                  text=True, timeout=30).stdout.strip()
        except OSError:
            return ''

    commit = git('rev-parse', '--short', 'HEAD') if os.path.isdir(os.path.join(
        folder, 'wheelleg_balance')) else ''
    if not commit:
        return 'this tree' if tree is None else folder
    dirty = git('status', '--porcelain', '--untracked-files=no')
    return '%s%s%s' % ('this tree, ' if tree is None else '', commit,
                       '+changes' if dirty else '')


def bench(trees: Sequence[Optional[str]], quick: bool = False, log=None) -> Dict[str, Any]:
    """
    Run the benchmark's ``replay`` part: each tree's tick over the window, counted, timed.

    trees: None (this tree) first, then other source trees. Without valgrind: skipped, one
    line ({'skipped': why}). Per tree: instructions per tick of the tick alone (callgrind),
    wall time per tick (median and mean of the window, the fastest of 3 replays), the modes
    and the agreement with the recording in the window.
    """
    import importlib.util
    import shutil
    if shutil.which('valgrind') is None:
        return {'skipped': 'valgrind not found (apt install valgrind): no instruction count'}
    if importlib.util.find_spec('msgpack') is None:
        return {'skipped': 'msgpack not found (python3-msgpack): the recording cannot be read'}
    window = (BENCH_WINDOW[0], BENCH_WINDOW[1], 100 if quick else BENCH_WINDOW[2])
    rec = load()
    out = {'window': list(window), 'recording': rec['commit'], 'trees': []}
    for tree in trees:
        label = tree_label(tree)
        counted = count(tree, mode='callgrind', window=window)
        timed = count(tree, mode='time', window=window, repeat=1 if quick else 3)
        row = {'label': label, 'tree': counted['tree'],
               'instructions_per_tick': counted['instructions_per_tick'],
               'wall_median_us': timed['wall_median_us'], 'wall_mean_us': timed['wall_mean_us'],
               'modes': counted['modes'], 'moving_share': counted['moving_share'],
               'as_recorded_share': timed['as_recorded_share'],
               'as_recorded_under_valgrind': counted['as_recorded_share'],
               'dropped': counted['dropped']}
        out['trees'].append(row)
        if log is not None:
            log('[replay] %s: %.0f instructions per tick, %.1f us median' % (
                label, row['instructions_per_tick'], row['wall_median_us']))
    return out


def targets(report: Dict[str, Any]) -> List[Dict[str, Any]]:
    """Return the pass/fail row: this tree's instructions per tick over the next tree's."""
    trees = report.get('trees', [])
    if len(trees) < 2:
        return []
    ratio = trees[0]['instructions_per_tick'] / trees[1]['instructions_per_tick']
    return [dict(name='tick instructions / %s' % trees[1]['label'], unit='ratio', value=ratio,
                 limit=TARGET_RATIO, **{'pass': ratio <= TARGET_RATIO})]


def print_report(report: Dict[str, Any], w) -> None:
    """Print the replay part's table (or its one skip line)."""
    if 'skipped' in report:
        w('\nreplay: skipped: %s\n' % report['skipped'])
        return
    run, label, n = report['window']
    w('\nreplay: BalanceLoop.tick alone, %d ticks of run %s from %r (balancing and driving; '
      'inputs recorded at %s; instructions: valgrind callgrind)\n'
      % (n, run, label, report['recording'][:7]))
    w('  %-30s %14s %14s %14s %9s %6s\n' % ('tree', 'instr./tick', 'wall median',
                                            'wall mean', 'as rec.', 'modes'))
    for t in report['trees']:
        w('  %-30s %14.0f %11.1f us %11.1f us %8.0f%% %6s\n' % (
            t['label'][-30:], t['instructions_per_tick'], t['wall_median_us'],
            t['wall_mean_us'], 100.0 * t['as_recorded_share'],
            ','.join(map(str, t['modes']))))
        if t['dropped']:
            w('    (%s: recorded inputs and parameters it does not take: %s)\n'
              % (t['label'], ', '.join(t['dropped'])))


def compare_all(path: str = RECORDING, limit: int = 10) -> Dict[str, Any]:
    """Replay every run of a recording into the importable tree's loop: the differences."""
    rec = load(path)
    out = {'blas_cores': blas_cores(), 'recorded_blas_cores': rec.get('blas_cores'),
           'commit': rec['commit'], 'runs': {}}
    for name, run in rec['runs'].items():
        replay = Replay(run)
        out['runs'][name] = {'ticks': run['ticks'], 'dropped': replay.dropped,
                             'differences': compare(replay, limit=limit)}
    return out


def _child(args) -> int:
    """Run as the child of ``count``: replay with the tree's BalanceLoop, write figures."""
    sys.path.insert(0, args.tree)
    rec = load(args.file)
    name, label, n = args.window.split(',')
    replay = Replay(rec['runs'][name])
    result = run_window(replay, args.mode, (name, label, int(n)), args.repeat,
                        instrument_now if args.instrument_at_window else None)
    result.update(recorded_at=rec['commit'],
                  loop_module=sys.modules[replay.api['BalanceLoop'].__module__].__file__)
    with open(args.output, 'w') as f:
        json.dump(result, f)
    return 0


def main(argv=None) -> int:
    """Run the record, compare, run and count commands (see the module docstring)."""
    parser = argparse.ArgumentParser(prog='replay', description=__doc__.split('\n')[1])
    sub = parser.add_subparsers(dest='command', required=True)
    p = sub.add_parser('record', help='record the runs with this tree (MuJoCo)')
    p.add_argument('--output', default=RECORDING)
    p = sub.add_parser('compare', help="replay every run into a tree's tick: differences")
    p.add_argument('--tree', default=None)
    p.add_argument('--file', default=RECORDING)
    for name in ('run', 'count'):
        p = sub.add_parser(name, help='replay the window of a tree: count or time it'
                           if name == 'count' else 'the child of count')
        p.add_argument('--tree', default=None)
        p.add_argument('--file', default=RECORDING)
        p.add_argument('--mode', default='callgrind', choices=('callgrind', 'time'))
        p.add_argument('--window', default=','.join(map(str, BENCH_WINDOW)))
        p.add_argument('--repeat', type=int, default=3)
        p.add_argument('--output', default=None)
        p.add_argument('--instrument-at-window', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.command == 'record':
        print(json.dumps(record(args.output), indent=1, default=str))
        return 0
    if args.command == 'run':
        return _child(args)
    if args.command == 'compare':
        if args.tree:
            sys.path.insert(0, os.path.abspath(args.tree))
        result = compare_all(args.file)
        print(json.dumps(result, indent=1))
        return 1 if any(r['differences'] for r in result['runs'].values()) else 0
    name, label, n = args.window.split(',')
    print(json.dumps(count(args.tree, args.file, args.mode, (name, label, int(n)),
                           repeat=args.repeat), indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
