"""launch/robot_ct.launch.xml: the graph as ROS starts it. `launch` itself is not installable here, so its
structure is checked, and each node it names is built in-process the way ros2 launch would start it
(its parameter files, its name, a namespace), which also proves the parameter files load into the nodes."""

import ast
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "robot_ct.launch.xml"


def _setup_executables() -> dict:
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "NODES" for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError("setup.py has no NODES")


def _nodes():
    root = ET.parse(LAUNCH).getroot()
    assert root.tag == "launch"
    args = {a.get("name"): a.get("default") for a in root.findall("arg")}
    out = []
    for n in root.iter("node"):
        files = [p.get("from") for p in n.findall("param") if p.get("from")]
        values = {p.get("name"): p.get("value") for p in n.findall("param") if p.get("name")}
        out.append((n.get("pkg"), n.get("exec"), n.get("name"), files, values))
    return root, args, out


def _config(ref: str) -> Path:
    prefix = "$(var config_dir)/"
    assert ref.startswith(prefix), ref
    return REPO / "config" / ref[len(prefix):]


def test_launch_structure():
    root, args, nodes = _nodes()
    executables = _setup_executables()
    assert args["config_dir"] == "$(find-pkg-share robot_ct_ros)/config" and "namespace" in args
    pushes = list(root.iter("push-ros-namespace"))
    assert len(pushes) == 1 and pushes[0].get("namespace") == "$(var namespace)"
    names = [name for _, _, name, _, _ in nodes]
    assert len(names) == len(set(names)), names
    assert {exe for _, exe, _, _, _ in nodes} == set(executables) - {"replay"}  # the whole online graph
    for pkg, exe, name, files, _ in nodes:
        assert pkg == "robot_ct_ros" and exe in executables, exe
        assert files, f"{name} gets no parameter file"
        for ref in files:
            path = _config(ref)
            assert path.is_file(), ref
            keys = {k.split("#")[0].strip().rstrip(":") for k in path.read_text().splitlines()
                    if k and not k[0].isspace() and not k.startswith("#")}
            # the file applies to this node in any namespace
            assert "/**" in keys or f"/**/{name}" in keys, (ref, name, keys)
        if exe in ("pcd_grabber", "geometry_publisher", "scan_orchestrator"):
            assert "$(var config_dir)/hand_eye.yaml" in files, name
    roles = {name: exe for _, exe, name, _, _ in nodes}
    assert roles.get("source_arm_driver") == roles.get("detector_arm_driver") == "arm_driver"


def _node_class(exe: str):
    import importlib
    import inspect

    from rclpy.node import Node

    module = importlib.import_module(_setup_executables()[exe].split(":")[0])
    classes = [c for _, c in inspect.getmembers(module, inspect.isclass)
               if issubclass(c, Node) and c.__module__ == module.__name__]
    assert len(classes) == 1, classes
    return classes[0]


@pytest.mark.parametrize("namespace", ["/", "/scanner_a"])
def test_every_launched_node_starts_with_its_parameter_files_in_a_namespace(namespace, tmp_path, monkeypatch):
    import inspect
    import os

    import rclpy
    from rclpy.context import Context

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.chdir(tmp_path)  # relative output folders land here
    _, _, nodes = _nodes()
    for _, exe, name, files, values in nodes:
        argv = ["--ros-args", "-r", f"__ns:={namespace}", "-r", f"__node:={name}"]
        for ref in files:
            argv += ["--params-file", str(_config(ref))]
        for key, value in values.items():
            argv += ["-p", f"{key}:={value.replace('$(var bag_dir)', 'bags').replace('$(var recon_dir)', 'recon')}"]
        argv += ["-p", "autostart:=false"]  # nothing connects or voxelises here
        context = Context()
        rclpy.init(context=context, args=argv, domain_id=190 + os.getpid() % 10)
        try:
            cls = _node_class(exe)
            kwargs = {"context": context}
            if "node_name" in inspect.signature(cls.__init__).parameters:
                kwargs["node_name"] = exe  # remapped to `name` by __node, as ros2 launch does
            node = cls(**kwargs)
            try:
                assert node.get_name() == name and node.get_namespace() == namespace
                if exe == "arm_driver":  # the per-arm section of arm_driver.yaml reached it
                    assert node.role == name.split("_")[0]
                    assert node.sim_settings.seed == (1 if node.role == "source" else 2)
            finally:
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)


def test_one_parameter_file_combining_every_nodes_file_gives_each_node_only_its_own(tmp_path, monkeypatch):
    """Outside test E, finding 7: config/arm_driver.yaml put the arms' parameters under /**, which matches every
    node, so one file combining all of config/<node>.yaml (run/all.yaml) made source_control warn about 23 and
    geometry_publisher about 20 parameters they do not have. Each arm has its own full section now: every launched
    node started with the combined file is given none it lacks, apart from hand_eye.yaml's hand_eye.* (a /**
    section on purpose: one calibration shared by three nodes), and each arm still gets every parameter of its
    section."""
    import inspect
    import os

    import rclpy
    import yaml
    from rclpy.context import Context

    from robot_ct_ros.nodes.common import warn_undeclared_parameters

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.chdir(tmp_path)
    _, _, nodes = _nodes()
    files = sorted({_config(ref) for *_, refs, _ in nodes for ref in refs})
    combined = tmp_path / "all.yaml"
    combined.write_text("\n".join(f.read_text() for f in files))
    arm_sections = yaml.safe_load((REPO / "config" / "arm_driver.yaml").read_text())
    unknown = {}
    for _, exe, name, _, _ in nodes:
        context = Context()
        rclpy.init(context=context, args=["--ros-args", "-r", f"__node:={name}", "--params-file", str(combined),
                                          "-p", "autostart:=false"], domain_id=190 + os.getpid() % 10)
        try:
            cls = _node_class(exe)
            kwargs = {"context": context}
            if "node_name" in inspect.signature(cls.__init__).parameters:
                kwargs["node_name"] = exe
            node = cls(**kwargs)
            try:
                unknown[name] = [n for n in warn_undeclared_parameters(node)  # autostart: this test's -p, to all
                                 if not n.startswith("hand_eye.") and n != "autostart"]
                if exe == "arm_driver":
                    section = arm_sections[f"/**/{name}"]["ros__parameters"]
                    assert set(section) <= set(node._parameter_overrides), name
                    assert node.role == name.split("_")[0]
            finally:
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)
    assert unknown == {name: [] for *_, name, _, _ in nodes}, "nodes given parameters they do not have"
    source, detector = (arm_sections[f"/**/{name}"]["ros__parameters"] for name in ("source_arm_driver",
                                                                                    "detector_arm_driver"))
    assert {"robot_ip", "speed", "sim_seed", "role"} <= set(source)  # each arm's section has all
    # the shipped sections differ in role and sim_seed alone (a shared value edited in one only is a slip)
    assert {k for k in source.keys() | detector.keys() if source.get(k) != detector.get(k)} == {"role", "sim_seed"}
