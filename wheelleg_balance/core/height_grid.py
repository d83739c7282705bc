"""
Linear interpolation over a grid of heights l: the one rule every height schedule uses.

The gains and matrices that depend on the height (the LQR gain k_x(l), core/lqr.py; the
observer's matrices (8), core/observer.py) are computed offline at grid heights and
interpolated per tick. ``bracket`` gives where l falls: clamped to the grid's ends (the robot's
height range), so a reading outside it uses the nearest end's values.
"""
from bisect import bisect_right
from typing import Sequence, Tuple


def bracket(heights: Sequence[float], l: float) -> Tuple[int, float]:
    """
    Return (i, t): l [m] lies a fraction t in [0, 1] of the way from heights[i] to heights[i+1].

    heights: strictly increasing [m]. Below the first, (0, 0.0); above the last (or a grid of
    one), (len - 1, 0.0): the caller then uses row i alone.
    """
    last = len(heights) - 1
    if l <= heights[0]:
        return 0, 0.0
    if l >= heights[last]:
        return last, 0.0
    i = bisect_right(heights, l) - 1
    return i, (l - heights[i]) / (heights[i + 1] - heights[i])
