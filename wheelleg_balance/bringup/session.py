"""
The bring-up procedure on the CAN buses (python-can through nodes/can_io.CanIo; no rclpy).

``BringUp.run`` does, in order, and prints each finding as it comes (report.py):

1. refuses to go on while something else drives the motors: a balance_node in the ROS graph
   (``owners``, given by the caller) or command frames to the configured motors on a bus that
   bring-up has not spoken to yet (each motor set's protocol tells a command of its motors,
   ``command_motor_ids``; replies alone are no sign: a C620 sends its feedback unasked);
2. the CAN interfaces' settings (``links``, iplink.py, for SocketCAN);
3. every configured motor, in its motor set's protocol (the wheels' ``can.protocol``, the
   hips' ``legs.can.protocol``): its control mode where the protocol can ask
   (``mode_query_frames`` / ``mode_problem``: a motor in a wrong mode is named with the fix and
   never enabled), then enable, one zero-torque command, disable (the replies: position,
   temperature, the protocol's error reason); for a silent one, a scan of the other IDs with
   the protocol's disable frames (harmless) and a look at the other bus, to name the likely
   cause;
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
from ..core.protocols.base import Frame, MotorFeedback, MotorProtocol

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


class Motors:
    """
    The configured motors on their buses, each in its motor set's protocol.

    ``codec[slot key]`` is the codec of a motor (the wheels' or the hips' one); a frame on a bus
    is read with the codecs of that bus's motors, so wheels and hips of two protocols can share
    a bus. Keys of ``_slots``: (bus, codec, motor ID).
    """

    def __init__(self, cfg: BalanceConfig, ios: Sequence):
        self.ios = list(ios)
        self.slots = mc.motor_slots(cfg)
        self.channels = mc.channels(cfg)
        wheel, hip = mc.motor_protocols(cfg)
        self.codec: Dict[str, MotorProtocol] = {
            s.key: hip if s.kind == 'hip' else wheel for s in self.slots}
        self._slots: Dict[tuple, mc.MotorSlot] = {
            (s.bus, self.codec[s.key], s.motor_id): s for s in self.slots}

    def codecs(self, bus: int) -> List[MotorProtocol]:
        """Return the codecs of the motors (also those looked for) on a bus, wheels' first."""
        out: List[MotorProtocol] = []
        for b, codec, _ in self._slots:
            if b == bus and codec not in out:
                out.append(codec)
        return out

    def look_for(self, slot: mc.MotorSlot, bus: int) -> Optional[mc.MotorSlot]:
        """Take a motor's replies on another bus for a while (``forget`` ends it)."""
        key = (bus, self.codec[slot.key], slot.motor_id)
        if key in self._slots:
            return None
        self._slots[key] = other = mc.MotorSlot(
            slot.key, slot.name, slot.motor_id, bus, slot.direction, slot.kind, slot.index,
            slot.id_param, slot.direction_param)
        return other

    def forget(self, slot: mc.MotorSlot) -> None:
        """End look_for."""
        key = (slot.bus, self.codec[slot.key], slot.motor_id)
        if self._slots.get(key) is slot:
            del self._slots[key]

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
        """
        Return (configured motor, its reply), (None, a stranger's reply) or (None, None).

        A reply that one codec of the bus reads as a configured motor's is that motor's, even
        if another codec reads it as a stranger's (MIT and DaMiao replies share ID 0).
        """
        stranger = None
        for codec in self.codecs(bus):
            fb = codec.decode_feedback(frame)
            if fb is None:
                continue
            slot = self._slots.get((bus, codec, fb.motor_id))
            if slot is not None:
                return slot, fb
            stranger = stranger or fb
        return None, stranger

    def mode_answer(self, bus: int, frame: Frame) -> Optional[Tuple[Optional[mc.MotorSlot],
                                                                    Optional[str]]]:
        """Return (the motor, what is wrong with its mode or None) for a mode answer, else None."""
        for codec in self.codecs(bus):
            answer = codec.mode_problem(frame)
            if answer is not None:
                return self._slots.get((bus, codec, answer[0])), answer[1]
        return None

    def commanded(self, bus: int, frame: Frame) -> Optional[mc.MotorSlot]:
        """Return the configured motor a frame commands (another sender's), else None."""
        for codec in self.codecs(bus):
            for motor_id in codec.command_motor_ids(frame):
                slot = self._slots.get((bus, codec, motor_id))
                if slot is not None:
                    return slot
        return None

    def read_by_none(self, bus: int, frame: Frame) -> bool:
        """Tell whether no codec of the bus reads a frame: no reply, command or mode answer."""
        return not any(c.decode_feedback(frame) is not None or c.command_motor_ids(frame)
                       or c.mode_problem(frame) is not None for c in self.codecs(bus))

    def frames_by_bus(self, slots: Sequence[mc.MotorSlot], kind: str) -> Dict[int, List[Frame]]:
        """Return {bus: the frames of ``kind`` ('enable_frames', ...) for those of slots}."""
        out: Dict[int, List[Frame]] = {}
        for bus in sorted({s.bus for s in slots}):
            for codec in self.codecs(bus):
                ids = [s.motor_id for s in slots if s.bus == bus and self.codec[s.key] is codec]
                if ids:
                    out.setdefault(bus, []).extend(getattr(codec, kind)(ids))
        return out


class Poller:
    """Zero-torque commands every POLL_PERIOD to the motors; their newest replies, unwrapped."""

    def __init__(self, motors: Motors, slots: Sequence[mc.MotorSlot], clock=time.monotonic):
        self.m = motors
        self.slots = list(slots)
        self._clock = clock
        self._lock = threading.Lock()
        self._unwrap = {s.key: mc.Unwrapper(self.m.codec[s.key]) for s in self.slots}
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
        frames = self.m.frames_by_bus(self.slots, 'zero_torque_frames')
        buses = sorted(frames)
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
            commanded = [m.commanded(b, frame) for frame in m.receive(b)]
            ours = ['a command to %s' % slot.label for slot in commanded if slot is not None]
            if ours:
                raise Refused('%s carries motor traffic before bring-up said anything (%d '
                              'frames in %.1f s, e.g. %s): another controller, a balance_node '
                              'on another computer?, drives these motors' % (
                                  channel, len(ours), LISTEN, ours[0]))
        self.report.add(Check(PASS, 'bus', 'no balance_node in the ROS graph, no motor traffic '
                              'on %s' % ', '.join(m.channels)))

    # ---- 3. finding the motors -------------------------------------------------------------

    def _exchange(self, bus: int, frames: Sequence[Frame], want: Optional[mc.MotorSlot],
                  seen: dict) -> List[MotorFeedback]:
        """Send frames one by one; return the replies of ``want`` that came to each."""
        got = []
        for frame in frames:
            seen['sent'][bus].add(tuple(frame))   # an echo of it (LK's run, off) is no stranger
            self.motors.send(bus, [frame])
            end = time.monotonic() + REPLY_WAIT
            while time.monotonic() < end:
                time.sleep(0.002)
                for f in self.motors.receive(bus):
                    slot, fb = self._note(bus, f, seen)
                    if slot is want and fb is not None:
                        got.append(fb)
        return got

    def _note(self, bus: int, frame: Frame, seen: dict
              ) -> Tuple[Optional[mc.MotorSlot], Optional[MotorFeedback]]:
        """Record what a frame says (a mode answer, a stranger, unread); return decode's."""
        m = self.motors
        mode = m.mode_answer(bus, frame)   # first: a DaMiao register answer looks like a reply
        if mode is not None:
            if mode[0] is not None:
                seen['modes'][mode[0].key] = mode[1]
            return None, None
        slot, fb = m.decode(bus, frame)
        if slot is None and fb is not None:
            seen['strangers'][bus].add(fb.motor_id)
        elif fb is None and tuple(frame) not in seen['sent'][bus] \
                and m.read_by_none(bus, frame):
            seen['unread'][bus] += 1
        return slot, fb

    def find_motors(self) -> None:
        """Check every configured motor's mode, probe it; name the likely cause of a silence."""
        m = self.motors
        n = len(m.ios)
        seen = {'unread': [0] * n, 'strangers': [set() for _ in range(n)], 'modes': {},
                'sent': [set() for _ in range(n)]}
        # The modes first, every motor still as powered up (a DaMiao answers register reads
        # only while disabled); a motor in a wrong mode is never enabled.
        for s in m.slots:
            self._exchange(s.bus, m.codec[s.key].mode_query_frames((s.motor_id,)), None, seen)
        modes = seen['modes']
        replies: Dict[str, List[MotorFeedback]] = {}
        for s in m.slots:
            codec = m.codec[s.key]
            ids = (s.motor_id,)
            if modes.get(s.key) is not None:
                replies[s.key] = []
                continue
            self._entered.append(s)
            replies[s.key] = self._exchange(
                s.bus, codec.enable_frames(ids) + codec.disable_frames(ids), s, seen)
        missing = [s for s in m.slots if not replies[s.key] and modes.get(s.key) is None]
        elsewhere: Dict[str, str] = {}
        if missing:
            for b in range(n):
                for codec in m.codecs(b):
                    configured = {s.motor_id for s in m.slots
                                  if s.bus == b and m.codec[s.key] is codec}
                    for i in self.scan_ids:
                        if i not in configured:
                            self._exchange(b, codec.disable_frames((i,)), None, seen)
            for s in missing:
                for b in range(n):
                    other = m.look_for(s, b) if b != s.bus else None
                    if other is None:
                        continue
                    if self._exchange(b, m.codec[s.key].disable_frames((s.motor_id,)), other,
                                      seen):
                        elsewhere[s.key] = m.channels[b]
                    m.forget(other)
        for s in m.slots:
            ours = {o.motor_id for o in m.slots if o.bus == s.bus}
            strangers = sorted(seen['strangers'][s.bus] - ours)
            self.report.add(mc.probe_check(s, m.codec[s.key], replies[s.key], m.channels[s.bus],
                                           strangers, elsewhere.get(s.key),
                                           seen['unread'][s.bus], modes.get(s.key)))
        self.found = [s for s in m.slots if replies[s.key] and modes.get(s.key) is None]

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
        for b, frames in m.frames_by_bus(found, 'enable_frames').items():
            m.send(b, frames)
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
        R.say('== 3. Motors (control mode, enable, zero torque, disable)')
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
