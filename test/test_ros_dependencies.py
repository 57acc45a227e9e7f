"""package.xml names only rosdep keys that resolve on Jazzy's platform, and every third-party module the
package imports is provided by one of them or by requirements-ros.txt (pip, without ROS wheels or numpy 2)."""

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# Keys of rosdistro's rosdep/python.yaml (ros/rosdistro, read at commit 000730dc5f91) with a rule for
# Ubuntu noble ('*' or noble): the Python keys this package may use. Checked there: python3-numba has
# ubuntu rules for bionic and focal only; python3-threadpoolctl, python3-tifffile, python3-rosbags*,
# python3-mcap* and python3-ur-rtde* do not exist.
ROSDEP_PYTHON_KEYS_NOBLE = {"python3-numpy", "python3-scipy", "python3-yaml", "python3-matplotlib", "python3-tqdm",
                            "python3-pil", "python3-pytest", "python3-psutil", "python3-lxml"}
ROS_PACKAGES = {"rclpy", "rcl_interfaces", "builtin_interfaces", "lifecycle_msgs", "std_msgs", "std_srvs",
                "sensor_msgs", "geometry_msgs", "diagnostic_msgs", "ament_copyright", "ament_index_python",
                "launch_ros", "launch_xml", "ros2launch"}
NOT_ROSDEP_KEYS = {"python3-threadpoolctl", "python3-tifffile", "python3-numba", "python3-rosbags-pip",
                   "python3-mcap-pip", "python3-mcap-ros2-support-pip", "python3-ur-rtde-pip"}

# import name -> where it comes from: a rosdep key of package.xml, or a pip distribution of requirements-ros.txt
PROVIDERS = {"numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml",
             "matplotlib": "python3-matplotlib", "tqdm": "python3-tqdm",
             "numba": "pip:numba", "threadpoolctl": "pip:threadpoolctl", "tifffile": "pip:tifffile",
             "rosbags": "pip:rosbags", "mcap": "pip:mcap", "rtde_control": "pip:ur-rtde", "rtde_receive": "pip:ur-rtde"}
OPTIONAL = {"itk": "test/bench only (itk-rtk), imported lazily", "lz4": "compressed MCAP chunks, optional",
            "zstandard": "compressed MCAP chunks, optional", "backports": "zstd fallback, optional",
            "compression": "Python >= 3.14 zstd, optional",
            "dask": "the scheduler setting only (pip install dask distributed), imported lazily",
            "distributed": "the scheduler setting only (pip install dask distributed), imported lazily"}


def _depends():
    root = ET.parse(REPO / "package.xml").getroot()
    return {e.tag: [x.text for x in root.findall(e.tag)] for e in root} | \
        {"exec": [e.text for e in root.findall("exec_depend")], "test": [e.text for e in root.findall("test_depend")]}


def _requirements():
    out = {}
    for line in (REPO / "requirements-ros.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name = re.split(r"[<>=!~\[ ;]", line, maxsplit=1)[0].lower()
            out[name] = line
    return out


def _imports():
    mods = set()
    for f in (REPO / "robot_ct_ros").rglob("*.py"):
        for n in ast.walk(ast.parse(f.read_text())):
            if isinstance(n, ast.Import):
                mods |= {a.name.split(".")[0] for a in n.names}
            elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                mods.add(n.module.split(".")[0])
    return {m for m in mods if m not in sys.stdlib_module_names and m != "robot_ct_ros"}


def test_package_xml_uses_only_keys_rosdep_resolves_on_noble():
    deps = _depends()
    for key in deps["exec"] + deps["test"]:
        assert key not in NOT_ROSDEP_KEYS, f"{key} is not a rosdep key that resolves on noble"
        assert key in ROS_PACKAGES or key in ROSDEP_PYTHON_KEYS_NOBLE, f"unknown dependency key {key}"


def test_every_imported_module_has_a_provider():
    deps, reqs = _depends(), _requirements()
    for module in sorted(_imports()):
        if module in OPTIONAL:
            continue
        if module in ROS_PACKAGES:
            assert module in deps["exec"], f"package.xml lacks <exec_depend>{module}</exec_depend>"
            continue
        assert module in PROVIDERS, f"robot_ct_ros imports {module}: give it a rosdep key or a pip line"
        provider = PROVIDERS[module]
        if provider.startswith("pip:"):
            assert provider[4:] in reqs, f"requirements-ros.txt lacks {provider[4:]} (for import {module})"
        else:
            assert provider in deps["exec"], f"package.xml lacks {provider} (for import {module})"


def test_the_launch_files_run_after_rosdep_install():
    """README: `ros2 launch robot_ct_ros robot_ct.launch.xml` works after `rosdep install`; package.xml declared
    none of what that needs (the launch verb, the XML front end, launch_ros's actions)."""
    assert list((REPO / "launch").glob("*.launch.xml"))
    missing = {"launch_ros", "launch_xml", "ros2launch"} - set(_depends()["exec"])
    assert not missing, f"package.xml lacks <exec_depend> for {sorted(missing)}"


def test_requirements_ros_never_pulls_ros_wheels_or_numpy_2():
    reqs = _requirements()
    assert not [n for n in reqs if n.startswith("ros-") or n in ("rclpy", "scipy", "matplotlib", "pyyaml")], reqs
    assert reqs.get("numpy") == "numpy<2"  # a bound that keeps the system numpy
    # every pip-only line is pinned below a major version that would need numpy 2 (numba) or a new API
    assert "<" in reqs["numba"] and "<" in reqs["rosbags"]
