"""The one height-grid interpolation (core/height_grid.py) and its two users."""
import numpy as np
import pytest

from wheelleg_balance.core.height_grid import bracket
from wheelleg_balance.core.lqr import GainSchedule
from wheelleg_balance.core.observer import DisturbanceObserver
from wheelleg_balance.core.params import RobotParams

H = [0.37, 0.45, 0.60, 0.70]


@pytest.mark.parametrize('l,expected', [
    (0.30, (0, 0.0)), (0.37, (0, 0.0)), (0.41, (0, 0.5)), (0.45, (1, 0.0)),
    (0.65, (2, 0.5)), (0.70, (3, 0.0)), (0.90, (3, 0.0))])
def test_bracket_clamps_to_the_grid_and_gives_the_fraction(l, expected):
    i, t = bracket(H, l)
    assert i == expected[0] and t == pytest.approx(expected[1])


def test_gain_schedule_and_observer_interpolate_linearly_between_grid_heights():
    p = RobotParams()
    gs = GainSchedule(p, heights=np.array(H))
    mid = gs.gain(0.525)
    assert mid == pytest.approx(0.5 * (gs.gains[1] + gs.gains[2]))
    assert gs.gain(0.2) == pytest.approx(gs.gains[0])
    obs = DisturbanceObserver(p, heights=H)
    f_mid = obs.matrices(0.525)[0]
    assert f_mid == pytest.approx(0.5 * (obs.matrices(0.45)[0] + obs.matrices(0.60)[0]))
    assert obs.matrices(0.9)[0] == pytest.approx(obs.matrices(0.70)[0])
