"""The simulated robot: MuJoCo model robot.xml and its numpy wrapper RobotSim (no ROS here)."""
from .robot_sim import GROUND_TRUTH_FIELDS, MODEL_PATH, Push, RobotSim, Slope

__all__ = ['GROUND_TRUTH_FIELDS', 'MODEL_PATH', 'Push', 'RobotSim', 'Slope']
