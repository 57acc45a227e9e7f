"""The streaming driver: frames paired by the collector go to a worker process at a lower priority, and
each comes back with its live geometry, the running projection NCC and the running volume's slices."""

from __future__ import annotations

import os
import time

import numpy as np

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag import read_raw_messages, read_scan
from robot_ct_ros.bag.collector import ScanCollector
from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.jobs.simulate import simulate_bag
from robot_ct_ros.jobs.streaming import StreamingCorrector


def test_frames_stream_through_a_niced_worker_and_come_back_with_their_geometry(tmp_path):
    n = 8
    bag = simulate_bag(tmp_path / "scan", phantom="mouse", views=n, rows=16, cols=24, sigma_mm=0.05, sigma_deg=0.05,
                       seed=2, progress=False, say=lambda s: None)
    scan = read_scan(bag)
    collector = ScanCollector()
    stream = StreamingCorrector(CalibrationSettings(method="ncc-lle-exact"), warmup_views=3, nice=5)
    try:
        updates = []
        for m in read_raw_messages(bag).messages:  # as the node receives them, a message at a time
            if m.topic in fmt.LATCHED_TOPICS:
                collector.add_latched(m.topic, m.data)
            elif m.topic in (fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY):
                collector.add_frame_message(m.topic, m.data)
            for stamp, image, geometry in collector.take_new_pairs():
                stream.add_frame(stamp, image, geometry, collector.latched)
            updates += stream.poll()
        deadline = time.monotonic() + 120.0
        while stream.busy and time.monotonic() < deadline:
            stream.wait(timeout_s=max(0.0, deadline - time.monotonic()))
            updates += stream.poll()
        assert not stream.busy and not stream.error, stream.error
        stamps = np.concatenate([u.stamps_ns for u in updates])
        assert sorted(stamps.tolist()) == [int(s) for s in scan.stamps_ns]  # every frame, once
        assert updates[0].views >= 3 and updates[-1].views == n
        for u in updates:
            assert u.geom.n_views == len(u.stamps_ns) == len(u.ncc) == len(u.latency_s)
            assert set(u.slices) == {"axial", "sagittal", "coronal"} and all(s.ndim == 2 for s in u.slices.values())
        i = [int(s) for s in scan.stamps_ns].index(int(updates[-1].stamps_ns[-1]))
        # the live geometry is the frame's nominal one, moved by the estimate (within the prior's reach)
        assert np.abs(updates[-1].geom.source_mm[-1] - scan.geom.source_mm[i]).max() < 2.0
        summary = stream.summary()
        assert summary["views"] == n and summary["worker_nice"] == 5 and summary["latency_s_median"] > 0
        assert np.isfinite(summary["mean_projection_ncc"])
        assert summary["frames_received"] == n and "no live estimate" not in summary["note"]
        # the worker runs at a lower priority than this process
        assert os.getpriority(os.PRIO_PROCESS, stream.worker_pid) >= min(19, os.getpriority(os.PRIO_PROCESS, 0) + 5)
    finally:
        stream.close()


def test_frames_that_come_before_the_scan_info_wait_for_it(tmp_path):
    """An outside check: with three frames sent before /ct/scan_info, the worker decoded them without it ("no
    /ct/scan_info message") and every later batch failed the same way: nothing live for the whole scan. Frames now
    wait for the scan_info, and a latched message that comes later (the flat field) reaches the worker too."""
    n = 6
    bag = simulate_bag(tmp_path / "scan", phantom="mouse", views=n, rows=12, cols=16, sigma_mm=0.05, sigma_deg=0.05,
                       seed=2, progress=False, say=lambda s: None)
    messages = read_raw_messages(bag).messages
    latched_msgs = [m for m in messages if m.topic in fmt.LATCHED_TOPICS]
    collector = ScanCollector()
    stream = StreamingCorrector(CalibrationSettings(method="ncc-lle-exact"), warmup_views=3, nice=5)
    try:
        updates, fed = [], 0
        for m in messages:
            if m.topic in (fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY):
                collector.add_frame_message(m.topic, m.data)
            for stamp, image, geometry in collector.take_new_pairs():
                stream.add_frame(stamp, image, geometry, collector.latched)
                fed += 1
                if fed == 3:  # the latched messages only now, the flat field last
                    for lm in sorted(latched_msgs, key=lambda x: x.topic == fmt.TOPIC_FLAT_FIELD):
                        collector.add_latched(lm.topic, lm.data)
                        updates += stream.poll(collector.latched)
            updates += stream.poll(collector.latched)
        deadline = time.monotonic() + 120.0
        while stream.busy and time.monotonic() < deadline:
            stream.wait(timeout_s=max(0.0, deadline - time.monotonic()))
            updates += stream.poll(collector.latched)
        assert not stream.error, stream.error
        assert sum(len(u.stamps_ns) for u in updates) == n and stream.summary()["frames_dropped"] == 0
    finally:
        stream.close()


def test_the_collector_hands_each_pair_over_once_and_forgets_them_with_a_new_scan(tmp_path):
    bag = simulate_bag(tmp_path / "scan", phantom="mouse", views=4, rows=8, cols=12, progress=False, say=lambda s: None)
    msgs = read_raw_messages(bag).messages
    collector = ScanCollector()
    frames = [m for m in msgs if m.topic == fmt.TOPIC_PROJECTION]
    geoms = [m for m in msgs if m.topic == fmt.TOPIC_GEOMETRY]
    collector.add_frame_message(fmt.TOPIC_PROJECTION, frames[0].data)
    assert collector.take_new_pairs() == []  # no geometry yet
    collector.add_frame_message(fmt.TOPIC_GEOMETRY, geoms[0].data)
    collector.add_frame_message(fmt.TOPIC_GEOMETRY, geoms[0].data)  # a repeat pairs nothing new
    (pair,) = collector.take_new_pairs()
    assert pair[1] == frames[0].data and pair[2] == geoms[0].data and collector.take_new_pairs() == []
    # the repeat is dropped, and said (the bag written from the collection cannot show it)
    (warning,) = collector.warnings
    assert warning.startswith(f"1 {fmt.TOPIC_GEOMETRY} messages with a stamp already seen were dropped")
    collector.add_frame_message(fmt.TOPIC_GEOMETRY, geoms[1].data)
    collector.reset()
    assert collector.warnings == []
    collector.add_frame_message(fmt.TOPIC_PROJECTION, frames[1].data)
    assert collector.take_new_pairs() == []


def test_a_scan_shorter_than_the_warm_up_says_why_it_has_no_live_estimate():
    """Fewer frames than stream_warmup_views: no live estimate can exist, and the summary (report.json's live) once
    said nothing about why."""
    stream = StreamingCorrector(CalibrationSettings(method="ncc-lle-exact"), warmup_views=8, nice=5)
    try:
        for k in range(3):
            stream.add_frame(k, b"", b"", {})
        summary = stream.summary()
        assert summary["views"] == 0 and summary["frames_received"] == 3
        assert "no live estimate: the scan gave 3 frames, fewer than stream_warmup_views (8)" in summary["note"]
        stream.new_scan()
        assert stream.summary()["frames_received"] == 0
    finally:
        stream.close()


def _frames(tmp_path, views):
    """The latched messages (topic -> (type, bytes)) and the (stamp, image, geometry) frames of a small simulated scan,
    as the node hands them to the worker; and a function giving a frame's all-NaN twin."""
    bag = simulate_bag(tmp_path / "scan", phantom="mouse", views=views, rows=12, cols=16, sigma_mm=0.05,
                       sigma_deg=0.05, seed=3, progress=False, say=lambda s: None)
    latched, images, geoms = {}, {}, {}
    for m in read_raw_messages(bag).messages:
        if m.topic in fmt.LATCHED_TOPICS:
            latched[m.topic] = (m.msgtype, m.data)
        elif m.topic in (fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY):
            stamp = fmt.stamp_to_ns(fmt.deserialize(m.data, m.msgtype).header.stamp)
            (images if m.topic == fmt.TOPIC_PROJECTION else geoms)[stamp] = m.data
    frames = [(s, images[s], geoms[s]) for s in sorted(images)]

    def nan(frame):
        a = np.full((12, 16), np.nan, np.float32)
        return frame[0], fmt.serialize(fmt.image_from_array(a, frame[0]), fmt.IMAGE), frame[2]
    return latched, frames, nan


def _task(scan, latched, batch, warmup=4):
    from robot_ct_ros.jobs.streaming import _stream_task

    res = _stream_task(scan, latched, batch, {"settings": CalibrationSettings(method="ncc-lle-exact"),
                                              "warmup_views": warmup})
    if res["stamps"]:  # the stamps are those of the views estimated, in the geometry's order
        assert len(res["stamps"]) == res["geom"].n_views == len(res["ncc"])
    return res


def test_frames_the_worker_drops_during_the_warm_up_are_counted_and_the_warm_up_waits_for_usable_views(tmp_path):
    """From an outside check: the warm-up started after stream_warmup_views FRAMES, but the decoder drops an all-NaN
    frame and a repeated stamp, so the estimator got fewer views than its warm-up, returned nothing and the batch
    failed (AttributeError); later batches came back with stamps that did not match their geometries. Now the
    warm-up waits for enough usable views, the dropped frames are counted with their cause, and every usable frame
    comes back once with its own geometry."""
    latched, frames, nan = _frames(tmp_path, 10)
    stamps = [f[0] for f in frames]
    res = _task(901, latched, [frames[0], nan(frames[1]), frames[2], frames[0]])  # 4 frames, 2 usable
    assert res["stamps"] == [] and res["dropped"] == 2 and "NaN" in res["drop_reason"]
    res = _task(901, latched, [frames[3]])  # 3 usable views: still warming up
    assert res["stamps"] == [] and res["dropped"] == 2
    got = []
    for batch in ([frames[4], frames[5]], [frames[2]], frames[6:]):  # the warm-up; a stamp again, alone; the rest
        res = _task(901, latched, batch)
        got += res["stamps"]
    assert res["dropped"] == 3 and "already received" in res["drop_reason"]
    assert got == [s for i, s in enumerate(stamps) if i != 1] and res["views"] == 9


def test_an_unusable_frame_mid_stream_is_dropped_not_a_lasting_error(tmp_path):
    """From an outside check: one all-NaN frame alone in a batch after the warm-up made the decoder refuse the batch
    ("not a usable scan: 0 paired views"), and that error stayed on /diagnostics and in report.json until the scan
    ended. Now the frame is counted as dropped and the scan goes on."""
    latched, frames, nan = _frames(tmp_path, 7)
    assert len(_task(902, latched, frames[:4])["stamps"]) == 4
    res = _task(902, latched, [nan(frames[4])])
    assert res["stamps"] == [] and res["dropped"] == 1 and "NaN" in res["drop_reason"]
    res = _task(902, latched, frames[5:])
    assert res["stamps"] == [frames[5][0], frames[6][0]] and res["views"] == 6 and res["dropped"] == 1


def test_the_live_estimates_name_the_frame_of_the_scans_geometry(tmp_path):
    """Outside test 27 A #1: the live geometry (and slices) named "world" whatever frame the scan's /ct/geometry
    named; the worker now says which frame its estimates are in."""
    latched, frames, _ = _frames(tmp_path, 5)

    def in_lab(frame):
        msg = fmt.deserialize(frame[2], fmt.POSE_ARRAY)
        msg.header.frame_id = "lab"
        return frame[0], frame[1], fmt.serialize(msg, fmt.POSE_ARRAY)
    res = _task(903, latched, [in_lab(f) for f in frames])
    assert len(res["stamps"]) == 5 and res["frame_id"] == "lab"


def test_the_summary_counts_the_dropped_frames_and_keeps_no_error():
    """The worker's count of dropped frames reaches the summary (report.json's live, /diagnostics), with or without
    views in the batch; the batch without views is no error and no update."""
    from concurrent.futures import Future

    stream = StreamingCorrector(CalibrationSettings(method="ncc-lle-exact"), warmup_views=8, nice=5)
    try:
        assert stream.wait(120.0)
        stream.poll()  # the worker's warm-up
        for k in range(3):
            stream.add_frame(k, b"", b"", {})
        done = Future()
        done.set_result({"scan": stream.scan, "stamps": [], "dropped": 1, "drop_reason": "1 frames dropped: NaN",
                         "worker_s": 0.0})
        stream._future, stream._queue = done, []
        assert stream.poll() == []
        summary = stream.summary()
        assert summary["frames_dropped"] == 1 and summary["drop_reason"] == "1 frames dropped: NaN"
        assert not summary["error"]
        assert "the scan gave 2 usable frames (3 received, 1 dropped), fewer than stream_warmup_views" \
            in summary["note"]
        stream.new_scan()
        assert stream.summary()["frames_dropped"] == 0
    finally:
        stream.close()


def test_the_worker_gets_its_numba_threads_when_numba_was_imported_before_its_initializer():
    """A spawn worker imports the caller's main module (a node's executable) before its initializer, and with it
    numba, configured with the caller's thread count. The initializer only set NUMBA_NUM_THREADS: a kernel compiled
    afterwards (no numba cache yet, as on a fresh installation) found the count changed after the threads were
    launched, and every live batch failed (RuntimeError: Cannot set NUMBA_NUM_THREADS ...); with a cache the worker
    ran on the caller's threads. Here in a fresh interpreter, as such a worker."""
    import subprocess
    import sys

    code = ("import numba\n"
            "from robot_ct_ros.jobs.streaming import _init_worker\n"
            "_init_worker(0, 1)\n"
            "n = numba.get_num_threads()\n"  # launches the threads, as the projector does before its kernels
            "@numba.njit(parallel=True, cache=False)\n"
            "def f(a):\n"
            "    s = 0.0\n"
            "    for i in numba.prange(a.size):\n"
            "        s += a[i]\n"
            "    return s\n"
            "import numpy as np\n"
            "print(n, f(np.ones(4)))\n")
    env = dict(os.environ, NUMBA_NUM_THREADS="2")  # the caller's count, inherited
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-800:]
    assert out.stdout.split() == ["1", "4.0"]
