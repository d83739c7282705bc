"""
Identification of the robot's model from recorded phases (docs/identification.md; no ROS here).

records.py: what a phase's recording holds (the topics of an MCAP recording) and its reader;
excite.py: the phases played on the MuJoCo robot in-process (scripted torques, the package's
own control tick); fit.py: the least-squares fits and the report; params.py: the report as
balance_node parameters.
"""
