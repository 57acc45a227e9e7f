"""pcd_grabber: the photon-counting detector (PCD); one frame per exposure request.

Topics (contract names from robot_ct_ros.bag.format; relative names follow the node namespace):
  publishes   /ct/projection (sensor_msgs/Image 32FC1: binned photon counts, header.stamp = middle of
              the exposure, frame_id "pcd_detector"; reliable, depth 100),
              /ct/flat_field (Image 32FC1, mean counts per frame without object) and /ct/dead_pixels
              (Image mono8, 1 = unusable: dead, hot, chip gap), once at start, transient-local,
              /ct/geometry_true (geometry_msgs/PoseArray, simulated detector only: the true geometry
              of each frame, same stamp), /diagnostics (1 Hz)
  subscribes  source/beam_on (std_msgs/Bool, transient-local): only the simulated detector uses it,
              to scale the flux by the fraction of the exposure with the beam on (beam off = dark
              frame; the detector itself knows no interlock), source_arm/true_tool_pose and
              detector_arm/true_tool_pose (geometry_msgs/PoseStamped, simulated arms): the true poses
              the simulated detector projects with
  services    pcd/expose (std_srvs/Trigger): expose for exposure_s and publish the frame; answered
              when the frame is out (message: JSON {"stamp_ns", "frame", "exposure_s", "n_rows",
              "n_cols"}) or with success false and the reason (detector timeout: no frame within
              exposure_timeout_s of the request; busy; driver error). Never blocks the executor:
              the acquisition runs on a worker thread and the answer is sent when it ends.
/ct/scan_info is not published here: the scan orchestrator knows the scan (views, ROI) and
publishes it; this node knows only the detector.
Parameters: see config/pcd_grabber.yaml (detector grid, exposure, simulation: phantom, voxel size,
photon counts, defects, seed, fault injection) and the hand_eye.* parameters (nodes/hand_eye_params.py).
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.simulation import DetectorModel
from robot_ct_ros.hardware.detector import (DetectorConfig, Frame, SimulatedDetector, build_scene,
                                            make_phantom)
from robot_ct_ros.nodes.common import run_node
from robot_ct_ros.nodes.hand_eye_params import declare_hand_eye, pose_to_matrix_mm, stamp_to_ns

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


class DeferredService:
    """A service whose callback may answer later, from the executor thread, without blocking it.

    rclpy sends the callback's return value right after the callback; here the callback may
    return :meth:`defer` (a marker response) instead, and :meth:`answer` sends the real response
    later. rclpy's own alternative, an ``async`` callback awaiting a future, makes the
    SingleThreadedExecutor poll the pending task in a busy loop.
    """

    def __init__(self, node: Node, srv_type, name: str, callback):
        self._srv = node.create_service(srv_type, name, callback)
        self._send = self._srv.send_response
        self._srv.send_response = self._send_or_hold
        self._held: dict[int, object] = {}  # id(marker response) -> request header
        self._markers: dict[int, object] = {}

    def defer(self, response):
        """Return this from the callback to answer later with :meth:`answer` (token = the response)."""
        self._markers[id(response)] = response
        return response

    def _send_or_hold(self, response, header) -> None:
        if id(response) in self._markers and self._markers[id(response)] is response:
            self._held[id(response)] = header
            return
        self._send(response, header)

    def answer(self, token, response=None) -> bool:
        """Send the deferred answer (``response`` or the token itself, filled in); False if unknown."""
        key = id(token)
        header = self._held.pop(key, None)
        self._markers.pop(key, None)
        if header is None:
            return False
        try:
            self._send(token if response is None else response, header)
        except Exception:  # noqa: BLE001 - the client may be gone; nothing to answer then
            return False
        return True


class PcdGrabberNode(Node):
    def __init__(self, node_name: str = "pcd_grabber", *, detector_factory=None, **kwargs):
        super().__init__(node_name, **kwargs)
        p = self.declare_parameter
        self.driver = p("driver", "simulated").value
        self.exposure_s = float(p("exposure_s", 0.1).value)
        self.exposure_timeout_s = float(p("exposure_timeout_s", 5.0).value)
        self.frame_id = p("frame_id", fmt.FRAME_DETECTOR).value
        self.config = DetectorConfig(n_rows=p("n_rows", 272).value, n_cols=p("n_cols", 636).value,
                                     binning=p("binning", 2).value, raw_pixel_mm=p("raw_pixel_m", 55e-6).value * 1e3)
        self.publish_true_geometry = p("publish_true_geometry", True).value
        if not 0 < self.exposure_s < self.exposure_timeout_s:
            raise ValueError(f"need 0 < exposure_s < exposure_timeout_s, got {self.exposure_s}, "
                             f"{self.exposure_timeout_s}")
        self.hand_eye = declare_hand_eye(self)
        self._sim = {
            "phantom": p("sim_phantom", "carotid").value,
            "phantom_center_m": list(p("sim_phantom_center_m", [0.4, 0.0, 0.3]).value),
            "phantom_seed": p("sim_phantom_seed", 0).value,
            "voxel_size_m": p("sim_voxel_size_m", 5e-4).value,
            "region_size_m": list(p("sim_region_size_m", [0.0, 0.0, 0.0]).value),
            "roi_size_m": list(p("sim_roi_size_m", [0.0, 0.0, 0.0]).value),
            "roi_voxel_size_m": p("sim_roi_voxel_size_m", 5e-5).value,
            "supersample": p("sim_supersample", 1).value,
            "photons_per_pixel": p("sim_photons_per_pixel", 49000.0).value,
            "chip_size_px": p("sim_chip_size_px", 256).value,
            "chip_gap_px": p("sim_chip_gap_px", 2).value,
            "dead_pixel_fraction": p("sim_dead_pixel_fraction", 1e-3).value,
            "hot_pixel_fraction": p("sim_hot_pixel_fraction", 2e-4).value,
            "flat_field_sigma": p("sim_flat_field_sigma", 0.03).value,
            "flat_frames": p("sim_flat_frames", 20).value,
            "poisson": p("sim_poisson", True).value,
            "seed": p("sim_seed", 0).value,
            "fail": p("sim_fail", "none").value,
            "readout_s": p("sim_readout_s", 0.0).value,
            "pose_max_age_s": p("sim_pose_max_age_s", 1.0).value,
            "source_mount_error_m": list(p("sim_mount_error.source_translation_m", [0.0, 0.0, 0.0]).value),
            "detector_mount_error_m": list(p("sim_mount_error.detector_translation_m", [0.0, 0.0, 0.0]).value),
            "detector_mount_error_rotvec": list(p("sim_mount_error.detector_rotvec_rad", [0.0, 0.0, 0.0]).value),
        }

        self.frame_pub = self.create_publisher(Image, fmt.TOPIC_PROJECTION, STREAM)
        self.flat_pub = self.create_publisher(Image, fmt.TOPIC_FLAT_FIELD, LATCHED)
        self.dead_pub = self.create_publisher(Image, fmt.TOPIC_DEAD_PIXELS, LATCHED)
        self.true_geom_pub = self.create_publisher(PoseArray, fmt.TOPIC_GEOMETRY_TRUE, STREAM)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, 10)

        self._lock = threading.Lock()
        self._beam_log: list[tuple[int, bool]] = []
        self._true_pose: dict[str, tuple[int, np.ndarray]] = {}
        self.create_subscription(Bool, "source/beam_on", self._on_beam, LATCHED)
        for role in ("source", "detector"):
            self.create_subscription(PoseStamped, f"{role}_arm/true_tool_pose",
                                     lambda m, r=role: self._on_true_pose(r, m), 10)

        self.frames_published = 0
        self.failures = 0
        self.last_error = ""
        self.last_beam_fraction: float | None = None
        self._pending = None     # the exposure request being served
        self._worker: threading.Thread | None = None
        self._results: list = []  # (request id, Frame | Exception) from the worker
        self._request_id = 0
        self._done_gc = self.create_guard_condition(self._on_worker_done)

        factory = detector_factory or self._make_simulated_detector
        t0 = time.monotonic()
        self.detector = factory()
        self.detector.connect()
        self.get_logger().info(f"detector ready ({self.driver}, {self.config.n_rows} x {self.config.n_cols} "
                               f"binned {self.config.binning}x{self.config.binning}) in {time.monotonic() - t0:.1f} s")
        self._publish_calibration()
        self._expose_srv = DeferredService(self, Trigger, "pcd/expose", self._on_expose)
        self.create_timer(1.0, self._publish_diagnostics)

    # -- detector ----------------------------------------------------------------------------
    def _make_simulated_detector(self):
        if self.driver != "simulated":
            raise ValueError(f"detector driver {self.driver!r} is not available (only 'simulated')")
        s = self._sim
        center_mm = np.asarray(s["phantom_center_m"], float) * 1e3
        phantom = make_phantom(s["phantom"], center_mm, seed=s["phantom_seed"])
        scene = build_scene(phantom, s["voxel_size_m"] * 1e3, region_center_mm=center_mm,
                            region_size_mm=np.asarray(s["region_size_m"], float) * 1e3, roi_center_mm=center_mm,
                            roi_size_mm=np.asarray(s["roi_size_m"], float) * 1e3,
                            roi_voxel_size_mm=s["roi_voxel_size_m"] * 1e3, supersample=s["supersample"])
        model = DetectorModel(photons_per_pixel=s["photons_per_pixel"], binning=self.config.binning,
                              chip_size_px=s["chip_size_px"], chip_gap_px=s["chip_gap_px"],
                              dead_pixel_fraction=s["dead_pixel_fraction"], hot_pixel_fraction=s["hot_pixel_fraction"],
                              flat_field_sigma=s["flat_field_sigma"], flat_frames=s["flat_frames"],
                              poisson=s["poisson"], raw_pitch_mm=self.config.raw_pixel_mm, seed=s["seed"])
        true_mounts = self.hand_eye.with_errors(
            source_translation_mm=np.asarray(s["source_mount_error_m"], float) * 1e3,
            detector_translation_mm=np.asarray(s["detector_mount_error_m"], float) * 1e3,
            detector_rotvec=s["detector_mount_error_rotvec"])
        self.get_logger().info(f"simulated detector: {s['phantom']} phantom, {scene.n_voxels} voxels")
        return SimulatedDetector(self.config, model, scene, true_mounts, self._true_poses, self._beam_fraction,
                                 self._now_ns, seed=s["seed"] + 7, fail=s["fail"], readout_s=s["readout_s"],
                                 pose_wait_s=min(1.0, 0.5 * (self.exposure_timeout_s - self.exposure_s)))

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _publish_calibration(self) -> None:
        flat, bad = self.detector.flat_field()
        stamp = self._now_ns()
        self.flat_pub.publish(fmt.serialize(fmt.image_from_array(flat, stamp, self.frame_id), fmt.IMAGE))
        self.dead_pub.publish(fmt.serialize(fmt.mask_image(bad, stamp, self.frame_id), fmt.IMAGE))

    # -- inputs of the simulation ------------------------------------------------------------
    def _on_beam(self, msg: Bool) -> None:
        now = self._now_ns()
        with self._lock:
            if not self._beam_log or self._beam_log[-1][1] != msg.data:
                self._beam_log.append((now, bool(msg.data)))
            # keep one minute of history, and always the state before it
            while len(self._beam_log) > 2 and self._beam_log[1][0] < now - 60_000_000_000:
                self._beam_log.pop(0)

    def _beam_fraction(self, start_ns: int, end_ns: int) -> float:
        """Fraction of [start, end] with the beam on (reception times of source/beam_on)."""
        if end_ns <= start_ns:
            return 0.0
        with self._lock:
            log = list(self._beam_log)
        on_ns, state, t = 0, False, start_ns
        for t_i, s_i in log:
            if t_i <= start_ns:
                state = s_i
                continue
            if t_i >= end_ns:
                break
            if state:
                on_ns += t_i - t
            t, state = t_i, s_i
        if state:
            on_ns += end_ns - t
        return on_ns / (end_ns - start_ns)

    def _on_true_pose(self, role: str, msg: PoseStamped) -> None:
        try:
            T = pose_to_matrix_mm(msg.pose)
        except ValueError as exc:
            self.get_logger().warn(f"{role} true pose ignored: {exc}")
            return
        with self._lock:
            self._true_pose[role] = (stamp_to_ns(msg.header.stamp), T)

    def _true_poses(self):
        now = self._now_ns()
        max_age = self._sim["pose_max_age_s"] * 1e9
        with self._lock:
            poses = [self._true_pose.get(r) for r in ("source", "detector")]
        if any(p is None or now - p[0] > max_age for p in poses):
            return None
        return poses[0][1], poses[1][1]

    # -- exposures -----------------------------------------------------------------------------
    def _on_expose(self, request, response):
        problem = None
        if self._pending is not None:
            response.success, response.message = False, "detector busy: an exposure is in progress"
            return response  # not a detector fault
        if self._worker is not None and self._worker.is_alive():
            problem = "detector not responding: the previous acquisition never completed"
        elif not self.detector.is_connected:
            problem = "detector not connected"
        if problem is not None:
            self.failures += 1
            self.last_error = problem
            self.get_logger().error(f"exposure refused: {problem}")
            response.success, response.message = False, problem
            return response
        self._request_id += 1
        rid = self._request_id
        deadline = self.create_timer(self.exposure_timeout_s, lambda: self._on_deadline(rid))
        self._pending = {"id": rid, "response": response, "deadline": deadline}
        self._worker = threading.Thread(target=self._acquire, args=(rid,), name="pcd_acquire", daemon=True)
        self._worker.start()
        return self._expose_srv.defer(response)

    def _acquire(self, rid: int) -> None:
        try:
            result = self.detector.acquire(self.exposure_s)
        except Exception as exc:  # DetectorError, or a bug in a driver: reported, never raised into the void
            result = exc
        with self._lock:
            self._results.append((rid, result))
        try:
            self._done_gc.trigger()
        except Exception:  # the node is being destroyed
            pass

    def _finish(self, success: bool, message: str) -> None:
        pending, self._pending = self._pending, None
        if pending is None:
            return
        pending["deadline"].cancel()
        self.destroy_timer(pending["deadline"])
        response = pending["response"]
        response.success, response.message = success, message
        if success:
            self.last_error = ""  # recovered
        else:
            self.failures += 1
            self.last_error = message
            self.get_logger().error(f"exposure failed: {message}")
        self._expose_srv.answer(response)

    def _on_deadline(self, rid: int) -> None:
        if self._pending is not None and self._pending["id"] == rid:
            self._finish(False, f"detector timeout: no frame within {self.exposure_timeout_s:.3g} s")

    def _on_worker_done(self) -> None:
        with self._lock:
            results, self._results = self._results, []
        for rid, result in results:
            if self._pending is None or self._pending["id"] != rid:
                self.get_logger().warn("a late frame arrived after its request timed out; discarded")
                continue
            if isinstance(result, Exception):
                self._finish(False, f"{type(result).__name__}: {result}")
                continue
            self._publish_frame(result)
            self._finish(True, json.dumps({"stamp_ns": result.stamp_ns, "frame": self.frames_published,
                                           "exposure_s": self.exposure_s, "n_rows": self.config.n_rows,
                                           "n_cols": self.config.n_cols}))

    def _publish_frame(self, frame: Frame) -> None:
        stamp = frame.stamp_ns
        self.frame_pub.publish(fmt.serialize(fmt.image_from_array(frame.counts, stamp, self.frame_id), fmt.IMAGE))
        self.frames_published += 1
        geom = frame.info.get("geometry")
        if self.publish_true_geometry and geom is not None:
            msg = fmt.view_pose_array(geom.source_mm[0], geom.detector_mm[0], geom.u[0], geom.v[0], stamp)
            self.true_geom_pub.publish(fmt.serialize(msg, fmt.POSE_ARRAY))
        fraction = frame.info.get("beam_fraction")
        if fraction is not None:
            self.last_beam_fraction = fraction
            if fraction < 1.0:
                self.get_logger().warn(f"frame {self.frames_published} exposed with the beam on for only "
                                       f"{100 * fraction:.0f}% of the exposure")

    # -- health -------------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        connected = self.detector.is_connected
        if not connected or self.last_error:
            level = DiagnosticStatus.ERROR if self.last_error.startswith(("detector timeout", "detector not")) \
                else DiagnosticStatus.WARN
        else:
            level = DiagnosticStatus.OK
        values = [("driver", self.driver), ("connected", connected), ("frames", self.frames_published),
                  ("failures", self.failures), ("exposure_s", self.exposure_s),
                  ("exposure_timeout_s", self.exposure_timeout_s),
                  ("shape", f"{self.config.n_rows}x{self.config.n_cols}"), ("binning", self.config.binning),
                  ("busy", self._pending is not None)]
        if self.driver == "simulated":
            values += [("phantom", self._sim["phantom"]), ("last_beam_fraction", self.last_beam_fraction)]
        status = DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: detector",
                                  hardware_id=f"{self.driver}_pcd",
                                  message=self.last_error or ("ready" if connected else "not connected"),
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def destroy_node(self):
        detector = getattr(self, "detector", None)
        if detector is not None:
            detector.disconnect()  # releases a hanging acquisition
        if self._worker is not None:
            self._worker.join(2.0)
        return super().destroy_node()


def main(argv=None) -> int:
    return run_node(PcdGrabberNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
