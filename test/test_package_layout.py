"""The ament_python layout: install the package the way colcon does and check what ros2 run needs.

colcon's ament_python build runs ``setup.py egg_info``, ``build`` and ``install --prefix``
with ``--single-version-externally-managed``; ``ros2 run robot_ct_ros X`` then looks for
``<prefix>/lib/robot_ct_ros/X`` and the package marker in the ament index.
"""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE_FILES = ["package.xml", "setup.py", "setup.cfg", "resource", "robot_ct_ros", "config", "launch"]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "robot_ct_ros"
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
        else:
            shutil.copy2(path, src / name)
    build, prefix = ws / "build", ws / "install"
    build.mkdir()
    cmd = [sys.executable, "setup.py", "egg_info", "--egg-base", str(build),
           "build", "--build-base", str(build),
           "install", "--prefix", str(prefix), "--record", str(build / "install.log"),
           "--single-version-externally-managed"]
    proc = subprocess.run(cmd, cwd=src, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    site = next(prefix.glob("lib/python3*/site-packages"))
    return prefix, site


def _entry_points(site: Path) -> list[str]:
    eggs = list(site.glob("robot_ct_ros-*.egg-info"))
    assert eggs, "no egg-info installed"
    cfg = configparser.ConfigParser()
    cfg.read(eggs[0] / "entry_points.txt")
    return list(cfg["console_scripts"])


def test_ament_index_and_manifest(installed):
    prefix, _ = installed
    assert (prefix / "share/ament_index/resource_index/packages/robot_ct_ros").is_file()
    manifest = prefix / "share/robot_ct_ros/package.xml"
    assert manifest.is_file()
    root = ET.parse(manifest).getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "robot_ct_ros"
    assert root.findtext("export/build_type") == "ament_python"


def test_manifest_declares_the_ros_packages_the_code_imports():
    root = ET.parse(REPO / "package.xml").getroot()
    declared = {e.text for e in root.iter() if e.tag in ("exec_depend", "depend")}
    imported = set()
    for py in (REPO / "robot_ct_ros").rglob("*.py"):
        for line in py.read_text().splitlines():
            words = line.split()
            if len(words) >= 2 and words[0] in ("from", "import"):
                top = words[1].split(".")[0]
                if top.endswith("_msgs") or top.endswith("_srvs") or top == "rclpy":
                    imported.add(top)
    assert imported <= declared, f"undeclared: {imported - declared}"


def test_every_executable_installed_to_lib_and_answers_help(installed):
    prefix, site = installed
    names = _entry_points(site)
    assert "robot-ct" in names and "source_control" in names
    env = dict(os.environ, PYTHONPATH=str(site))
    for name in names:
        exe = prefix / "lib" / "robot_ct_ros" / name
        assert exe.is_file() and os.access(exe, os.X_OK), f"{exe} missing"
        proc = subprocess.run([str(exe), "--help"], capture_output=True, text=True, env=env, timeout=120)
        assert proc.returncode == 0, f"{name} --help failed: {proc.stderr[-2000:]}"
        assert "usage" in proc.stdout.lower()
        # the installed copy, not the checkout, answered
        assert str(REPO) not in proc.stderr


def test_node_executable_starts_and_stops_cleanly_on_sigint(installed):
    import signal
    import time

    prefix, site = installed
    env = dict(os.environ, PYTHONPATH=str(site), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(150 + os.getpid() % 50))
    import threading

    proc = subprocess.Popen([str(prefix / "lib/robot_ct_ros/source_control"), "--ros-args", "-p", "kvp:=80.0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    # SIGINT once the node is up (its log says so), not after a guessed time: on a loaded machine the
    # imports alone can take longer, and a SIGINT during them is a KeyboardInterrupt traceback
    lines, up = [], threading.Event()

    def read(stream):
        for line in stream:
            lines.append(line)
            if "source configured" in line:
                up.set()
    readers = [threading.Thread(target=read, args=(s,), daemon=True) for s in (proc.stdout, proc.stderr)]
    for t in readers:
        t.start()
    deadline = time.monotonic() + 120.0
    while not up.wait(0.2):
        assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)[-2000:]
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=30)
    for t in readers:
        t.join(5.0)
    assert proc.returncode == 0, "".join(lines)[-2000:]


def test_launch_files_and_the_parameter_files_they_name_are_installed(installed):
    """``ros2 launch robot_ct_ros robot_ct.launch.xml`` finds the file and every params file it names."""
    import re

    prefix, _ = installed
    share = prefix / "share/robot_ct_ros"
    launches = sorted((REPO / "launch").glob("*.launch.xml"))
    assert launches
    for launch in launches:
        assert (share / "launch" / launch.name).is_file(), launch.name
        for ref in re.findall(r'from="\$\(var config_dir\)/([^"]+)"', launch.read_text()):
            assert (share / "config" / ref).is_file(), ref


def test_the_installed_package_reads_its_installed_config(installed, tmp_path):
    """``robot-ct demo`` and the scan graph read hand_eye.yaml and the scan protocols from config/: installed
    without the source checkout, that is ``<prefix>/share/robot_ct_ros/config`` (the checkout's path ended the
    installed demo with "cannot access .../site-packages/config/hand_eye.yaml")."""
    prefix, site = installed
    env = dict(os.environ, PYTHONPATH=str(site))
    env.pop("AMENT_PREFIX_PATH", None)
    code = ("from robot_ct_ros.nodes.config_files import package_config_dir; "
            "from robot_ct_ros.testing.demo import _config_hand_eye; "
            "print(package_config_dir()); print(sorted(_config_hand_eye()))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    found, mounts = proc.stdout.splitlines()[:2]
    assert Path(found) == prefix / "share/robot_ct_ros/config"
    assert mounts == "['detector', 'source']"
