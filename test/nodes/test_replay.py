"""replay in-process: republishes every frame of a bag with its stamps; runs the offline job."""

from __future__ import annotations

import json

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import String

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.bag.writer import default_stamps
from robot_ct_ros.ct.trajectory import robotic_roi_scan
from robot_ct_ros.nodes.recorder import LATCHED, STREAM
from robot_ct_ros.nodes.replay import ReplayNode, frame_groups

N = 12


def _bag(tmp_path):
    geom = robotic_roi_scan(n_views=N, n_rows=8, n_cols=12, fov_diameter_mm=0.5)
    frames = np.random.default_rng(0).poisson(500.0, (N, 8, 12)).astype(np.float32)
    stamps = default_stamps(N)
    bag = write_scan(tmp_path / "scan", frames, geom, flat=np.full((8, 12), 900.0, np.float32), stamps_ns=stamps)
    return bag, geom, frames, stamps


def _params(**kw):
    return [Parameter(k, value=v) for k, v in kw.items()]


def test_replay_republishes_every_frame(ros, tmp_path):
    bag, geom, frames, stamps = _bag(tmp_path)
    probe = ros.node("probe")
    got_frames, got_geoms, got_info = [], [], []
    probe.create_subscription(Image, fmt.TOPIC_PROJECTION, got_frames.append, STREAM)
    probe.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY, got_geoms.append, STREAM)
    probe.create_subscription(String, fmt.TOPIC_SCAN_INFO, got_info.append, LATCHED)
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=100.0, wait_for_subscribers=1)))
    assert ros.spin_until(lambda: node.done and len(got_frames) == N and len(got_geoms) == N, timeout_s=20.0)
    assert node.published_frames == N
    assert json.loads(got_info[0].data)["n_rows"] == 8
    for i, msg in enumerate(got_frames):
        assert (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec) == stamps[i]
        np.testing.assert_array_equal(np.frombuffer(bytes(msg.data), "<f4").reshape(8, 12), frames[i])
    g = got_geoms[5]
    assert g.poses[0].position.x == geom.source_mm[5, 0] * 1e-3


def test_replay_runs_the_offline_job(ros, tmp_path):
    bag, geom, frames, stamps = _bag(tmp_path)
    probe = ros.node("probe")
    reports = []
    probe.create_subscription(String, "/replay/report", reports.append, LATCHED)
    out = tmp_path / "out"
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=0.0, method="none", output_dir=str(out))))
    assert ros.spin_until(lambda: node.done and reports, timeout_s=60.0)
    assert node.error is None, node.error
    report = json.loads(reports[-1].data)
    assert report["n_views"] == N and report["method_used"] == "none"
    assert (out / "volume.npy").exists() and (out / "volume.tif").exists() and (out / "report.json").exists()
    assert read_scan(out / "scan_corrected").geom_corrected.allclose(geom, atol=1e-9)


def test_replay_reconstructs_on_the_grid_its_parameters_give(ros, tmp_path):
    """replay had no grid parameters (only the bag's default grid), where the recon_service and the command line
    have them: voxel_size_m and roi_shape now come from the same settings class as the recon_service's."""
    bag, geom, frames, stamps = _bag(tmp_path)
    out = tmp_path / "out"
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=0.0, method="none", output_dir=str(out), voxel_size_m=0.00005,
        roi_shape=[6, 5, 4])))
    assert ros.spin_until(lambda: node.done, timeout_s=60.0)
    assert node.error is None, node.error
    assert np.load(out / "volume.npy").shape == (4, 5, 6)
    grid = json.loads((out / "volume_grid.json").read_text())
    assert np.allclose(grid["voxel_size_mm"], 0.05), grid


def test_frame_groups_end_with_a_projection():
    from robot_ct_ros.bag import RawMessage

    def m(topic, t):
        return RawMessage(topic, fmt.TOPIC_TYPES[topic], t, b"")

    msgs = [m(fmt.TOPIC_SCAN_INFO, 0), m(fmt.TOPIC_GEOMETRY, 1), m(fmt.TOPIC_PROJECTION, 2), m(fmt.TOPIC_PROJECTION, 3),
            m(fmt.TOPIC_GEOMETRY, 4), m(fmt.TOPIC_DIAGNOSTICS, 5)]
    latched, groups = frame_groups(msgs)
    assert [x.log_time_ns for x in latched] == [0]
    assert [[x.log_time_ns for x in g] for g in groups] == [[1, 2], [3, 4, 5]]


def test_exit_when_done_ends_the_executable_with_the_jobs_status(tmp_path):
    """Run as an offline tool (``ros2 run robot_ct_ros replay ... exit_when_done:=true``) the node ends once the
    job is done: exit 0 with the report written, 1 when the job failed (here: the output folder holds the results
    of another job; an output place that cannot be written is refused at start)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    bag = _bag(tmp_path)[0]
    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               PYTHONPATH=str(repo))
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "report.json").write_text(json.dumps({"job": "reconstruct"}))
    for out, status in ((tmp_path / "out", 0), (tmp_path / "other", 1)):
        proc = subprocess.run([sys.executable, "-m", "robot_ct_ros.nodes.replay", "--ros-args", "-p",
                               f"bag_path:={bag}", "-p", "rate_hz:=0.0", "-p", "method:=none", "-p",
                               f"output_dir:={out}", "-p", "exit_when_done:=true"],
                              capture_output=True, text=True, env=env, timeout=120)
        assert proc.returncode == status, proc.stderr[-2000:]
        assert "exiting (exit_when_done)" in proc.stderr, proc.stderr[-2000:]
        assert json.loads((out / "report.json").read_text()).get("job") == ("calibrate" if status == 0 else
                                                                            "reconstruct")


def test_an_exiting_replay_delivers_its_report_to_the_subscriber_waiting_for_it(ros, tmp_path):
    """With exit_when_done the node ended about 35 ms after publishing ~/report, and a script waiting on it missed
    the report in 2 of 7 runs; the node now waits for its subscribers' acknowledgement first."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    bag = _bag(tmp_path)[0]
    probe = ros.node("probe")
    reports = []
    probe.create_subscription(String, "/replay/report", reports.append, LATCHED)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]), ROS_DOMAIN_ID=str(ros.domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    for k in range(3):
        reports.clear()
        proc = subprocess.Popen([sys.executable, "-m", "robot_ct_ros.nodes.replay", "--ros-args", "-p",
                                 f"bag_path:={bag}", "-p", "rate_hz:=0.0", "-p", "method:=none", "-p",
                                 f"output_dir:={tmp_path / f'out{k}'}", "-p", "exit_when_done:=true"],
                                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert ros.spin_until(lambda: proc.poll() is not None, timeout_s=120.0)
        ros.spin_for(0.3)
        assert proc.returncode == 0 and reports, f"run {k}: no report received"
        assert json.loads(reports[-1].data).get("method_used") == "none"


def test_the_beam_state_reaches_transient_local_subscribers_from_a_replayed_bag(ros, tmp_path):
    """/source/beam_on is transient-local live, and the nodes (recorder, orchestrator, grabber) subscribe to it so;
    a bag recorded it as volatile and replay republished it so, which no transient-local reader matches (DDS): a
    re-recorded replay lost the beam state. The bag's metadata and the replay now offer it transient-local."""
    import yaml
    from std_msgs.msg import Bool

    from robot_ct_ros.bag.writer import ScanBagWriter

    geom = robotic_roi_scan(n_views=N, n_rows=8, n_cols=12, fov_diameter_mm=0.5)
    frames = np.random.default_rng(0).poisson(500.0, (N, 8, 12)).astype(np.float32)
    stamps = default_stamps(N)
    bool_cls = fmt.typestore().types[fmt.BOOL]
    with ScanBagWriter(tmp_path / "scan", fmt.scan_info_for(geom), start_ns=int(stamps[0]) - 2) as w:
        w.write_flat(np.full((8, 12), 900.0, np.float32), int(stamps[0]) - 2)
        w.write_msg(fmt.TOPIC_BEAM_ON, bool_cls(data=True), int(stamps[0]) - 1)
        for i in range(N):
            w.write_frame(frames[i], geom, int(stamps[i]), i)
        w.write_msg(fmt.TOPIC_BEAM_ON, bool_cls(data=False), int(stamps[-1]) + 1)
    meta = yaml.safe_load((tmp_path / "scan" / "metadata.yaml").read_text())
    topics = {t["topic_metadata"]["name"]: t["topic_metadata"] for t in meta["rosbag2_bagfile_information"]
              ["topics_with_message_count"]}
    qos = topics[fmt.TOPIC_BEAM_ON]["offered_qos_profiles"]
    assert "transient_local" in str(qos), qos
    probe = ros.node("probe")
    beam = []
    probe.create_subscription(Bool, fmt.TOPIC_BEAM_ON, lambda m: beam.append(m.data), LATCHED)
    got_frames = []
    probe.create_subscription(Image, fmt.TOPIC_PROJECTION, got_frames.append, STREAM)
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(tmp_path / "scan"), rate_hz=100.0, wait_for_subscribers=1)))
    assert ros.spin_until(lambda: node.done and len(got_frames) == N and beam and beam[-1] is False, timeout_s=20.0)
    assert beam[0] is True


def test_an_unwritable_output_dir_is_refused_at_start_when_a_job_will_write_there(ros, tmp_path):
    """Review N3: replay failed on an output_dir it cannot write only after republishing the whole bag; the node
    refuses it at start, as recon_service does, when it has a job (method) to run; without one it is not used."""
    import pytest

    bag = _bag(tmp_path)[0]
    (tmp_path / "a_file").write_text("not a folder")
    with pytest.raises(ValueError, match="parameter output_dir"):
        ReplayNode(context=ros.context, parameter_overrides=_params(
            bag_path=str(bag), rate_hz=100.0, method="none", output_dir=str(tmp_path / "a_file" / "out")))
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=0.0, output_dir=str(tmp_path / "a_file" / "out"))))
    assert node.done and node.error is None


def _with_extra_topics(bag, out, extra):
    """A copy of ``bag`` at ``out`` with ``extra`` [(topic, msgtype, offered QoS list, [CDR bytes, ...])] written
    just before its first message, as ``ros2 bag record -a`` records other nodes' topics."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    ts = fmt.typestore()
    with Reader(bag) as r, Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts,
                                           offered_qos_profiles=c.ext.offered_qos_profiles) for c in r.connections}
        first = True
        for c, t, d in r.messages():
            if first:
                for topic, msgtype, qos, datas in extra:
                    conn = w.add_connection(topic, msgtype, typestore=ts, offered_qos_profiles=qos)
                    for k, data in enumerate(datas):
                        w.write(conn, t - len(datas) + k, data)
                first = False
            w.write(conns[c.topic], t, d)
    return out


def _recorded_qos(depth: int, latched: bool, best_effort: bool = False):
    from rosbags.interfaces import QosReliability

    q = fmt._qos(depth, latched)
    return q._replace(reliability=QosReliability.BEST_EFFORT) if best_effort else q


def test_a_topic_recorded_transient_local_is_replayed_transient_local(ros, tmp_path):
    """Outside test E, finding 2: replay gave the recorded QoS only to the contract's topics and reliable volatile to
    every other one, so a /robot_description recorded transient-local (depth 1, as robot_state_publisher offers it)
    never reached a transient-local subscriber that came after the replay (late_tl.py: 0 messages; ``ros2 bag play``
    honours the bag's offered_qos_profiles). Now a late transient-local subscriber gets it."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    ts = fmt.typestore()
    desc = ts.serialize_cdr(ts.types[fmt.STRING](data="<robot name='ct'/>"), fmt.STRING)
    bag = _with_extra_topics(_bag(tmp_path)[0], tmp_path / "with_desc",
                             [("/robot_description", fmt.STRING, [_recorded_qos(1, True)], [desc])])
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(bag_path=str(bag), rate_hz=100.0)))
    assert ros.spin_until(lambda: node.done, timeout_s=20.0)
    probe = ros.node("late")
    got = []
    probe.create_subscription(String, "/robot_description", got.append,
                              QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                         durability=DurabilityPolicy.TRANSIENT_LOCAL))
    assert ros.spin_until(lambda: got, timeout_s=10.0), "a late transient-local subscriber got no /robot_description"
    assert got[0].data == "<robot name='ct'/>"
    infos = probe.get_publishers_info_by_topic("/robot_description")
    assert [i.qos_profile.durability for i in infos] == [DurabilityPolicy.TRANSIENT_LOCAL]


def test_replay_qos_follows_the_recorded_offers_outside_the_contract():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    from robot_ct_ros.nodes.replay import replay_qos

    tl, vol = _recorded_qos(1, True), _recorded_qos(10, False)
    q = replay_qos("/tf_static", [tl, tl, tl])  # three static broadcasters: a late subscriber gets all three
    assert (q.durability, q.reliability, q.history, q.depth) == (DurabilityPolicy.TRANSIENT_LOCAL,
                                                                 ReliabilityPolicy.RELIABLE, HistoryPolicy.KEEP_LAST, 3)
    q = replay_qos("/tf_static", [tl, vol])  # mixed offers: volatile, as ros2 bag play falls back to
    assert (q.durability, q.depth) == (DurabilityPolicy.VOLATILE, STREAM.depth)
    q = replay_qos("/scan", [_recorded_qos(5, False, best_effort=True)])
    assert (q.reliability, q.durability) == (ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE)
    assert replay_qos("/robot_description", []) == STREAM  # nothing recorded: as before
    assert replay_qos(fmt.TOPIC_BEAM_ON, [vol]) == LATCHED  # the contract's topics keep the contract's QoS
    assert replay_qos(fmt.TOPIC_PROJECTION, [_recorded_qos(5, False, best_effort=True)]) == STREAM


def test_the_recorded_graphs_log_and_parameter_events_are_not_republished(ros, tmp_path):
    """Outside test E, finding 3: replay put a bag's recorded /rosout and /parameter_events back into the live graph
    (rosout_check.py: 48 stale log lines and 1 foreign parameter event reached live tools). They are skipped by
    default (skip_topics), and the log says so; ``skip_topics: [""]`` republishes them."""
    from rcl_interfaces.msg import Log, ParameterEvent

    ts = fmt.typestore()
    log_t, pev_t = "rcl_interfaces/msg/Log", "rcl_interfaces/msg/ParameterEvent"
    logs = [ts.serialize_cdr(ts.types[log_t](stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=k),
                                             level=20, name="recorded_node", msg=f"line {k}", file="", function="",
                                             line=0), log_t) for k in range(3)]
    pev = ts.serialize_cdr(ts.types[pev_t](stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                           node="/recorded_node", new_parameters=[], changed_parameters=[],
                                           deleted_parameters=[]), pev_t)
    vol = _recorded_qos(10, False)
    bag = _with_extra_topics(_bag(tmp_path)[0], tmp_path / "with_log",
                             [("/rosout", log_t, [vol], logs), ("/parameter_events", pev_t, [vol], [pev])])
    probe = ros.node("probe")
    got = {"log": 0, "events": 0}
    probe.create_subscription(Log, "/rosout", lambda m: got.__setitem__(
        "log", got["log"] + (m.name == "recorded_node")), 100)
    probe.create_subscription(ParameterEvent, "/parameter_events", lambda m: got.__setitem__(
        "events", got["events"] + (m.node == "/recorded_node")), 100)
    frames = []
    probe.create_subscription(Image, fmt.TOPIC_PROJECTION, frames.append, STREAM)
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=100.0, wait_for_subscribers=1)))
    assert ros.spin_until(lambda: node.done and len(frames) == N, timeout_s=20.0)
    ros.spin_for(0.3)
    assert got == {"log": 0, "events": 0}
    assert node.skipped_topics == ["/parameter_events", "/rosout"]
    # the same bag with nothing skipped: the probe receives them (so the zeros above are the skipping's)
    ros.executor.remove_node(node)
    ros.nodes.remove(node)
    node.destroy_node()
    frames.clear()
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=100.0, wait_for_subscribers=1, skip_topics=[""])))
    assert node.skipped_topics == []
    assert ros.spin_until(lambda: node.done and len(frames) == N and got == {"log": 3, "events": 1},
                          timeout_s=20.0), got


def test_the_latched_topics_are_published_after_the_wait_for_subscribers(ros, tmp_path):
    """Outside test E, finding 8: replay published /ct/scan_info, the flat field and the dead pixels when it
    started, before waiting for wait_for_subscribers, where the docs say replay starts once /ct/projection has that
    many subscribers: a volatile /ct/scan_info subscriber in another process, which matched later, got nothing
    (qos_early.py: 0 on two bags of three); this one, in the same process, got it before the wait was over. Nothing
    is published before the wait ends now; the latched topics go just before the first frame, to publishers made
    at start, which the subscribers that came during the wait have matched."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    bag = _bag(tmp_path)[0]
    probe = ros.node("probe")
    volatile = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    info, frames = [], []
    probe.create_subscription(String, fmt.TOPIC_SCAN_INFO, info.append, volatile)
    probe.create_subscription(Image, fmt.TOPIC_PROJECTION, frames.append, STREAM)
    node = ros.add(ReplayNode(context=ros.context, parameter_overrides=_params(
        bag_path=str(bag), rate_hz=100.0, wait_for_subscribers=2)))
    assert ros.spin_until(lambda: node._pubs[fmt.TOPIC_SCAN_INFO].get_subscription_count() == 1, timeout_s=10.0)
    ros.spin_for(0.3)
    assert info == [] and frames == [] and node.published_frames == 0  # one subscriber of two: still waiting
    ros.node("probe2").create_subscription(Image, fmt.TOPIC_PROJECTION, lambda m: None, STREAM)
    assert ros.spin_until(lambda: node.done and len(frames) == N, timeout_s=20.0)
    ros.spin_for(0.2)
    assert len(info) == 1, "a volatile /ct/scan_info subscriber that came during the wait got nothing"
    assert json.loads(info[0].data)["n_rows"] == 8
