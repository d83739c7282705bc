"""
`experiments --quick` (validation/paper/experiments.py): what it writes and the claims it carries.

The numbers checked here are simulated by the run itself (nonlinear model (1) + BalanceCore).
"""
import contextlib
import io
import json
import math
import os

import pytest

from wheelleg_balance.validation.paper import experiments, table

COMMON = ('overshoot_deg', 'settling_time_s', 'peak_torque_nm', 'fell')
STANDING = ('d_hat_error_deg', 'drift_m', 'x_dot_final_mps')


@pytest.fixture(scope='module')
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('experiments')
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert experiments.main(['--output', str(out), '--quick']) == 0
    with open(out / 'experiments.json') as f:
        data = json.load(f)
    return out, data, buf.getvalue()


def test_json_has_every_experiment_and_the_required_keys(quick_run):
    _, data, _ = quick_run
    for exp in ('startup', 'standing_still', 'height_change', 'rotating'):
        assert data[exp], exp
        for name, m in data[exp].items():
            for key in COMMON:
                assert key in m, (exp, name, key)
            assert isinstance(m['fell'], bool)
    for key in STANDING:
        assert key in data['standing_still']['output_regulation']
    assert set(data['robustness']) == set(experiments.PERTURBATIONS)
    for row in data['robustness'].values():
        assert set(row) == set(experiments.controllers())
        for m in row.values():
            for key in COMMON:
                assert key in m
    assert {'ida_pbc_table_i', 'lqr'} <= set(data['startup'])


def test_start_up_from_the_tail_ida_pbc_does_not_fall(quick_run):
    _, data, _ = quick_run
    for name, m in data['startup'].items():
        if name.startswith('ida_pbc'):
            assert m['fell'] is False, name
            assert m['settling_time_s'] is not None and m['settling_time_s'] < 4.0, name
            assert 0.0 < m['peak_torque_nm'] <= 12.0 + 1e-9, name
            assert m['overshoot_deg'] < 36.0, name


def test_standing_still_meets_its_targets(quick_run):
    _, data, _ = quick_run
    m = data['standing_still']['output_regulation']
    assert m['fell'] is False
    assert m['d_hat_error_5s_deg'] <= 0.1
    assert m['d_hat_within_0p1deg_s'] is not None and m['d_hat_within_0p1deg_s'] <= 5.0
    assert m['d_hat_error_deg'] <= 0.1
    assert m['x_dot_final_mps'] < 1e-3
    assert m['drift_m'] < 0.01


def test_height_change_keeps_ida_pbc_up(quick_run):
    _, data, _ = quick_run
    m = data['height_change']['ida_pbc_table_i']
    assert m['fell'] is False
    assert math.isfinite(m['velocity_error_rms_mps']) and m['velocity_error_rms_mps'] < 0.3


def test_rotating_follows_the_yaw_rate_reference_and_stays_up(quick_run):
    _, data, _ = quick_run
    m = data['rotating']['ida_pbc_table_i']
    assert m['fell'] is False
    assert abs(m['yaw_rate_final_dps'] - 165.0) < 2.0
    assert m['max_abs_theta_deg'] < 1.0


def test_plots_and_table_are_written_and_the_folder_is_printed(quick_run):
    out, _, printed = quick_run
    for name in ['startup.png', 'standing_still.png', 'height_change.png', 'rotating.png'] + [
            'robustness_%s.png' % p for p in experiments.PERTURBATIONS]:
        path = out / name
        assert path.is_file() and path.stat().st_size > 5000, name
        with open(path, 'rb') as f:
            assert f.read(8) == b'\x89PNG\r\n\x1a\n'
    table = (out / 'comparison.md').read_text()
    assert '| ida_pbc_table_i |' in table and 'Standing still' in table
    assert str(out) in printed.strip().splitlines()[-1]
    assert os.path.isabs(printed.strip().splitlines()[-1].split(': ', 1)[1])


def test_the_experiments_metrics_and_targets_are_the_tables(quick_run):
    _, data, _ = quick_run
    entries = table.for_runner('model1')
    assert list(data) == [e.model1_key for e in entries] + ['meta']
    for e in entries:
        allowed = set(table.metric_names(e, 'model1'))
        rows = data[e.model1_key].values()
        if e.kind == 'robustness':              # per perturbation, per controller
            rows = [m for row in rows for m in row.values()]
        for m in rows:
            assert set(m) <= allowed, (e.name, set(m) - allowed)
    assert data['meta']['targets'] == table.BY_NAME['standing'].model1.limits() == {
        'd_hat_error_deg': 0.1, 'd_hat_time_s': 5.0, 'x_dot_final_mps': 1e-3, 'drift_m': 0.01}
    assert data['meta']['paper'] == json.loads(json.dumps(table.PAPER_FIGURES))
