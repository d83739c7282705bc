"""
The fault-injection suite (docs/faults.md): test doubles, rigs, scenarios and the report.

``bench``: the control tick (core/balance_loop.py) driven directly on a virtual clock;
``doubles``: fake motors and buses; ``plants``: what the sensors see; ``rig``: balance_node as
it runs on the robot, over DDS; ``scenarios``, ``matrices``: the faults; ``report``: the
``fault_report`` command.
"""
