"""
Margins of an identified robot: its motor delay in the loop, its configuration against the default.

core/margins.py ``delayed`` against the closed loop with extra ticks, and ``margins_report
--config`` (validation/paper/margins_fitted.py).
"""
import json

import numpy as np
import pytest
from wheelleg_balance.core import margins
from wheelleg_balance.core.model import linearize
from wheelleg_balance.core.params import RobotParams
from wheelleg_balance.validation.paper import margins_fitted, margins_report
import yaml

L = 0.45


@pytest.fixture(scope='module')
def loop():
    core = margins.build_core('default')
    return margins.build_loop(core.controllers['lqr'], core.observer, L)


@pytest.mark.parametrize('ticks', [1, 2, 3])
def test_delayed_loop_closes_as_extra_ticks_of_delay(loop, ticks):
    ours = np.sort_complex(np.linalg.eigvals(margins.closed_loop_matrix(
        margins.delayed(loop, ticks))))
    theirs = np.sort_complex(np.linalg.eigvals(margins.closed_loop_matrix(loop, 1.0, ticks)))
    assert np.allclose(ours, theirs, atol=1e-9)


def test_a_pure_delay_takes_its_length_off_the_delay_margin(loop):
    base, late = margins.loop_margins(loop), margins.loop_margins(margins.delayed(loop, 2))
    assert late.stable
    assert late.delay_margin_s == pytest.approx(base.delay_margin_s - 2 * loop.dt, abs=1e-6)
    assert late.gain_margin_up_db < base.gain_margin_up_db


def test_delay_ticks_round_up():
    assert margins.delay_ticks(0.0) == 0
    assert margins.delay_ticks(0.002) == 1
    assert margins.delay_ticks(0.0021) == 2
    assert margins.delay_ticks(0.0039568) == 2


def _write(path, params):
    path.write_text(yaml.safe_dump({'balance_node': {'ros__parameters': params}}))
    return str(path)


def test_the_default_configuration_changes_nothing(tmp_path, capsys):
    cfg = _write(tmp_path / 'same.yaml', {'controller': 'auto'})
    code = margins_report.main(['--config', cfg, '--extra-delay', '0', '--step', '0.33',
                                '--docs', str(tmp_path)])
    assert code == 0
    assert 'changed, default -> fitted: nothing' in capsys.readouterr().out
    assert (tmp_path / 'img' / 'margins_fitted.png').stat().st_size > 10000


def test_a_heavier_robot_with_a_delay_changes_the_margins(tmp_path, capsys):
    robot = _write(tmp_path / 'robot.yaml', {'controller': 'auto'})
    fitted = _write(tmp_path / 'fitted.yaml', {'body_mass': 16.0, 'wheel_radius': 0.12,
                                               'wheel_mass': 3.8})
    report = tmp_path / 'identify_report.json'
    report.write_text(json.dumps({
        'quantities': {'robot.motor_delay': {'value': 0.004}},
        'lumped': [{'mass': 16.0, 'l': 0.4, 'inertia_about_axle': 16.0 * 0.16 + 0.15},
                   {'mass': 16.0, 'l': 0.5, 'inertia_about_axle': 16.0 * 0.25 + 0.13}]}))
    margins_report.main(['--config', robot, '--config', fitted, '--identify-report',
                         str(report), '--step', '0.33', '--docs', str(tmp_path)])
    out = capsys.readouterr().out
    assert 'changed, default -> fitted: nothing' not in out
    text = (tmp_path / 'margins_fitted.md').read_text()
    assert 'body_mass 16.000 kg' in text and '2 tick(s)' in text
    assert 'beyond m l^2 0.1400 kg m^2' in text and '| lqr | fitted, with I |' in text
    cfg = margins_fitted.configuration([robot, fitted])
    results = margins_fitted.run(cfg, 0.004, step=0.33)
    late = margins_fitted.summary(results[('lqr', 'fitted')])
    assert late['dm_s'] < margins_fitted.summary(results[('lqr', 'default')])['dm_s']


def test_delay_options_need_a_config():
    with pytest.raises(SystemExit):
        margins_report.main(['--extra-delay', '0.004'])


@pytest.mark.parametrize('inertia', [0.0, 0.05, 0.3])
def test_the_pendulum_inertia_in_the_linearization(inertia):
    p, l, theta, u = RobotParams(), 0.45, 0.01, 3.0
    m, M, g = p.body_mass, p.wheel_mass, p.gravity
    # (1) linearized with J = m l^2 + I: the mass matrix solved for the accelerations.
    x_dd, th_dd = np.linalg.solve([[M + m, m * l], [m * l, m * l * l + inertia]],
                                  [u, m * g * l * theta])
    A, B = linearize(l, p, inertia)
    xi_dot = A @ np.array([theta, 0.0, 0.0, 0.0]) + B * u
    assert xi_dot[3] == pytest.approx(x_dd, rel=1e-9)
    assert xi_dot[1] == pytest.approx(th_dd, rel=1e-9)
