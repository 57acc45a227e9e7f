"""Science core: geometry, projector, reconstruction, simulation, calibration, metrics.

Nothing under ``robot_ct_ros.ct`` imports ROS; the nodes are thin shells around it.
"""
