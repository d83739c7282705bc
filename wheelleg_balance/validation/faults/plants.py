"""
What the sensors see in a fault scenario: a robot that does not move, or the MuJoCo robot.

``sense()`` returns (orientation x y z w, gyro x y z, accel x y z, wheel velocities, leg
angles); ``advance(tau_left, tau_right, dt)`` moves the plant under forward-positive wheel
torques [N m].
"""
import threading
from typing import Dict

from .bench import quaternion_pitch


class StaticPlant:
    """A robot that does not move: the IMU reads ``theta`` [rad], the wheels stand still."""

    def __init__(self, theta: float = 0.05):
        self.theta = theta
        self.legs = None   # four hip angles [rad] to publish, or None

    def advance(self, tau_left: float, tau_right: float, dt: float) -> None:
        """Torques change nothing."""

    def sense(self):
        """(orientation x y z w, gyro x y z, accel x y z, wheel velocities, leg angles)."""
        return (quaternion_pitch(self.theta), (0.0, 0.0, 0.0), (0.0, 0.0, 9.81), (0.0, 0.0),
                self.legs)

    def wheel_angles(self):
        """(left, right) wheel angles [rad], forward positive, relative to the leg."""
        return 0.0, 0.0


class MujocoPlant:
    """
    The MuJoCo robot of sim/robot_sim.py as the plant, driven by the fake motors' torques.

    It starts resting on its tail (``pose='tail'``) or standing at ``pitch`` [rad]; the IMU
    is mounted pitched by ``imu_offset`` [rad] (it reads theta + d).
    """

    def __init__(self, pose: str = 'tail', pitch: float = 0.0, imu_offset: float = 0.0):
        from ...sim.robot_sim import RobotSim
        self.sim = RobotSim(d_offset=imu_offset)
        self.sim.reset(pose, pitch=pitch)
        self.tail_pitch = self.sim.tail_rest_pitch()
        self.sim.reset(pose, pitch=pitch)
        self.legs = None
        self._lock = threading.Lock()

    def advance(self, tau_left: float, tau_right: float, dt: float) -> None:
        """Step the physics by dt [s] (whole 0.5 ms steps) under the wheel torques [N m]."""
        with self._lock:
            self.sim.step(tau_left, tau_right, dt)

    def sense(self):
        """(orientation x y z w, gyro x y z, accel x y z, wheel velocities, leg angles)."""
        with self._lock:
            q, gyro, accel = self.sim.imu()
            return q, gyro, accel, self.sim.wheel_velocities(), self.legs

    def wheel_angles(self):
        """(left, right) wheel angles [rad], forward positive, relative to the leg."""
        with self._lock:
            return self.sim.wheel_angles()

    def push(self, force_x: float, duration: float = 0.1) -> None:
        """Push the body along x [N] for ``duration`` [s] from now (simulated time)."""
        from ...sim.robot_sim import Push
        with self._lock:
            self.sim.pushes.append(Push(self.sim.time, duration, force_x))

    def truth(self) -> Dict[str, float]:
        """Return the true state (sim/robot_sim.py ground_truth)."""
        with self._lock:
            return self.sim.ground_truth()
