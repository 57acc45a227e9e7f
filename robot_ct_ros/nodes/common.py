"""What every node executable shares: argument handling, spinning and clean shutdown."""

from __future__ import annotations

import argparse
import sys
from typing import Callable


def run_node(node_factory: Callable[[], "object"], description: str, argv: list[str] | None = None) -> int:
    """Entry point body of a node executable (``ros2 run robot_ct_ros <name>``).

    ``--help`` is answered without starting ROS; ROS arguments (``--ros-args ...``) are
    passed to rclpy untouched. The node spins on a SingleThreadedExecutor (the Jazzy
    wheel's MultiThreadedExecutor is slow, rclpy issue 1452) until SIGINT/SIGTERM.
    """
    argv = list(sys.argv if argv is None else argv)
    prog = argv[0].rsplit("/", 1)[-1] if argv else "node"
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
        epilog="ROS arguments follow --ros-args, e.g. --ros-args -p name:=value -r __ns:=/ns")
    parser.parse_args(user_args)

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    rclpy.init(args=argv)
    node = None
    try:
        node = node_factory()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
