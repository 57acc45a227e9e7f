"""recorder in-process and as a process: published frames end up in a readable scan bag."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import String
from geometry_msgs.msg import PoseArray, PoseStamped
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag import read_scan, scan_info_for
from robot_ct_ros.bag.writer import default_stamps
from robot_ct_ros.ct.trajectory import robotic_roi_scan
from robot_ct_ros.nodes.recorder import LATCHED, STREAM, RecorderNode

REPO = Path(__file__).resolve().parents[2]
N = 8


def _scan():
    geom = robotic_roi_scan(n_views=N, n_rows=6, n_cols=10, fov_diameter_mm=0.5)
    frames = np.random.default_rng(0).poisson(500.0, (N, 6, 10)).astype(np.float32)
    return geom, frames, default_stamps(N)


def _both_readers(path) -> dict:
    from rosbags.rosbag2 import Reader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages
    a, b = {}, {}
    with Reader(path) as reader:
        for conn, _, raw in reader.messages():
            fmt.deserialize(raw, conn.msgtype)
            a[conn.topic] = a.get(conn.topic, 0) + 1
    for m in read_ros2_messages(str(next(Path(path).glob("*.mcap")))):
        b[m.channel.topic] = b.get(m.channel.topic, 0) + 1
    assert a == b
    return a


def _rclpy_image(frame, stamp_ns) -> Image:
    """A frame built the way a detector driver would, with rclpy message classes."""
    msg = Image(height=frame.shape[0], width=frame.shape[1], encoding="32FC1", is_bigendian=0,
                step=frame.shape[1] * 4, data=np.ascontiguousarray(frame, "<f4").tobytes())
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = "pcd_detector"
    return msg


def _publishers(probe):
    return {
        "info": probe.create_publisher(String, fmt.TOPIC_SCAN_INFO, LATCHED),
        "flat": probe.create_publisher(Image, fmt.TOPIC_FLAT_FIELD, LATCHED),
        "proj": probe.create_publisher(Image, fmt.TOPIC_PROJECTION, STREAM),
        "geom": probe.create_publisher(PoseArray, fmt.TOPIC_GEOMETRY, STREAM),
        "pose": probe.create_publisher(PoseStamped, fmt.TOPIC_SOURCE_POSE, 10),
    }


def _publish_scan(pubs, geom, frames, stamps, views):
    for i in views:
        pubs["proj"].publish(_rclpy_image(frames[i], stamps[i]))
        pubs["geom"].publish(fmt.serialize(fmt.view_pose_array(geom.source_mm[i], geom.detector_mm[i], geom.u[i],
                                                               geom.v[i], int(stamps[i])), fmt.POSE_ARRAY))


def test_recorder_writes_a_readable_bag_and_stop_closes_it(ros, tmp_path):
    geom, frames, stamps = _scan()
    node = ros.add(RecorderNode(context=ros.context,
                                parameter_overrides=[Parameter("output_dir", value=str(tmp_path))]))
    probe = ros.node("probe")
    pubs = _publishers(probe)
    for key in ("info", "flat", "proj", "geom"):
        assert ros.wait_for_subscribers(pubs[key])
    info = scan_info_for(geom)
    pubs["info"].publish(String(data=fmt.scan_info_to_msg(info).data))
    pubs["flat"].publish(fmt.serialize(fmt.image_from_array(np.full((6, 10), 900.0, np.float32), 1), fmt.IMAGE))
    assert ros.spin_until(lambda: node.writer is not None)
    _publish_scan(pubs, geom, frames, stamps, range(N))
    pose = PoseStamped()
    pose.header.frame_id = "world"
    pubs["pose"].publish(pose)
    assert ros.spin_until(lambda: node.writer.counts.get(fmt.TOPIC_PROJECTION, 0) == N
                          and node.writer.counts.get(fmt.TOPIC_GEOMETRY, 0) == N)
    ros.spin_until(lambda: node.writer.counts.get(fmt.TOPIC_SOURCE_POSE, 0) == 1, timeout_s=2.0)

    stop = probe.create_client(Trigger, "/recorder/stop")
    answer = ros.call(stop, Trigger.Request())
    assert answer.success and node.writer is None
    bag = Path(answer.message)
    assert bag.parent == tmp_path
    counts = _both_readers(bag)
    assert counts[fmt.TOPIC_PROJECTION] == N and counts[fmt.TOPIC_SCAN_INFO] == 1
    scan = read_scan(bag)
    assert scan.warnings == [] and scan.n_views == N
    np.testing.assert_array_equal(scan.counts, frames)
    np.testing.assert_array_equal(scan.stamps_ns, stamps)
    assert scan.geom.allclose(geom, atol=1e-9)

    # the next frame opens a new bag that starts with the cached scan_info and flat field
    _publish_scan(pubs, geom, frames, stamps, [0])
    assert ros.spin_until(lambda: node.writer is not None and node.writer.counts.get(fmt.TOPIC_GEOMETRY, 0) == 1)
    second = node.close_bag()  # what shutdown (destroy_node) does
    assert second != bag and _both_readers(second)[fmt.TOPIC_PROJECTION] == 1  # one frame: no scan yet (MIN_VIEWS)
    assert not ros.call(stop, Trigger.Request()).success  # nothing open


def test_recorder_process_closes_the_bag_on_sigint(ros, tmp_path):
    geom, frames, stamps = _scan()
    env = dict(os.environ, PYTHONPATH=str(REPO))  # the fixture's ROS_DOMAIN_ID and localhost discovery
    proc = subprocess.Popen([sys.executable, "-m", "robot_ct_ros.nodes.recorder", "--ros-args",
                             "-p", f"output_dir:={tmp_path}", "-p", "bag_prefix:=proc"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        probe = ros.node("probe")
        pubs = _publishers(probe)
        for key in ("info", "flat", "proj", "geom"):
            assert ros.wait_for_subscribers(pubs[key], timeout_s=30.0)
        pubs["info"].publish(String(data=fmt.scan_info_to_msg(scan_info_for(geom)).data))
        pubs["flat"].publish(fmt.serialize(fmt.image_from_array(np.full((6, 10), 900.0, np.float32), 1), fmt.IMAGE))
        ros.spin_for(0.3)
        _publish_scan(pubs, geom, frames, stamps, range(N))

        def recorded() -> int:
            bags = list(tmp_path.glob("proc_*"))
            if not bags:
                return 0
            try:
                return read_scan(bags[0]).n_views  # the open bag, recovered from the flushed chunks
            except Exception:  # noqa: BLE001 - not there yet
                return 0

        assert ros.spin_until(lambda: recorded() == N, timeout_s=20.0)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    (bag,) = tmp_path.glob("proc_*")
    assert (bag / "metadata.yaml").exists(), proc.stderr.read()
    assert _both_readers(bag)[fmt.TOPIC_PROJECTION] == N
    scan = read_scan(bag)
    assert not scan.recovered and scan.n_views == N


def _raw(geom, frames, stamps, i):
    from rclpy.serialization import serialize_message

    return (serialize_message(_rclpy_image(frames[i], stamps[i])),
            fmt.serialize(fmt.view_pose_array(geom.source_mm[i], geom.detector_mm[i], geom.u[i], geom.v[i],
                                              int(stamps[i])), fmt.POSE_ARRAY))


def test_scans_in_a_row_keep_their_own_flat_frames_and_bags(ros, tmp_path):
    """An earlier scan's flat field went into the next scan's bag (another detector shape: the bag was unusable);
    a frame before the scan_info opened a bag without one; the same scan replayed twice filled one bag."""
    node = ros.add(RecorderNode(context=ros.context, parameter_overrides=[Parameter("output_dir", value=str(tmp_path))]))
    geom, frames, stamps = _scan()

    def feed(scan_info, n=N, flat=None, early=0):
        for i in range(early):  # frames and geometries that arrive before the scan_info
            for topic, data in zip((fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY), _raw(geom, frames, stamps, i)):
                node._on_message(topic, fmt.TOPIC_TYPES[topic], data)
        if flat is not None:
            node._on_message(fmt.TOPIC_FLAT_FIELD, fmt.IMAGE, fmt.serialize(fmt.image_from_array(flat, 1), fmt.IMAGE))
        node._on_message(fmt.TOPIC_SCAN_INFO, fmt.STRING, fmt.serialize(fmt.scan_info_to_msg(scan_info), fmt.STRING))
        for i in range(early, n):
            for topic, data in zip((fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY), _raw(geom, frames, stamps, i)):
                node._on_message(topic, fmt.TOPIC_TYPES[topic], data)

    feed(scan_info_for(geom), flat=np.full((6, 10), 900.0, np.float32), early=2)  # a fresh recorder, frames first
    first = node.close_bag()
    scan = read_scan(first)
    assert scan.n_views == N and scan.flat is not None
    np.testing.assert_array_equal(scan.counts, frames)
    # another detector, line integrals: the 6 x 10 flat is not its own
    other = scan_info_for(geom.with_detector(4, 8, 1.0, 1.0), projection_units="line_integral")
    from rclpy.serialization import serialize_message

    frames_small = frames[:, :4, :8].copy()
    node._on_message(fmt.TOPIC_SCAN_INFO, fmt.STRING, fmt.serialize(fmt.scan_info_to_msg(other), fmt.STRING))
    for i in range(N):
        node._on_message(fmt.TOPIC_PROJECTION, fmt.IMAGE, serialize_message(_rclpy_image(frames_small[i], stamps[i])))
        node._on_message(fmt.TOPIC_GEOMETRY, fmt.POSE_ARRAY, _raw(geom.with_detector(4, 8, 1.0, 1.0), frames,
                                                                  stamps, i)[1])
    second = node.close_bag()
    scan2 = read_scan(second)
    assert scan2.flat is None and scan2.n_views == N  # no foreign flat field: the bag is usable
    # the same scan replayed twice: two bags
    feed(scan_info_for(geom))
    feed(scan_info_for(geom))
    node.close_bag()
    bags = sorted(set(node.closed_bags) - {first, second})
    assert len(bags) == 2 and all(read_scan(b).n_views == N and not read_scan(b).warnings for b in bags)


def test_frames_before_the_scan_info_follow_it_by_log_time_too(ros, tmp_path):
    """Frames that came before the scan_info were written after it in the file but kept their earlier log times:
    by log time (rosbags, MCAP readers, `ros2 bag play`) the bag started with frames, not /ct/scan_info."""
    import time

    from rosbags.rosbag2 import Reader

    node = ros.add(RecorderNode(context=ros.context, parameter_overrides=[Parameter("output_dir", value=str(tmp_path))]))
    geom, frames, stamps = _scan()
    for i in range(3):  # frames and geometries first
        for topic, data in zip((fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY), _raw(geom, frames, stamps, i)):
            node._on_message(topic, fmt.TOPIC_TYPES[topic], data)
    time.sleep(0.01)
    node._on_message(fmt.TOPIC_FLAT_FIELD, fmt.IMAGE,
                     fmt.serialize(fmt.image_from_array(np.full((6, 10), 900.0, np.float32), 1), fmt.IMAGE))
    time.sleep(0.01)
    node._on_message(fmt.TOPIC_SCAN_INFO, fmt.STRING, fmt.serialize(fmt.scan_info_to_msg(scan_info_for(geom)),
                                                                    fmt.STRING))
    for i in range(3, N):
        for topic, data in zip((fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY), _raw(geom, frames, stamps, i)):
            node._on_message(topic, fmt.TOPIC_TYPES[topic], data)
    bag = node.close_bag()
    with Reader(bag) as reader:
        topics = [conn.topic for conn, _, _ in reader.messages()]  # by log time (ties: file order)
    assert topics[:2] == [fmt.TOPIC_SCAN_INFO, fmt.TOPIC_FLAT_FIELD], topics[:4]
    assert topics.count(fmt.TOPIC_PROJECTION) == N
    scan = read_scan(bag)
    assert scan.n_views == N and scan.flat is not None and not scan.warnings
    np.testing.assert_array_equal(scan.counts, frames)


def test_a_write_error_gives_the_bag_up_and_keeps_the_node_up(ros, tmp_path):
    """A full disk raised out of the subscription callback and ended the recorder (no /diagnostics at all)."""
    node = ros.add(RecorderNode(context=ros.context, parameter_overrides=[Parameter("output_dir", value=str(tmp_path))]))
    geom, frames, stamps = _scan()
    node._on_message(fmt.TOPIC_SCAN_INFO, fmt.STRING, fmt.serialize(fmt.scan_info_to_msg(scan_info_for(geom)),
                                                                     fmt.STRING))
    proj, pose = _raw(geom, frames, stamps, 0)
    node._on_message(fmt.TOPIC_PROJECTION, fmt.IMAGE, proj)

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    node.writer.write_raw = full
    node._on_message(fmt.TOPIC_GEOMETRY, fmt.POSE_ARRAY, pose)  # no exception out of the callback
    assert node.writer is None and node.failures == 1 and "No space left" in node.last_error
    proj1, _ = _raw(geom, frames, stamps, 1)
    node._on_message(fmt.TOPIC_PROJECTION, fmt.IMAGE, proj1)  # the rest of that scan: dropped, no new bag
    assert node.writer is None
    diag = []
    probe = ros.node("probe")
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    probe.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 10)
    assert ros.spin_until(lambda: any(s.name.endswith(": recorder") and s.level == DiagnosticStatus.ERROR
                                      for a in diag for s in a.status))
    # the next scan records again
    node._on_message(fmt.TOPIC_SCAN_INFO, fmt.STRING, fmt.serialize(fmt.scan_info_to_msg(scan_info_for(geom)),
                                                                     fmt.STRING))
    assert node.writer is not None


def test_every_beam_state_change_is_recorded_even_when_several_arrive_between_two_callbacks(ros, tmp_path):
    """The recorder subscribed to /source/beam_on with a depth of 1 (as the latched topics): a replay sends a frame's
    beam off and the next frame's on in one tick, and the first of each pair was overwritten before the recorder took
    it (a replayed scan's 24 changes were recorded as 12, the beam almost always on). Every change is kept now."""
    import time

    from std_msgs.msg import Bool

    geom, frames, stamps = _scan()
    node = ros.add(RecorderNode(context=ros.context,
                                parameter_overrides=[Parameter("output_dir", value=str(tmp_path))]))
    probe = ros.node("probe")
    pubs = _publishers(probe)
    beam = probe.create_publisher(Bool, fmt.TOPIC_BEAM_ON, LATCHED)  # as source_control publishes it
    for pub in (pubs["info"], beam):
        assert ros.wait_for_subscribers(pub)
    pubs["info"].publish(String(data=fmt.scan_info_to_msg(scan_info_for(geom)).data))
    assert ros.spin_until(lambda: node.writer is not None)
    sent = [k % 2 == 0 for k in range(10)]
    for on in sent:  # no callback runs in between: the messages wait in the subscription's queue
        beam.publish(Bool(data=on))
        time.sleep(0.005)
    assert ros.spin_until(lambda: node.writer.counts.get(fmt.TOPIC_BEAM_ON, 0) >= len(sent), timeout_s=3.0), \
        node.writer.counts.get(fmt.TOPIC_BEAM_ON, 0)
    node.close_bag()
