"""robot_ct_ros: robotic micro-CT with data-driven 9-DOF geometry correction (ROS 2 Jazzy)."""

__version__ = "0.1.0"
