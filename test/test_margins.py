"""
Stability margins of every controller over the height range (core/margins.py, issue 12 item 3).

The certification: for ida_pbc, output_regulation and lqr at the default gains and at Table I's,
the 2 ms loop with one tick of delay, broken at the wheel torque command and linearized every
1 cm over 0.37..0.70 m, is stable with >= 6 dB of gain margin up and down and >= 10 ms of delay
margin. The cases that fall short are marked xfail (strict) with their measured numbers
(docs/margins.md); the margins they do meet are still asserted.

The tool itself is tested to fail: destabilizing gains, a first-order loop with margins by hand,
the delay margin's worth of ticks, and the real tick (BalanceCore) against the numbers.
"""
from functools import lru_cache
import math

import numpy as np
import pytest
from scipy.signal import cont2discrete, dfreqresp, StateSpace

from wheelleg_balance.core import margins
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.ida_pbc import ida_pbc_terms
from wheelleg_balance.core.lqr import FixedGain, table_i_force_gain
from wheelleg_balance.core.model import linearize
from wheelleg_balance.core.output_regulation import LqrController
from wheelleg_balance.core.pipeline import CONTROLLER_NAMES, Measurement, Reference

CFG = BalanceConfig()
P = CFG.model
DT = CFG.loop.control_period
#: Every centimetre from 0.37 to 0.70 m: 34 heights (the gain and observer schedules' grid).
HEIGHTS = margins.height_grid(0.01, P)
GM = margins.REQUIRED_GAIN_MARGIN_DB
DM = margins.REQUIRED_DELAY_MARGIN_S
CASES = [(c, g) for c in CONTROLLER_NAMES for g in margins.GAIN_SETS]

#: Measured shortfalls (2026-12-02/03, docs/margins.md): case -> (the margin short, why).
KNOWN_SHORT = {
    ('ida_pbc', 'table_i'): (
        'gain_margin_down',
        'ida_pbc at Table I gains (a constant k_v 0.05): gain margin down 2.31 dB at l = 0.37 m '
        'to 3.08 dB at 0.70 m, short of 6 dB at every height (up >= 14.93 dB, delay >= 35.4 '
        'ms); the defaults add damping near upright and are certified (docs/margins.md)'),
    ('output_regulation', 'table_i'): (
        'gain_margin_down',
        "output_regulation as (9) prints it (the observer's xi_hat fed back) with Table I's k_x "
        '(per-wheel torque, x 20): gain margin down 4.04..4.53 dB, short of 6 dB at every '
        'height (up >= 6.82 dB, delay margin >= 15.5 ms: met)'),
    ('lqr', 'table_i'): (
        'delay_margin',
        "lqr with Table I's k_x (per-wheel torque, x 20): delay margin 6.66 ms at l = 0.37 m "
        'rising to 9.80 ms at 0.46 m (9.98 ms at 0.465 m on the docs 5 mm grid), short of '
        '10 ms for l <= 0.465 m (gain crossover 150 rad/s at 0.37 m); gain margins up >= '
        '10.32 dB, down >= 24.31 dB: met'),
}


@lru_cache(maxsize=None)
def certified(controller, gains_set):
    return tuple(margins.certify(controller, gains_set, HEIGHTS, CFG))


@lru_cache(maxsize=None)
def core(gains_set):
    return margins.build_core(gains_set, CFG)


def loop_at(controller, gains_set, l):
    c = core(gains_set)
    return margins.build_loop(c.controllers[controller], c.observer, l, c.p, c.dt)


def _param(case):
    if case in KNOWN_SHORT:
        return pytest.param(*case, marks=pytest.mark.xfail(
            strict=True, raises=AssertionError, reason=KNOWN_SHORT[case][1]))
    return pytest.param(*case)


# --- the certification --------------------------------------------------------------------


@pytest.mark.parametrize('controller,gains_set', [_param(c) for c in CASES])
def test_margins_over_the_height_range(controller, gains_set):
    ms = certified(controller, gains_set)
    assert len(ms) >= 34 and ms[0].l == pytest.approx(0.37) and ms[-1].l == pytest.approx(0.70)
    short = ['l = %.2f m: %s' % (m.l, '; '.join(m.shortfalls())) for m in ms if m.shortfalls()]
    assert not short, '%s at %s gains:\n' % (controller, gains_set) + '\n'.join(short)
    for m in ms:   # the same, spelled out
        assert m.stable and m.spectral_radius < 1.0
        assert m.gain_margin_up_db >= GM and m.gain_margin_down_db >= GM
        assert m.delay_margin_s >= DM and m.delay_confirmed


@pytest.mark.parametrize('controller,gains_set', CASES)
def test_the_margins_a_short_case_does_meet(controller, gains_set):
    """The xfail above covers one shortfall; every other requirement still holds."""
    known = KNOWN_SHORT.get((controller, gains_set), ('',))[0]
    for m in certified(controller, gains_set):
        assert m.stable and m.spectral_radius < 1.0, m
        assert m.delay_confirmed, m
        if known != 'gain_margin_up':
            assert m.gain_margin_up_db >= GM, m
        if known != 'gain_margin_down':
            assert m.gain_margin_down_db >= GM, m
        if known != 'delay_margin':
            assert m.delay_margin_s >= DM, m
    if known:   # and the shortfall is the one recorded, not something new
        assert any(s.startswith(known.replace('_', ' ')) for m in certified(
            controller, gains_set) for s in m.shortfalls())


# --- what is linearized -------------------------------------------------------------------


@pytest.mark.parametrize('l', [0.37, 0.525, 0.70])
def test_jacobians_are_the_controllers_gains(l):
    c = core('default')
    k_x = c.schedule.gain(l)
    J = margins.controller_jacobian(c.controllers['lqr'], l)
    np.testing.assert_allclose(J, np.append(k_x, np.zeros(5)), rtol=1e-7, atol=1e-6)
    # Output regulation as balance_node runs it (feedback: measured): k_x on the sensors, and
    # -k_x[0] on d_hat; as (9) prints it (the table_i set, feedback: observer): on xi_hat.
    J = margins.controller_jacobian(c.controllers['output_regulation'], l)
    np.testing.assert_allclose(J, np.concatenate([k_x, np.zeros(4), [-k_x[0]]]), rtol=1e-7,
                               atol=1e-6)
    t1 = core('table_i')
    k_t = t1.schedule.gain(l)
    J = margins.controller_jacobian(t1.controllers['output_regulation'], l)
    np.testing.assert_allclose(J, np.concatenate([np.zeros(4), k_t, [-k_t[0]]]), rtol=1e-7,
                               atol=1e-6)
    # IDA-PBC (13) through (3), compensated: u = m g th + M (dA_3/dth th - k_v A_4 p_bar) with
    # th = theta~ - d_hat (A_2 is quadratic in p_bar, so it drops out; the bell's slopes meet
    # e = 0) and k_v = k_v(0, 0) = k_v + k_v_upright: the damping at upright rest.
    g = c.config.ida_pbc
    assert g.k_v_upright > 0.0
    kv0 = g.k_v + g.k_v_upright
    t = ida_pbc_terms(0.0, l, g, P.gravity)
    dA3 = 3.0 * P.gravity + g.P * (3.0 * l + 6.0 * l * g.m22_0 / g.k) * t.A1
    k_th = P.body_mass * P.gravity + P.wheel_mass * dA3
    want = np.zeros(9)
    want[0], want[8] = k_th, -k_th
    want[1] = -P.wheel_mass * kv0 * t.A4[0]
    want[3] = -P.wheel_mass * kv0 * t.A4[1]
    J = margins.controller_jacobian(c.controllers['ida_pbc'], l)
    np.testing.assert_allclose(J, want, rtol=1e-6, atol=1e-6)


def test_table_i_gains_are_used():
    c = core('table_i')
    k_t = table_i_force_gain(P)
    J = margins.controller_jacobian(c.controllers['lqr'], 0.5)
    np.testing.assert_allclose(J[:4], k_t, rtol=1e-7)
    assert c.controllers['ida_pbc'].gains == margins.TABLE_I_IDA_PBC
    with pytest.raises(ValueError):
        margins.certify('lqr', 'tuned', [0.5])
    with pytest.raises(ValueError):
        margins.certify('pid', 'default', [0.5])


@pytest.mark.filterwarnings('ignore::scipy.signal.BadCoefficients')
def test_frequency_response_agrees_with_scipy_where_that_is_well_conditioned():
    # dfreqresp goes through the transfer function's polynomials: off by orders of magnitude
    # below ~10 rad/s for these loops (double pole at z = 1), exact enough above.
    loop = loop_at('lqr', 'default', 0.52)
    w = np.array([100.0, 300.0, 1000.0, 1500.0])
    _, ref = dfreqresp(loop, w=w * DT)
    np.testing.assert_allclose(margins.freq_response(loop, w), ref, rtol=1e-6)


# --- the tool can fail ----------------------------------------------------------------------


def scaled(loop, s):
    return StateSpace(loop.A, loop.B, s * np.asarray(loop.C), loop.D, dt=loop.dt)


def test_negated_or_tenfold_feedback_is_unstable():
    for c, g in CASES:
        loop = loop_at(c, g, 0.37)
        m = margins.loop_margins(scaled(loop, -1.0), 0.37)
        assert not m.stable and m.shortfalls() and math.isnan(m.gain_margin_up_db)
    # lqr: 17.0 dB up at 0.37 m, so x 10 (20 dB) is beyond it; x 4 (12 dB) leaves 5 dB
    loop = loop_at('lqr', 'default', 0.37)
    assert not margins.loop_margins(scaled(loop, 10.0)).stable
    m0 = margins.loop_margins(loop, 0.37)
    m4 = margins.loop_margins(scaled(loop, 4.0), 0.37)
    assert m4.stable and m4.gain_margin_up_db < GM
    assert any(s.startswith('gain margin up') for s in m4.shortfalls())
    assert m4.gain_margin_up_db == pytest.approx(m0.gain_margin_up_db - 20 * math.log10(4.0),
                                                 abs=1e-6)
    assert m4.gain_margin_down_db == pytest.approx(
        m0.gain_margin_down_db + 20 * math.log10(4.0), abs=1e-6)
    m = margins.loop_margins(scaled(loop, 0.25), 0.37)
    assert m.stable and any(s.startswith('gain margin down') for s in m.shortfalls())


def test_table_i_as_a_force_gain_is_reported_unstable():
    c = core('default')
    ctrl = LqrController(P, FixedGain(table_i_force_gain(P, 'force')))
    for l in (0.37, 0.52, 0.70):
        m = margins.loop_margins(margins.build_loop(ctrl, c.observer, l, P, DT), l)
        assert not m.stable and m.spectral_radius > 1.0


def first_order_loop(a, g, dt=DT):
    """L(z) = g / (z - a): x_{k+1} = a x_k + e_k, output g x_k."""
    return StateSpace([[a]], [[1.0]], [[g]], [[0.0]], dt=dt)


def test_first_order_loop_by_hand():
    a, g = 1.1, 0.6   # open-loop pole 1.1 (unstable), closed loop a - k g: stable for
    loop = first_order_loop(a, g)   # (a - 1) / g < k < (a + 1) / g
    m = margins.loop_margins(loop)
    assert m.stable and m.spectral_radius == pytest.approx(0.5)
    assert m.gain_margin_up_db == pytest.approx(20 * math.log10((a + 1) / g), abs=1e-6)
    assert m.gain_margin_down_db == pytest.approx(20 * math.log10(g / (a - 1)), abs=1e-6)
    # |L| = 1 where |e^jw - a| = g: cos w = (1 + a^2 - g^2) / (2 a), w per sample
    w = math.acos((1 + a * a - g * g) / (2 * a))
    pm = 180.0 - math.degrees(math.atan2(math.sin(w), math.cos(w) - a))
    assert m.crossover_rad_s == pytest.approx(w / DT, rel=1e-9)
    assert m.phase_margin_deg == pytest.approx(pm, abs=1e-7)
    assert m.delay_margin_s == pytest.approx(math.radians(pm) / (w / DT), rel=1e-9)
    assert m.delay_margin_s / DT == pytest.approx(1.966, abs=1e-3)
    # ... so one extra tick keeps it stable and the second destabilizes.
    assert margins.spectral_radius(loop, 1.0, 1) < 1.0
    assert margins.spectral_radius(loop, 1.0, 2) > 1.0
    assert m.delay_ticks == 1 and m.delay_confirmed
    # the gain boundaries are where a pole crosses the unit circle: z = 1 and z = -1
    assert margins.spectral_radius(loop, 3.5 * (1 - 1e-6)) < 1.0 < margins.spectral_radius(
        loop, 3.5 * (1 + 1e-6))
    # L(1) = g / (1 - a) = -6 and L(-1) = -g / (1 + a): the axis crossings at k = 1/6, 3.5
    assert [k for _, k in margins.negative_real_crossings(loop)] == pytest.approx([1 / 6, 3.5])


def test_first_order_loop_that_is_already_short():
    # a = 1.5, g = 1.0: stable for 0.5 < k < 2.5 -> only 6.02 dB down, 7.96 dB up
    m = margins.loop_margins(first_order_loop(1.5, 1.0))
    assert m.gain_margin_down_db == pytest.approx(20 * math.log10(2.0), abs=1e-6)
    assert m.gain_margin_up_db == pytest.approx(20 * math.log10(2.5), abs=1e-6)
    m = margins.loop_margins(first_order_loop(1.5, 0.9))   # 0.556 < k < 2.78: 5.1 dB down
    assert m.stable and m.gain_margin_down_db == pytest.approx(5.105, abs=1e-3)
    assert 'gain margin down 5.11 dB < 6.0 dB' in m.shortfalls()
    assert not margins.loop_margins(first_order_loop(1.5, 0.4)).stable   # 1.1 > 1


@pytest.mark.parametrize('controller,gains_set', CASES)
def test_delay_margins_worth_of_ticks_destabilizes(controller, gains_set):
    for l in (0.37, 0.52, 0.70):
        loop = loop_at(controller, gains_set, l)
        m = margins.loop_margins(loop, l)
        ticks = m.delay_margin_s / DT
        assert m.delay_ticks == math.floor(ticks)
        assert margins.spectral_radius(loop, 1.0, math.floor(ticks)) < 1.0
        assert margins.spectral_radius(loop, 1.0, math.ceil(ticks)) > 1.0


@pytest.mark.parametrize('controller,gains_set', CASES)
def test_gain_margins_are_where_the_loop_goes_unstable(controller, gains_set):
    for l in (0.37, 0.70):
        loop = loop_at(controller, gains_set, l)
        m = margins.loop_margins(loop, l)
        k_max, k_min = 10 ** (m.gain_margin_up_db / 20), 10 ** (-m.gain_margin_down_db / 20)
        for k, inside in ((k_max, 1 - 1e-5), (k_min, 1 + 1e-5)):
            assert margins.spectral_radius(loop, k * inside) < 1.0
            assert margins.spectral_radius(loop, k / inside) > 1.0
        # the eigenvalue boundary is a crossing of the negative real axis, L = -1 / k
        ks = [k for _, k in margins.negative_real_crossings(loop)]
        assert min(abs(k - k_max) / k_max for k in ks) < 1e-6
        assert min(abs(k - k_min) / k_min for k in ks) < 1e-6


# --- the real tick agrees -------------------------------------------------------------------


def run_tick(controller, gains_set, l, k=1.0, extra_ticks=0, seconds=4.0, theta0=1e-4):
    """
    Run BalanceCore on the linear plant; return max |theta| over the last second / the first.

    The plant is (2), ZOH-exact at 2 ms, with actuator gain k and 1 + extra_ticks of delay.
    """
    c = margins.build_core(gains_set, CFG)
    c.select(controller)
    A, B = linearize(l, P)
    Ad, Bd, _, _, _ = cont2discrete((A, B.reshape(4, 1), np.eye(4), np.zeros((4, 1))), DT)
    xi = np.array([theta0, 0.0, 0.0, 0.0])
    c.reset(Measurement(theta0, 0.0, 0.0, 0.0, l))
    queue = [0.0] * (1 + extra_ticks)
    theta = []
    for _ in range(int(seconds / DT)):
        w = xi[3] / P.wheel_radius - xi[1]   # wheel speed relative to the leg
        out = c.step(Measurement(xi[0], xi[1], w, w, l), Reference())
        queue.append(k * out.u_cmd)
        xi = Ad @ xi + Bd[:, 0] * queue.pop(0)
        theta.append(abs(xi[0]))
    n = int(1.0 / DT)
    return max(theta[-n:]) / max(theta[:n])


def test_the_real_tick_goes_unstable_where_the_margins_say():
    # lqr at Table I gains, 0.37 m: 3.3 ticks of delay margin, 10.3 dB up (k_max 3.28)
    m = certified('lqr', 'table_i')[0]
    assert m.l == pytest.approx(0.37) and m.delay_ticks == 3
    assert run_tick('lqr', 'table_i', 0.37, extra_ticks=3) < 0.1
    assert run_tick('lqr', 'table_i', 0.37, extra_ticks=4) > 10.0
    k_max = 10 ** (m.gain_margin_up_db / 20)
    assert run_tick('lqr', 'table_i', 0.37, k=0.97 * k_max) < 1.0
    assert run_tick('lqr', 'table_i', 0.37, k=1.03 * k_max) > 10.0
    # output regulation, default gains, 0.37 m: the low gain margin (k_min 0.764) is real
    m = certified('output_regulation', 'default')[0]
    k_min = 10 ** (-m.gain_margin_down_db / 20)
    assert run_tick('output_regulation', 'default', 0.37, k=1.03 * k_min, seconds=12.0) < 1.0
    assert run_tick('output_regulation', 'default', 0.37, k=0.97 * k_min, seconds=12.0) > 1.0


# --- the report -----------------------------------------------------------------------------


def test_margins_report_writes_the_tables_and_one_figure_per_controller(tmp_path, monkeypatch):
    pytest.importorskip('matplotlib')
    from wheelleg_balance.validation.paper import margins_report as report
    results = {case: list(certified(*case)) for case in CASES}
    monkeypatch.setattr(report, 'run', lambda heights: results)
    doc = tmp_path / 'margins.md'
    doc.write_text('# Margins\n\nby hand\n\n%s\nold\n%s\n\nafter\n' % (report.BEGIN, report.END))
    assert report.main(['--docs', str(tmp_path), '--step', '0.01']) == 1   # cases fall short
    text = doc.read_text()
    assert text.startswith('# Margins\n\nby hand\n') and text.endswith('\n\nafter\n')
    assert 'old' not in text and text.count(report.BEGIN) == 1
    assert '| lqr | default | yes | 17.03 (0.370) | 14.23 (0.370) |' in text
    assert 'delay margin < 10 ms at l = 0.370..0.460 m (6.66..9.80 ms)' in text
    assert text.count('**default gains**') == text.count('**table_i gains**') == 3
    assert '**default = table_i gains**' not in text
    for c in CONTROLLER_NAMES:
        png = tmp_path / 'img' / ('margins_%s.png' % c)
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
        assert '](img/margins_%s.png)' % c in text
    # two gain sets with the same margins get one table (as IDA-PBC's did when its default
    # was Table I's)
    results[('ida_pbc', 'table_i')] = results[('ida_pbc', 'default')]
    report.main(['--docs', str(tmp_path), '--step', '0.01'])
    text = doc.read_text()
    assert text.count('**default = table_i gains**') == 1
    assert text.count('**default gains**') == text.count('**table_i gains**') == 2
