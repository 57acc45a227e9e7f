"""Shared fixtures of the scan-bag tests: a tiny scan and an independent-reader check."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def tiny_scan():
    """(geom, frames, flat, dead) of a 12-view 8x12 robotic ROI scan with counts around 1000."""
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=12, n_rows=8, n_cols=12, fov_diameter_mm=0.5)
    rng = np.random.default_rng(0)
    frames = rng.poisson(800.0, (12, 8, 12)).astype(np.float32)
    flat = np.full((8, 12), 1000.0, np.float32)
    dead = np.zeros((8, 12), bool)
    dead[2, 3] = True
    return geom, frames, flat, dead


def read_with_independent_readers(path) -> dict:
    """Message counts per topic read with rosbags and with mcap-ros2-support; asserts they agree."""
    from pathlib import Path

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the module warns about itself on import
        from mcap_ros2.reader import read_ros2_messages
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    import yaml

    meta = yaml.safe_load((Path(path) / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    ts = get_typestore(Stores.ROS2_JAZZY)
    a: dict[str, int] = {}
    with Reader(path) as reader:
        for conn, _, raw in reader.messages():
            ts.deserialize_cdr(raw, conn.msgtype)
            a[conn.topic] = a.get(conn.topic, 0) + 1
    b: dict[str, int] = {}
    (mcap,) = sorted(Path(path).glob("*.mcap"))
    for m in read_ros2_messages(str(mcap)):
        assert m.ros_msg is not None
        b[m.channel.topic] = b.get(m.channel.topic, 0) + 1
    assert a == b
    return a


@pytest.fixture
def check_bag():
    return read_with_independent_readers
