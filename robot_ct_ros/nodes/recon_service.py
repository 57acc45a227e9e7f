"""recon_service: reconstruction and data-driven geometry correction of a scan, as a service with progress.

Topics and services (contract names from robot_ct_ros.bag.format; relative names follow the node namespace):
  subscribes  /ct/scan_info, /ct/flat_field, /ct/dead_pixels (transient-local), /ct/projection,
              /ct/geometry, /ct/geometry_true (reliable): the scan, kept as received (CDR bytes);
              a /ct/scan_info different from the current one starts a new scan (the collection is reset);
              scan/status (std_msgs/String JSON of the scan_orchestrator): with auto_run, state "done"
              starts the correction once every frame of the scan has arrived (at most 5 s later)
  services    recon/run (std_srvs/Trigger): start the correction of what has been collected (or of
              bag_path); answers at once (the job runs on a worker thread, the executor keeps spinning)
  publishes   recon/progress (std_msgs/String JSON {"state", "stage", "message", "run", "n_views",
              "elapsed_s"}: one per step), /ct/geometry_corrected (geometry_msgs/PoseArray per frame,
              the frame's stamp, reliable), recon/slice_axial, recon/slice_sagittal, recon/slice_coronal
              (sensor_msgs/Image 32FC1, the middle slices of the volume, transient-local),
              recon/report (std_msgs/String JSON, transient-local: where the results are and the
              figures), /diagnostics (1 Hz)
Parameters (config/recon_service.yaml): method (a calibration method of robot_ct_ros.ct.calibration,
or "fdk" for no correction), iterations (at most), stop_update_px (stop earlier when an iteration moves the
views less than this, px), schedule (accurate or fast, calibration.SCHEDULES), drift_order (-1 = off:
independent per-view errors; a degree, e.g. 3: the geometry drifts slowly, calibration.fit_drift),
prior_sigma_translation_m and prior_sigma_rotation_rad (the robots' per-view coordination error, the
prior of the calibration's MAP estimate; 0 = the data alone), seed (the LLE methods' sampling seed:
another seed, another estimate of the same scan), ensemble (average that many runs with different
seeds: calibration.calibrate_ensemble), voxel_size_m (0: scan_info's, else pitch / magnification),
roi_shape ([nx, ny, nz] voxels; zeros: scan_info's ROI or the field of view), output_dir, auto_run,
every_n_views (0 = off: also correct every N frames during the scan, into output_dir/partial_NNNN),
bag_path ("" = the collected topics), evaluate_truth (simulated scans: error of the nominal and the
corrected geometry against /ct/geometry_true, SSIM of the reconstructions against the true-geometry one).

every_n_views: while the scan runs (until scan/status says done or aborted, or a whole-scan run
starts), every N paired frames start a partial run on the frames so far, into
``<output_dir>/partial_NNNN`` (NNNN = its frame count), unless a run is still busy (then the next
multiple of N counts); a partial run publishes progress, slices and recon/report ("partial": true), but
not /ct/geometry_corrected, which carries the whole-scan correction only. The whole-scan run (auto_run)
starts when the partial run in progress ends. Runs, partial ones included, execute on one worker
thread in this process, not a child process: the numba kernels hold the GIL, but each call is short
and the scan's executor kept serving (measured on 2 cores with graph.run_scan_graph, 36 views, 136 x 318
detector, a 63 s partial run of 12 views during the scan: largest gap between arm in_position reports at
the orchestrator 0.17 s, at scan start, against the 1 s arm report timeout; the scan went on at ~80 % speed).

A run writes the scan as received into ``<output_dir>/scan`` (a scan bag), then does what
``robot-ct calibrate`` does (robot_ct_ros.cli.calibrate_bag): ``scan_corrected`` (the bag plus
/ct/geometry_corrected), ``volume.npy``/``.tif``/``_grid.json``, ``report.json``; this node adds
the figures below to ``report.json`` and writes ``report.md``. Calibration is deterministic, so
``robot-ct calibrate`` of the recorder's bag with the same method, iterations and grid gives the
same corrected geometry.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.nodes.common import declare_drift_order, declare_prior_sigma, declare_sampling, run_node
from robot_ct_ros.nodes.recorder import message_class

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
STATUS = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
PER_FRAME = (fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY, fmt.TOPIC_GEOMETRY_TRUE)
SLICES = ("axial", "sagittal", "coronal")
PUBLISH_BATCH = 10  # corrected geometries per 50 ms tick: subscribers keep up, their depth-100 history never overflows


def _json_default(o):
    from robot_ct_ros.cli import _json_default as d
    return d(o)


# ------------------------------------------------------------------------------ the job (no ROS)
def mid_slices(volume: np.ndarray) -> dict:
    """The middle slices of a volume ``[z, y, x]``: axial (y, x), coronal (z, x), sagittal (z, y)."""
    nz, ny, nx = volume.shape
    return {"axial": volume[nz // 2], "coronal": volume[:, ny // 2, :], "sagittal": volume[:, :, nx // 2]}


def truth_metrics(bag, geom_corrected, volume_corrected, grid) -> dict | None:
    """Figures against the true geometry of a simulated scan (None without /ct/geometry_true).

    Gauge-aligned reprojection error (pixels) of the nominal and of the corrected geometry
    against /ct/geometry_true on points filling the ROI, and SSIM of the nominal and the
    corrected reconstruction against the reconstruction with the true geometry (same grid,
    same FDK).
    """
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.metrics import reprojection_error, roi_points, ssim
    from robot_ct_ros.ct.reconstruction import fdk

    scan = read_scan(bag)
    if scan.geom_true is None:
        return None
    pts = roi_points(grid)
    out = {}
    for name, g in (("nominal", scan.geom), ("corrected", geom_corrected)):
        e = reprojection_error(g, scan.geom_true, pts)
        out[f"reprojection_error_{name}_px"] = {"mean": e["mean_px"], "p95": e["p95_px"], "max": e["max_px"]}
    li, mask = scan.to_line_integrals()
    ref = fdk(li, scan.geom_true, grid, valid_mask=mask)
    nominal = fdk(li, scan.geom, grid, valid_mask=mask)
    rng = float(ref.max() - ref.min())
    out["ssim_nominal"] = ssim(nominal, ref, data_range=rng)
    out["ssim_corrected"] = ssim(np.asarray(volume_corrected, np.float32), ref, data_range=rng)
    out["note"] = ("reprojection error: pixels, ROI points, best global rigid motion removed; "
                   "SSIM against the FDK with /ct/geometry_true on the same grid")
    return out


def markdown_report(report: dict) -> str:
    lines = [f"# Reconstruction report: {report.get('scan_id') or report.get('bag')}", "",
             f"- views: {report.get('n_views')}, detector {report.get('detector')}",
             f"- method: {report.get('method_used', report.get('method'))}, "
             + (f"{report['iterations_run']} of " if "iterations_run" in report else "")
             + f"{report.get('iterations')} iteration(s), "
             f"{report.get('wall_s', 0.0):.1f} s",
             f"- grid: {report.get('grid', {}).get('shape_zyx')} voxels (z, y, x) of "
             f"{[round(float(v) * 1000, 2) for v in report.get('grid', {}).get('voxel_size_mm', [])]} um",
             f"- correction applied: {report.get('correction_rms_translation_mm', 0.0):.4f} mm RMS translation, "
             f"{report.get('correction_rms_rotation_deg', 0.0):.4f} deg RMS rotation"]
    if report.get("ensemble_spread_px") is not None:
        lines.append(f"- ensemble: the mean of {report['ensemble']} runs with different sampling seeds, which lie "
                     f"{report['ensemble_spread_px']:.3f} px from it (the estimate's sampling noise)")
    last, prior = (report.get("history") or [{}])[-1], report.get("prior_sigma")
    if last.get("independent_fraction") is not None and prior:
        lines.append(f"- last iteration: projection NCC {last['projection_ncc']:.4f}; independent pixels "
                     f"{last['independent_fraction']:.3f} (near 0: the data explain little of the projections and "
                     f"the correction leans on the prior of {prior[0]:.3g} mm / {np.rad2deg(prior[6]):.3g} deg)")
    t = report.get("truth")
    if t:
        n, c = t["reprojection_error_nominal_px"], t["reprojection_error_corrected_px"]
        lines += ["", "## Against the true geometry (simulation)", "",
                  "| | nominal | corrected |", "| --- | --- | --- |",
                  f"| reprojection error, mean (px) | {n['mean']:.3f} | {c['mean']:.3f} |",
                  f"| reprojection error, p95 (px) | {n['p95']:.3f} | {c['p95']:.3f} |",
                  f"| SSIM vs true-geometry reconstruction | {t['ssim_nominal']:.4f} | {t['ssim_corrected']:.4f} |",
                  "", t["note"]]
    lines += ["", "## Files", ""] + [f"- {k}: `{v}`" for k, v in report.get("paths", {}).items()]
    return "\n".join(lines) + "\n"


def run_correction(bag, out, *, method: str, iterations: int, voxel_mm=None, shape=None, evaluate_truth=True,
                   schedule: str = "accurate", prior_sigma="default", stop_update_px: float | None = None,
                   drift_order: int | None = None, seed: int = 0, ensemble: int = 1, say=print) -> dict:
    """``robot-ct calibrate`` of ``bag`` into ``out`` (cli.calibrate_bag), then the figures of this node.

    Returns the report (also in ``out/report.json`` and ``out/report.md``) with ``paths``, and the
    corrected geometry and volume under the private keys ``_geom``, ``_stamps``, ``_volume``, ``_grid``.
    """
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.cli import calibrate_bag
    from robot_ct_ros.ct.geometry import VolumeGrid

    out = Path(out)
    report = calibrate_bag(bag, out, method=method, iterations=iterations, voxel_mm=voxel_mm, shape=shape,
                           schedule=schedule, prior_sigma=prior_sigma, stop_update_px=stop_update_px,
                           drift_order=drift_order, seed=seed, ensemble=ensemble, say=say)
    corrected = read_scan(report["corrected_bag"])
    geom = corrected.geom_corrected if corrected.geom_corrected is not None else corrected.geom
    volume = np.load(out / "volume.npy")
    grid = VolumeGrid.from_dict(report["grid"])
    if evaluate_truth:
        say("comparing with the true geometry")
        report["truth"] = truth_metrics(bag, geom, volume, grid)
    report["paths"] = {"input_bag": str(bag), "corrected_bag": report["corrected_bag"],
                       "volume_npy": str(out / "volume.npy"), "volume_tif": str(out / "volume.tif"),
                       "report_json": str(out / "report.json"), "report_md": str(out / "report.md")}
    (out / "report.json").write_text(json.dumps(report, indent=2, default=_json_default))
    (out / "report.md").write_text(markdown_report(report))
    report.update({"_geom": geom, "_stamps": corrected.stamps_ns, "_volume": volume, "_grid": grid})
    return report


# ------------------------------------------------------------------------------ node
class ReconServiceNode(Node):
    def __init__(self, node_name: str = "recon_service", **kwargs):
        super().__init__(node_name, **kwargs)
        p = self.declare_parameter
        self.method = p("method", "ncc-lle-exact").value
        self.iterations = int(p("iterations", 2).value)
        self.stop_update_px = float(p("stop_update_px", 0.05).value)
        self.schedule = p("schedule", "accurate").value
        self.prior_sigma = declare_prior_sigma(self)
        self.drift_order = declare_drift_order(self)
        self.seed, self.ensemble = declare_sampling(self)
        voxel = float(p("voxel_size_m", 0.0).value)
        self.voxel_mm = voxel * 1e3 if voxel > 0 else None
        shape = [int(x) for x in p("roi_shape", [0, 0, 0]).value]
        self.shape = tuple(shape) if len(shape) == 3 and min(shape) > 0 else None
        self.output_dir = Path(p("output_dir", "recon_out").value)
        self.auto_run = bool(p("auto_run", True).value)
        self.every_n_views = int(p("every_n_views", 0).value)
        self.bag_path = p("bag_path", "").value
        self.evaluate_truth = bool(p("evaluate_truth", True).value)

        # collected scan: latched messages and per-frame messages by stamp, as CDR bytes
        self._latched: dict[str, tuple[str, bytes]] = {}
        self._per_frame: dict[str, dict[int, bytes]] = {t: {} for t in PER_FRAME}
        self.scan_id = ""
        for topic in fmt.LATCHED_TOPICS:
            self.create_subscription(message_class(fmt.TOPIC_TYPES[topic]), topic,
                                     lambda d, t=topic: self._on_latched(t, d), LATCHED, raw=True)
        for topic in PER_FRAME:
            self.create_subscription(message_class(fmt.TOPIC_TYPES[topic]), topic,
                                     lambda d, t=topic: self._on_per_frame(t, d), STREAM, raw=True)
        self.create_subscription(String, "scan/status", self._on_status, STATUS)

        self.progress_pub = self.create_publisher(String, "recon/progress", 50)
        self.report_pub = self.create_publisher(String, "recon/report", LATCHED)
        self.corrected_pub = self.create_publisher(PoseArray, fmt.TOPIC_GEOMETRY_CORRECTED, STREAM)
        self.slice_pubs = {k: self.create_publisher(Image, f"recon/slice_{k}", LATCHED) for k in SLICES}
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, 10)
        self.create_service(Trigger, "recon/run", self._on_run)

        self.state = "idle"          # idle | running | done | failed
        self.message = "waiting for a scan"
        self.runs = 0
        self.full_runs = 0           # runs on the whole scan (not partial), started
        self.partial_runs = 0        # every_n_views runs, started
        self.run_partial = False     # whether the current (or last) run is a partial one
        self.partial_reports: list[dict] = []  # reports of finished partial runs
        self.report: dict | None = None   # last finished run's report (public part)
        self.error = ""
        self.corrected_published = 0
        self._worker: threading.Thread | None = None
        self._result = None
        self._lock = threading.Lock()
        self._done_gc = self.create_guard_condition(self._on_job_done)
        self._to_publish: list[bytes] = []
        self._auto_pending: tuple[str, int, float] | None = None  # (scan_id, frames, deadline)
        self._auto_done: set[str] = set()
        self._scans_over: set[str] = set()  # scan ids scan/status reported done or aborted
        self._full_run_started = False      # a whole-scan run of this collection started: no more partial runs
        self._next_partial = self.every_n_views
        self._t_run = 0.0
        self.create_timer(0.05, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"recon_service: method {self.method}, {self.iterations} iteration(s), "
                               f"output {self.output_dir}/, auto_run {self.auto_run}")

    # -- collection ------------------------------------------------------------------------------
    def _on_latched(self, topic: str, data: bytes) -> None:
        data = bytes(data)
        old = self._latched.get(topic)
        if topic == fmt.TOPIC_SCAN_INFO and old is not None and old[1] != data:
            self._reset("a new scan_info: new scan")
        self._latched[topic] = (fmt.TOPIC_TYPES[topic], data)
        if topic == fmt.TOPIC_SCAN_INFO:
            try:
                info = json.loads(fmt.deserialize(data, fmt.STRING).data)
                self.scan_id = str((info.get("notes") or {}).get("scan_id", "")) if isinstance(info, dict) else ""
            except (ValueError, AttributeError):
                self.scan_id = ""

    def _on_per_frame(self, topic: str, data: bytes) -> None:
        data = bytes(data)
        try:
            stamp = fmt.stamp_to_ns(fmt.deserialize(data, fmt.TOPIC_TYPES[topic]).header.stamp)
        except Exception:  # noqa: BLE001 - a damaged message is not collected
            self.get_logger().warning(f"undecodable message on {topic} ignored", once=True)
            return
        self._per_frame[topic].setdefault(stamp, data)

    def _reset(self, why: str) -> None:
        self.get_logger().info(f"collection reset: {why}")
        for d in self._per_frame.values():
            d.clear()
        self._next_partial = self.every_n_views
        self._full_run_started = False

    @property
    def n_paired(self) -> int:
        return len(set(self._per_frame[fmt.TOPIC_PROJECTION]) & set(self._per_frame[fmt.TOPIC_GEOMETRY]))

    def _on_status(self, msg: String) -> None:
        try:
            status = json.loads(msg.data)
        except ValueError:
            return
        sid = str(status.get("scan_id", ""))
        if status.get("state") in ("done", "aborted"):
            self._scans_over.add(sid)  # no partial run after the scan: the whole-scan run follows
        if not self.auto_run or status.get("state") != "done":
            return
        if sid in self._auto_done or (self._auto_pending and self._auto_pending[0] == sid):
            return
        self._auto_pending = (sid, int(status.get("frames", 0)), time.monotonic() + 5.0)

    def _tick(self) -> None:
        # publish corrected geometries in batches
        if self._to_publish:
            batch, self._to_publish = self._to_publish[:PUBLISH_BATCH], self._to_publish[PUBLISH_BATCH:]
            for data in batch:
                self.corrected_pub.publish(data)
                self.corrected_published += 1
        if self.running:
            return
        if self._auto_pending is not None:
            sid, frames, deadline = self._auto_pending
            if self.n_paired >= frames or time.monotonic() > deadline:
                self._auto_pending = None
                self._auto_done.add(sid)
                if self.n_paired == 0 and not self.bag_path:
                    self.get_logger().info(f"scan {sid} done but no frame was collected here; nothing to correct")
                    return
                ok, why = self.start_run()
                if not ok:
                    self.get_logger().error(f"automatic correction not started: {why}")
            return
        if (self.every_n_views > 0 and self.n_paired >= self._next_partial and not self._full_run_started
                and self.scan_id not in self._scans_over):
            n = self.n_paired
            self._next_partial = (n // self.every_n_views + 1) * self.every_n_views
            self.start_run(partial=True)

    # -- runs ---------------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def _on_run(self, request, response):
        response.success, response.message = self.start_run()
        return response

    def _snapshot(self, path: Path) -> tuple[Path, int]:
        """Write the collected scan (paired frames only) into a new scan bag at ``path``."""
        from robot_ct_ros.bag import ScanBagWriter

        if fmt.TOPIC_SCAN_INFO not in self._latched:
            raise ValueError("no /ct/scan_info received yet")
        frames, geoms = self._per_frame[fmt.TOPIC_PROJECTION], self._per_frame[fmt.TOPIC_GEOMETRY]
        true = self._per_frame[fmt.TOPIC_GEOMETRY_TRUE]
        stamps = sorted(set(frames) & set(geoms))
        if not stamps:
            raise ValueError(f"no frame paired with a geometry yet ({len(frames)} frames, {len(geoms)} geometries)")
        if path.exists():
            shutil.rmtree(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        t0 = stamps[0] - 1_000_000
        with ScanBagWriter(path, None, flush_every_frame=False) as w:
            for topic in fmt.LATCHED_TOPICS:  # scan_info first
                if topic in self._latched:
                    w.write_raw(topic, *self._latched[topic], t0)
            for s in stamps:
                w.write_raw(fmt.TOPIC_PROJECTION, fmt.IMAGE, frames[s], s)
                w.write_raw(fmt.TOPIC_GEOMETRY, fmt.POSE_ARRAY, geoms[s], s)
                if s in true:
                    w.write_raw(fmt.TOPIC_GEOMETRY_TRUE, fmt.POSE_ARRAY, true[s], s)
        return path, len(stamps)

    def start_run(self, partial: bool = False) -> tuple[bool, str]:
        """Start a correction run on a worker thread; (started, message)."""
        if self.running:
            return False, f"a run is in progress ({self.message})"
        run = self.runs + 1
        try:
            if self.bag_path and not partial:
                out, bag, n = self.output_dir, Path(self.bag_path), None
            else:
                n = self.n_paired
                out = self.output_dir / f"partial_{n:04d}" if partial else self.output_dir
                bag, n = self._snapshot(out / "scan")
        except (ValueError, OSError) as exc:
            return False, f"cannot run: {exc}"
        self.runs = run
        self.run_partial = partial
        if partial:
            self.partial_runs += 1
        else:
            self.full_runs += 1
            self._full_run_started = True
        self.state, self.error, self._t_run = "running", "", time.monotonic()
        self.message = f"run {run}: {n if n is not None else 'bag'} views, {self.method}"
        self._progress("start", self.message, run, n)
        self._worker = threading.Thread(target=self._job, args=(run, bag, out, n, partial), name="recon", daemon=True)
        self._worker.start()
        return True, f"started run {run} on {bag} ({n if n is not None else '?'} views) into {out}"

    def _progress(self, stage: str, message: str, run: int, n) -> None:
        self.message = message
        data = {"state": self.state, "stage": stage, "message": message, "run": run, "n_views": n,
                "elapsed_s": round(time.monotonic() - self._t_run, 3)}
        try:
            self.progress_pub.publish(String(data=json.dumps(data)))
        except Exception:  # noqa: BLE001 - shutting down
            pass

    def _job(self, run: int, bag: Path, out: Path, n, partial: bool) -> None:
        log = self.get_logger()

        def say(line: str) -> None:
            log.info(line)
            self._progress("calibrate", line, run, n)
        try:
            report = run_correction(bag, out, method=self.method, iterations=self.iterations, voxel_mm=self.voxel_mm,
                                    shape=self.shape, schedule=self.schedule, prior_sigma=self.prior_sigma,
                                    stop_update_px=self.stop_update_px, drift_order=self.drift_order,
                                    seed=self.seed, ensemble=self.ensemble, evaluate_truth=self.evaluate_truth,
                                    say=say)
            report["partial"] = partial
            report["scan_id"] = self.scan_id
            result = (run, report, None)
        except Exception as exc:  # noqa: BLE001 - reported; the node keeps serving
            result = (run, None, f"{type(exc).__name__}: {exc}")
        with self._lock:
            self._result = result
        try:
            self._done_gc.trigger()
        except Exception:  # noqa: BLE001 - node destroyed meanwhile
            pass

    def _on_job_done(self) -> None:
        with self._lock:
            result, self._result = self._result, None
        if result is None:
            return
        run, report, error = result
        if error is not None:
            self.state, self.error = "failed", error
            self.get_logger().error(f"run {run} failed: {error}")
            self._progress("failed", error, run, None)
            self.report_pub.publish(String(data=json.dumps({"run": run, "error": error})))
            return
        geom, stamps, volume = report.pop("_geom"), report.pop("_stamps"), report.pop("_volume")
        report.pop("_grid")
        if report.get("partial"):
            # /ct/geometry_corrected carries the correction of the whole scan only (the recorder keeps it);
            # a partial run's corrected geometry is in its partial_NNNN/scan_corrected bag
            self.partial_reports.append(report)
        else:
            msgs = fmt.geometry_pose_arrays(geom, stamps)
            self._to_publish.extend(fmt.serialize(m, fmt.POSE_ARRAY) for m in msgs)
        now = self.get_clock().now().nanoseconds
        for k, sl in mid_slices(volume).items():
            self.slice_pubs[k].publish(fmt.serialize(fmt.image_from_array(sl, now, fmt.FRAME_WORLD), fmt.IMAGE))
        report["run"] = run
        self.report = report
        self.report_pub.publish(String(data=json.dumps(report, default=_json_default)))
        self.state = "done"
        self._progress("done", f"run {run} done in {report.get('wall_s', 0.0):.1f} s: {report['paths']['report_json']}",
                       run, report.get("n_views"))

    @property
    def done(self) -> bool:
        """The last run finished (or failed) and its corrected geometry is all published."""
        return self.state in ("done", "failed") and not self.running and not self._to_publish

    # -- health -------------------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        level = DiagnosticStatus.ERROR if self.state == "failed" else DiagnosticStatus.OK
        values = [("state", self.state), ("method", self.method), ("iterations", self.iterations),
                  ("frames", len(self._per_frame[fmt.TOPIC_PROJECTION])), ("paired", self.n_paired),
                  ("runs", self.runs), ("output_dir", self.output_dir), ("last_error", self.error),
                  ("report", (self.report or {}).get("paths", {}).get("report_json", ""))]
        status = DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: reconstruction",
                                  hardware_id="recon_service", message=self.error or self.message,
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def destroy_node(self):
        if self._worker is not None and self._worker.is_alive():
            self.get_logger().warning("shutting down during a run; its results are lost")
        return super().destroy_node()


def main(argv=None) -> int:
    return run_node(ReconServiceNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
