"""ament_python build of robot_ct_ros: `colcon build` installs the nodes to lib/robot_ct_ros."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "robot_ct_ros"

# ROS executables (`ros2 run robot_ct_ros <name>`), each a thin rclpy shell in robot_ct_ros/nodes.
NODES = {
    "arm_driver": "robot_ct_ros.nodes.arm_driver:main",
    "geometry_publisher": "robot_ct_ros.nodes.geometry_publisher:main",
    "pcd_grabber": "robot_ct_ros.nodes.pcd_grabber:main",
    "recon_service": "robot_ct_ros.nodes.recon_service:main",
    "recorder": "robot_ct_ros.nodes.recorder:main",
    "replay": "robot_ct_ros.nodes.replay:main",
    "scan_orchestrator": "robot_ct_ros.nodes.scan_orchestrator:main",
    "source_control": "robot_ct_ros.nodes.source_control:main",
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench", "bench.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.xml")),  # ros2 launch robot_ct_ros robot_ct.launch.xml
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="robot_ct_ros developers",
    maintainer_email="dev@robot-ct-ros.local",
    description="Robotic micro-CT with data-driven 9-DOF geometry correction (NCC-LLE), ROS 2 Jazzy",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{name} = {target}" for name, target in NODES.items()]
        + ["robot-ct = robot_ct_ros.cli:main"],
    },
)
