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
