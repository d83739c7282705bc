"""
The IMU at the tail rest (pure): pitch near the tail angle, roll near 0, and the mounting.

Resting on its tail the robot leans forward by the tail angle (``tail_pitch``, about 36 deg)
and is level across: through the configured ``imu_mounting_rpy`` (core/attitude.py) the body
pitch must read the tail angle (plus the small offset d, which the observer estimates) and the
roll about 0. When it does not, ``suggest_mounting`` tries the 24 rotations that turn the IMU's
axes onto the body's (boards are mounted square to the frame) and names the one under which
the reading is the tail rest: at the tail rest "up" in body coordinates is (-sin 36 deg, 0,
cos 36 deg), which no rotation of the cube's symmetry group maps onto itself, so one reading
picks the rotation. A still IMU also has a small gyro reading and a specific force of about g.
"""
import itertools
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

from .report import Check, FAIL, INFO, PASS, WARN
from ..core.attitude import body_attitude, ImuMounting, rotation_matrix

#: |roll| at the tail rest that passes [rad].
ROLL_TOLERANCE = math.radians(3.0)
#: Gyro norm [rad/s] and |specific force - g| [m/s^2] of an IMU at rest.
STILL_RATE = 0.05
GRAVITY_TOLERANCE = 0.5


class ImuSample(NamedTuple):
    """One sensor_msgs/Imu: orientation (x, y, z, w), its covariance[0], gyro, accel."""

    orientation: Tuple[float, float, float, float]
    covariance0: float
    angular_velocity: Tuple[float, float, float]
    linear_acceleration: Tuple[float, float, float]


def attitude(samples: Sequence[ImuSample], rpy: Sequence[float]) -> Tuple[float, float, str]:
    """Return the mean body (roll, pitch) [rad] of samples through mounting rpy, and the source."""
    m = ImuMounting(rpy)
    rolls, pitches, sources = [], [], set()
    for s in samples:
        a = body_attitude(m, s.orientation, s.covariance0, s.linear_acceleration)
        if math.isfinite(a.roll) and math.isfinite(a.pitch):
            rolls.append(a.roll)
            pitches.append(a.pitch)
            sources.add(a.source)
    if not rolls:
        return math.nan, math.nan, 'none'
    # Mean of angles near each other (a still robot): through sin/cos for roll near +-pi.
    roll = math.atan2(sum(map(math.sin, rolls)), sum(map(math.cos, rolls)))
    return roll, sum(pitches) / len(pitches), '+'.join(sorted(sources))


def square_mountings() -> List[Tuple[float, float, float]]:
    """Return rpy [rad] of the 24 rotations that map the IMU's axes onto the body's."""
    out, seen = [], set()
    quarter = (0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi)
    for rpy in itertools.product(quarter, repeat=3):
        m = ImuMounting(rpy)
        key = tuple(round(v) for row in rotation_matrix(m.q_bi) for v in row)
        if key not in seen:
            seen.add(key)
            out.append(rpy)
    return out


def suggest_mounting(samples: Sequence[ImuSample], tail_pitch: float, tolerance: float
                     ) -> Optional[Tuple[Tuple[float, float, float], float, float]]:
    """
    Return (rpy, roll, pitch) of the square mounting under which samples read the tail rest.

    None when none comes within tolerance [rad] of (roll 0, pitch tail_pitch).
    """
    best = None
    for rpy in square_mountings():
        roll, pitch, _ = attitude(samples, rpy)
        if not math.isfinite(pitch):
            continue
        cost = math.hypot(pitch - tail_pitch, roll)
        if best is None or cost < best[0]:
            best = (cost, rpy, roll, pitch)
    if best is None or best[0] > tolerance:
        return None
    return best[1], best[2], best[3]


def _fmt_rpy(rpy: Sequence[float]) -> str:
    return '[%s]' % ', '.join('%.4f' % v if abs(v) > 1e-9 else '0.0' for v in rpy)


def imu_checks(samples: Sequence[ImuSample], rpy: Sequence[float], tail_pitch: float,
               pitch_tolerance: float, topic: str = 'imu') -> Tuple[List[Check], dict]:
    """
    Judge IMU samples taken at the tail rest.

    rpy: imu_mounting_rpy; tail_pitch, pitch_tolerance: tail_pitch and arm_pose_tolerance
    [rad]. Returns the findings and the parameter changes: a mounting that explains the
    reading, and tail_pitch as measured (it includes the offset d; arming compares with it).
    """
    item = 'IMU (%s)' % topic
    if not samples:
        return [Check(FAIL, item, 'no messages: is the IMU driver running and publishing on '
                      'this topic (remap with --ros-args -r imu:=<its topic>)?')], {}
    out: List[Check] = []
    changes: dict = {}
    roll, pitch, source = attitude(samples, rpy)
    n = len(samples)
    gyro = sum(math.sqrt(sum(v * v for v in s.angular_velocity)) for s in samples) / n
    force = sum(math.sqrt(sum(v * v for v in s.linear_acceleration)) for s in samples) / n
    if gyro > STILL_RATE:
        out.append(Check(WARN, item, 'gyro reads %.3f rad/s at rest (robot moving, or a gyro '
                         'bias to calibrate)' % gyro))
    if abs(force - 9.81) > GRAVITY_TOLERANCE:
        out.append(Check(WARN, item, 'specific force %.2f m/s^2 at rest, not about 9.81 (units? '
                         'an uncalibrated accelerometer?)' % force))
    if not math.isfinite(pitch):
        out.append(Check(FAIL, item, 'no usable attitude in %d samples: the orientation is '
                         'broken (not a unit quaternion) and no gravity fallback applies' % n))
        return out, changes
    text = 'at the tail rest: pitch %.1f deg (tail_pitch %.1f), roll %.1f deg, from the %s ' \
        '(%d samples)' % (math.degrees(pitch), math.degrees(tail_pitch), math.degrees(roll),
                          source, n)
    if abs(pitch - tail_pitch) <= pitch_tolerance and abs(roll) <= ROLL_TOLERANCE:
        out.append(Check(PASS, item, text + '; mounting %s is right' % _fmt_rpy(rpy)))
        changes['tail_pitch'] = round(pitch, 4)
        out.append(Check(INFO, item, 'tail_pitch := %.4f rad (%.1f deg) as measured (it includes '
                         "the IMU's pitch offset d, which the observer estimates on the first "
                         'balance)' % (pitch, math.degrees(pitch))))
        return out, changes
    found = suggest_mounting(samples, tail_pitch, pitch_tolerance)
    if found is not None and any(abs(a - b) > 1e-6 for a, b in zip(found[0], rpy)):
        m_rpy, m_roll, m_pitch = found
        out.append(Check(FAIL, item, text + ': the IMU is mounted otherwise; as %s it reads '
                         'pitch %.1f deg, roll %.1f deg' % (_fmt_rpy(m_rpy), math.degrees(m_pitch),
                                                            math.degrees(m_roll)),
                         ['imu_mounting_rpy: %s (and the same rpy on imu_joint in '
                          'urdf/wheelleg_balance.urdf)' % _fmt_rpy(m_rpy)]))
        changes['imu_mounting_rpy'] = [float(v) for v in m_rpy]
        changes['tail_pitch'] = round(m_pitch, 4)
        return out, changes
    out.append(Check(FAIL, item, text + ': not the tail rest under any square mounting: is the '
                     'robot resting on its tail (legs at the lowest height, both wheels down)?'))
    return out, changes
