"""recon_service: reconstruction and data-driven geometry correction of a scan, as a service with progress.

Collects the scan's topics as received (/ct/scan_info, /ct/flat_field, /ct/dead_pixels,
/ct/projection, /ct/geometry, /ct/geometry_true); recon/run (std_srvs/Trigger), or scan/status
"done" with auto_run, starts a correction on a worker thread: the scan is written as a bag into
``<output_dir>/scan`` and corrected by the calibration job (robot_ct_ros.jobs.calibrate), exactly
as ``robot-ct calibrate`` corrects a recorded bag (with bag_path, that bag is corrected instead:
no ``scan``, the corrected copy is ``<output_dir>/<bag name>_corrected``). Publishes recon/progress, /ct/geometry_corrected
(one PoseArray per frame, the frame's stamp), recon/slice_{axial,sagittal,coronal},
recon/report and /diagnostics. every_n_views > 0 also corrects the frames so far every N frames
during the scan, into ``<output_dir>/partial_NNNN`` (not published on /ct/geometry_corrected).
stream=true estimates each frame as it arrives against a running volume in a worker process at a
lower OS priority (robot_ct_ros.jobs.streaming) and publishes it on /ct/geometry_live (same
encoding as /ct/geometry_corrected), with the running volume's slices; the whole-scan run follows.
Parameters: the calibration settings (robot_ct_ros.ct.calibration.CalibrationSettings, SI units)
and the service's own (robot_ct_ros.jobs.online.ServiceSettings). Reference: docs/nodes.md.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag.collector import PER_FRAME, ScanCollector
from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.jobs.online import RunPlanner, ServiceSettings
from robot_ct_ros.jobs.streaming import StreamingCorrector, mid_slices
from robot_ct_ros.nodes.common import (LATCHED, STREAM, declare_settings, publish_diagnostic, run_settings_node,
                                       topic_qos, writable_dir)
from robot_ct_ros.nodes.recorder import message_class

STATUS = topic_qos(fmt.TOPIC_SCAN_INFO, depth=10)  # scan/status: latched as the scan's own topics are; 10 kept
SLICES = ("axial", "sagittal", "coronal")
PUBLISH_BATCH = 10  # corrected geometries per 50 ms tick: subscribers keep up, their depth-100 history never overflows


def method_text(settings: CalibrationSettings) -> str:
    """The method and its outer iterations, as the start-up line says them (method none corrects nothing)."""
    if settings.method == "none":
        return "method none (no correction: reconstructs with the nominal geometry)"
    return f"method {settings.method}, {settings.iterations_text()} iteration(s)"


class ReconServiceNode(Node):
    def __init__(self, node_name: str = "recon_service", **kwargs):
        super().__init__(node_name, **kwargs)
        self.settings = declare_settings(self, CalibrationSettings)
        self.service = declare_settings(self, ServiceSettings)
        # absolute: reports name files, not cwd-relative paths; refused at start if it cannot be written
        self.output_dir = writable_dir(self.service.output_dir, "output_dir")

        self.scan = ScanCollector()
        for topic in fmt.LATCHED_TOPICS:
            self.create_subscription(message_class(fmt.TOPIC_TYPES[topic]), fmt.node_topic(topic),
                                     lambda d, t=topic: self._on_latched(t, d), LATCHED, raw=True)
        for topic in PER_FRAME:
            self.create_subscription(message_class(fmt.TOPIC_TYPES[topic]), fmt.node_topic(topic),
                                     lambda d, t=topic: self._on_frame(t, d), STREAM, raw=True)
        self.create_subscription(String, "scan/status", self._on_status, STATUS)
        self.progress_pub = self.create_publisher(String, "recon/progress", 50)
        self.report_pub = self.create_publisher(String, "recon/report", LATCHED)
        self.corrected_pub = self.create_publisher(PoseArray, fmt.node_topic(fmt.TOPIC_GEOMETRY_CORRECTED), STREAM)
        self.live_pub = self.create_publisher(PoseArray, fmt.node_topic(fmt.TOPIC_GEOMETRY_LIVE), STREAM)
        self.slice_pubs = {k: self.create_publisher(Image, f"recon/slice_{k}", LATCHED) for k in SLICES}
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.node_topic(fmt.TOPIC_DIAGNOSTICS), 10)
        self.create_service(Trigger, "recon/run", self._on_run)

        self.state, self.message, self.error = "idle", "waiting for a scan", ""  # state: idle|running|done|failed
        self.runs = self.full_runs = self.partial_runs = self.corrected_published = 0
        self.run_partial = False
        self.partial_reports: list[dict] = []
        self.report: dict | None = None   # last finished run's report
        self._worker: threading.Thread | None = None
        self._result = None
        self._lock = threading.Lock()
        self._done_gc = self.create_guard_condition(self._on_job_done)
        self._to_publish: list[bytes] = []
        self.planner = RunPlanner(self.service.auto_run, self.service.every_n_views)
        self._t_run = 0.0
        self.live_published = 0
        self.stream = None if not self.service.stream else StreamingCorrector(
            self.settings, warmup_views=self.service.stream_warmup_views, nice=self.service.stream_nice,
            threads=self.service.stream_threads, voxel_mm=self.service.voxel_mm, shape_xyz=self.service.shape_xyz)
        self.create_timer(0.05, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"recon_service: {method_text(self.settings)}, output {self.output_dir}/, "
                               f"auto_run {self.service.auto_run}"
                               + (f", bag_path {self.service.bag_path}" if self.service.bag_path else ""))

    @property
    def method(self) -> str:
        return self.settings.method

    @property
    def prior_sigma(self):
        return self.settings.prior_sigma

    @property
    def n_paired(self) -> int:
        return self.scan.n_paired

    # -- collection -------------------------------------------------------------------------------
    def _on_latched(self, topic: str, data: bytes) -> None:
        if self.scan.add_latched(topic, data):
            self.get_logger().info("collection reset: a new scan_info: new scan")
            self.planner.new_scan()
            if self.stream is not None:
                self.stream.new_scan()

    def _on_frame(self, topic: str, data: bytes) -> None:
        if not self.scan.add_frame_message(topic, data):
            self.get_logger().warning(f"undecodable message on {topic} ignored", once=True)
        pairs = self.scan.take_new_pairs()
        if self.stream is not None:
            for stamp, image, geometry in pairs:
                self.stream.add_frame(stamp, image, geometry, self.scan.latched)

    def _on_status(self, msg: String) -> None:
        try:
            self.planner.on_status(json.loads(msg.data))
        except (ValueError, AttributeError):
            return

    def _tick(self) -> None:
        if self._to_publish:  # corrected geometries, in batches
            batch, self._to_publish = self._to_publish[:PUBLISH_BATCH], self._to_publish[PUBLISH_BATCH:]
            for data in batch:
                self.corrected_pub.publish(data)
                self.corrected_published += 1
        if self.stream is not None:
            self._poll_live()
        if self.running:
            return
        run = self.planner.next_run(self.n_paired, self.scan.scan_id)
        if run == "full":
            if self.n_paired == 0 and not self.service.bag_path:  # the scan's run is used up: said as a failure
                self._fail(self.runs + 1, "automatic correction not started: the scan is done but no frame was "
                           "collected here (frames are not latched: a recon_service started after the scan has none; "
                           "set bag_path to the recorded bag, or replay it)", 0)
                return
            short = []
            if self.planner.shortfall is not None:
                announced, paired = self.planner.shortfall
                short = [f"the scan announced {announced} frames; {paired} arrived here with their geometry within "
                         f"{self.planner.wait_s:g} s of its end: corrected with those"]
            ok, why = self.start_run(notes=short)
            if not ok:  # the scan's run is used up: say so where a run's failure is said, not only in the log
                self._fail(self.runs + 1, f"automatic correction not started: {why}", self.n_paired)
        elif run == "partial":
            self.start_run(partial=True)

    def _poll_live(self) -> None:
        """The live path's finished batch, published. A failure here is the live path's (live_error on /diagnostics,
        report.json's live.error) and never leaves the timer: the node keeps collecting and running."""
        stream = self.stream
        try:
            dropped = stream.dropped
            for update in stream.poll(self.scan.latched):
                self._publish_live(update)
            if stream.dropped > dropped:
                self.get_logger().warning(f"live: {stream.dropped} frame(s) of this scan dropped so far, not "
                                          f"estimated: {stream.drop_reason}")
        except Exception as exc:  # noqa: BLE001 - reported; the node keeps serving
            error = f"live: {type(exc).__name__}: {exc}"
            if stream.error != error:
                self.get_logger().error(error)
            stream.error = error

    def _publish_live(self, update) -> None:
        """A batch of live estimates: its geometries on /ct/geometry_live, the running volume's slices."""
        for m in fmt.geometry_pose_arrays(update.geom, update.stamps_ns, update.frame_id):  # the scan's frame
            self.live_pub.publish(fmt.serialize(m, fmt.POSE_ARRAY))
            self.live_published += 1
        if not self.running and not self.planner.full_started:  # nor are a run's slices, during or after it
            now = self.get_clock().now().nanoseconds
            for k, sl in update.slices.items():
                self.slice_pubs[k].publish(fmt.serialize(fmt.image_from_array(sl, now, update.frame_id), fmt.IMAGE))

    # -- runs ---------------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def _on_run(self, request, response):
        response.success, response.message = self.start_run()
        if not response.success:  # the caller has the answer; a progress monitor sees the refusal too
            self._publish_progress("refused", response.message, self.runs + 1, None, 0.0)
        return response

    def start_run(self, partial: bool = False, notes=()) -> tuple[bool, str]:
        """Start a correction run on a worker thread; (started, message). ``notes``: what this run's report's
        bag_warnings say first (the automatic run's note of frames that did not arrive)."""
        from robot_ct_ros.jobs.calibrate import refuse_another_bags_folder
        from robot_ct_ros.jobs.output import refuse_other_job

        if self.running:
            return False, f"a run is in progress ({self.message})"
        try:
            if self.service.bag_path and not partial:  # the bag's scan: its id is the job's to read
                out, bag, n = self.output_dir, Path(self.service.bag_path), None
                scan_id, warnings = None, None
            else:
                out = self.output_dir / f"partial_{self.n_paired:04d}" if partial else self.output_dir
                refuse_other_job(out, "calibrate", "output_dir")  # before the scan is written there, as the job would
                refuse_another_bags_folder(out, "scan", "output_dir")
                bag, n = self.scan.write_bag(out / "scan")
                # the scan as written, taken here: the collection is the executor's, and a new scan resets it
                scan_id, warnings = self.scan.scan_id, list(notes) + self.scan.warnings
        except (ValueError, OSError) as exc:
            return False, f"cannot run: {exc}"
        self.runs += 1
        self.run_partial = partial
        self.partial_runs += partial
        self.full_runs += not partial
        self.planner.full_started |= not partial
        self.state, self.error, self._t_run = "running", "", time.monotonic()
        self.message = f"run {self.runs}: {f'{n} views' if n is not None else f'bag {bag}'}, {self.method}"
        self._progress("start", self.message, self.runs, n)
        self._worker = threading.Thread(target=self._job, args=(self.runs, bag, out, n, partial, scan_id, warnings),
                                        name="recon", daemon=True)
        self._worker.start()
        # the view count of a bag given by path is known once the job has read it (recon/progress, the report)
        return True, f"started run {self.runs} on {bag}{f' ({n} views)' if n is not None else ''} into {out}"

    def _progress(self, stage: str, message: str, run: int, n) -> None:
        self.message = message
        self._publish_progress(stage, message, run, n, time.monotonic() - self._t_run)

    def _publish_progress(self, stage: str, message: str, run: int, n, elapsed_s: float) -> None:
        """One recon/progress message (the node's own message unchanged)."""
        data = {"state": self.state, "stage": stage, "message": message, "run": run, "n_views": n,
                "elapsed_s": round(elapsed_s, 3)}
        try:
            self.progress_pub.publish(String(data=json.dumps(data)))
        except Exception:  # noqa: BLE001 - shutting down
            pass

    def _job(self, run: int, bag: Path, out: Path, n, partial: bool, scan_id, warnings) -> None:
        """The correction of ``bag`` on the worker thread, which never reads the collection (the executor feeds it).
        ``scan_id`` and ``warnings`` (the run's notes, then what the collection dropped): the collected scan's, taken
        when the run started; None for a bag given by path (its own id; its reader's warnings are the job's)."""
        from robot_ct_ros.jobs.calibrate import calibrate_bag
        from robot_ct_ros.jobs.output import write_json

        def say(line: str) -> None:
            self.get_logger().info(line)
            self._progress("calibrate", line, run, n)
        try:
            correction = calibrate_bag(bag, out, self.settings, voxel_mm=self.service.voxel_mm,
                                       shape_xyz=self.service.shape_xyz,
                                       evaluate_truth=self.service.evaluate_truth, markdown=True, say=say,
                                       options="ROS parameters")
            if scan_id is None:
                scan_id = fmt.scan_id_of(correction.scan.info)
            report = correction.report | {"partial": partial, "scan_id": scan_id, "run": run}
            if warnings is not None:  # the scan as received: what the collection dropped
                report["bag_warnings"] = warnings + list(report.get("bag_warnings", []))
                for warning in warnings:
                    self.get_logger().warning(warning)
            if self.stream is not None:
                report["live"] = self.stream.summary()
            try:  # report.json holds what recon/report says; the run is done whether or not this rewrite succeeds
                write_json(report["paths"]["report_json"], report)
            except OSError as exc:
                self.get_logger().warning(f"report.json keeps the job's own report: {exc}")
            result = (run, report, correction, None)
        except Exception as exc:  # noqa: BLE001 - reported; the node keeps serving
            result = (run, None, None, f"{type(exc).__name__}: {exc}")
        with self._lock:
            self._result = result
        try:
            self._done_gc.trigger()
        except Exception:  # noqa: BLE001 - node destroyed meanwhile
            pass

    def _fail(self, run: int, error: str, n, log: str | None = None) -> None:
        """Run ``run`` failed (or could not start): state failed, the reason logged, on recon/progress and on
        recon/report."""
        self.state, self.error = "failed", error
        self.get_logger().error(log or error)
        self._progress("failed", error, run, n)
        self.report_pub.publish(String(data=json.dumps({"run": run, "error": error})))

    def _on_job_done(self) -> None:
        from robot_ct_ros.jobs.output import clean_json, json_default

        with self._lock:
            result, self._result = self._result, None
        if result is None:
            return
        run, report, correction, error = result
        if error is not None:
            self._fail(run, error, None, log=f"run {run} failed: {error}")
            return
        if report["partial"]:  # /ct/geometry_corrected carries the correction of the whole scan only
            self.partial_reports.append(report)
        else:
            # in the frame of the scan's /ct/geometry (one frame per bag: docs/bag-format.md)
            msgs = fmt.geometry_pose_arrays(correction.geom, correction.scan.stamps_ns, correction.scan.frame_id)
            self._to_publish.extend(fmt.serialize(m, fmt.POSE_ARRAY) for m in msgs)
        now = self.get_clock().now().nanoseconds
        for k, sl in mid_slices(correction.volume).items():
            self.slice_pubs[k].publish(fmt.serialize(fmt.image_from_array(sl, now, correction.scan.frame_id),
                                                     fmt.IMAGE))
        self.report = report
        self.report_pub.publish(String(data=json.dumps(clean_json(report), default=json_default)))
        self.state = "done"
        self._progress("done", f"run {run} done in {report.get('wall_s', 0.0):.1f} s: {report['paths']['report_json']}",
                       run, report.get("n_views"))

    @property
    def done(self) -> bool:
        """The last run finished (or failed) and its corrected geometry is all published."""
        return self.state in ("done", "failed") and not self.running and not self._to_publish

    # -- health -------------------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        values = [("state", self.state), ("method", self.method),
                  ("iterations", "none" if self.method == "none" else self.settings.iterations_text()),
                  ("frames", self.scan.n_frames), ("paired", self.n_paired), ("runs", self.runs),
                  ("output_dir", self.output_dir), ("last_error", self.error),
                  ("report", (self.report or {}).get("paths", {}).get("report_json", ""))]
        if self.stream is not None:
            live = self.stream.summary()
            values += [("live_views", live["views"]), ("live_mean_projection_ncc", live["mean_projection_ncc"]),
                       ("live_latency_s_median", live["latency_s_median"]), ("live_error", live["error"]),
                       ("live_frames_dropped", live["frames_dropped"]), ("live_drop_reason", live["drop_reason"])]
        live_error = self.stream.error if self.stream is not None else ""
        level = (DiagnosticStatus.ERROR if self.state == "failed" else DiagnosticStatus.WARN if live_error
                 else DiagnosticStatus.OK)
        publish_diagnostic(self, self.diag_pub, level, "reconstruction", "recon_service",
                           self.error or self.message + (f"; {live_error}" if live_error else ""), values)

    def destroy_node(self):
        if self._worker is not None and self._worker.is_alive():
            self.get_logger().warning("shutting down during a run; its results are lost")
        if self.stream is not None:
            self.stream.close()
        return super().destroy_node()


def main(argv=None) -> int:
    return run_settings_node(ReconServiceNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
