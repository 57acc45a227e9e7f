"""pcd_grabber: the photon-counting detector (PCD) as a ROS 2 lifecycle node; one frame per exposure request.

Topics (contract names from robot_ct_ros.bag.format; relative names follow the node namespace):
  publishes   /ct/projection (sensor_msgs/Image 32FC1: binned photon counts, header.stamp = middle of the
              exposure, frame_id "pcd_detector"; reliable, depth 100),
              /ct/flat_field (Image 32FC1, mean counts per frame without object) and /ct/dead_pixels
              (Image mono8, 1 = unusable: dead, hot, chip gap), on activation, transient-local,
              /ct/geometry_true (geometry_msgs/PoseArray, simulated detector only: the true geometry
              of each frame, same stamp), /ct/projection_rejected (Image 32FC1: beam-interrupted
              frames, below), /diagnostics (1 Hz)
  subscribes  source/beam_on (std_msgs/Bool, transient-local): the beam state over each exposure, by
              reception time (below); the simulated detector also scales its flux by it (beam off =
              dark frame; the detector itself knows no interlock), source_arm/true_tool_pose and
              detector_arm/true_tool_pose (geometry_msgs/PoseStamped, simulated arms): the true poses
              the simulated detector projects with
  services    pcd/expose (std_srvs/Trigger): expose for exposure_s and publish the frame; answered
              when the frame is out (message: JSON {"stamp_ns", "frame", "exposure_s", "n_rows",
              "n_cols"}) or with success false and the reason (detector timeout: no frame within
              exposure_timeout_s of the request; busy; not active; driver error; beam interrupted).
              <node>/change_state, <node>/get_state (lifecycle_msgs)
Beam-interrupted frames (README "Bag format"): a frame is a projection when the beam was on throughout
its exposure, or a dark frame when it was off throughout and already off at the request. Any other
frame (the beam dropped, or came on, during the exposure: the interlock or an e-stop cut it) is
published on /ct/projection_rejected (same layout, no true geometry) and never on /ct/projection, so
no geometry is made for it and neither the recorder's scan nor recon_service pairs it; pcd/expose
then answers success false ("beam interrupted ..."). With no source/beam_on publisher the beam counts
as off (every frame is a dark frame).
/ct/scan_info is not published here: the scan orchestrator knows the scan (views, ROI) and
publishes it; this node knows only the detector.

Lifecycle: configure builds and connects the detector (simulated: voxelises the phantom, compiles
the projector) and offers pcd/expose; activate publishes the flat field and dead-pixel map and
serves exposures; deactivate stops exposing (an exposure in flight is answered with failure, its
frame dropped) and refuses requests; cleanup/shutdown/error withdraw pcd/expose and disconnect the
detector (which releases a hung acquisition). Unconfigured, pcd/expose does not exist, so the scan
orchestrator's start check sees no detector; inactive, the orchestrator refuses to start from the
lifecycle_state this node reports on /diagnostics. With autostart (default) the node configures and
activates itself in its constructor, as the node did before it had a lifecycle.

Threads: pcd/expose is served on its own executor thread (nodes/common.ServiceThread): its callback
starts the acquisition on a worker thread and waits (threading.Event) for the frame or the deadline,
then publishes the frame and answers, so the executor spinning this node never waits for an exposure.
Parameters: see config/pcd_grabber.yaml (detector grid, exposure, simulation: phantom, voxel size,
photon counts, defects, seed, fault injection), autostart, and the hand_eye.* parameters
(nodes/hand_eye_params.py).
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.simulation import DetectorModel
from robot_ct_ros.hardware.detector import (DetectorConfig, DetectorError, Frame, SimulatedDetector, build_scene,
                                            make_phantom)
from robot_ct_ros.nodes.common import ServiceThread, run_node
from robot_ct_ros.nodes.hand_eye_params import declare_hand_eye, pose_to_matrix_mm, stamp_to_ns

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


class _Exposure:
    """One pcd/expose request in flight: the worker fills ``result``; ``done`` wakes the service thread."""

    def __init__(self, rid: int, requested_ns: int):
        self.id = rid
        self.requested_ns = requested_ns
        self.done = threading.Event()
        self.result: Frame | Exception | None = None
        self.cancelled = ""   # why the node gave up on it (deactivated, shutting down)
        self.abandoned = False  # answered already (timeout, cancel): a late frame is dropped


class PcdGrabberNode(LifecycleNode):
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
            # where the simulated region and fine ROI are centred; [] = the phantom centre
            "region_center_m": list(p("sim_region_center_m", Parameter.Type.DOUBLE_ARRAY).value or []),
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

        autostart = p("autostart", True).value

        self.frame_pub = self.create_publisher(Image, fmt.TOPIC_PROJECTION, STREAM)
        self.frame_rejected_pub = self.create_publisher(Image, fmt.TOPIC_PROJECTION_REJECTED, STREAM)
        self.flat_pub = self.create_publisher(Image, fmt.TOPIC_FLAT_FIELD, LATCHED)
        self.dead_pub = self.create_publisher(Image, fmt.TOPIC_DEAD_PIXELS, LATCHED)
        self.true_geom_pub = self.create_publisher(PoseArray, fmt.TOPIC_GEOMETRY_TRUE, STREAM)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, 10)

        self._lock = threading.Lock()  # beam log, true poses, and the exposure state below
        self._beam_log: list[tuple[int, bool]] = []
        self._true_pose: dict[str, tuple[int, np.ndarray]] = {}
        self.create_subscription(Bool, "source/beam_on", self._on_beam, LATCHED)
        for role in ("source", "detector"):
            self.create_subscription(PoseStamped, f"{role}_arm/true_tool_pose",
                                     lambda m, r=role: self._on_true_pose(r, m), 10)

        self.frames_published = 0
        self.frames_rejected = 0
        self.failures = 0
        self.last_error = ""
        self.last_beam_fraction: float | None = None
        self.detector = None                          # exists between configure and cleanup
        self._detector_factory = detector_factory or self._make_simulated_detector
        self._expose_srv: ServiceThread | None = None  # exists between configure and cleanup
        self._active = False
        self._pending: _Exposure | None = None         # the exposure request being served
        self._worker: threading.Thread | None = None
        self._request_id = 0
        self.create_timer(1.0, self._publish_diagnostics)
        if autostart and self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        return self._state_machine.current_state[1]

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        t0 = time.monotonic()
        try:
            detector = self._detector_factory()
            detector.connect()
        except (DetectorError, ValueError, OSError) as exc:
            self.last_error = f"configure failed: {exc}"
            self.get_logger().error(self.last_error)
            return TransitionCallbackReturn.FAILURE
        self.detector, self.last_error = detector, ""
        self._expose_srv = ServiceThread(self, Trigger, "pcd/expose", self._on_expose)
        self.get_logger().info(f"detector ready ({self.driver}, {self.config.n_rows} x {self.config.n_cols} "
                               f"binned {self.config.binning}x{self.config.binning}) in {time.monotonic() - t0:.1f} s")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        flat, bad = self.detector.flat_field()
        stamp = self._now_ns()
        self.flat_pub.publish(fmt.serialize(fmt.image_from_array(flat, stamp, self.frame_id), fmt.IMAGE))
        self.dead_pub.publish(fmt.serialize(fmt.mask_image(bad, stamp, self.frame_id), fmt.IMAGE))
        self._active = True
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_exposing("the detector was deactivated during the exposure")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("the detector was cleaned up during the exposure")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("the detector was shut down during the exposure")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("detector error during the exposure")
        return TransitionCallbackReturn.SUCCESS

    def _stop_exposing(self, why: str) -> None:
        with self._lock:
            self._active = False
            pending = self._pending
            if pending is not None:
                pending.cancelled = why
        if pending is not None:
            pending.done.set()  # the service thread answers failure and drops the frame

    def _release(self, why: str) -> None:
        self._stop_exposing(why)
        srv, self._expose_srv = self._expose_srv, None
        if srv is not None:
            srv.close()
        detector, self.detector = self.detector, None
        if detector is not None:
            detector.disconnect()  # releases a hanging acquisition
        if self._worker is not None:
            self._worker.join(2.0)

    def destroy_node(self):
        self._release("the node shut down during the exposure")
        return super().destroy_node()

    # -- detector ----------------------------------------------------------------------------
    def _make_simulated_detector(self):
        if self.driver != "simulated":
            raise ValueError(f"detector driver {self.driver!r} is not available (only 'simulated')")
        s = self._sim
        center_mm = np.asarray(s["phantom_center_m"], float) * 1e3
        region_mm = np.asarray(s["region_center_m"], float) * 1e3 if len(s["region_center_m"]) else center_mm
        if region_mm.shape != (3,):
            raise ValueError(f"sim_region_center_m needs 3 values (m), got {s['region_center_m']}")
        phantom = make_phantom(s["phantom"], center_mm, seed=s["phantom_seed"])
        scene = build_scene(phantom, s["voxel_size_m"] * 1e3, region_center_mm=region_mm,
                            region_size_mm=np.asarray(s["region_size_m"], float) * 1e3, roi_center_mm=region_mm,
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

    # -- exposures (the service thread; the worker thread acquires) ----------------------------
    def _refusal(self) -> tuple[str, bool] | None:
        """Why a request cannot start now (and whether that is a detector fault); called under the lock."""
        if not self._active:
            return f"detector not active (lifecycle state {self.lifecycle_state})", False
        if self._pending is not None:
            return "detector busy: an exposure is in progress", False
        if self._worker is not None and self._worker.is_alive():
            return "detector not responding: the previous acquisition never completed", True
        if self.detector is None or not self.detector.is_connected:
            return "detector not connected", True
        return None

    def _on_expose(self, request, response):
        with self._lock:
            refusal = self._refusal()
            if refusal is None:
                self._request_id += 1
                exposure = self._pending = _Exposure(self._request_id, self._now_ns())
                self._worker = threading.Thread(target=self._acquire, args=(exposure, self.detector),
                                                name="pcd_acquire", daemon=True)
                self._worker.start()
        if refusal is not None:
            problem, fault = refusal
            if fault:
                self._failed(f"exposure refused: {problem}", problem)
            response.success, response.message = False, problem
            return response

        in_time = exposure.done.wait(self.exposure_timeout_s)
        with self._lock:
            exposure.abandoned = True
            if self._pending is exposure:
                self._pending = None
            result, cancelled = exposure.result, exposure.cancelled
        if cancelled:
            response.success, response.message = False, cancelled
        elif not in_time or result is None:
            problem = f"detector timeout: no frame within {self.exposure_timeout_s:.3g} s"
            self._failed(f"exposure failed: {problem}", problem)
            response.success, response.message = False, problem
        elif isinstance(result, Exception):
            problem = f"{type(result).__name__}: {result}"
            self._failed(f"exposure failed: {problem}", problem)
            response.success, response.message = False, problem
        else:
            fraction = self._beam_fraction(result.start_ns, result.end_ns)
            self.last_beam_fraction = fraction
            if fraction == 1.0 or (fraction == 0.0 and not self._beam_on_at(exposure.requested_ns)):
                self._publish_frame(result)
                self.last_error = ""  # recovered
                response.success = True
                response.message = json.dumps({"stamp_ns": result.stamp_ns, "frame": self.frames_published,
                                               "exposure_s": self.exposure_s, "n_rows": self.config.n_rows,
                                               "n_cols": self.config.n_cols})
            else:
                problem = self._reject_frame(result, fraction)
                self.last_error = problem  # not a detector fault: not counted in failures
                self.get_logger().warn(f"frame rejected: {problem}")
                response.success, response.message = False, problem
        return response

    def _acquire(self, exposure: _Exposure, detector) -> None:
        try:
            result = detector.acquire(self.exposure_s)
        except Exception as exc:  # DetectorError, or a bug in a driver: reported, never raised into the void
            result = exc
        with self._lock:
            exposure.result = result
            late = exposure.abandoned
        exposure.done.set()
        if late and not isinstance(result, Exception):
            self.get_logger().warn("a late frame arrived after its request was answered; discarded")

    def _beam_on_at(self, t_ns: int) -> bool:
        """The beam state at ``t_ns`` as received on source/beam_on (off before the first message)."""
        with self._lock:
            states = [on for t, on in self._beam_log if t <= t_ns]
        return bool(states) and states[-1]

    def _reject_frame(self, frame: Frame, fraction: float) -> str:
        """Publish a beam-interrupted frame on /ct/projection_rejected only (bag contract); the reason."""
        self.frame_rejected_pub.publish(
            fmt.serialize(fmt.image_from_array(frame.counts, frame.stamp_ns, self.frame_id), fmt.IMAGE))
        self.frames_rejected += 1
        return (f"beam interrupted: on for {100 * fraction:.0f}% of the exposure; the frame (stamp "
                f"{frame.stamp_ns}) went to {fmt.TOPIC_PROJECTION_REJECTED}, not {fmt.TOPIC_PROJECTION}")

    def _failed(self, log: str, problem: str) -> None:
        self.failures += 1
        self.last_error = problem
        self.get_logger().error(log)

    def _publish_frame(self, frame: Frame) -> None:
        stamp = frame.stamp_ns
        self.frame_pub.publish(fmt.serialize(fmt.image_from_array(frame.counts, stamp, self.frame_id), fmt.IMAGE))
        self.frames_published += 1
        geom = frame.info.get("geometry")
        if self.publish_true_geometry and geom is not None:
            msg = fmt.view_pose_array(geom.source_mm[0], geom.detector_mm[0], geom.u[0], geom.v[0], stamp)
            self.true_geom_pub.publish(fmt.serialize(msg, fmt.POSE_ARRAY))

    # -- health -------------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        state = self.lifecycle_state
        connected = self.detector is not None and self.detector.is_connected
        if self.last_error:
            level = DiagnosticStatus.ERROR if self.last_error.startswith(("detector timeout", "detector not",
                                                                          "configure failed")) \
                else DiagnosticStatus.WARN
        elif not self._active or not connected:
            level = DiagnosticStatus.WARN
        else:
            level = DiagnosticStatus.OK
        values = [("lifecycle_state", state), ("driver", self.driver), ("connected", connected),
                  ("frames", self.frames_published), ("frames_rejected", self.frames_rejected),
                  ("failures", self.failures), ("exposure_s", self.exposure_s),
                  ("exposure_timeout_s", self.exposure_timeout_s),
                  ("shape", f"{self.config.n_rows}x{self.config.n_cols}"), ("binning", self.config.binning),
                  ("busy", self._pending is not None)]
        values.append(("last_beam_fraction", self.last_beam_fraction))
        if self.driver == "simulated":
            values.append(("phantom", self._sim["phantom"]))
        message = self.last_error or ("ready" if self._active and connected else state)
        status = DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: detector",
                                  hardware_id=f"{self.driver}_pcd", message=message,
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


def main(argv=None) -> int:
    return run_node(PcdGrabberNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
