"""ROS 2's own forms of armfusion's output: the estimates as ROS 2 messages in a rosbag2 MCAP
file (:mod:`~armfusion.fusion.ros2.estimates_bag`, with the frames and covariances of REP 103 and REP 145
in :mod:`~armfusion.fusion.ros2.conventions`), and the arm's URDF from its config
(:mod:`~armfusion.fusion.ros2.urdf`) for robot_state_publisher. docs/ros2.md says how to plug them in.
A bag is read by the import (:mod:`armfusion.fusion.importing.bag`); the file is written by
:mod:`armfusion.sensors.ros2_mcap`, which knows nothing of arms.
"""
