"""
Robot parameters and the paper's Table I.

Units are SI throughout. Naming follows DESIGN.md section 1: ``body_mass`` is the pendulum mass m
(11 kg) and ``wheel_mass`` the cart mass M (3 kg, both wheels) -- the paper's prose swaps them, but
equation (1), the linearization (2) and Table I only agree with this reading.
"""
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of the inverted pendulum on a cart (model (1)), Table I."""

    body_mass: float = 11.0        # m [kg], pendulum (body) mass
    wheel_mass: float = 3.0        # M [kg], cart (both wheels) mass
    gravity: float = 9.81          # g [m/s^2]
    wheel_radius: float = 0.1      # r_w [m]
    wheel_separation: float = 0.47  # d_w [m], track
    height_min: float = 0.37       # l_min [m]
    height_max: float = 0.70       # l_max [m]

    def clamp_height(self, l: float) -> float:
        """Clamp a height l [m] into [height_min, height_max]."""
        return min(max(l, self.height_min), self.height_max)


@dataclass(frozen=True)
class IdaPbcGains:
    """IDA-PBC free parameters (Table I): k > 0, m22_0 >= 0, k_v > 0, P >= 0."""

    k: float = 0.015
    m22_0: float = 0.04
    k_v: float = 0.05
    P: float = 0.2


#: Table I output-regulation gains exactly as printed (units: see core/lqr.py TABLE_I_* notes).
TABLE_I_K_X = np.array([150.0, 12.0, 0.001, 10.0])
TABLE_I_K_D = -167.0
TABLE_I_L = np.array([27.63, 397.75, -6.48, -111.4, -0.45])

#: Control period of the paper [s].
CONTROL_PERIOD = 0.002
