"""rclpy nodes: thin shells (parameters in, messages out) around robot_ct_ros.ct and robot_ct_ros.hardware."""
