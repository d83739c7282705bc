"""
main_job: the paper's experiments 1-8 (Sec. V-B) with the real processes against the sim robot.

Each experiment starts, as separate ``python -m`` processes, sim_node (the MuJoCo robot) and
balance_node with parameter files written into the experiment's folder, and for the driving
experiments teleop_node (config/teleop_xbox.yaml) fed by a scripted joystick
(validation/paper/joy_script.py, publishing sensor_msgs/Joy on ``joy``). They talk over ROS 2
(this machine only) and CAN over python-can's udp_multicast interface (a group and port of this
run only), as on the robot apart from the bus. This process records sim_node's
``~/ground_truth``, balance_node's ``~/state`` and ``cmd_vel``, arms the robot through
``balance_node/arm``, starts the joystick script (``joy_script/start``), changes balance_node
parameters (controller, yaw-rate gain) with SetParameters calls, and writes per experiment the
CSVs, a plot in the paper's figure layout and the node logs; then one report: ``report.md`` and
``report.json``.

The experiments are the main_job entries of validation/paper/table.py (``main_job --list``;
docs/main_job.md). One job per module:

- ``cli``: the command line (``main_job``, or ``python -m
  wheelleg_balance.validation.paper.main_job``);
- ``scenarios``: how MuJoCo plays each table entry (timeline, joystick, parameters);
- ``params``: the parameter files of a run and the joystick script in stick deflections;
- ``orchestrate``: starting and stopping the processes, arming, one run, the retry of a run
  starved of CPU;
- ``record``: the ROS recorder and a run's trace;
- ``evaluate``: the metrics and criteria of a run;
- ``report``: report.md and report.json;
- ``plots``: the figures.

``--short`` shortens the start-up and standing runs (the CI run: ``--only startup,standing
--short``, test/test_main_job.py).
"""
