"""pcd_grabber: the photon-counting detector (PCD) as a ROS 2 lifecycle node; one frame per exposure request.

Topics (contract names from robot_ct_ros.bag.format; relative names follow the node namespace):
  publishes   /ct/projection (sensor_msgs/Image 32FC1: binned photon counts, header.stamp = middle of the
              exposure, frame_id "pcd_detector"; reliable, depth 100),
              /ct/flat_field (Image 32FC1, mean counts per frame without object) and /ct/dead_pixels
              (Image mono8, 1 = unusable: dead, hot, chip gap), on activation, transient-local,
              /ct/geometry_true (geometry_msgs/PoseArray, simulated detector only: the true geometry
              of each frame, same stamp, frame world_frame), /ct/projection_rejected (Image 32FC1: beam-interrupted
              frames, below), /diagnostics (1 Hz)
  subscribes  source/beam_on (std_msgs/Bool, transient-local): the beam state over each exposure, by
              reception time (below); the simulated detector also scales its flux by it (beam off =
              dark frame; the detector itself knows no interlock), source_arm/true_tool_pose and
              detector_arm/true_tool_pose (geometry_msgs/PoseStamped, simulated arms): the true poses
              the simulated detector projects with (in world_frame; a pose in another frame is ignored)
  services    pcd/expose (std_srvs/Trigger): expose for exposure_s and publish the frame; answered
              when the frame is out (message: JSON {"stamp_ns", "frame", "exposure_s", "n_rows",
              "n_cols"}) or with success false and the reason (detector timeout: no frame within
              exposure_timeout_s of the request; busy; not active; driver error; beam interrupted).
              <node>/change_state, <node>/get_state (lifecycle_msgs)
Beam-interrupted frames (docs/bag-format.md; the rule: robot_ct_ros.hardware.exposure): a frame
neither a projection (beam on throughout) nor a dark frame (off throughout and at the request) is
published on /ct/projection_rejected (same layout, no true geometry) and never on /ct/projection, so
no geometry is made for it and neither the recorder's scan nor recon_service pairs it; pcd/expose
then answers success false ("beam interrupted ..."). With no source/beam_on publisher the beam counts
as off (every frame is a dark frame).
/ct/scan_info is not published here: the scan orchestrator knows the scan (views, ROI) and
publishes it; this node knows only the detector.

Lifecycle: configure builds and connects the detector (simulated: voxelises the phantom, compiles
the projector) and offers pcd/expose; activate publishes the flat field and dead-pixel map and serves
exposures; deactivate stops exposing (an exposure in flight is answered with failure, its frame
dropped); cleanup/shutdown/error withdraw pcd/expose and disconnect the detector (which releases a
hung acquisition). A driver raising something other than a DetectorError, or the pcd/expose
thread failing, is an ERROR on /diagnostics and takes the node through the lifecycle error
transition (on_error releases the detector; the node ends unconfigured). Unconfigured, pcd/expose does not exist, so the scan orchestrator's start check
sees no detector; inactive, the orchestrator refuses to start from the lifecycle_state reported on
/diagnostics. With autostart (default) the node configures and activates itself in its constructor.
Threads: pcd/expose is served on its own executor thread (nodes/common.ServiceThread) and waits there
for the acquisition (hardware.exposure.ExposureGate), so the executor spinning this node never waits.
Data quality: a frame with fewer valid pixels (as robot-ct info counts them:
hardware.detector.valid_pixel_fraction) than min_valid_pixel_fraction is still published, with a WARN
in the log and on /diagnostics naming the fraction; a dead-pixel map that alone leaves too few is
warned about on activation.
Parameters (config/pcd_grabber.yaml): hardware.detector.DetectorSettings, sim_*:
hardware.detector.SimulatedDetectorSettings, autostart, and hand_eye.* (nodes/hand_eye_params.py).
"""

from __future__ import annotations

import json
import time

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.hardware.detector import (DetectorError, DetectorSettings, Frame, SimulatedDetectorSettings,
                                            TruePoses, make_detector, valid_pixel_fraction)
from robot_ct_ros.hardware.exposure import BeamLog, ExposureGate, frame_usable
from robot_ct_ros.nodes.common import (LATCHED, STREAM, LifecycleSettings, ServiceThread, WorkerFaults,
                                      declare_settings, error_transition, publish_diagnostic,
                                      refuse_unavailable_transitions, run_settings_node, transition_result)
from robot_ct_ros.nodes.hand_eye_params import declare_hand_eye, pose_to_matrix_mm, stamp_to_ns

__all__ = ["PcdGrabberNode", "LATCHED", "STREAM", "main"]



class PcdGrabberNode(LifecycleNode):
    def __init__(self, node_name: str = "pcd_grabber", *, detector_factory=None, **kwargs):
        super().__init__(node_name, **kwargs)
        refuse_unavailable_transitions(self)
        self.detector_settings = d = declare_settings(self, DetectorSettings)
        self.sim = declare_settings(self, SimulatedDetectorSettings, prefix="sim_")
        autostart = declare_settings(self, LifecycleSettings).autostart
        self.driver, self.exposure_s, self.exposure_timeout_s = d.driver, d.exposure_s, d.exposure_timeout_s
        self.frame_id, self.world_frame, self.config = d.frame_id, d.world_frame, d.config
        self.min_valid_pixel_fraction = d.min_valid_pixel_fraction
        self.hand_eye = declare_hand_eye(self)

        self.frame_pub = self.create_publisher(Image, fmt.node_topic(fmt.TOPIC_PROJECTION), STREAM)
        self.frame_rejected_pub = self.create_publisher(Image, fmt.node_topic(fmt.TOPIC_PROJECTION_REJECTED), STREAM)
        self.flat_pub = self.create_publisher(Image, fmt.node_topic(fmt.TOPIC_FLAT_FIELD), LATCHED)
        self.dead_pub = self.create_publisher(Image, fmt.node_topic(fmt.TOPIC_DEAD_PIXELS), LATCHED)
        self.true_geom_pub = self.create_publisher(PoseArray, fmt.node_topic(fmt.TOPIC_GEOMETRY_TRUE), STREAM)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.node_topic(fmt.TOPIC_DIAGNOSTICS), 10)

        self.beam_log = BeamLog()
        self.true_poses = TruePoses(self._now_ns, self.sim.pose_max_age_s)
        self.create_subscription(Bool, "source/beam_on", lambda m: self.beam_log.record(self._now_ns(), m.data),
                                 LATCHED)
        for role in TruePoses.ROLES:
            self.create_subscription(PoseStamped, f"{role}_arm/true_tool_pose",
                                     lambda m, r=role: self._on_true_pose(r, m), 10)

        self.faults = WorkerFaults(self, self._on_fault)
        self.error_transition_pending = False
        self.frames_published = self.frames_rejected = self.failures = 0
        self.last_error, self.last_beam_fraction = "", None
        self._flat = self._bad = None  # the maps published on activation
        self.map_valid_fraction = self.last_valid_fraction = None  # valid pixels: of the maps, of the last frame
        self.frames_low_valid = 0  # frames below min_valid_pixel_fraction
        self.valid_warning = ""  # the last low-valid-pixel warning, for /diagnostics (WARN) until a good frame
        self.detector = None                          # exists between configure and cleanup
        self._detector_factory = detector_factory or self._make_detector
        self._expose_srv: ServiceThread | None = None  # exists between configure and cleanup
        self.exposures = ExposureGate(self._now_ns, lambda: self.get_logger().warn(
            "a late frame arrived after its request was answered; discarded"))
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
        self._expose_srv = ServiceThread(self, Trigger, "pcd/expose", self._on_expose, on_error=self.faults.report)
        self.get_logger().info(f"detector ready ({self.driver}, {self.config.n_rows} x {self.config.n_cols} "
                               f"binned {self.config.binning}x{self.config.binning}) in {time.monotonic() - t0:.1f} s")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        flat, bad = self.detector.flat_field()
        stamp = self._now_ns()
        self.flat_pub.publish(fmt.serialize(fmt.image_from_array(flat, stamp, self.frame_id), fmt.IMAGE))
        self.dead_pub.publish(fmt.serialize(fmt.mask_image(bad, stamp, self.frame_id), fmt.IMAGE))
        self._flat, self._bad = flat, bad
        self.map_valid_fraction = valid_pixel_fraction(flat, bad)
        self.valid_warning = ""
        if self.map_valid_fraction < self.min_valid_pixel_fraction:
            self.valid_warning = (f"the dead-pixel map and flat field leave only {100 * self.map_valid_fraction:.2f} % "
                                  f"of the pixels valid (min_valid_pixel_fraction "
                                  f"{100 * self.min_valid_pixel_fraction:g} %): every frame will be mostly invalid")
            self.get_logger().warn(self.valid_warning)
        self.exposures.activate()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.exposures.cancel("the detector was deactivated during the exposure")
        return transition_result(self)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("the detector was cleaned up during the exposure")
        return transition_result(self)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._release("the detector was shut down during the exposure")

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._release("detector error during the exposure")

    def _release(self, why: str) -> TransitionCallbackReturn:
        self.exposures.cancel(why)
        srv, self._expose_srv = self._expose_srv, None
        if srv is not None:
            srv.close()
        detector, self.detector = self.detector, None
        if detector is not None:
            detector.disconnect()  # releases a hanging acquisition
        self.exposures.join(2.0)
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self):
        self._release("the node shut down during the exposure")
        return super().destroy_node()

    # -- detector and its inputs --------------------------------------------------------------
    def _on_fault(self, reason: str) -> None:  # executor, from WorkerFaults
        self.failures += 1
        self.last_error = f"fault: {reason}"
        self.get_logger().error(f"{self.last_error}; lifecycle error transition (configure to restart)")
        error_transition(self)
        self._publish_diagnostics()

    def _make_detector(self):
        detector = make_detector(self.detector_settings, self.sim, self.hand_eye, self.true_poses,
                                 self.beam_log.fraction, self._now_ns)
        self.get_logger().info(f"simulated detector: {self.sim.phantom} phantom, {detector.scene.n_voxels} voxels")
        return detector

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on_true_pose(self, role: str, msg: PoseStamped) -> None:
        if msg.header.frame_id not in ("", self.world_frame):  # as geometry_publisher: another frame is no pose
            self.get_logger().warn(f"{role} true pose ignored: frame {msg.header.frame_id!r} is not world_frame "
                                   f"{self.world_frame!r}", throttle_duration_sec=5.0)
            return
        try:
            self.true_poses.update(role, stamp_to_ns(msg.header.stamp), pose_to_matrix_mm(msg.pose))
        except ValueError as exc:
            self.get_logger().warn(f"{role} true pose ignored: {exc}")

    # -- exposures (the service thread; the gate's worker thread acquires) ---------------------
    def _on_expose(self, request, response):
        result = self.exposures.expose(self.detector, self.exposure_s, self.exposure_timeout_s, self.lifecycle_state)
        if result.crashed:  # a driver bug, not a detector fault: as a dead worker thread
            self.faults.report(f"detector driver raised {result.problem}")
            response.success, response.message = False, f"detector driver failed: {result.problem}"
            return response
        if result.fault:  # a detector fault: counted, and an error on /diagnostics
            self.failures, self.last_error = self.failures + 1, result.problem
            self.get_logger().error(result.fault)
        frame = result.frame
        if frame is None:
            response.success, response.message = False, result.problem
            return response
        fraction = self.beam_log.fraction(frame.start_ns, frame.end_ns)
        self.last_beam_fraction = fraction
        if frame_usable(fraction, self.beam_log.on_at(result.requested_ns)):
            self._publish_frame(frame)
            self.last_error = ""  # recovered
            response.success = True
            response.message = json.dumps({"stamp_ns": frame.stamp_ns, "frame": self.frames_published,
                                           "exposure_s": self.exposure_s, "n_rows": self.config.n_rows,
                                           "n_cols": self.config.n_cols,
                                           "valid_pixel_fraction": self.last_valid_fraction})
        else:
            problem = self._reject_frame(frame, fraction)
            self.last_error = problem  # not a detector fault: not counted in failures
            self.get_logger().warn(f"frame rejected: {problem}")
            response.success, response.message = False, problem
        return response

    def _reject_frame(self, frame: Frame, fraction: float) -> str:
        """Publish a beam-interrupted frame on /ct/projection_rejected only (bag contract); the reason."""
        self.frame_rejected_pub.publish(
            fmt.serialize(fmt.image_from_array(frame.counts, frame.stamp_ns, self.frame_id), fmt.IMAGE))
        self.frames_rejected += 1
        return (f"beam interrupted: on for {100 * fraction:.0f}% of the exposure; the frame (stamp "
                f"{frame.stamp_ns}) went to {fmt.TOPIC_PROJECTION_REJECTED}, not {fmt.TOPIC_PROJECTION}")

    def _publish_frame(self, frame: Frame) -> None:
        stamp = frame.stamp_ns
        self.frame_pub.publish(fmt.serialize(fmt.image_from_array(frame.counts, stamp, self.frame_id), fmt.IMAGE))
        self.frames_published += 1
        self._check_valid_pixels(frame)
        geom = frame.info.get("geometry")
        if self.detector_settings.publish_true_geometry and geom is not None:
            msg = fmt.view_pose_array(geom.source_mm[0], geom.detector_mm[0], geom.u[0], geom.v[0], stamp,
                                      self.world_frame)
            self.true_geom_pub.publish(fmt.serialize(msg, fmt.POSE_ARRAY))

    def _check_valid_pixels(self, frame: Frame) -> None:
        """Warn (log, /diagnostics) when fewer than min_valid_pixel_fraction of the frame's pixels are valid."""
        if self._flat is None or self._flat.shape != frame.counts.shape:
            return
        fraction = self.last_valid_fraction = valid_pixel_fraction(self._flat, self._bad, frame.counts)
        if fraction >= self.min_valid_pixel_fraction:
            if self.map_valid_fraction is not None and self.map_valid_fraction >= self.min_valid_pixel_fraction:
                self.valid_warning = ""
            return
        self.frames_low_valid += 1
        self.valid_warning = (f"frame {self.frames_published} (stamp {frame.stamp_ns}): only {100 * fraction:.2f} % of "
                              f"the pixels valid (min_valid_pixel_fraction {100 * self.min_valid_pixel_fraction:g} %; "
                              f"{self.frames_low_valid} such frame(s)): dead, hot or gap pixels, no flat field, or "
                              f"non-finite or negative counts")
        self.get_logger().warn(self.valid_warning)

    # -- health -------------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        state = self.lifecycle_state
        connected = self.detector is not None and self.detector.is_connected
        if self.last_error:
            level = DiagnosticStatus.ERROR if self.last_error.startswith(("detector timeout", "detector not",
                                                                          "configure failed", "fault")) \
                else DiagnosticStatus.WARN
        elif not self.exposures.active or not connected or self.valid_warning:
            level = DiagnosticStatus.WARN
        else:
            level = DiagnosticStatus.OK
        values = [("lifecycle_state", state), ("driver", self.driver), ("connected", connected),
                  ("frames", self.frames_published), ("frames_rejected", self.frames_rejected),
                  ("failures", self.failures), ("exposure_s", self.exposure_s),
                  ("exposure_timeout_s", self.exposure_timeout_s),
                  ("shape", f"{self.config.n_rows}x{self.config.n_cols}"), ("binning", self.config.binning),
                  ("busy", self.exposures.pending is not None), ("last_beam_fraction", self.last_beam_fraction),
                  ("valid_pixel_fraction", self.last_valid_fraction), ("map_valid_pixel_fraction",
                                                                        self.map_valid_fraction),
                  ("frames_low_valid_pixels", self.frames_low_valid),
                  ("min_valid_pixel_fraction", self.min_valid_pixel_fraction)]
        if self.driver == "simulated":
            values.append(("phantom", self.sim.phantom))
        message = self.last_error or self.valid_warning or ("ready" if self.exposures.active and connected else state)
        publish_diagnostic(self, self.diag_pub, level, "detector", f"{self.driver}_pcd", message, values)

def main(argv=None) -> int:
    return run_settings_node(PcdGrabberNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
