"""Every node executable refuses a bad parameter value in one line on stderr, exit status 2, no traceback
(``ros2 run robot_ct_ros <node> --ros-args -p kvp:=abc``)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

CASES = [
    ("source_control", "kvp:=abc", "parameter kvp"),
    ("source_control", "kvp:=-5.0", "parameter kvp"),
    ("arm_driver", "publish_rate_hz:=fast", "parameter publish_rate_hz"),
    ("pcd_grabber", "exposure_s:=abc", "parameter exposure_s"),
    ("geometry_publisher", "hand_eye.source.translation_m:=abc", "parameter hand_eye.source.translation_m"),
    ("scan_orchestrator", "tick_period_s:=-1.0", "parameter tick_period_s"),
    ("recon_service", "iterations:=abc", "parameter iterations"),
    ("recorder", "flush_period_s:=abc", "parameter flush_period_s"),
    ("replay", "rate_hz:=abc", "parameter rate_hz"),
    ("replay", "bag_path:=/nonexistent/bag", "parameter bag_path"),
    ("replay", "method:=foo", "parameter method"),
    ("recorder", "output_dir:=/proc/version", "parameter output_dir"),  # a file: refused at start, not at the scan
    ("recon_service", "output_dir:=/proc/version", "parameter output_dir"),
]


SOURCE_REFUSES = [("source_control", "kvp:=200.0", "kVp 200.0 outside"),  # the source's own range: it stayed up,
                  ("source_control", "power_w:=500.0", "power 500.0 W outside")]  # unconfigured for good


@pytest.mark.parametrize("node, assignment, words, autostart", [c + (False,) for c in CASES] + [
    c + (True,) for c in SOURCE_REFUSES], ids=[f"{n}:{a}" for n, a, _ in CASES + SOURCE_REFUSES])
def test_a_bad_parameter_is_one_line_and_exit_2(node, assignment, words, autostart):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               PYTHONPATH=str(REPO))
    args = ["--ros-args", "-p", assignment, "-p", f"autostart:={str(autostart).lower()}"]
    if node == "replay" and not assignment.startswith("bag_path"):
        args += ["-p", "bag_path:=/nonexistent/bag"]
    proc = subprocess.run([sys.executable, "-m", f"robot_ct_ros.nodes.{node}", *args], capture_output=True, text=True,
                          env=env, timeout=60)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and words in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_a_shutdown_that_loses_the_race_with_the_sigint_handler_still_exits_cleanly():
    """rclpy's SIGINT handler may shut the context down between try_shutdown's check and its call;
    rcl then says "already called", which is no failure. Any other shutdown error is."""
    from types import SimpleNamespace

    from rclpy.impl.implementation_singleton import rclpy_implementation

    from robot_ct_ros.nodes.common import shutdown_once

    def failing(message):
        def try_shutdown(context=None):
            raise rclpy_implementation.RCLError(message)
        return SimpleNamespace(try_shutdown=try_shutdown)

    shutdown_once(failing("failed to shutdown: rcl_shutdown already called on the given context"))
    with pytest.raises(rclpy_implementation.RCLError, match="invalid context"):
        shutdown_once(failing("failed to shutdown: invalid context"))


def test_a_publish_that_loses_the_race_with_the_sigint_handler_is_skipped():
    """On the way out a node publishes (the beam off, the arm not in position) only while its context is
    up; when rclpy's SIGINT handler shuts the context down between the check and the publish, rcl
    says "publisher's context is invalid" and the message is dropped, not raised (the node then
    exits 0). A publishing error while the context is up still propagates."""
    from types import SimpleNamespace

    from rclpy.impl.implementation_singleton import rclpy_implementation

    from robot_ct_ros.nodes.common import publish_while_up

    state = {"up": True, "sent": []}
    node = SimpleNamespace(context=SimpleNamespace(ok=lambda: state["up"]))

    def publisher(shut_down_first: bool):
        def publish(msg):
            if shut_down_first:
                state["up"] = False  # the handler's thread wins the race
            if not state["up"]:
                raise rclpy_implementation.RCLError("Failed to publish: publisher's context is invalid")
            state["sent"].append(msg)
        return SimpleNamespace(publish=publish)

    assert publish_while_up(node, publisher(False), "a") and state["sent"] == ["a"]
    assert not publish_while_up(node, publisher(True), "b") and state["sent"] == ["a"]
    assert not publish_while_up(node, publisher(False), "c")  # already down: not even tried
    state["up"] = True

    def broken(msg):
        raise rclpy_implementation.RCLError("Failed to publish: some other error")
    with pytest.raises(rclpy_implementation.RCLError, match="other error"):
        publish_while_up(node, SimpleNamespace(publish=broken), "d")


def test_a_ros_argument_rcl_cannot_parse_is_one_reason_and_exit_2():
    """``-p name:=`` (no value) made rclpy.init raise: a traceback and exit 1. rcl logs its own line first."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "robot_ct_ros.nodes.recorder", "--ros-args", "-p", "output_dir:="],
                          capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert "bad ROS arguments" in last and "output_dir:=" in last and "name:=''" in last, proc.stderr
    # a params file rcl cannot open is another mistake: no hint about empty values
    proc = subprocess.run([sys.executable, "-m", "robot_ct_ros.nodes.recorder", "--ros-args", "--params-file",
                           "/nonexistent/recorder.yaml"], capture_output=True, text=True, env=env, timeout=60)
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode == 2 and "bad ROS arguments" in last and "recorder.yaml" in last, proc.stderr
    assert "name:=''" not in last, last


def test_a_parameter_the_node_does_not_have_is_named_with_the_closest_one():
    """rclpy ignores an undeclared parameter: a misspelt itterations:=5 ran with the default without a word."""
    import signal
    import time

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "robot_ct_ros.nodes.recon_service", "--ros-args", "-p",
                             "itterations:=5", "-p", "prior_sigma_translatoin_m:=0.0001"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    import select

    try:
        deadline, lines = time.monotonic() + 120, []  # the import takes long on a loaded machine
        while time.monotonic() < deadline and not any("does not have" in line for line in lines):
            if select.select([proc.stderr], [], [], 1.0)[0]:  # never blocks past the deadline
                lines.append(proc.stderr.readline())
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    warning = next(line for line in lines if "does not have" in line)
    assert "itterations (did you mean iterations?)" in warning, warning
    assert "prior_sigma_translatoin_m (did you mean prior_sigma_translation_m?)" in warning, warning
