"""
The builder's hand on the simulated robot: moves joints the way bring-up asks a person to.

The bring-up command (wheelleg_balance/bringup) asks the builder to turn each wheel forward by
hand and to move each leg to its stop; against sim_node (``bringup --sim``) the simulator does
it. A ``Hand`` grabs joints and pulls each one towards a target angle with a spring and a
damper of limited torque (a hand, not a motor: it gives way against a hard stop and holds the
joint there), as an external torque on the joint, apart from the motors: what the motors
report of it is what a person's hand would make them report, miswired direction included.

Joint indices and conventions are sim/robot_motors.py JOINTS' (the two wheels forward positive
relative to the leg, then the four hips in FiveBarLeg's convention). Pure Python, no MuJoCo.
"""
import math
from typing import Dict, List, Mapping, Sequence, Tuple


class Hand:
    """
    A hand on some of the joints (see the module docstring).

    kp [N m/rad], kd [N m s/rad]: the hand's stiffness and damping; max_torque [N m]: the most
    it pushes with. ``grab`` sets the targets, ``release`` lets go, ``torques`` is evaluated at
    every physics step.
    """

    def __init__(self, n_joints: int = 6, kp: float = 20.0, kd: float = 1.0,
                 max_torque: float = 6.0):
        if not (kp > 0.0 and kd >= 0.0 and max_torque > 0.0 and n_joints > 0):
            raise ValueError('hand: kp > 0, kd >= 0, max_torque > 0')
        self.n = int(n_joints)
        self.kp, self.kd, self.max_torque = float(kp), float(kd), float(max_torque)
        #: {joint index: (target angle [rad], torque limit [N m])}; replaced whole (threads).
        self.targets: Dict[int, Tuple[float, float]] = {}

    def grab(self, displacements: Mapping[int, float], q: Sequence[float],
             limits: Mapping[int, float] = None) -> None:
        """
        Hold the joints {index: displacement [rad]} at their angle in q plus the displacement.

        limits: {index: torque limit [N m]} (default and ceiling: max_torque). Joints not named
        are let go; a non-finite displacement or an index out of range is ignored.
        """
        limits = limits or {}
        targets = {}
        for k, dq in displacements.items():
            if not (0 <= k < self.n and math.isfinite(dq) and math.isfinite(q[k])):
                continue
            lim = limits.get(k, self.max_torque)
            lim = self.max_torque if not (math.isfinite(lim) and lim > 0.0) else \
                min(lim, self.max_torque)
            targets[k] = (q[k] + dq, lim)
        self.targets = targets

    def release(self) -> None:
        """Let go of every joint."""
        self.targets = {}

    @property
    def holding(self) -> bool:
        """Return True while the hand holds a joint."""
        return bool(self.targets)

    def torques(self, q: Sequence[float], v: Sequence[float]) -> List[float]:
        """Return the hand's torque on each joint [N m] for the angles q and speeds v."""
        out = [0.0] * self.n
        for k, (target, lim) in self.targets.items():
            tau = self.kp * (target - q[k]) - self.kd * v[k]
            out[k] = min(max(tau, -lim), lim) if math.isfinite(tau) else 0.0
        return out
