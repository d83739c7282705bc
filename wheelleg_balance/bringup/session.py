"""
The bring-up procedure on the CAN buses (python-can through nodes/can_io.CanIo; no rclpy).

``BringUp.run`` does, in order, and prints each finding as it comes (report.py):

1. refuses to go on while something else drives the motors: a balance_node in the ROS graph
   (``owners``, given by the caller) or command and reply frames of the configured motors on
   a bus that bring-up has not spoken to yet (MIT motors speak only when spoken to);
2. the CAN interfaces' settings (``links``, iplink.py, for SocketCAN);
3. every configured motor: enter motor mode, one zero-torque command, exit (each answered by a
   reply: position, temperature, error code); for a silent one, a scan of the other IDs with
   exit frames (rest mode: harmless) and a look at the other bus, to name the likely cause;
4. with the motors that answered in motor mode at zero torque (polled every 10 ms), the
   builder (``operator``) turns each wheel forward, folds each leg to its stop and stretches it
   off again: directions, crossed IDs and the hips' offsets (motor_checks.py);
5. exit motor mode on every motor (also on any error or Ctrl-C);
6. the IMU at the tail rest (``imu``: samples for a duration; imu_check.py).

It returns the parameter changes the checks imply, for robot_config.py.
"""
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from . import imu_check, motor_checks as mc
from .report import Check, FAIL, INFO, PASS, Report
from ..core.config import BalanceConfig
from ..core.protocols.base import Frame, MotorFeedback
from ..core.protocols.mit import MitProtocol

#: How long bring-up listens before it speaks [s], waits for one reply [s], polls [s].
LISTEN = 0.5
REPLY_WAIT = 0.03
POLL_PERIOD = 0.01
#: IDs scanned for a motor that does not answer.
SCAN_IDS = range(1, 33)
#: How long the IMU is read at the tail rest [s].
IMU_TIME = 1.0


class Refused(Exception):
    """Bring-up must not run now (the reason is the message)."""


class Operator:
    """The builder's hands: ``ask`` returns when a step is done (and held), ``done`` lets go."""

    def ask(self, step: str, slots: Sequence[mc.MotorSlot], text: str) -> None:
        """Have the step done: 'wheel_forward', 'leg_fold' or 'leg_stretch' on slots."""
        raise NotImplementedError

    def done(self) -> None:
        """Let go of what the last step holds."""


class ConsoleOperator(Operator):
    """A person at the terminal: the instruction is printed, Enter says it is done."""

    def __init__(self, say: Callable[[str], None] = print, read: Callable[[str], str] = input):
        self._say, self._read = say, read

    def ask(self, step, slots, text):
        """Print the instruction and wait for Enter."""
        self._say('>>> ' + text)
        try:
            self._read('    press Enter when done > ')
        except EOFError:
            raise Refused('no terminal to ask the builder on (run bringup in a terminal, or '
                          '--sim)') from None


def _codec(limits) -> MitProtocol:
    return MitProtocol(**limits.codec_ranges())


class Motors:
    """The configured motors on their buses: frames out, decoded replies in."""

    def __init__(self, cfg: BalanceConfig, ios: Sequence):
        self.ios = list(ios)
        self.slots = mc.motor_slots(cfg)
        self.channels = mc.channels(cfg)
        wheel, hip = _codec(cfg.can.mit), _codec(cfg.legs.mit)
        self.codec = {s.key: hip if s.kind == 'hip' else wheel for s in self.slots}
        self.by_bus_id = {(s.bus, s.motor_id): s for s in self.slots}
        self._default = [hip if any(s.bus == b and s.kind == 'hip' for s in self.slots)
                         and not any(s.bus == b and s.kind == 'wheel' for s in self.slots)
                         else wheel for b in range(len(self.ios))]

    def send(self, bus: int, frames: Sequence[Frame]) -> Optional[str]:
        """Send frames on a bus; the error text or None."""
        return self.ios[bus].send(frames)

    def receive(self, bus: int) -> List[Frame]:
        """Return the frames received on a bus since the last call."""
        got: List[Tuple[float, Frame]] = []
        self.ios[bus].poll(got)
        return [f for _, f in got]

    def decode(self, bus: int, frame: Frame) -> Tuple[Optional[mc.MotorSlot],
                                                      Optional[MotorFeedback]]:
        """Return (configured motor, its reply), (None, a stranger's reply) or (None, None)."""
        data = bytes(frame.data)
        if frame.is_extended_id or len(data) not in (6, 8):
            return None, None
        slot = self.by_bus_id.get((bus, data[0]))
        codec = self.codec[slot.key] if slot is not None else self._default[bus]
        return slot, codec.decode_feedback(frame)


class Poller:
    """Zero-torque commands every POLL_PERIOD to the motors; their newest replies, unwrapped."""

    def __init__(self, motors: Motors, slots: Sequence[mc.MotorSlot], clock=time.monotonic):
        self.m = motors
        self.slots = list(slots)
        self._clock = clock
        self._lock = threading.Lock()
        self._unwrap = {s.key: mc.Unwrapper(self.m.codec[s.key].p_max) for s in self.slots}
        self.raw: Dict[str, float] = {}
        self.replies = 0
        self.errors: List[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='bringup_poll', daemon=True)

    def start(self) -> 'Poller':
        """Start polling."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop polling (the motors stay in motor mode, at zero torque)."""
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        buses = sorted({s.bus for s in self.slots})
        frames = {b: [f for s in self.slots if s.bus == b
                      for f in self.m.codec[s.key].zero_torque_frames((s.motor_id,))]
                  for b in buses}
        next_t = self._clock()
        while not self._stop.is_set():
            for b in buses:
                err = self.m.send(b, frames[b])
                if err and len(self.errors) < 10:
                    self.errors.append(err)
            next_t += POLL_PERIOD
            time.sleep(max(0.0, next_t - self._clock()))
            for b in buses:
                for frame in self.m.receive(b):
                    slot, fb = self.m.decode(b, frame)
                    if slot is None or fb is None or slot.key not in self._unwrap:
                        continue
                    with self._lock:
                        self.raw[slot.key] = fb.position
                        self._unwrap[slot.key].update(fb.position)
                        self.replies += 1

    def positions(self) -> Dict[str, float]:
        """Return {slot key: unwrapped position [rad]} of the motors that replied."""
        with self._lock:
            return {k: u.value for k, u in self._unwrap.items() if u.value is not None}

    def reported(self) -> Dict[str, float]:
        """Return the newest position [rad] each motor sent, not unwrapped, by slot key."""
        with self._lock:
            return dict(self.raw)


def _delta(after: Dict[str, float], before: Dict[str, float]) -> Dict[str, float]:
    return {k: after[k] - before[k] for k in after if k in before}


class BringUp:
    """The procedure (see the module docstring); ``run`` returns the parameter changes."""

    def __init__(self, cfg: BalanceConfig, ios: Sequence, operator: Operator,
                 imu: Callable[[float], List[imu_check.ImuSample]], report: Report,
                 owners: Callable[[], List[str]] = lambda: [],
                 links: Callable[[], List[Check]] = lambda: [], settle: float = 0.3,
                 scan_ids=SCAN_IDS, imu_topic: str = 'imu',
                 wait: Callable[[float], None] = time.sleep):
        self.cfg = cfg
        self.motors = Motors(cfg, ios)
        self.operator = operator
        self.imu = imu
        self.report = report
        self.owners = owners
        self.links = links
        self.settle = settle
        self.wait = wait   # the robot's clock: sim_node's with --sim
        self.scan_ids = scan_ids
        self.imu_topic = imu_topic
        self.found: List[mc.MotorSlot] = []
        self.changes: Dict[str, object] = {}
        self._entered: List[mc.MotorSlot] = []

    # ---- 1. who owns the bus ---------------------------------------------------------------

    def check_owner(self) -> None:
        """Raise Refused when a balance_node runs or the motors are being driven."""
        owners = self.owners()
        if owners:
            raise Refused("%s runs: it owns the motors' bus, and bring-up must not drive them "
                          'beside it (stop it first: Ctrl-C in its terminal, or stop the launch)'
                          % ', '.join(owners))
        m = self.motors
        for b in range(len(m.ios)):
            m.receive(b)   # what was queued before
        time.sleep(LISTEN)
        for b, channel in enumerate(m.channels):
            ours = []
            for frame in m.receive(b):
                slot, fb = m.decode(b, frame)
                if slot is not None and fb is not None:
                    ours.append('a reply of %s' % slot.label)
                elif not frame.is_extended_id and (b, frame.arbitration_id) in m.by_bus_id:
                    ours.append('a command to %s' % m.by_bus_id[(b, frame.arbitration_id)].label)
            if ours:
                raise Refused('%s carries motor traffic before bring-up said anything (%d '
                              'frames in %.1f s, e.g. %s): another controller, a balance_node '
                              'on another computer?, drives these motors' % (
                                  channel, len(ours), LISTEN, ours[0]))
        self.report.add(Check(PASS, 'bus', 'no balance_node in the ROS graph, no motor traffic '
                              'on %s' % ', '.join(m.channels)))

    # ---- 3. finding the motors -------------------------------------------------------------

    def _exchange(self, bus: int, frames: Sequence[Frame], want: mc.MotorSlot, seen: dict
                  ) -> List[MotorFeedback]:
        got = []
        for frame in frames:
            self.motors.send(bus, [frame])
            end = time.monotonic() + REPLY_WAIT
            while time.monotonic() < end:
                time.sleep(0.002)
                for f in self.motors.receive(bus):
                    self._note(bus, f, seen)
                    slot, fb = self.motors.decode(bus, f)
                    if slot is want and fb is not None:
                        got.append(fb)
        return got

    def _note(self, bus: int, frame: Frame, seen: dict) -> None:
        slot, fb = self.motors.decode(bus, frame)
        if frame.is_extended_id:
            seen['extended'][bus] += 1
        elif slot is None and fb is not None:
            seen['strangers'][bus].add(fb.motor_id)
        elif slot is None and (bus, frame.arbitration_id) not in self.motors.by_bus_id:
            seen['other'][bus] += 1

    def find_motors(self) -> None:
        """Probe every configured motor; name the likely cause for those that stay silent."""
        m = self.motors
        n = len(m.ios)
        seen = {'extended': [0] * n, 'strangers': [set() for _ in range(n)], 'other': [0] * n}
        replies = {}
        for s in m.slots:
            codec = m.codec[s.key]
            self._entered.append(s)
            replies[s.key] = self._exchange(
                s.bus, codec.enable_frames((s.motor_id,)) + codec.disable_frames((s.motor_id,)),
                s, seen)
        missing = [s for s in m.slots if not replies[s.key]]
        elsewhere: Dict[str, str] = {}
        if missing:
            for b in range(n):
                configured = {s.motor_id for s in m.slots if s.bus == b}
                codec = m._default[b]
                for i in self.scan_ids:
                    if i not in configured:
                        self._exchange(b, codec.disable_frames((i,))[-1:], None, seen)
            for s in missing:
                for b in range(n):
                    if b != s.bus:
                        other = mc.MotorSlot(s.key, s.name, s.motor_id, b, s.direction, s.kind,
                                             s.index, s.id_param, s.direction_param)
                        m.by_bus_id.setdefault((b, s.motor_id), other)
                        if self._exchange(b, m.codec[s.key].disable_frames((s.motor_id,))[-1:],
                                          other, seen):
                            elsewhere[s.key] = m.channels[b]
                        if m.by_bus_id.get((b, s.motor_id)) is other:
                            del m.by_bus_id[(b, s.motor_id)]
        for s in m.slots:
            ours = {o.motor_id for o in m.slots if o.bus == s.bus}
            strangers = sorted(seen['strangers'][s.bus] - ours)
            self.report.add(mc.probe_check(s, replies[s.key], m.channels[s.bus], strangers,
                                           elsewhere.get(s.key), seen['extended'][s.bus],
                                           seen['other'][s.bus]))
        self.found = [s for s in m.slots if replies[s.key]]

    # ---- 4. by hand ------------------------------------------------------------------------

    def _step(self, poller: Poller, step: str, slots, text: str) -> Tuple[dict, dict, dict]:
        self.wait(self.settle)
        before = poller.positions()
        self.operator.ask(step, slots, text)
        self.wait(self.settle)
        after, raw = poller.positions(), poller.reported()
        return before, after, raw

    def by_hand(self) -> None:
        """Directions and offsets with the builder's hands (the motors at zero torque)."""
        found = self.found
        if not found:
            return
        m = self.motors
        for b in sorted({s.bus for s in found}):
            codec_frames = [f for s in found if s.bus == b
                            for f in m.codec[s.key].enable_frames((s.motor_id,))]
            m.send(b, codec_frames)
        poller = Poller(m, found).start()
        try:
            for s in [s for s in found if s.kind == 'wheel']:
                before, after, _ = self._step(
                    poller, 'wheel_forward', [s], 'Turn the %s forward by hand (the way it '
                    'rolls when the robot drives forward), a quarter turn or more, and let go.'
                    % s.name.upper())
                self.operator.done()
                check, changes = mc.wheel_check(s, _delta(after, before), m.slots)
                self.report.add(check)
                self.changes.update(changes)
            legs = self.cfg.legs
            for side, leg in enumerate(mc.LEG_NAMES):
                hips = [s for s in found if s.kind == 'hip' and s.key.startswith(leg + '_')]
                if len(hips) < 2:
                    if any(s.kind == 'hip' for s in m.slots):
                        self.report.add(Check(INFO, '%s leg' % leg, 'skipped: its hips did '
                                              'not both answer'))
                    continue
                _, stop, raw = self._step(
                    poller, 'leg_fold', hips, 'Fold the %s LEG to its stop (the wheel up '
                    'towards the body until both hips rest on their lower stops) and hold it '
                    'there.' % leg.upper())
                _, stretched, _ = self._step(
                    poller, 'leg_stretch', hips, 'Now stretch the %s LEG off its stop (the '
                    "wheel a hand's width away from the body) and hold it there."
                    % leg.upper())
                self.operator.done()
                checks, changes = mc.leg_checks(side, m.slots, raw, _delta(stretched, stop),
                                                legs.stop_angles, legs.offsets, legs.homing)
                self.report.extend(checks)
                for k, v in changes.items():
                    self.changes.setdefault(k, {}).update(v)
            if poller.errors:
                self.report.add(Check(FAIL, 'bus', 'sends failed while polling: %s'
                                      % poller.errors[0]))
            if poller.replies == 0:
                self.report.add(Check(FAIL, 'bus', 'no replies while polling'))
        finally:
            poller.stop()

    def exit_all(self) -> None:
        """Zero torque and exit motor mode on every motor spoken to (never raises)."""
        m = self.motors
        for s in self._entered:
            try:
                m.send(s.bus, m.codec[s.key].disable_frames((s.motor_id,)))
            except Exception:  # noqa: B902 -- the way out must not fail
                pass

    # ---- the whole procedure ---------------------------------------------------------------

    def run(self) -> Dict[str, object]:
        """Run the procedure; return the parameter changes (Refused when it must not run)."""
        R = self.report
        R.say('== 1. Who drives the motors')
        self.check_owner()
        R.say('== 2. CAN interface')
        R.extend(self.links() or [Check(INFO, ', '.join(self.motors.channels),
                                        'not SocketCAN (%s): no ip link settings to check'
                                        % self.cfg.can.interface)])
        R.say('== 3. Motors (enter motor mode, zero torque, exit)')
        try:
            self.find_motors()
            R.say('== 4. Directions and zero offsets, by hand (motors at zero torque)')
            self.by_hand()
        finally:
            self.exit_all()
        R.say('== 5. IMU at the tail rest')
        samples = self.imu(IMU_TIME)
        safety = self.cfg.safety
        checks, changes = imu_check.imu_checks(samples, self.cfg.imu.imu_mounting_rpy,
                                               safety.tail_pitch, safety.arm_pose_tolerance,
                                               self.imu_topic)
        R.extend(checks)
        self.changes.update(changes)
        return self.changes
