"""
The paper's experiments (Sec. V-B), run two ways from one table.

- ``table``: the experiments as data: name, title, figure, what the paper reports, and per runner
  the metrics (with definitions) and criteria (bounds);
- ``metrics``: each metric defined once, on numpy arrays;
- ``experiments``: the ``experiments`` command, the closed-loop simulation of model (1)
  (core/simulation.py) with BalanceCore;
- ``main_job``: the ``main_job`` command, balance_node, sim_node (MuJoCo) and teleop_node as
  separate processes (docs/main_job.md);
- ``joy_script``: the scripted joystick main_job drives teleop_node with.
"""
