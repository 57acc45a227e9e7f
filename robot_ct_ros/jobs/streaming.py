"""Streaming online correction: the recon_service's live per-view estimation, in a worker process.

:class:`StreamingCorrector` takes the scan's frames as they are paired (the CDR bytes of the
projection and its geometry, plus the latched scan_info / flat field / dead pixels) and hands
them in batches to one worker process (``concurrent.futures.ProcessPoolExecutor``, ``spawn``
context, started at a lower OS priority with ``os.nice`` and its own numba thread count). The
worker decodes them (:func:`robot_ct_ros.bag.reader.scan_from_raw`; a frame with nothing usable in it
or a stamp already received is dropped and counted, never an error), holds the scan's
:class:`~robot_ct_ros.ct.calibration.streaming.StreamingEstimator` and returns each batch's
corrected geometry, the running projection NCC and the middle slices of the running volume.
The caller polls (:meth:`StreamingCorrector.poll`, non-blocking): it never waits on numba, and
a batch is whatever arrived while the previous one was estimated, so the worker never falls
behind by more than one batch. Nothing here changes the whole-scan correction
(robot_ct_ros.jobs.calibrate), which runs on the recorded scan afterwards as before.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import wait as _wait_futures
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np

from robot_ct_ros.bag.format import FRAME_WORLD, TOPIC_SCAN_INFO

__all__ = ["StreamingCorrector", "LiveUpdate", "mid_slices"]


def mid_slices(volume: np.ndarray) -> dict:
    """The middle slices of a volume ``[z, y, x]``: axial (y, x), coronal (z, x), sagittal (z, y)."""
    nz, ny, nx = volume.shape
    return {"axial": volume[nz // 2], "coronal": volume[:, ny // 2, :], "sagittal": volume[:, :, nx // 2]}


@dataclass(frozen=True)
class LiveUpdate:
    """One batch estimated by the worker: the frames' stamps, their corrected geometry (a
    ConeGeometry of those views), the projection NCC of each against the running volume (nan for
    the warm-up views), the running mean, the middle slices of the running volume (ROI, coarse
    level) and how long after its arrival here each frame's geometry came back (s); ``frame_id`` the world frame
    of the frames' /ct/geometry, which the estimates are in."""

    scan: int
    stamps_ns: np.ndarray
    geom: object
    ncc: np.ndarray
    mean_ncc: float
    views: int
    slices: dict
    latency_s: np.ndarray
    worker_s: float
    frame_id: str = FRAME_WORLD


# ------------------------------------------------------------------------------ worker process
_STATE: dict = {}


def _init_worker(nice: int, threads: int) -> None:
    """Worker initializer: lower priority, numba threads (before numba launches its threads here).

    A ``spawn`` worker imports the caller's main module before this runs (a pip-installed node executable, a
    script), and with it numba, whose configuration is then read without the worker's thread count: numba is
    told again (``reload_config``, ``set_num_threads``) before its first parallel call. Without that, a kernel
    compiled in the worker (a fresh installation, no cache) found the count changed after the threads were
    launched and every batch failed (RuntimeError: Cannot set NUMBA_NUM_THREADS ...), and with the kernels
    cached the worker ran on the caller's threads."""
    import sys

    if nice > 0:
        try:
            os.nice(int(nice))
        except OSError:
            pass
    if threads > 0:
        os.environ["NUMBA_NUM_THREADS"] = str(int(threads))
        numba = sys.modules.get("numba")
        if numba is not None:
            try:
                numba.config.reload_config()
            except RuntimeError:  # its threads run already (the caller's main module used them)
                pass
            # the pool numba launches keeps the size read at its import: the tasks (this thread's) use threads of it
            numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(k, "1")


def _warm(settings) -> int:
    """Import the science modules and run a tiny stream (6 views of 8 x 12 pixels) through them: numba's
    kernels are compiled or loaded from its cache while the scan starts, not with its first frames."""
    import robot_ct_ros.bag.reader  # noqa: F401
    from robot_ct_ros.ct.calibration.streaming import StreamingEstimator
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=6, n_rows=8, n_cols=12, fov_diameter_mm=0.6)
    grid = VolumeGrid.centered((6, 6, 6), 0.1)
    vol = np.zeros(grid.shape_zyx, np.float32)
    vol[2:4, 2:4, 1:5] = 1.0
    li = forward_project(vol, grid, geom).astype(np.float32)
    est = StreamingEstimator(settings, grid, geom.n_views, warmup_views=4)
    for i in range(geom.n_views):
        est.add_views(li[i:i + 1], np.ones((1,) + geom.det_shape, bool), geom.subset(np.array([i])), [i])
    return os.getpid()


def _decode(latched: dict, frames: list):
    from pathlib import Path

    from robot_ct_ros.bag import format as fmt
    from robot_ct_ros.bag.reader import RawBag, RawMessage, scan_from_raw

    msgs = [RawMessage(topic, msgtype, 0, data) for topic, (msgtype, data) in latched.items()]
    for stamp, image, geometry in frames:
        msgs.append(RawMessage(fmt.TOPIC_PROJECTION, fmt.IMAGE, int(stamp), image))
        msgs.append(RawMessage(fmt.TOPIC_GEOMETRY, fmt.POSE_ARRAY, int(stamp), geometry))
    return scan_from_raw(RawBag(Path("live"), msgs, [], False, "live"), "live", min_views=1)


def _stream_task(scan: int, latched, frames: list, options: dict) -> dict:
    """Estimate a batch of frames of scan ``scan`` (the worker keeps one scan's state).

    Each batch is decoded as it arrives: a frame the decoder drops (nothing usable in it: all NaN, no positive
    count; a stamp already seen, in this batch or an earlier one) is counted in ``dropped`` (the scan's total so far,
    ``drop_reason`` the last cause) and estimated never. The warm-up waits for ``warmup_views`` usable views, not
    frames; ``stamps`` are always those of the views in ``geom``, in its order (none while the warm-up collects)."""
    from dataclasses import replace

    from robot_ct_ros.bag.format import TooFewViewsError
    from robot_ct_ros.ct.calibration.streaming import StreamingEstimator
    from robot_ct_ros.ct.geometry import ConeGeometry
    from robot_ct_ros.ct.reconstruction import resample
    from robot_ct_ros.jobs.calibrate import scan_grid

    t0 = time.perf_counter()
    st = _STATE
    if st.get("scan") != scan:
        st.clear()
        st.update(scan=scan, latched=latched, buffer=[], estimator=None, next_id=0, seen=set(), stamp_of={},
                  dropped=0, drop_reason="")
    elif latched is not None:  # the scan's latched messages, more of them than before
        st["latched"] = latched
    fresh = [f for f in frames if int(f[0]) not in st["seen"]]
    notes = []
    if len(fresh) < len(frames):
        notes.append(f"{len(frames) - len(fresh)} frame(s) with a stamp already received were dropped (the first one "
                     "is used; header.stamp is the pairing key and must differ from frame to frame)")
    data = None
    if fresh:
        try:
            data = _decode(st["latched"], fresh)
        except TooFewViewsError as exc:  # none of these frames is usable: dropped, the scan goes on
            notes += [c for c in exc.causes if "geometries" not in c] or [str(exc)]
    used = 0 if data is None else data.n_views
    if data is not None:
        notes += [w for w in data.warnings if ("dropped" in w or "not used" in w) and "geometries" not in w]
        st["seen"].update(int(s) for s in data.stamps_ns)
    if used < len(frames):
        st["dropped"] += len(frames) - used
        st["drop_reason"] = "; ".join(notes)
    out = {"scan": scan, "stamps": [], "dropped": st["dropped"], "drop_reason": st["drop_reason"]}
    if data is None:
        return out | {"worker_s": time.perf_counter() - t0}
    li, mask = data.to_line_integrals()
    geom = data.geom
    ids = np.arange(st["next_id"], st["next_id"] + used)
    st["next_id"] += used
    st["stamp_of"].update(zip(ids.tolist(), (int(s) for s in data.stamps_ns)))
    est = st["estimator"]
    if est is None:  # the warm-up: the first warmup_views usable views make the first volume
        st["buffer"].append((geom, li, mask, ids))
        if sum(len(p[3]) for p in st["buffer"]) < options["warmup_views"]:
            return out | {"worker_s": time.perf_counter() - t0}
        parts, st["buffer"] = st["buffer"], []
        geom = ConeGeometry.concatenate([p[0] for p in parts])
        li, mask, ids = (np.concatenate([p[j] for p in parts]) for j in (1, 2, 3))
        grid = scan_grid(replace(data, geom=geom), options.get("voxel_mm"), options.get("shape_xyz"))
        n = data.info.get("n_views")
        est = st["estimator"] = StreamingEstimator(options["settings"], grid, n if isinstance(n, int) and n > 0
                                                   else options.get("n_views_default", 360),
                                                   warmup_views=options["warmup_views"])
    step = est.add_views(li, mask, geom, ids)
    if step is None:
        return out | {"worker_s": time.perf_counter() - t0}
    stamps = [st["stamp_of"].pop(int(i)) for i in step.view_ids]  # the views of step.geom, in its order
    roi = est.roi_grid.binned(est.binning) if est.binning > 1 else est.roi_grid
    preview = resample(est.volume, est.grid, roi)
    slices = {k: np.ascontiguousarray(v, np.float32) for k, v in mid_slices(preview).items()}
    return out | {"stamps": stamps, "geom": step.geom, "ncc": step.ncc, "mean_ncc": step.mean_ncc,
                  "views": est.n_estimated, "slices": slices, "worker_s": time.perf_counter() - t0,
                  "frame_id": data.frame_id}


# ------------------------------------------------------------------------------ the caller's side
@dataclass
class StreamingCorrector:
    """Live per-view correction in one worker process (see the module docstring).

    ``settings``: the CalibrationSettings (method, schedule, prior, seed, padding); ``warmup_views``
    usable frames make the first volume (``dropped`` counts those the worker could not use); ``nice``:
    the worker's niceness increment (0: the caller's priority); ``threads``: its numba threads (0:
    numba's default, every core; one thread slowed the simulated scan less, docs/calibration.md §13a);
    ``voxel_mm`` / ``shape_xyz``: the ROI grid's overrides (as the whole-scan job's).
    """

    settings: object
    warmup_views: int = 8
    nice: int = 10
    threads: int = 1
    voxel_mm: object = None
    shape_xyz: object = None
    context: str = "spawn"
    scan: int = 1
    error: str = ""
    latencies: list = field(default_factory=list)
    ncc: list = field(default_factory=list)
    views: int = 0
    mean_ncc: float = float("nan")
    received: int = 0  # frames handed in for this scan
    dropped: int = 0  # of them, frames the worker could not use (nothing usable in them, a stamp already received)
    drop_reason: str = ""  # why the last of them were dropped

    def __post_init__(self):
        self._pool = ProcessPoolExecutor(1, mp_context=get_context(self.context), initializer=_init_worker,
                                         initargs=(int(self.nice), int(self.threads)))
        self._future = self._pool.submit(_warm, self.settings)  # spawns the worker now, while the scan starts
        self._warming = True
        self._queue: list = []
        self._arrived: dict = {}
        self._latched_sent = 0
        self._latched = None
        self.worker_pid = None

    @property
    def options(self) -> dict:
        return {"settings": self.settings, "warmup_views": int(self.warmup_views), "voxel_mm": self.voxel_mm,
                "shape_xyz": self.shape_xyz}

    def new_scan(self) -> None:
        """A new scan started: forget the frames queued and the figures."""
        self.scan += 1
        self._queue.clear()
        self._arrived.clear()
        self.latencies, self.ncc, self.views, self.mean_ncc, self.error = [], [], 0, float("nan"), ""
        self.received, self.dropped, self.drop_reason = 0, 0, ""

    def add_frame(self, stamp_ns: int, image: bytes, geometry: bytes, latched: dict) -> None:
        """A frame paired with its geometry (CDR bytes), with the scan's latched messages as held now
        (topic -> (type, bytes)): queued for the next batch."""
        self._queue.append((int(stamp_ns), bytes(image), bytes(geometry)))
        self.received += 1
        self._arrived[int(stamp_ns)] = time.monotonic()
        self._latched = dict(latched)

    @property
    def busy(self) -> bool:
        """A batch is being estimated, or frames wait for one."""
        return self._future is not None or bool(self._queue)

    def wait(self, timeout_s: float) -> bool:
        """Wait at most ``timeout_s`` for the batch in flight (poll afterwards); True when none is left
        in flight. For tests and batch drivers: a node polls from its timer instead."""
        if self._future is not None:
            _wait_futures([self._future], timeout=timeout_s)
        return self._future is None or self._future.done()

    def poll(self, latched: dict | None = None) -> list:
        """Collect the finished batch (a list of at most one :class:`LiveUpdate`) and hand the frames
        queued since to the worker. Never blocks. ``latched``: the scan's latched messages as held now, where
        some may have come after the last frame (frames wait for /ct/scan_info)."""
        if latched is not None and self._queue:
            self._latched = dict(latched)
        out = []
        if self._future is not None and self._future.done():
            fut, self._future = self._future, None
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 - reported; the scan goes on
                if not self._warming:
                    self.error = f"{type(exc).__name__}: {exc}"
                res = None
            if self._warming:  # a failed warm-up only means the first batch compiles
                self._warming, self.worker_pid, res = False, res, None
            if res is not None and res["scan"] == self.scan:
                self.dropped, self.drop_reason = int(res.get("dropped", 0)), str(res.get("drop_reason", ""))
            if res is not None and res["scan"] == self.scan and res["stamps"] \
                    and len(res["stamps"]) != res["geom"].n_views:  # never published with the wrong stamps
                self.error = f"live: {len(res['stamps'])} stamps for {res['geom'].n_views} views; the batch is dropped"
            elif res is not None and res["scan"] == self.scan and res["stamps"]:
                now = time.monotonic()
                stamps = np.asarray(res["stamps"], np.int64)
                lat = np.array([now - self._arrived.pop(int(s), now) for s in stamps])
                self.latencies.extend(lat.tolist())
                self.ncc.extend(np.asarray(res["ncc"], float).tolist())
                self.views, self.mean_ncc = int(res["views"]), float(res["mean_ncc"])
                out.append(LiveUpdate(res["scan"], stamps, res["geom"], np.asarray(res["ncc"], float),
                                      float(res["mean_ncc"]), int(res["views"]), res["slices"], lat,
                                      float(res["worker_s"]), str(res.get("frame_id", FRAME_WORLD))))
        # frames wait for the scan's /ct/scan_info (a frame may come first): decoded without it, every frame of the
        # scan failed; the latched messages go again whenever one more has arrived (a late flat field)
        if self._future is None and self._queue and TOPIC_SCAN_INFO in (self._latched or {}):
            frames, self._queue = self._queue, []
            latched, sent = None, (self.scan, tuple(sorted(self._latched)))
            if self._latched_sent != sent:
                latched, self._latched_sent = self._latched, sent
            try:
                self._future = self._pool.submit(_stream_task, self.scan, latched, frames, self.options)
            except RuntimeError as exc:  # the worker died (BrokenProcessPool) or the pool is shut down
                self.error = self.error or f"{type(exc).__name__}: {exc}"
        return out

    def summary(self) -> dict:
        """The live figures of the scan so far (report.json's ``live``)."""
        lat = np.asarray(self.latencies, float)
        return {"views": self.views, "mean_projection_ncc": None if not np.isfinite(self.mean_ncc) else self.mean_ncc,
                "latency_s_median": float(np.median(lat)) if lat.size else None,
                "latency_s_max": float(lat.max()) if lat.size else None, "worker_nice": int(self.nice),
                "warmup_views": int(self.warmup_views), "error": self.error, "frames_received": int(self.received),
                "frames_dropped": int(self.dropped), "drop_reason": self.drop_reason,
                "note": (f"no live estimate: the scan gave {self.received - self.dropped} "
                         f"{'usable ' if self.dropped else ''}frames"
                         + (f" ({self.received} received, {self.dropped} dropped)" if self.dropped else "")
                         + f", fewer than stream_warmup_views ({self.warmup_views}), the views the first running "
                           "volume is made of; "
                         if self.views == 0 and self.received - self.dropped < self.warmup_views else "")
                        + "per-view estimates against the running volume (coarse level); the final correction is "
                          "the whole-scan run"}

    def close(self) -> None:
        """Stop the worker: queued frames are dropped, the batch in progress ends first."""
        self._queue.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)
