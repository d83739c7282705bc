"""
The loop benchmarks (docs/benchmarks.md): the tick's compute time, reference loops, the node.

``core``: the control tick alone; ``loops``: the floor (a bare deadline loop) and an rclpy
baseline; ``node``: balance_node with sensor and motor processes; ``stats``: the figures;
``profiling``: py-spy summaries; ``benchmark``: the command that runs them in one go.
"""
