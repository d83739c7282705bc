"""
The figures the paper's experiments are judged by, each defined once, on plain numpy arrays.

Both runners use them: ``experiments`` on the closed-loop simulation of model (1)
(validation/paper/experiments.py) and ``main_job`` on the recordings of the real processes
(validation/paper/main_job/evaluate.py). Arrays are samples in time order; ``t`` in [s]; an
angle comes back in the unit it went in (rad or deg). Where the two runners sample differently
(the end of a settling excursion), the function says which sample it reports.
"""
import math
from typing import NamedTuple, Optional, Tuple

import numpy as np

#: Band of the model-(1) runs' settling time ``settling_time_s`` [deg].
SETTLING_BAND_DEG = 2.0


def settling_band_note(band_deg: float = SETTLING_BAND_DEG) -> str:
    """Return the definition of the model-(1) settling time in words (for reports)."""
    return ('Settling time: time from arming after which the true pitch stays within '
            '+-%g deg for the rest of the run.' % band_deg)


def window(t: np.ndarray, t0: float, t1: float = math.inf) -> np.ndarray:
    """Return the mask of the samples with t0 <= t < t1."""
    return (t >= t0) & (t < t1)


def mean_or_none(a: np.ndarray) -> Optional[float]:
    """Return the mean of ``a``, None when it is empty."""
    return float(np.mean(a)) if len(a) else None


def first_index(condition: np.ndarray) -> Optional[int]:
    """Return the index of the first True of a boolean array, None when there is none."""
    hits = np.flatnonzero(condition)
    return int(hits[0]) if hits.size else None


def first_time(t: np.ndarray, condition: np.ndarray) -> Optional[float]:
    """Return the first time [s] at which ``condition`` holds, None when it never does."""
    i = first_index(condition)
    return float(t[i]) if i is not None else None


def overshoot(theta: np.ndarray, reference: float = 0.0, start_sign: float = 1.0) -> float:
    """
    Return the largest excursion of ``theta`` past ``reference`` away from the start side.

    start_sign: +1 when the run starts above the reference (the start-up from the tail at
    +36 deg), -1 below. 0 when theta never passes the reference. Raises ValueError on an empty
    array. The paper's figure (Sec. V-C, Fig. 3): 1 deg for IDA-PBC, 12 deg for the linear
    controller; model (1) measures past 0, main_job past the final pitch.
    """
    return max(0.0, float(np.max(start_sign * (reference - theta))))


def settling_time(t: np.ndarray, err: np.ndarray, band: float, since: Optional[float] = None,
                  edge: str = 'inside') -> Optional[float]:
    """
    Return when |err| entered ``band`` for good: the end of its last excursion outside [s].

    Only samples with t >= since count (None: all). edge 'inside': the first sample of the
    final stretch inside the band, None when the run ends outside (model (1)); edge 'outside':
    the last sample outside, one sample earlier (main_job). A series that never leaves the band
    settled at ``since`` (or at t[0]); an empty one gives None.
    """
    if t.size == 0:
        return None
    outside = np.abs(err) > band
    if since is not None:
        outside &= t >= since
    idx = np.flatnonzero(outside)
    if idx.size == 0:
        return float(since) if since is not None else float(t[0])
    last = int(idx[-1])
    if edge == 'outside':
        return float(t[last])
    return float(t[last + 1]) if last + 1 < t.size else None


def rest_point(t: np.ndarray, v: np.ndarray, x: np.ndarray, speed: float,
               since: float = 0.0) -> Tuple[Optional[float], Optional[float]]:
    """
    Return (time, distance) at which a run came to rest: |v| below ``speed`` to its end.

    The time is the last sample faster than ``speed`` (settling_time's edge 'outside', from
    ``since`` [s]; ``since`` itself when none is); the distance is |x there - x[0]|
    (interpolated). (None, None) when the run is still faster at its end or empty. main_job's
    start-up and the tuning's MuJoCo runs.
    """
    if t.size == 0 or abs(v[-1]) >= speed:
        return None, None
    t_rest = settling_time(t, v, speed, since=since, edge='outside')
    return t_rest, abs(float(np.interp(t_rest, t, x)) - float(x[0]))


def extrapolated_stop(t_end: float, travel: float, v: float,
                      decel: float) -> Tuple[float, float]:
    """
    Return (rest time [s], distance [m]) of a run still moving at ``v`` [m/s] at ``t_end``.

    It is taken to stop at ``decel`` [m/s^2] from there: t_end + |v| / a, and the ``travel``
    so far plus v^2 / (2 a).
    """
    return t_end + abs(v) / decel, travel + v * v / (2.0 * decel)


def peak_abs(*series: np.ndarray) -> float:
    """Return the largest magnitude over all the series (e.g. the two wheel torques [N m])."""
    return float(max(np.max(np.abs(s)) for s in series))


def max_deviation(a: np.ndarray, reference: float = 0.0) -> float:
    """Return max |a - reference|; raises ValueError on an empty array."""
    return float(np.max(np.abs(a - reference)))


def drift(x: np.ndarray) -> float:
    """Return |x(end) - x(start)|, the net displacement over the samples [m]."""
    return float(abs(x[-1] - x[0]))


class TrackingError(NamedTuple):
    """Error of a signal against its reference over a window (unit of the signal)."""

    mean_abs: float   # mean |signal - reference|
    rms: float        # root mean square of signal - reference
    max_abs: float    # largest |signal - reference|
    std: float        # standard deviation of signal - reference: the swing, without an offset


def tracking_error(signal: np.ndarray, reference) -> TrackingError:
    """Return the error figures of ``signal`` against ``reference`` (array or number)."""
    err = signal - reference
    if err.size == 0:
        nan = float('nan')
        return TrackingError(nan, nan, nan, nan)
    return TrackingError(mean_abs=float(np.mean(np.abs(err))),
                         rms=float(np.sqrt(np.mean(err * err))),
                         max_abs=float(np.max(np.abs(err))), std=float(np.std(err)))


def zero_crossings(a: np.ndarray) -> int:
    """Return how often ``a`` changes sign (e.g. velocity reversals)."""
    return int(np.sum(np.diff(np.sign(a)) != 0))
