"""
The simulated robot, its motors and sim_node's configuration (no ROS here).

MuJoCo model robot.xml (sim/robot_sim.py RobotSim), the motors' firmware (sim/motor_emulator.py,
sim/robot_motors.py), sim_node's configuration (sim/config.py) and the model's names and limits
(sim/layout.py). Only robot_sim and robot_motors need MuJoCo, so the modules are imported where
needed (the emulator and the configuration run without it).
"""
