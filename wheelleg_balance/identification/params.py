"""
The identification's report as balance_node parameters: what the controllers use of it.

Model (1) has a pendulum of mass m (``body_mass``: everything but the wheels) whose centre of
mass is l above the axle, and wheels of mass M (``wheel_mass``, both). balance_node computes
l from the legs' kinematics as ``leg.com_height`` less the axle's height under the hips, so
the file sets ``leg.com_height`` and ``leg.com_x`` to the *whole pendulum's* centre of mass
(the body's with the legs and the tail, fit.py ``lumped``), averaged over the heights
balanced, so that m l is the pendulum's first moment. ``d_hat0`` is the IMU's offset from the
pendulum's line at the lowest height (the IMU offset d less that line's angle from the body
axis), where the robot arms; ``lift_wheel_inertia`` is one wheel's. The quantities model (1)
has no place for (body inertia, wheel damping, motor delay) stay in the report.
"""
import math
from typing import Dict

import yaml

from ..core.config import BalanceConfig
from ..core.schema import check, from_flat, nest


def balance_params(report: Dict) -> Dict[str, float]:
    """Return the fitted balance_node parameters {name: value} of a full report (3 phases)."""
    q = {k: v['value'] for k, v in report['quantities'].items()}
    lumped = sorted(report['lumped'], key=lambda h: h['height_state'])
    n = len(lumped)
    com_height = sum(h['l'] * math.cos(h['com_angle']) - h['axle_below_hips'] for h in lumped) / n
    com_x = sum(h['l'] * math.sin(h['com_angle']) + h['axle_ahead_of_hips'] for h in lumped) / n
    params = {'body_mass': lumped[0]['mass'], 'wheel_mass': 2.0 * q['robot.wheel_mass'],
              'wheel_radius': q['robot.wheel_radius'], 'leg.com_height': com_height,
              'leg.com_x': com_x,
              'd_hat0': q['imu_pitch_offset'] - lumped[0]['com_angle'],
              'lift_wheel_inertia': q['robot.wheel_inertia']}
    return {k: float(v) for k, v in params.items()}


def params_yaml(params: Dict[str, float]) -> str:
    """
    Return a balance_node parameter file of ``params``, loaded after the robot's own.

    Raises ValueError when a value is outside its parameter's range (check the fit).
    """
    problems = check(from_flat(BalanceConfig, params))
    if problems:
        raise ValueError('; '.join(problems))
    return "# Fitted by identification (docs/identification.md): load after the robot's " \
        'own file.\n' + yaml.safe_dump({'balance_node': {'ros__parameters': nest(params)}},
                                       sort_keys=True)
