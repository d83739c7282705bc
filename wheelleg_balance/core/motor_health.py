"""
Motor health from the replies: temperature, error codes, a reboot (no rclpy, no CAN).

- Temperature (the 8-byte MIT reply's, the DJI C620's): from ``temp_derate`` on, the motor's
  torque limit falls linearly, to half at ``temp_max``; at ``temp_max`` balancing ends: the
  sit-down (with the half that is left to brake), or a fault where it cannot run. The two
  thresholds are per motor model (``can.mit.*`` for the wheels, ``legs.mit.*`` for the hips,
  ``can.dji.*``): a motor's figures come from its data sheet.
- Error code (the 8-byte MIT reply's last byte, CubeMars AK firmware; CyberGear's fault bits,
  DaMiao's fault status): any code but 0 is a fault with the reason the protocol decodes
  (``MotorProtocol.error_reason``); the drive has switched its output off.
- Reboot: a motor that lost power and came back is in rest mode (no torque) and knows its
  angle only modulo a rotor turn, so its position reading jumps. A reply whose position is off
  the previous reply's extrapolation by more than ``jump_limit`` (after the wrap of the reply
  field) is a fault: such a motor is never silently "alive" again.
"""
import math
from typing import List, Optional, Tuple

from .safety import MOTOR_ERROR, MOTOR_REBOOTED

#: Share of the torque limit left at temp_max.
DERATE_FLOOR = 0.5


def derate(temperature: Optional[float], temp_derate: float, temp_max: float) -> float:
    """
    Return the share (0..1) of the torque limit a motor at ``temperature`` [deg C] may use.

    1 below temp_derate (and when the motor reports no temperature), falling linearly to
    DERATE_FLOOR at temp_max and staying there (what the sit-down brakes with).
    """
    if temperature is None or not math.isfinite(temperature) or temperature <= temp_derate:
        return 1.0
    if temperature >= temp_max or temp_max <= temp_derate:
        return DERATE_FLOOR
    return 1.0 - (1.0 - DERATE_FLOOR) * (temperature - temp_derate) / (temp_max - temp_derate)


#: Angular acceleration [rad/s^2] a joint can reach between two replies (a free wheel at 12 N m:
#: 1600 rad/s^2): what the extrapolation may miss over a late reply, 0.5 A t^2.
MAX_ACCELERATION = 2000.0
#: Uncertainty [s] of a reply's time: replies are stamped when a tick reads them, and after a
#: late tick the replies of up to MAX_CATCH_UP + 1 ticks (12 ms) are read at once; at speed v
#: that alone moves the extrapolation by v times this (a falling robot's wheels at 40 rad/s
#: read as a 0.4 rad jump on a loaded host).
RECEIPT_JITTER = 0.012


def position_jump(p_prev: float, v_prev: float, t_prev: float, p: float, v: float, t: float,
                  span: float) -> float:
    """
    Return how far [rad] a position reading is off the previous one's extrapolation.

    The reply field wraps every ``span`` [rad] (p_max - p_min; inf: it does not), so the
    difference is taken modulo it. What the joint's acceleration can explain over the gap
    (MAX_ACCELERATION) and what the speed covers within the replies' receipt-time uncertainty
    (RECEIPT_JITTER) are not counted: a loaded host's late or bunched replies are no reboot.
    """
    gap = t - t_prev
    v_sum = v_prev + v
    d = p - (p_prev + 0.5 * v_sum * gap)
    if 0.0 < span < math.inf:
        d = (d + 0.5 * span) % span - 0.5 * span
    d = abs(d) - 0.5 * MAX_ACCELERATION * gap * gap - 0.5 * abs(v_sum) * RECEIPT_JITTER
    return d if d > 0.0 else 0.0


def judge_motors(sets, wheels, name, commanding: bool = False
                 ) -> Tuple[float, Optional[str], List[Tuple[str, str]]]:
    """
    Judge the newest replies of every motor set; return (scale, hot, problems).

    sets: (MotorSet, its model's figures: temp_derate, temp_max) pairs; wheels: the wheels'
    MotorSet (their temperature derates the torque limit); name: a motor's name in a text;
    commanding: the motors are meant to be enabled (a motor that answers disabled after enabled
    then counts as rebooted; after a disarm that is expected).
    scale: the wheels' torque limit factor [-]; hot: why a motor is at temp_max (None: none);
    problems: (fault code, text) of each error code and reboot, and ('', text) for heat. A
    motor's error code is taken (reset) as it is judged; the drive's error (``drive_error``:
    the newest reply's code) is judged again at every call until a reply clears it.
    """
    problems, hot, scale = [], None, 1.0
    for motors, model in sets:
        if not motors.notable:
            continue   # no temperature, error code or reboot: no problem, a scale of 1
        notable = False
        temp_max = model.temp_max
        for m in motors.motors:
            fb = m.feedback
            if fb is None:
                if m.error or m.rebooted is not None:
                    notable = True   # judged once a reply comes
                continue
            code = m.error or m.drive_error
            if code:
                m.error = 0
                if m.drive_error:
                    notable = True   # still reported: judged again next tick
                problems.append((MOTOR_ERROR, '%s error %d: %s'
                                 % (name(m), code, motors.protocol.error_reason(code))))
            if m.switched_off:
                m.switched_off = False
                if commanding and m.rebooted is None:
                    m.rebooted = ('answered disabled while commanded: rebooted, or switched off '
                                  'by its own protection')
            if m.rebooted is not None:
                notable = True
                problems.append((MOTOR_REBOOTED, '%s %s' % (name(m), m.rebooted)))
            t = fb[4]   # temperature [deg C] or None
            if t is None:
                continue   # derate gives 1.0: the scale stays
            notable = True
            if motors is wheels:
                share = derate(t, model.temp_derate, temp_max)
                if share < scale:
                    scale = share
            if t >= temp_max:
                hot = '%s at %.0f deg C, temp_max %.0f deg C' % (name(m), t, temp_max)
                problems.append(('', hot))
        motors.notable = notable
    return scale, hot, problems
