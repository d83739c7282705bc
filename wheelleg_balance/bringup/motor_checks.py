"""
The motors' bring-up judgements (pure): who answers, which way they turn, where their zero is.

``motor_slots`` lists the six motors a BalanceConfig drives (two wheels, four hips) with
the parameter that holds each one's direction; ``motor_protocols`` the codecs they speak (the
wheels' ``can.protocol``, the hips' ``legs.can.protocol``): every frame, reply, error reason
and mode check comes from there. The rest judges what session.py recorded:

- ``probe_check``: a motor's answer to its mode query (the protocol's ``mode_problem``: a
  DaMiao motor not in MIT mode, a CyberGear not in run_mode 0, with the fix), to enable / zero
  torque / disable (position, temperature and the protocol's error reason), or, when it stayed
  silent, the likely cause from what else the bus showed (an unconfigured ID that answers, the
  motor answering on the other bus, frames no configured protocol reads, nothing at all);
- ``wheel_check``: the builder turned a wheel forward by hand; the motor's unwrapped position
  change times its direction must be positive (a wheel's joint angle is direction times the
  motor's, core/motors.py), else the direction is wrong; if the motor did not move but the other
  wheel's did, their IDs are crossed;
- ``leg_checks``: the builder folded a leg to its stop and stretched it off the stop again:
  q = direction p + offset (core/legs.py) must grow while the leg stretches (FiveBarLeg: q > 0
  turns the thigh down), and the reading at the stop gives the offset,
  ``offset = stop_angle - direction p``; with ``legs.homing: set_zero`` it must be the
  configured one, else the hip was powered up away from its zero pose (a hip knows its angle
  only modulo one rotor turn, 2 pi / 9 for a 9:1 gear, after power-up) or was zeroed elsewhere.
"""
from dataclasses import dataclass
import math
from typing import Dict, List, Optional, Sequence, Tuple

from .report import Check, FAIL, INFO, PASS, WARN
from ..core.config import BalanceConfig
from ..core.protocols import protocol_for
from ..core.protocols.base import MotorFeedback, MotorProtocol

#: Smallest turn of a wheel [rad] and stretch of a hip [rad] that counts as moved by hand.
MIN_WHEEL_TURN = 0.5
MIN_HIP_MOTION = 0.08
#: Largest difference between a measured and the configured hip offset [rad] (set_zero).
OFFSET_TOLERANCE = math.radians(3.0)
#: Temperatures [deg C] above which a motor at rest is suspicious.
WARM = 50.0
#: A hip motor's rotor turn at the output of a 9:1 gear [rad] (the offsets' usual step).
ROTOR_TURN_9_1 = 2.0 * math.pi / 9.0
LEG_NAMES = ('left', 'right')


@dataclass(frozen=True)
class MotorSlot:
    """
    One configured motor.

    key: 'left_wheel', 'right_wheel', 'left_front', 'left_rear', 'right_front', 'right_rear';
    name: as printed; motor_id; bus: index into channels(); direction: the configured sign;
    kind: 'wheel' or 'hip'; index: 0/1 for the wheels, 0..3 for the hips (legs.* order);
    id_param / direction_param: the parameters that hold its ID and direction.
    """

    key: str
    name: str
    motor_id: int
    bus: int
    direction: int
    kind: str
    index: int
    id_param: str
    direction_param: str

    @property
    def label(self) -> str:
        """Return 'left wheel (ID 1)'."""
        return '%s (ID %d)' % (self.name, self.motor_id)


def channels(cfg: BalanceConfig) -> List[str]:
    """Return the CAN channels: the wheels', then the hips' when they have a bus of their own."""
    legs = cfg.legs
    if legs.driven and legs.channel and legs.channel != cfg.can.channel:
        return [cfg.can.channel, legs.channel]
    return [cfg.can.channel]


def motor_protocols(cfg: BalanceConfig) -> Tuple[MotorProtocol, MotorProtocol]:
    """Return the codecs of (the wheels, the hips): can.protocol, legs.can.protocol."""
    return (protocol_for(cfg.can.protocol, cfg.can),
            protocol_for(cfg.legs.protocol, cfg.legs))


def motor_slots(cfg: BalanceConfig) -> List[MotorSlot]:
    """Return the motors a configuration drives: the two wheels, the four hips if driven."""
    c = cfg.can
    out = [MotorSlot('left_wheel', 'left wheel', c.left_motor_id, 0, c.left_direction,
                     'wheel', 0, 'can.left_motor_id', 'can.left_direction'),
           MotorSlot('right_wheel', 'right wheel', c.right_motor_id, 0, c.right_direction,
                     'wheel', 1, 'can.right_motor_id', 'can.right_direction')]
    if cfg.legs.driven:
        bus = len(channels(cfg)) - 1
        for i, key in enumerate(('left_front', 'left_rear', 'right_front', 'right_rear')):
            out.append(MotorSlot(key, key.replace('_', ' ') + ' hip', cfg.legs.motor_ids[i], bus,
                                 cfg.legs.directions[i], 'hip', i, 'legs.motor_ids[%d]' % i,
                                 'legs.directions[%d]' % i))
    return out


class Unwrapper:
    """
    A motor's position made continuous across its reply's wrap (the protocol's position_step).

    MIT's 16-bit position wraps at +-p_max, a C620's or an LK's single-turn encoder every
    rotor turn; between two replies 10 ms apart a hand turns a motor far less than half that
    span, so the protocol's shortest step is the true one.
    """

    def __init__(self, protocol: MotorProtocol):
        self.protocol = protocol
        self.value: Optional[float] = None
        self._last: Optional[float] = None

    def update(self, p: float) -> float:
        """Take a reported position [rad]; return the unwrapped one."""
        if self._last is None:
            self.value = self._last = float(p)
            return self.value
        step = self.protocol.position_step(self._last, p)
        self._last = float(p)
        self.value += step
        return self.value


# ---- finding the motors --------------------------------------------------------------------

def feedback_text(fb: MotorFeedback, protocol: MotorProtocol) -> str:
    """Return 'position 0.123 rad, temperature 25 degC, error 0 (no error)' for a reply."""
    parts = ['position %+.3f rad' % fb.position]
    parts.append('temperature %.0f degC' % fb.temperature if fb.temperature is not None
                 else 'no temperature in its replies')
    if fb.error is not None:
        reason = protocol.error_reason(fb.error) if fb.error else 'no error'
        parts.append('error %d (%s)' % (fb.error, reason))
    return ', '.join(parts)


def probe_check(slot: MotorSlot, protocol: MotorProtocol, replies: Sequence[MotorFeedback],
                channel: str, strangers: Sequence[int] = (), elsewhere: Optional[str] = None,
                unread_frames: int = 0, mode_problem: Optional[str] = None) -> Check:
    """
    Judge a motor's answers to its mode query and to enable, zero torque, disable.

    protocol: its motor set's codec; replies: the replies that came; mode_problem: what the
    protocol's mode_problem said is wrong with its mode (and the fix), None when its mode is
    right or unknown. For a silent motor: strangers, IDs that answered on its bus though no
    motor is configured with them; elsewhere, the channel where its ID answered instead;
    unread_frames, frames on its bus that no configured protocol reads (neither a reply nor
    a command of theirs).
    """
    item = slot.label
    if mode_problem is not None:
        return Check(FAIL, item, 'answers on %s, but %s' % (channel, mode_problem),
                     ['set the mode as said, then run bringup again (docs/robot_setup.md, '
                      '"Motors: modes and IDs"); bring-up leaves a motor in a wrong mode '
                      'disabled'])
    if replies:
        fb = replies[-1]
        if fb.error:
            return Check(FAIL, item, 'answers, but reports %s' % feedback_text(fb, protocol),
                         ['clear the fault (power-cycle the motor; for an over-temperature let '
                          'it cool) before arming'])
        if fb.temperature is not None and fb.temperature > WARM:
            return Check(WARN, item, 'answers, warm at rest: %s' % feedback_text(fb, protocol))
        return Check(PASS, item, 'answers on %s (%s): %s (%d replies)'
                     % (channel, protocol.name, feedback_text(fb, protocol), len(replies)))
    causes: List[str] = []
    fixes: List[str] = []
    if elsewhere is not None:
        causes.append('it answers on %s instead: wrong bus' % elsewhere)
        fixes.append('connect it to %s, or set %s' % (
            channel, 'legs.can.channel: %s' % elsewhere if slot.kind == 'hip' else
            'can.channel: %s' % elsewhere))
    if strangers:
        causes.append('ID%s %s answer%s on %s though no motor is configured with %s: a wrong ID'
                      % ('s' if len(strangers) > 1 else '', ', '.join(map(str, strangers)),
                         '' if len(strangers) > 1 else 's', channel,
                         'them' if len(strangers) > 1 else 'it'))
        fixes.append("set this motor's ID to %d (docs/robot_setup.md, \"Motors: modes and "
                     'IDs\"), or %s: %d if that motor is this one'
                     % (slot.motor_id, slot.id_param, strangers[0]))
    if unread_frames:
        causes.append('%d frames on %s that the configured protocols do not read: a motor in '
                      'another mode or speaking another protocol, or %s is not the protocol '
                      'of this motor'
                      % (unread_frames, channel, protocol.name))
        fixes.append('set the motor to the mode protocol %s needs, or the protocol '
                     '(docs/robot_setup.md, "Motors: modes and IDs")' % protocol.name)
    if not causes:
        causes.append('nothing answers: no power (is its LED on?), the CAN wires (CAN_H/CAN_L '
                      'swapped or open), the termination (60 ohm between CAN_H and CAN_L with '
                      'the power off), not speaking protocol %s (its mode), or an ID outside '
                      'the scanned range' % protocol.name)
    return Check(FAIL, item, 'does not answer on %s: %s' % (channel, '; '.join(causes)), fixes)


# ---- directions and offsets -----------------------------------------------------------------

def wheel_check(slot: MotorSlot, deltas: Dict[str, float], slots: Sequence[MotorSlot]
                ) -> Tuple[Check, Dict[str, object]]:
    """
    Judge a wheel turned forward by hand; deltas: {slot key: unwrapped motor position change}.

    Returns the finding and the parameter changes it implies ({} when none).
    """
    d = deltas.get(slot.key, math.nan)
    item = slot.label
    if abs(d) >= MIN_WHEEL_TURN:
        joint = slot.direction * d
        if joint > 0.0:
            return Check(PASS, item, 'turned forward, the motor reads %+.2f rad: direction %+d '
                         'is right' % (d, slot.direction)), {}
        fixed = -slot.direction
        return (Check(FAIL, item, 'turned forward by hand, the motor reads %+.2f rad, i.e. '
                      'backwards for direction %+d: the direction is wrong (motor mounted or '
                      'wired the other way)' % (d, slot.direction),
                      ['%s: %d' % (slot.direction_param, fixed)]),
                {slot.direction_param: fixed})
    movers = [s for s in slots if s.kind == 'wheel' and s.key != slot.key
              and abs(deltas.get(s.key, 0.0)) >= MIN_WHEEL_TURN]
    if movers:
        m = movers[0]
        return (Check(FAIL, item, 'did not move (%+.2f rad), but %s did (%+.2f rad): the two '
                      "wheels' IDs are crossed" % (d, m.label, deltas[m.key]),
                      ['swap %s and %s (%d <-> %d)' % (slot.id_param, m.id_param,
                                                       slot.motor_id, m.motor_id)]),
                {slot.id_param: m.motor_id, m.id_param: slot.motor_id})
    return Check(FAIL, item, 'no turn seen (%+.2f rad; a quarter turn or more is needed): was it '
                 'this wheel, and did its motor answer?' % d), {}


def leg_checks(side: int, slots: Sequence[MotorSlot], at_stop: Dict[str, float],
               stretch: Dict[str, float], stop_angles: Sequence[float],
               offsets: Sequence[float], homing: str) -> Tuple[List[Check], Dict[str, object]]:
    """
    Judge one leg (side 0 left, 1 right) folded to its stop, then stretched off it by hand.

    at_stop: {hip key: unwrapped motor position at the stop}; stretch: {hip key: position
    change while stretching}; stop_angles, offsets: legs.stop_angles and legs.offsets (four);
    homing: legs.homing. Returns the findings and the parameter changes (directions, offsets).
    """
    leg = LEG_NAMES[side]
    hips = [s for s in slots if s.kind == 'hip' and s.key.startswith(leg + '_')]
    others = [s for s in slots if s.kind == 'hip' and s not in hips]
    out: List[Check] = []
    changes: Dict[str, object] = {}
    directions = {}
    for s in hips:
        d = stretch.get(s.key, math.nan)
        if abs(d) >= MIN_HIP_MOTION:
            if s.direction * d > 0.0:
                out.append(Check(PASS, s.label, 'leg stretched, the motor reads %+.3f rad: '
                                 'direction %+d is right' % (d, s.direction)))
                directions[s.key] = s.direction
            else:
                out.append(Check(FAIL, s.label, 'leg stretched by hand, the motor reads %+.3f '
                                 'rad, i.e. folding for direction %+d: the direction is wrong'
                                 % (d, s.direction),
                                 ['%s: %d' % (s.direction_param, -s.direction)]))
                directions[s.key] = -s.direction
                changes.setdefault('legs.directions', {})[s.index] = -s.direction
            continue
        movers = [o.label for o in others if abs(stretch.get(o.key, 0.0)) >= MIN_HIP_MOTION]
        out.append(Check(FAIL, s.label, 'no motion seen while the %s leg was stretched '
                         '(%+.3f rad)%s' % (leg, d, ": but %s moved: the legs' IDs are crossed"
                                            % ', '.join(movers) if movers else '')))
    for s in hips:
        p = at_stop.get(s.key, math.nan)
        d = directions.get(s.key)
        if d is None or not math.isfinite(p):
            continue
        measured = stop_angles[s.index] - d * p
        diff = measured - offsets[s.index]
        turns = diff / ROTOR_TURN_9_1
        text = 'at its stop (%.3f rad) the motor reads %+.3f rad: offset %+.4f rad' % (
            stop_angles[s.index], p, measured)
        if homing == 'hard_stops':
            out.append(Check(INFO, s.label, text + ' (homing hard_stops measures it at every '
                             'start; written as the first guess)'))
            changes.setdefault('legs.offsets', {})[s.index] = round(measured, 4)
        elif abs(diff) <= OFFSET_TOLERANCE:
            out.append(Check(PASS, s.label, text + ', the configured %+.4f rad (%+.1f deg off)'
                             % (offsets[s.index], math.degrees(diff))))
        else:
            hint = ('%.2f rotor turns of a 9:1 hip (40 deg each): the motor was powered up away '
                    'from its zero pose, or zeroed elsewhere' % turns
                    if abs(turns - round(turns)) < 0.1 else 'the zero is elsewhere')
            changes.setdefault('legs.offsets', {})[s.index] = round(measured, 4)
            out.append(Check(FAIL, s.label, text + ', configured %+.4f rad: %+.1f deg off, %s'
                             % (offsets[s.index], math.degrees(diff), hint),
                             ['with legs.homing set_zero power the robot up with the legs '
                              'folded at their stops (the zero pose), or write the measured '
                              'offset: %s' % 'legs.offsets[%d]: %.4f' % (s.index, measured)]))
    return out, changes


def apply_changes(flat: Dict[str, object], changes: Dict[str, object]) -> Dict[str, object]:
    """
    Return flat parameters with changes applied; list entries come as {name: {index: value}}.

    Names with an index ('legs.motor_ids[2]') set that entry of the list.
    """
    out = {k: (list(v) if isinstance(v, list) else v) for k, v in flat.items()}
    for name, value in changes.items():
        if isinstance(value, dict):
            for i, v in value.items():
                out[name][i] = v
        elif name.endswith(']'):
            base, index = name[:-1].split('[')
            out[base][int(index)] = value
        else:
            out[name] = value
    return out
