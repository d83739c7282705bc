"""
Robot parameters and the paper's Table I.

Units are SI throughout. Naming follows docs/interface.md: ``body_mass`` is the pendulum mass m
(11 kg) and ``wheel_mass`` the cart mass M (3 kg, both wheels) -- the paper's prose swaps them, but
equation (1), the linearization (2) and Table I only agree with this reading.
Both dataclasses are sections of the robot's configuration (core/config.py): the defaults,
descriptions and ranges below are the parameters' own.
"""
from dataclasses import dataclass

import numpy as np

from .schema import param

RO = True


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of the inverted pendulum on a cart (model (1)), Table I."""

    body_mass: float = param(11.0, 'm: body (pendulum) mass [kg]', 0.1, 200.0, read_only=RO)
    wheel_mass: float = param(3.0, 'M: mass of both wheels (cart) [kg]', 0.01, 100.0,
                              read_only=RO)
    gravity: float = param(9.81, 'g: gravitational acceleration [m/s^2]', 1.0, 20.0, read_only=RO)
    wheel_radius: float = param(0.1, 'r_w: wheel radius [m]', 0.01, 1.0, read_only=RO)
    wheel_separation: float = param(0.47, 'd_w: distance between the wheels [m]', 0.05, 3.0,
                                    read_only=RO)
    height_min: float = param(0.37, 'lowest body height l above the wheel axle [m]', 0.05,
                              3.0, read_only=RO)
    height_max: float = param(0.70, 'highest body height l above the wheel axle [m]', 0.05,
                              3.0, read_only=RO)

    def clamp_height(self, l: float) -> float:
        """Clamp a height l [m] into [height_min, height_max]."""
        return min(max(l, self.height_min), self.height_max)

    def problems(self):
        """Cross-field rules of the model section."""
        if not self.height_min < self.height_max:
            return ['height_min must be below height_max']
        return []


@dataclass(frozen=True)
class IdaPbcGains:
    """
    IDA-PBC free parameters: Table I's k, m22_0, k_v, P and the damping's bell near upright.

    The defaults of m22_0, k_v and P are the ``tuning`` command's best point of 2026-12-04
    (docs/tuning_report.json, docs/auto_mode.md); Table I's values are ``TABLE_I_IDA_PBC``.

    k > 0, m22_0 >= 0, k_v > 0, P >= 0 as in Table I; the damping injection is k_v +
    k_v_upright exp(-(theta / k_v_width)^2 - (theta_dot / k_v_rate_width)^2) (core/ida_pbc.py
    ``damping_gain``, docs/ida_pbc.md, section 8); k_v_upright = 0 is Table I's constant k_v
    (``TABLE_I_IDA_PBC``).
    """

    k: float = param(0.015, 'IDA-PBC k > 0 of M_d (Table I)', 1e-6, 10.0)
    m22_0: float = param(0.0627, 'IDA-PBC m22^0 >= 0 of M_d (Table I: 0.04)', 0.0, 10.0)
    k_v: float = param(0.05558, 'IDA-PBC damping injection k_v > 0 (Table I: 0.05), away from '
                       'upright', 1e-6, 10.0)
    P: float = param(9.338, 'IDA-PBC gain P >= 0 (Table I: 0.2; 0 makes (13) an exact IDA-PBC, '
                     'docs/ida_pbc.md)', 0.0, 100.0)
    k_v_upright: float = param(0.3, 'IDA-PBC damping injection added near upright rest: k_v + '
                               'k_v_upright exp(-(theta / k_v_width)^2 - (theta_dot / '
                               'k_v_rate_width)^2); 0: the constant k_v of Table I '
                               '(docs/ida_pbc.md, section 8)', 0.0, 10.0)
    k_v_width: float = param(0.05, 'IDA-PBC: width of that bell in theta [rad] (2.9 deg)',
                             1e-3, 1.5)
    k_v_rate_width: float = param(0.5, 'IDA-PBC: width of that bell in theta_dot [rad/s]',
                                  1e-3, 50.0)


#: Table I's IDA-PBC parameters (config/paper_table_i.yaml): a constant k_v.
TABLE_I_IDA_PBC = IdaPbcGains(k=0.015, m22_0=0.04, k_v=0.05, P=0.2, k_v_upright=0.0)


#: Table I output-regulation gain k_x exactly as printed (units: see core/lqr.py notes).
TABLE_I_K_X = np.array([150.0, 12.0, 0.001, 10.0])
#: Table I's k_d as printed (it does not cancel k_x: docs/linear_control.md).
TABLE_I_K_D = -167.0

#: Control period of the paper [s].
CONTROL_PERIOD = 0.002
