"""The whole scan graph in-process: simulated hardware -> scan -> record -> online correction.

:func:`run_scan_graph` starts source_control, two arm_driver nodes (simulated arms with
coordination errors), pcd_grabber (simulated photon-counting detector), geometry_publisher,
scan_orchestrator, recorder and recon_service on one SingleThreadedExecutor, in their own
rclpy context on a ROS_DOMAIN_ID of their own with localhost-only discovery (as the tests
do), runs one scan protocol, waits for the scan to end, the recorder to close the bag and the
recon_service to finish the correction (every wait bounded, with a clear error), and returns
where everything is. Used by ``robot-ct demo`` and by the end-to-end tests.
"""

from __future__ import annotations

import itertools
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from robot_ct_ros.hardware.detector import warm_up_projector
from robot_ct_ros.nodes.config_files import package_config_dir

__all__ = ["ARM_REPORT_TIMEOUT_S", "ROLES", "GraphError", "GraphResult", "run_scan_graph"]

ROLES = ("source", "detector")
_domains = itertools.count()
ARM_REPORT_TIMEOUT_S = 10.0
"""scan_orchestrator's ``arm_report_timeout_s`` in this harness (the node's own default is 1 s). Every node here
shares one thread, so a slow callback of another node (a simulated exposure on a loaded machine) holds back the
arms' reports for its whole duration; on the robot each node has its own process. ``orchestrator`` overrides it."""


class GraphError(RuntimeError):
    """The graph did not get through a step in time, or the scan aborted (the message says which and why)."""


@dataclass
class GraphResult:
    out_dir: Path
    bag: Path                         # the recorder's scan bag
    recon_dir: Path                   # recon_service output_dir
    corrected_bag: Path | None
    volume_npy: Path | None
    volume_tif: Path | None
    report_json: Path | None
    report_md: Path | None
    report: dict                      # recon/report as published (the node's report.json)
    frames: int
    corrected: dict = field(default_factory=dict)   # stamp_ns -> (source_mm, detector_mm, u, v), /ct/geometry_corrected
    slices: dict = field(default_factory=dict)      # axial|sagittal|coronal -> 2D array received on recon/slice_*
    progress: list = field(default_factory=list)    # recon/progress messages (dicts)
    timings_s: dict = field(default_factory=dict)
    live: dict = field(default_factory=dict)        # stamp_ns -> (s after the scan started, scan running), /ct/geometry_live


def _domain_id() -> int:
    # 201..232: clear of the test harness' 1..200, still inside FastDDS's port range
    return 201 + (os.getpid() * 7 + next(_domains)) % 32


def _params(d: dict):
    from rclpy.parameter import Parameter

    return [Parameter(k, value=v) for k, v in d.items()]


def _load_protocol(protocol, out_dir: Path) -> tuple[Path, object]:
    from robot_ct_ros.hardware.scan_protocol import ScanProtocol

    if isinstance(protocol, (str, Path)):
        path = Path(protocol)
        named = package_config_dir() / f"scan_protocol_{protocol}.yaml"
        if not path.exists() and named.exists():
            path = named
        return path, ScanProtocol.from_yaml(path)
    proto = ScanProtocol.from_dict(dict(protocol))
    path = out_dir / "scan_protocol.yaml"
    d = dict(protocol)
    path.write_text(yaml.safe_dump(d if "scan_protocol" in d else {"scan_protocol": d}))
    return path, proto


def _beam_off_first(nodes: list, executor, say) -> None:
    """A graph stopped while its source is up (interrupted, failed): abort the scan, switch the beam off and let the
    other nodes, the recorder among them, hear it before they stop. ``nodes`` loses the source."""
    from robot_ct_ros.nodes.scan_orchestrator import ScanOrchestratorNode
    from robot_ct_ros.nodes.source_control import SourceControlNode

    source = next((nd for nd in nodes if isinstance(nd, SourceControlNode)), None)
    if source is None:
        return
    try:
        for orch in (nd for nd in nodes if isinstance(nd, ScanOrchestratorNode)):
            if orch.running:
                orch.abort("the graph is stopping")
        executor.remove_node(source)
        source.destroy_node()  # the beam off, published (beam_on false) before the node goes
        nodes.remove(source)
        end = time.monotonic() + 0.3
        while time.monotonic() < end:  # the recorder records beam_on false
            executor.spin_once(timeout_sec=0.02)
        say("stopping the graph: scan aborted, beam off (source_control stopped)")
    except Exception as exc:  # noqa: BLE001 - best effort; the source's own teardown switches the beam off too
        say(f"stopping the graph: {type(exc).__name__}: {exc}")


def run_scan_graph(out_dir, protocol="quick", *, grabber: dict | None = None, arms: dict | None = None,
                   arm_errors: dict | None = None, recon: dict | None = None, recorder: dict | None = None,
                   orchestrator: dict | None = None,
                   scan_timeout_s: float | None = None, recon_timeout_s: float = 600.0, startup_timeout_s: float = 60.0,
                   say=print, progress_period_s: float = 5.0, quiet: bool = False) -> GraphResult:
    """Run one scan on the simulated graph; see the module docstring.

    ``protocol``: a scan protocol YAML path, a name (``quick`` -> config/scan_protocol_quick.yaml)
    or a dict (the YAML's content). The pcd_grabber gets the protocol's detector grid and
    exposure plus ``grabber`` (its ``sim_*`` parameters: phantom, voxel sizes, photons ...);
    ``arm_errors`` go to both arm drivers (default 0.1 mm / 0.05 deg per move), ``arms``
    per role on top; ``recon``: recon_service parameters (method, iterations, ...);
    ``recorder``: recorder parameters; ``orchestrator``: scan_orchestrator parameters on top of the protocol
    file and :data:`ARM_REPORT_TIMEOUT_S`. Bags go to ``out_dir/bags``, the correction to
    ``out_dir/recon``. ``quiet``: the nodes log warnings and errors only (progress still goes
    to ``say``). Raises :class:`GraphError` when a step does not complete.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from robot_ct_ros.bag import format as fmt
    from robot_ct_ros.nodes.arm_driver import ArmDriverNode
    from robot_ct_ros.nodes.geometry_publisher import GeometryPublisherNode
    from robot_ct_ros.nodes.pcd_grabber import PcdGrabberNode
    from robot_ct_ros.nodes.recon_service import LATCHED, STREAM, SLICES, ReconServiceNode
    from robot_ct_ros.nodes.recorder import RecorderNode
    from robot_ct_ros.nodes.scan_orchestrator import ScanOrchestratorNode
    from robot_ct_ros.nodes.source_control import SourceControlNode

    t_start = time.monotonic()
    timings: dict[str, float] = {}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    proto_path, proto = _load_protocol(protocol, out_dir)
    geom = proto.geometry()
    n = proto.n_views
    he_args = ["--ros-args", "--params-file", str(package_config_dir() / "hand_eye.yaml")]
    grabber_params = {"n_rows": geom.n_rows, "n_cols": geom.n_cols, "binning": proto.binning,
                      "raw_pixel_m": proto.raw_pixel_m, "exposure_s": proto.exposure_s,
                      "exposure_timeout_s": proto.exposure_timeout_s,
                      "sim_phantom_center_m": [float(x) for x in proto.roi_center_m],
                      "sim_region_center_m": [float(x) for x in proto.roi_center_m]}
    grabber_params.update(grabber or {})
    errors = {"sim_sigma_mm": 0.1, "sim_sigma_deg": 0.05}
    errors.update(arm_errors or {})
    recon_params = {"output_dir": str(out_dir / "recon"), "auto_run": True}
    recon_params.update(recon or {})
    recorder_params = {"output_dir": str(out_dir / "bags"), "bag_prefix": "scan"}
    recorder_params.update(recorder or {})
    orchestrator_params = {"arm_report_timeout_s": ARM_REPORT_TIMEOUT_S}
    orchestrator_params.update(orchestrator or {})
    if scan_timeout_s is None:
        scan_timeout_s = 60.0 + n * (2.0 + proto.exposure_s + proto.settle_s)

    dt = warm_up_projector()
    if dt > 1.0:
        say(f"compiled the projector in {dt:.1f} s (numba; cached for the next runs)")
    timings["compile_s"] = dt
    saved_env = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    domain = _domain_id()
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if quiet:
        from rclpy.logging import LoggingSeverity, set_logger_level

        for name in ("source_control", "source_arm_driver", "detector_arm_driver", "pcd_grabber",
                     "geometry_publisher", "scan_orchestrator", "recorder", "recon_service", "graph_probe"):
            set_logger_level(name, LoggingSeverity.WARN)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    executor = SingleThreadedExecutor(context=context)
    nodes = []

    def add(node):
        executor.add_node(node)
        nodes.append(node)
        return node

    def spin_until(pred, timeout_s: float, what, report=None, period_s: float = progress_period_s) -> None:
        end = time.monotonic() + timeout_s
        next_report = time.monotonic() + period_s
        while not pred():
            now = time.monotonic()
            if now > end:
                what = what() if callable(what) else what
                raise GraphError(f"timed out after {timeout_s:.0f} s waiting for {what}")
            if report is not None and now >= next_report:
                next_report = now + period_s
                report()
            executor.spin_once(timeout_sec=0.02)

    try:
        say(f"starting the graph (ROS_DOMAIN_ID {domain}, localhost only): protocol {proto.name} ({proto_path}), "
            f"{n} views, detector {geom.n_rows}x{geom.n_cols} of {geom.col_pitch_mm * 1000:.0f} um")
        source = add(SourceControlNode(context=context))
        arm_nodes = {}
        for r, seed in (("source", 1), ("detector", 2)):
            p = dict(role=r, sim_seed=seed, **errors)
            p.update((arms or {}).get(r, {}))
            arm_nodes[r] = add(ArmDriverNode(f"{r}_arm_driver", context=context, parameter_overrides=_params(p)))
        t0 = time.monotonic()
        grab = add(PcdGrabberNode(context=context, cli_args=he_args, parameter_overrides=_params(grabber_params)))
        timings["detector_setup_s"] = time.monotonic() - t0
        add(GeometryPublisherNode(context=context, cli_args=he_args))
        orchestrator_params["protocol_file"] = str(proto_path)
        orch = add(ScanOrchestratorNode(context=context, cli_args=he_args,
                                        parameter_overrides=_params(orchestrator_params)))
        rec = add(RecorderNode(context=context, parameter_overrides=_params(recorder_params)))
        recon_node = add(ReconServiceNode(context=context, parameter_overrides=_params(recon_params)))

        probe = add(rclpy.create_node("graph_probe", context=context))
        corrected, slices, progress, live = {}, {}, [], {}
        scan_t0 = {"t": None}

        def on_live(msg):
            t = None if scan_t0["t"] is None else time.monotonic() - scan_t0["t"]
            live.setdefault(fmt.stamp_to_ns(msg.header.stamp), (t, orch.state not in ("done", "aborted")))

        def on_corrected(msg):
            corrected[fmt.stamp_to_ns(msg.header.stamp)] = fmt.view_from_pose_array(msg)

        def on_progress(msg):
            d = json.loads(msg.data)
            progress.append(d)
            say(f"recon: {d['message']}")

        subs = [probe.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY_CORRECTED, on_corrected, STREAM),
                probe.create_subscription(String, "recon/progress", on_progress, 50),
                probe.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY_LIVE, on_live, STREAM)]
        for k in SLICES:
            subs.append(probe.create_subscription(Image, f"recon/slice_{k}",
                                                  lambda m, k=k: slices.__setitem__(k, fmt.array_from_image(m)),
                                                  LATCHED))

        # 1. the hardware nodes (lifecycle, autostart) come up, then the orchestrator accepts the scan
        hardware = {"source_control": source, "pcd_grabber": grab,
                    **{f"{r}_arm_driver": a for r, a in arm_nodes.items()}}
        spin_until(lambda: all(h.lifecycle_state == "active" for h in hardware.values()), startup_timeout_s,
                   lambda: "the hardware nodes to become active (" + ", ".join(
                       f"{k}: {h.lifecycle_state}" for k, h in hardware.items()) + ")")
        last = {"msg": ""}

        def try_start():
            o = orch
            if not (o.set_beam.service_is_ready() and o.expose.service_is_ready()):
                last["msg"] = "services not ready"
                return False
            ok, msg = o.start()
            last["msg"] = msg
            return ok
        try:
            spin_until(try_start, startup_timeout_s, "the scan to start")
        except GraphError as exc:
            raise GraphError(f"{exc}; last refusal: {last['msg']}") from None
        timings["startup_s"] = time.monotonic() - t_start
        say(f"scan {orch.scan_id} started ({timings['startup_s']:.1f} s after launch)")

        # 2. the scan
        t0 = scan_t0["t"] = time.monotonic()
        spin_until(lambda: orch.state in ("done", "aborted"), scan_timeout_s, f"the scan to end (state {orch.state})",
                   report=lambda: say(f"scan: view {orch.view + 1}/{n}, {orch.frames} frames, {orch.state}, "
                                      f"{time.monotonic() - t0:.0f} s"))
        timings["scan_s"] = time.monotonic() - t0
        if orch.state == "aborted":
            raise GraphError(f"the scan aborted after {orch.frames} frames: {orch.message}")
        frames = orch.frames
        say(f"scan done: {frames} frames in {timings['scan_s']:.1f} s ({orch.message})")

        # 3. the recorder has every frame and geometry: close the bag
        def recorded(topic):
            return 0 if rec.writer is None else rec.writer.counts.get(topic, 0)
        spin_until(lambda: recorded(fmt.TOPIC_PROJECTION) >= frames and recorded(fmt.TOPIC_GEOMETRY) >= frames,
                   15.0, f"the recorder to write {frames} frames and geometries "
                         f"(has {recorded(fmt.TOPIC_PROJECTION)} / {recorded(fmt.TOPIC_GEOMETRY)})")
        bag = rec.close_bag()
        say(f"recorder closed {bag}")

        # 4. the online correction (auto_run on scan/status done; else started here)
        t0 = time.monotonic()
        if not recon_node.service.auto_run:
            spin_until(lambda: recon_node.n_paired >= frames and not recon_node.running,
                       15.0 + (recon_timeout_s if recon_node.service.every_n_views else 0.0),
                       "recon_service to collect every frame (and end a partial run)")
            ok, msg = recon_node.start_run()
            if not ok:
                raise GraphError(f"recon/run refused: {msg}")
        # (every_n_views: partial runs may run before; the one on the whole scan is started once they end)
        spin_until(lambda: recon_node.full_runs > 0, 15.0 + (recon_timeout_s if recon_node.service.every_n_views else 0.0),
                   "the correction to start")
        # the acquisition is over: stop its nodes, so the executor (and the CPU) serves the correction
        # alone; the simulated arms alone publish hundreds of messages a second
        for node in [nd for nd in nodes if nd not in (recon_node, probe)]:
            executor.remove_node(node)
            node.destroy_node()
            nodes.remove(node)
        spin_until(lambda: recon_node.done and not recon_node.run_partial, recon_timeout_s,
                   "the correction to finish",
                   report=lambda: say(f"recon: working ({time.monotonic() - t0:.0f} s)"),
                   period_s=3 * progress_period_s)
        if recon_node.state == "failed":
            raise GraphError(f"the correction failed: {recon_node.error}")
        spin_until(lambda: len(corrected) >= frames and len(slices) == len(SLICES), 30.0,
                   f"the corrected geometry of {frames} frames and the slices (got {len(corrected)}, {len(slices)})")
        timings["recon_s"] = time.monotonic() - t0
        report = dict(recon_node.report or {})
        paths = report.get("paths", {})

        def path(key):
            return Path(paths[key]) if paths.get(key) else None
        timings["total_s"] = time.monotonic() - t_start
        return GraphResult(out_dir=out_dir, bag=Path(bag), recon_dir=Path(recon_params["output_dir"]),
                           corrected_bag=path("corrected_bag"), volume_npy=path("volume_npy"),
                           volume_tif=path("volume_tif"), report_json=path("report_json"),
                           report_md=path("report_md"), report=report, frames=frames, corrected=dict(corrected),
                           slices=dict(slices), progress=list(progress), timings_s=timings, live=dict(live))
    finally:
        _beam_off_first(nodes, executor, say)
        for node in reversed(nodes):
            try:
                executor.remove_node(node)
                node.destroy_node()
            except Exception:  # noqa: BLE001 - best effort teardown
                pass
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=context)
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
