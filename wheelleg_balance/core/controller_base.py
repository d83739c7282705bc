"""The interface every balance controller implements (see docs/architecture.md)."""
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass
class ControlInput:
    """
    What a controller sees each tick (SI units, REP 103).

    theta: measured pitch theta~ = theta + d [rad], theta > 0 leans forward.
    theta_dot: pitch rate [rad/s].
    x: position from wheel odometry [m]; x_dot: ground speed [m/s].
    l: height of the body above the wheel axle [m].
    x_dot_ref: velocity reference x_dot* [m/s].
    xi_hat: observer state [theta~_hat, theta_dot_hat, x_hat, x_dot_hat, d_hat].
    """

    theta: float = 0.0
    theta_dot: float = 0.0
    x: float = 0.0
    x_dot: float = 0.0
    l: float = 0.37
    x_dot_ref: float = 0.0
    xi_hat: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def d_hat(self) -> float:
        """Observer estimate of the IMU pitch offset d [rad]."""
        return float(self.xi_hat[4])


class Controller(Protocol):
    """A balance controller: ControlInput -> force u on the cart [N] (u > 0 pushes forward)."""

    name: str

    def compute(self, s: ControlInput) -> float:
        """Return the force u [N] for this tick."""

    def reset(self, s: ControlInput) -> None:
        """Take over from another controller with the current estimator state."""
