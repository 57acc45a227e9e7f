"""nodes.common: the nodes' topic QoS profiles come from one place, the topic contract (bag.format.offered_qos)."""

from __future__ import annotations

import importlib

import numpy as np

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from robot_ct_ros.bag import format as fmt

NODES = ("arm_driver", "geometry_publisher", "pcd_grabber", "recon_service", "recorder", "replay", "scan_orchestrator",
         "source_control")


def test_the_nodes_qos_profiles_are_the_contracts_and_unchanged():
    """Review I8: each node restated the contract's profiles; they are now common's, derived from offered_qos, and
    equal to what the nodes used before (no behaviour changes)."""
    from robot_ct_ros.nodes import common

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    stream = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
    assert common.LATCHED == latched and common.STREAM == stream
    for topic in fmt.LATCHED_TOPICS + fmt.STATE_TOPICS:
        assert common.topic_qos(topic) == latched, topic
    for topic in (fmt.TOPIC_PROJECTION, fmt.TOPIC_PROJECTION_REJECTED, fmt.TOPIC_GEOMETRY, fmt.TOPIC_GEOMETRY_TRUE,
                  fmt.TOPIC_GEOMETRY_CORRECTED):
        assert common.topic_qos(topic) == stream, topic
    for name in NODES:
        module = importlib.import_module(f"robot_ct_ros.nodes.{name}")
        for profile in ("LATCHED", "STREAM"):
            assert getattr(module, profile, getattr(common, profile)) is getattr(common, profile), (name, profile)
        assert not hasattr(module, "TOPIC_DIAGNOSTICS"), name  # the contract's fmt.TOPIC_DIAGNOSTICS
    recorder, recon = importlib.import_module("robot_ct_ros.nodes.recorder"), importlib.import_module(
        "robot_ct_ros.nodes.recon_service")
    assert recorder.STATE == QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                        reliability=ReliabilityPolicy.RELIABLE)
    assert recon.STATUS == QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                      reliability=ReliabilityPolicy.RELIABLE)


def test_every_parameter_of_every_node_comes_back_in_one_get_parameters_call(ros, tmp_path):
    """Outside test 27 A #2: rclpy answers a GetParameters request that names an unset parameter (declared by
    type only) with no values at all, so ``ros2 param dump`` (one request for every name) came back empty for
    pcd_grabber, geometry_publisher and scan_orchestrator. Optional parameters now hold an empty array (unset)."""
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import GetParameters, ListParameters
    from rclpy.parameter import Parameter

    from robot_ct_ros.bag import write_scan
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=4, n_rows=4, n_cols=6, fov_diameter_mm=0.3)
    bag = write_scan(tmp_path / "scan", np.ones((4, 4, 6), np.float32), geom, projection_units="line_integral")
    overrides = {"pcd_grabber": {"autostart": False}, "recon_service": {"output_dir": str(tmp_path / "recon")},
                 "recorder": {"output_dir": str(tmp_path / "bags")},
                 "replay": {"bag_path": str(bag), "rate_hz": 0.0, "output_dir": str(tmp_path / "replay")}}
    probe = ros.node("probe")
    for name in NODES:
        module = importlib.import_module(f"robot_ct_ros.nodes.{name}")
        cls = next(c for c in vars(module).values() if isinstance(c, type) and c.__module__ == module.__name__
                   and c.__name__.endswith("Node"))
        ros.add(cls(context=ros.context, parameter_overrides=[Parameter(k, value=v)
                                                              for k, v in overrides.get(name, {}).items()]))
        names = ros.call(probe.create_client(ListParameters, f"/{name}/list_parameters"),
                         ListParameters.Request()).result.names
        got = ros.call(probe.create_client(GetParameters, f"/{name}/get_parameters"),
                       GetParameters.Request(names=names))
        assert len(got.values) == len(names), (name, len(got.values), len(names))
        unset = [n for n, v in zip(names, got.values) if v.type == ParameterType.PARAMETER_NOT_SET]
        assert not unset, (name, unset)


def test_on_and_off_set_a_string_choice_though_yaml_reads_them_as_booleans(ros):
    """An outside check: `-p exterior:=off` and `-p fov_support:=on` were refused as booleans (YAML reads off and on
    so); they set the choice they name now. A boolean where no such choice exists is still refused."""
    import pytest
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.nodes.common import declare_settings

    node = ros.add(Node("choices", context=ros.context, parameter_overrides=[
        Parameter("exterior", value=False), Parameter("fov_support", value=True)]))
    settings = declare_settings(node, CalibrationSettings)
    assert (settings.exterior, settings.fov_support) == ("off", "on")
    other = ros.add(Node("choices_bad", context=ros.context, parameter_overrides=[Parameter("method", value=True)]))
    with pytest.raises(ValueError, match="method"):
        declare_settings(other, CalibrationSettings)


def _stacked(tmp_path, *texts):
    """``--params-file`` arguments for the shipped source_control.yaml and then each yaml text, written here."""
    from pathlib import Path

    args = ["--ros-args", "--params-file", str(Path(__file__).resolve().parents[2] / "config" / "source_control.yaml")]
    for i, text in enumerate(texts):
        (tmp_path / f"over{i}.yaml").write_text(text)
        args += ["--params-file", str(tmp_path / f"over{i}.yaml")]
    return args


def test_a_wrong_type_in_a_second_params_file_is_refused_as_when_alone(ros, tmp_path):
    """Outside test E #1: rcl keeps the type of the first file that sets a parameter, so a second file's
    ``kvp: "ninety"`` over the shipped ``kvp: 90.0`` was dropped and the node ran with 90.0 without a word (so was
    ``iterations: 2.5`` for recon_service). Each file named in the node's arguments is checked again, by rcl's
    rules for which sections apply."""
    import pytest
    from rclpy.node import Node

    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.hardware.xray_source import SourceSettings
    from robot_ct_ros.nodes.common import LifecycleSettings, declare_settings
    from robot_ct_ros.nodes.hand_eye_params import declare_hand_eye

    def settings(name, cls, *texts, namespace=None):
        node = ros.add(Node(name, namespace=namespace, context=ros.context, cli_args=_stacked(tmp_path, *texts)))
        return declare_settings(node, cls)

    for section in ("/**/source_control", "/**", "source_control", "/*"):
        with pytest.raises(ValueError, match=r"parameter kvp: .*'ninety' of type 'STRING', expecting type 'DOUBLE' "
                                             r"\(in .*over0.yaml\)"):
            settings("source_control", SourceSettings, f"{section}:\n  ros__parameters:\n    kvp: \"ninety\"\n")
    with pytest.raises(ValueError, match=r"kvp: .*\[90.0\].*'DOUBLE_ARRAY', expecting type 'DOUBLE'"):
        settings("source_control", SourceSettings, "/**:\n  ros__parameters:\n    kvp: [90.0]\n")
    with pytest.raises(ValueError, match=r"autostart: .*'1' of type 'INTEGER', expecting type 'BOOL'"):
        settings("source_control", LifecycleSettings, "/**:\n  ros__parameters:\n    autostart: 1\n")  # rcl: no bool
    # namespaces as rcl applies them: nested keys and /* match /scanner_a/source_control; a bare name does not
    for text in ("scanner_a:\n  source_control:\n    ros__parameters:\n      kvp: 'x'\n",
                 "/*/source_control:\n  ros__parameters:\n    kvp: 'x'\n"):
        with pytest.raises(ValueError, match="kvp"):
            settings("source_control", SourceSettings, text, namespace="/scanner_a")
    ignored = ("source_control:\n  ros__parameters:\n    kvp: 'x'\n", "/*:\n  ros__parameters:\n    kvp: 'x'\n",
               "/**/recorder:\n  ros__parameters:\n    kvp: 'x'\n")
    assert settings("source_control", SourceSettings, *ignored, namespace="/scanner_a").kvp == 90.0
    # what the declaration itself accepts: a whole number for a double, off/on for a choice naming them, [] unset
    assert settings("source_control", SourceSettings, "/**:\n  ros__parameters:\n    kvp: 80\n").kvp == 80.0
    calib = settings("recon_service", CalibrationSettings,
                     "/**:\n  ros__parameters:\n    exterior: 'off'\n    iterations: 3\n",
                     "/**:\n  ros__parameters:\n    exterior: off\n    iterations: 0x4\n")
    assert (calib.exterior, calib.iterations) == ("off", 4)
    with pytest.raises(ValueError, match=r"iterations: .*'2.5' of type 'DOUBLE', expecting type 'INTEGER'"):
        settings("recon_service", CalibrationSettings, "/**:\n  ros__parameters:\n    iterations: 2.5\n")
    he = "/**:\n  ros__parameters:\n    hand_eye:\n      source:\n        rotvec_rad: {}\n"
    node = ros.add(Node("he_ok", context=ros.context, cli_args=_stacked(tmp_path, he.format("[]"))))
    declare_hand_eye(node)
    node = ros.add(Node("he_bad", context=ros.context, cli_args=_stacked(tmp_path, he.format("['0', '0', '1']"))))
    with pytest.raises(ValueError, match=r"hand_eye.source.rotvec_rad: .*'STRING_ARRAY', expecting type "
                                         r"'DOUBLE_ARRAY'"):
        declare_hand_eye(node)


def test_the_node_executable_ends_with_one_line_and_status_2_on_a_wrong_type_in_a_second_file(tmp_path):
    """Outside test E #1 as it was run: the files in the executable's own (global) ROS arguments."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               PYTHONPATH=str(repo))
    proc = subprocess.run([sys.executable, "-m", "robot_ct_ros.nodes.source_control",
                           *_stacked(tmp_path, "/**/source_control:\n  ros__parameters:\n    kvp: \"ninety\"\n")],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert "parameter kvp" in last and "'ninety'" in last and "over0.yaml" in last, proc.stderr
def test_a_list_of_strings_setting_is_a_string_array_parameter_and_may_be_given_empty(ros):
    """replay's skip_topics is a list of strings, which settings knew only as lists of numbers: it is declared a string
    array with its default, any number of names is taken, and ``-p skip_topics:=[]`` (which rcl reads as no value)
    gives the empty list; a list of numbers is refused."""
    import pytest
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from robot_ct_ros.nodes.common import declare_settings
    from robot_ct_ros.nodes.replay import ReplaySettings

    def settings(name, args=(), overrides=()):
        node = ros.add(Node(name, context=ros.context, cli_args=["--ros-args", *args], parameter_overrides=[
            Parameter("bag_path", value="x"), *overrides]))
        return node, declare_settings(node, ReplaySettings)

    node, s = settings("strings_default")
    assert s.skip_topics == ("/rosout", "/parameter_events")
    assert node.get_parameter("skip_topics").type_ == Parameter.Type.STRING_ARRAY
    node, s = settings("strings_three", ["-p", 'skip_topics:=["/tf", "/tf_static", "/rosout"]'])
    assert s.skip_topics == ("/tf", "/tf_static", "/rosout")
    node, s = settings("strings_empty", ["-p", "skip_topics:=[]"])
    assert s.skip_topics == ()
    assert node.get_parameter("skip_topics").type_ == Parameter.Type.STRING_ARRAY
    with pytest.raises(ValueError, match="skip_topics"):
        settings("strings_numbers", ["-p", "skip_topics:=[1, 2]"])



def test_the_params_files_are_taken_from_the_command_line_where_rcl_cannot_be_asked(ros, tmp_path, monkeypatch):
    """The files are asked of rcl through ctypes (rclpy keeps no list of them); where that fails (another rcl
    build, say) the ``--params-file`` entries of ``sys.argv`` stand in: what ``ros2 run`` and launch pass."""
    import ctypes
    import sys

    from rclpy.node import Node

    from robot_ct_ros.nodes.common import _params_files

    args = _stacked(tmp_path, "/**:\n  ros__parameters:\n    kvp: 90.0\n")
    files = args[2::2]  # the shipped file, then over0.yaml
    node = ros.add(Node("source_control", context=ros.context, cli_args=args))
    assert _params_files(node) == files  # asked of rcl: the node's own arguments

    def no_library(*args, **kwargs):
        raise OSError("no such library")

    monkeypatch.setattr(ctypes, "CDLL", no_library)
    monkeypatch.setattr(sys, "argv", ["source_control", "--ros-args", "-r", "__node:=source_control", *args[1:]])
    assert _params_files(node) == files
