"""
validation/paper/metrics.py and table.py: the metric definitions and the experiment table.

The metrics are checked on hand-made series whose figures are known; the table on its own
consistency (every entry run by someone, every criterion stated with numbers where it compares).
"""
import math

import numpy as np
import pytest

from wheelleg_balance.validation.paper import metrics, table

T = np.arange(0.0, 1.0, 0.1)             # 10 samples, 0.0 .. 0.9 s


def test_overshoot_is_past_the_reference_away_from_the_start():
    theta = np.array([36.0, 10.0, -3.0, -1.0, 0.5, 0.0])
    assert metrics.overshoot(theta) == 3.0                        # past 0, start above
    assert metrics.overshoot(theta, reference=0.5) == 3.5          # past the final value
    assert metrics.overshoot(-theta, start_sign=-1.0) == 3.0       # start below
    assert metrics.overshoot(np.array([36.0, 5.0, 1.0])) == 0.0    # never past it
    with pytest.raises(ValueError):
        metrics.overshoot(np.array([]))


def test_settling_time_reports_either_edge_of_the_last_excursion():
    err = np.array([5.0, 3.0, 2.5, 1.0, 2.5, 0.5, 0.1, 0.0, 0.0, 0.0])
    # Last sample outside 2.0 is index 4 (t = 0.4); the stretch inside starts at 0.5.
    assert metrics.settling_time(T, err, 2.0) == pytest.approx(0.5)
    assert metrics.settling_time(T, err, 2.0, edge='outside') == pytest.approx(0.4)
    assert metrics.settling_time(T, err, 10.0) == 0.0                   # never outside: t[0]
    assert metrics.settling_time(T, err, 10.0, since=0.3, edge='outside') == 0.3
    assert metrics.settling_time(T, err + 1.0, 0.5) is None             # ends outside
    assert metrics.settling_time(T, np.abs(err) * -1.0, 2.0) == pytest.approx(0.5)
    # Samples before ``since`` do not count.
    assert metrics.settling_time(T - 0.45, err, 2.0, since=0.0, edge='outside') == 0.0
    assert metrics.settling_time(np.array([]), np.array([]), 1.0) is None


def test_tracking_error_figures():
    sig = np.array([1.0, 2.0, 3.0, 4.0])
    e = metrics.tracking_error(sig, np.array([1.0, 1.0, 1.0, 1.0]))
    assert e.mean_abs == 1.5 and e.max_abs == 3.0
    assert e.rms == pytest.approx(math.sqrt(14.0 / 4.0))
    assert e.std == pytest.approx(np.std([0.0, 1.0, 2.0, 3.0]))
    assert metrics.tracking_error(sig, 2.5).std == pytest.approx(e.std)  # offset left out
    assert all(math.isnan(v) for v in metrics.tracking_error(sig[:0], 0.0))


def test_peaks_drift_crossings_and_first_times():
    assert metrics.peak_abs(np.array([1.0, -7.0]), np.array([6.0])) == 7.0
    assert metrics.max_deviation(np.array([1.0, 4.0, -2.0]), 1.0) == 3.0
    assert metrics.drift(np.array([0.2, 5.0, -1.0, 0.25])) == pytest.approx(0.05)
    assert metrics.zero_crossings(np.array([1.0, 0.5, -0.5, -1.0, 2.0])) == 2
    assert metrics.first_time(T, T > 0.25) == pytest.approx(0.3)
    assert metrics.first_time(T, T > 5.0) is None
    assert metrics.first_index(T > 0.65) == 7
    assert metrics.mean_or_none(np.array([])) is None
    assert list(metrics.window(T, 0.2, 0.5)) == [False] * 2 + [True] * 3 + [False] * 5


def test_every_entry_is_run_and_names_are_unique():
    names = [e.name for e in table.EXPERIMENTS]
    assert len(set(names)) == len(names)
    for e in table.EXPERIMENTS:
        assert e.runners(), e.name
        assert bool(e.model1_key) == (e.model1 is not None), e.name
    keys = [e.model1_key for e in table.for_runner('model1')]
    assert keys == ['startup', 'standing_still', 'height_change', 'rotating', 'robustness']
    with pytest.raises(ValueError):
        table.for_runner('nobody')


def test_criteria_state_their_bounds_and_compare_keys_are_unique():
    judgings = [table.MAIN_JOB_COMMON] + [j for e in table.EXPERIMENTS
                                          for j in (e.model1, e.main_job) if j is not None]
    for j in judgings:
        for c in j.criteria:
            assert c.bound and all(isinstance(v, float) for v in c.limits.values()), c.name
        assert len({c.name for c in j.criteria}) == len(j.criteria)
        assert len({c.key for c in j.compare}) == len(j.compare)
        assert len({m.name for m in j.metrics}) == len(j.metrics)
        assert all(m.definition for m in j.metrics)
    with pytest.raises(KeyError):
        table.MAIN_JOB_COMMON.criterion('no such criterion')
