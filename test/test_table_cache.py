"""
The height tables solved once (core/table_cache.py): a table looked up is the table solved.

The LQR schedule (core/lqr.py) and the observer's matrices (core/observer.py) are solved at
34 heights; balance_node's start reads them instead (the build writes the default
configuration's, the control process keeps a robot's own in a cache folder). What is read must
be bit for bit what a fresh solve gives, and nothing may be read for other inputs.
"""
from dataclasses import replace
import json
import os

import numpy as np
import pytest

from wheelleg_balance.core import default_tables, lqr, observer, rise, table_cache
from wheelleg_balance.core.balance_loop import BalanceLoop
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.params import CONTROL_PERIOD, RobotParams


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """Give the test a cache folder of its own, no package tables, an empty memory."""
    monkeypatch.setattr(table_cache, '_package', None)
    monkeypatch.setattr(table_cache, '_folder', None)
    monkeypatch.setattr(table_cache, '_memory', {})
    table_cache.keep_in(str(tmp_path))
    return tmp_path


def _no_solving(monkeypatch):
    """Make any solve fail: what is built afterwards comes from the tables."""
    def refuse(*args, **kwargs):
        raise AssertionError('solved instead of read')
    monkeypatch.setattr(observer, 'observer_rows', refuse)
    monkeypatch.setattr(lqr, 'lqr_gain', refuse)
    monkeypatch.setattr(rise, 'plan_rise', refuse)


def _fresh(p: RobotParams = RobotParams()):
    """Return (observer rows, LQR gains) solved now, as the constructors did before the cache."""
    heights = np.linspace(p.height_min, p.height_max, 34)
    rows = observer.observer_rows(p, CONTROL_PERIOD, observer.DEFAULT_OBSERVER_POLES,
                                  [float(h) for h in heights])
    gains = np.array([lqr.lqr_gain(float(h), p) for h in heights])
    return rows, gains


def _same_bits(a, b) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


def test_the_default_tables_read_back_are_the_solved_ones_bit_for_bit(cache, monkeypatch):
    # the observer's, the LQR's and the planned rise's
    assert default_tables.write_defaults(str(cache)) == 3
    table_cache.forget()
    _no_solving(monkeypatch)
    cfg = BalanceConfig()
    loop = BalanceLoop(replace(cfg, auto=replace(cfg.auto, planned_rise=True)))
    monkeypatch.undo()
    rows, gains = _fresh()
    obs, schedule = loop.core.observer, loop.core.schedule
    assert _same_bits(np.array(obs._rows), rows)
    assert _same_bits(np.array(obs.gains), rows[:, :, 6:8])
    assert _same_bits(schedule.gains, gains)
    assert schedule._k == [tuple(float(v) for v in k) for k in gains]
    plan = loop.core.rise
    table_cache.keep_in(None)
    table_cache.forget()
    assert _same_bits(np.array(plan.rows), rise.rise_table(plan.p, plan.spec))   # solved


def test_a_new_table_is_written_once_and_then_read(cache, monkeypatch):
    p = RobotParams(body_mass=12.5)   # a robot's own model: no default table
    first = lqr.GainSchedule(p)
    files = sorted(os.listdir(cache))
    assert len(files) == 1 and files[0].endswith('.json')
    table_cache.forget()
    _no_solving(monkeypatch)
    again = lqr.GainSchedule(p)
    monkeypatch.undo()
    assert _same_bits(again.gains, first.gains)
    assert _same_bits(first.gains, _fresh(p)[1])


def test_a_robots_own_model_reads_back_its_own_solution(cache, monkeypatch):
    p = RobotParams(body_mass=12.5, height_max=0.66)
    obs = observer.DisturbanceObserver(p)
    table_cache.forget()
    _no_solving(monkeypatch)
    again = observer.DisturbanceObserver(p)
    monkeypatch.undo()
    heights = [float(h) for h in obs.heights]
    fresh = observer.observer_rows(p, CONTROL_PERIOD, observer.DEFAULT_OBSERVER_POLES, heights)
    assert _same_bits(np.array(again._rows), fresh)
    assert _same_bits(np.array(obs._rows), fresh)


def test_other_inputs_are_other_tables(cache, monkeypatch):
    default_tables.write_defaults(str(cache))
    table_cache.forget()
    solved = []
    real = lqr.lqr_gain
    monkeypatch.setattr(lqr, 'lqr_gain', lambda *a, **k: solved.append(1) or real(*a, **k))
    lqr.GainSchedule(RobotParams())
    assert solved == []                          # the default: read
    lqr.GainSchedule(RobotParams(), R=1.0 / 29.0 ** 2)
    assert len(solved) == 34                     # another weight: solved
    lqr.GainSchedule(RobotParams(wheel_radius=0.1000001))
    assert len(solved) == 68                     # another model, however close: solved


@pytest.mark.parametrize('damage', ['key', 'shape', 'values', 'json'])
def test_a_table_that_does_not_match_is_not_used(cache, monkeypatch, damage):
    p = RobotParams(body_mass=9.0)
    lqr.GainSchedule(p)
    (path,) = [cache / n for n in os.listdir(cache)]
    data = json.loads(path.read_text())
    if damage == 'key':
        data['key']['scipy'] = '0.0.1'           # solved by other libraries
    elif damage == 'shape':
        data['shape'] = [4, 34]
    elif damage == 'values':
        data['values'][0][0] = None
    text = json.dumps(data) if damage != 'json' else path.read_text()[:-20]
    path.write_text(text)
    table_cache.forget()
    solved = []
    real = lqr.lqr_gain
    monkeypatch.setattr(lqr, 'lqr_gain', lambda *a, **k: solved.append(1) or real(*a, **k))
    again = lqr.GainSchedule(p)
    monkeypatch.undo()
    assert len(solved) == 34
    assert _same_bits(again.gains, _fresh(p)[1])


def test_nothing_is_written_where_no_folder_was_asked_for(cache):
    table_cache.keep_in(None)
    lqr.GainSchedule(RobotParams(body_mass=8.0))
    assert os.listdir(cache) == []


def test_the_cache_folder_keeps_its_newest_tables(cache, monkeypatch):
    monkeypatch.setattr(table_cache, 'MAX_FILES', 2)
    for mass in (8.0, 9.0, 10.0):
        lqr.GainSchedule(RobotParams(body_mass=mass))
    assert len(os.listdir(cache)) == 2


def test_each_caller_gets_its_own_copy(cache):
    a = lqr.GainSchedule(RobotParams())
    a.gains[:] = 0.0
    b = lqr.GainSchedule(RobotParams())
    assert np.all(b.gains != 0.0)


def test_the_cache_folder_setting(monkeypatch, tmp_path):
    monkeypatch.setenv(table_cache.CACHE_ENV, str(tmp_path))
    assert table_cache.default_folder() == str(tmp_path)
    monkeypatch.setenv(table_cache.CACHE_ENV, '')
    assert table_cache.default_folder() is None    # empty: no cache folder
    monkeypatch.delenv(table_cache.CACHE_ENV)
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path))
    assert table_cache.default_folder() == os.path.join(str(tmp_path), 'wheelleg_balance')
