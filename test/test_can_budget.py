"""The CAN budget (core/can_budget.py): frame lengths, bus load, the catch-up bound."""
import pytest

from wheelleg_balance.core.can_budget import BusLoad, frame_bits, frames_bits, max_catch_up
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.schema import from_flat


def test_frame_bits_follow_iso_11898_with_worst_case_stuffing():
    # Standard id: 44 + 8n bits + 3 interframe, stuffing over the 34 + 8n bits SOF..CRC.
    assert frame_bits(0) == 47 + 33 // 4 == 55
    assert frame_bits(8) == 47 + 64 + 97 // 4 == 135   # an MIT command
    assert frame_bits(6) == 47 + 48 + 81 // 4 == 115   # a bgkatz MIT reply
    assert frame_bits(8, extended=True) == 67 + 64 + 117 // 4 == 160
    assert frame_bits(12) == frame_bits(8)              # classical CAN: at most 8 bytes
    assert frames_bits([8, 8, 6]) == 135 + 135 + 115


def test_six_motors_on_one_bus_take_three_quarters_of_a_megabit():
    per_tick = 6 * frame_bits(8) + 6 * frame_bits(6)
    assert 500 * per_tick / 1e6 == pytest.approx(0.75)


def test_bus_load_over_the_time_between_updates():
    load = BusLoad(1e6)
    assert load.update(10.0, 0) is None
    assert load.update(10.1, 25_000) == pytest.approx(25.0)   # 250 kbit/s of 1 Mbit/s
    assert load.update(10.2, 25_000) == pytest.approx(0.0)
    assert load.update(10.2, 90_000) == pytest.approx(0.0)    # no time passed: kept


@pytest.mark.parametrize('queue, per_tick, want', [
    (1000, 6, 5), (10, 6, 0), (10, 2, 4), (12, 6, 1), (6, 6, 0), (1, 2, 0), (10, 0, 5)])
def test_a_catch_up_burst_fits_the_tx_queue(queue, per_tick, want):
    n = max_catch_up(queue, per_tick, 5)
    assert n == want
    if per_tick:
        assert (n + 1) * per_tick <= max(queue, per_tick)   # this tick's frames and the missed


def test_control_loop_bounds_its_catch_up_by_the_configured_queue():
    from wheelleg_balance.nodes.control_runner import ControlRunner, MAX_CATCH_UP
    limit = ControlRunner.catch_up_limit
    robot = {'legs.driven': True}
    assert limit(from_flat(BalanceConfig, robot), False) == MAX_CATCH_UP
    short = dict(robot, **{'can.tx_queue_len': 10})
    # The hips in turns (legs.command_divider 2): four frames a tick, two missed ticks fit.
    assert limit(from_flat(BalanceConfig, short), False) == 1
    every_tick = dict(short, **{'legs.command_divider': 1})
    assert limit(from_flat(BalanceConfig, every_tick), False) == 0    # six frames a tick
    assert limit(from_flat(BalanceConfig, short), True) == 4     # the hips on their own bus
