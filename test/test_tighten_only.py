"""Safety parameters can only be tightened while the robot balances (core/config.py)."""
import math

from rclpy.parameter import Parameter

from wheelleg_balance.core.config import DEFAULTS, loosening, TIGHTEN_ONLY
from wheelleg_balance.core.schema import to_flat
from wheelleg_balance.nodes.params import ParameterGuard


def test_every_tighten_only_name_is_a_parameter():
    flat = to_flat(DEFAULTS)
    assert set(TIGHTEN_ONLY) <= set(flat)


def test_loosening_names_looser_values_only():
    assert loosening(DEFAULTS, {'imu_timeout': 0.04, 'fall_angle': 0.5,
                                'max_wheel_torque': 3.0, 'lift_min_load': 0.5}) == []
    reasons = loosening(DEFAULTS, {'imu_timeout': 0.2, 'max_wheel_torque': 12.5,
                                   'lift_min_load': 0.1, 'fall_roll_angle': math.nan,
                                   'height': 0.5})
    names = [r.split()[0] for r in reasons]
    assert names == ['imu_timeout', 'max_wheel_torque', 'lift_min_load', 'fall_roll_angle']


def test_the_guard_refuses_loosening_only_while_told_the_robot_balances():
    balancing = [True]
    accepted = []
    guard = ParameterGuard(DEFAULTS, lambda changes, cfg: accepted.append(changes),
                           lambda: balancing[0])
    result = guard([Parameter('motor_timeout', value=0.1)])
    assert not result.successful and 'only be tightened' in result.reason
    assert guard([Parameter('motor_timeout', value=0.03)]).successful
    # All or nothing: a tighter and a looser change together are refused together.
    result = guard([Parameter('fall_angle', value=0.6), Parameter('imu_timeout', value=1.0)])
    assert not result.successful and guard.config.safety.fall_angle == DEFAULTS.safety.fall_angle
    balancing[0] = False
    assert guard([Parameter('motor_timeout', value=0.1)]).successful
    assert accepted == [{'motor_timeout': 0.03}, {'motor_timeout': 0.1}]
