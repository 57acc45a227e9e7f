"""The main job on simulated hardware, end to end: scan -> record -> correct -> report.

``robot-ct demo --out out/demo`` (``make demo``; robot_ct_ros.cli holds its options) starts the whole node graph in one process
(robot_ct_ros.testing.graph): simulated arms with per-move coordination errors carry the source and the
photon-counting detector around a mouse phantom, the scan_orchestrator takes the scan, the
recorder writes the scan bag, and the recon_service corrects the per-view geometry online
(NCC-LLE) as soon as the scan is done, reconstructs, and reports. Since the simulation knows
the true geometry (/ct/geometry_true), the report gives the gauge-aligned reprojection error
of the nominal and of the corrected geometry against it, and the SSIM of the nominal and of
the corrected reconstruction against the reconstruction with the true geometry.

Default: 120 views of 0.1 s, detector cropped to 64 x 128 binned pixels (110 um), object
inside the field of view. The correction's prior (the recon_service's prior_sigma_* parameters)
is the simulated arms' accuracy, as a user sets it to their robots'. ``--quick``: 12 views on a
32 x 64 crop, one iteration (tests).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from robot_ct_ros.hardware.detector import make_phantom

__all__ = ["DEFAULTS", "MOUSE_SPINE_Y_M", "QUICK", "demo_settings", "demo_setup", "recon_parameters", "run_demo"]

DEFAULTS = {"views": 120, "rows": 64, "cols": 128, "phantom": "mouse", "method": "ncc-lle-exact", "iterations": None,
            "exposure_s": 0.1, "sigma_mm": 0.1, "sigma_deg": 0.05}
MOUSE_SPINE_Y_M = 0.0066  # the vertebral bodies lie 6.6 mm dorsal (-y) of the mouse phantom's centre
QUICK = {"views": 12, "rows": 32, "cols": 64, "iterations": 1, "exposure_s": 0.02}


def demo_settings(*, quick: bool = False, **given) -> dict:
    """The demo's settings: :data:`DEFAULTS`, then :data:`QUICK` with ``quick``, then the values
    given (None: keep)."""
    s = dict(DEFAULTS)
    if quick:
        s.update(QUICK)
    s.update({k: v for k, v in given.items() if v is not None and k in DEFAULTS})
    s["truncated"] = bool(given.get("truncated", False))
    s["quick"] = bool(quick)
    return s


def demo_setup(s: dict) -> tuple[dict, dict]:
    """(scan protocol dict, pcd_grabber simulation parameters) of the demo settings ``s``."""
    pitch_m = 2 * 55e-6
    magnification = 2.67
    fov_m = 0.98 * s["cols"] * pitch_m / magnification
    protocol = {"name": f"demo_{s['phantom']}_{s['views']}", "n_views": s["views"], "roi_center_m": [0.4, 0.0, 0.3],
                "axis": [0.0, 0.0, 1.0], "fov_diameter_m": fov_m, "sdd_m": 0.3424, "magnification": magnification,
                "detector": {"n_rows": s["rows"], "n_cols": s["cols"], "binning": 2, "raw_pixel_m": 55e-6},
                "exposure_s": s["exposure_s"], "settle_s": 0.05 if not s.get("quick") else 0.01,
                "move_timeout_s": 30.0, "exposure_timeout_s": 5.0}
    box = 0.6 * fov_m  # an object inside the field of view (its diagonal < the FOV diameter)
    roi_m = protocol["roi_center_m"]
    # the mouse's lumbar spine in the ROI: vertebrae and discs give every view axial structure
    # (a column through the heart and lungs has too little of it to fix the views along v)
    phantom_m = [roi_m[0], roi_m[1] + (MOUSE_SPINE_Y_M if s["phantom"] == "mouse" else 0.0), roi_m[2]]
    grabber = {"sim_phantom": s["phantom"], "sim_voxel_size_m": 0.0005, "sim_phantom_center_m": phantom_m,
               "sim_roi_size_m": [fov_m * 0.8] * 2 + [s["rows"] * pitch_m / magnification * 1.2],
               "sim_roi_voxel_size_m": 2.5e-5}
    if not s["truncated"]:
        grabber["sim_region_size_m"] = [box, box, 0.2]
    return protocol, grabber


def _config_hand_eye() -> dict:
    """The hand-eye mounts the demo's nodes get (config/hand_eye.yaml, SI form)."""
    import yaml

    from robot_ct_ros.nodes.config_files import package_config_dir

    with open(package_config_dir() / "hand_eye.yaml") as f:
        return yaml.safe_load(f)["/**"]["ros__parameters"]["hand_eye"]


def recon_parameters(s: dict) -> dict:
    """The recon_service parameters of the demo settings ``s``: method, iterations, and as the
    prior of the calibration the simulated arms' per-move error (per axis at the TCP:
    ``sigma_mm``, ``sigma_deg``) carried to the focal spot and the detector centre through the
    hand-eye mounts (ct.hand_eye.device_position_sigma_mm: a rotation error swings each device
    about its flange), each arm's largest per-axis error, which is the one across the beam; for a
    truncated scan the exterior model, reaching the phantom's far side. Stated as the TCP's own
    0.1 mm, the prior understates the source's error across the beam by 31 %, close to the
    guard's tolerance (docs/calibration.md §4, "Use"). The calibration's own default (0.3 mm,
    0.3 deg) is for robots whose accuracy nobody measured."""
    from robot_ct_ros.ct.geometry import axis_frame
    from robot_ct_ros.ct.hand_eye import HandEye, device_position_sigma_mm

    hand_eye = HandEye.from_dict(_config_hand_eye())
    rot_rad = math.radians(s["sigma_deg"])
    params = {"method": s["method"],
              "prior_sigma_translation_m": s["sigma_mm"] * 1e-3,
              "prior_sigma_source_m": float(device_position_sigma_mm(hand_eye.source, s["sigma_mm"], rot_rad).max())
              * 1e-3,
              "prior_sigma_detector_m": float(device_position_sigma_mm(hand_eye.detector, s["sigma_mm"], rot_rad).max())
              * 1e-3,
              "prior_sigma_rotation_rad": rot_rad}
    if s["iterations"] is not None:  # else the calibration's own: its schedule's (docs/calibration.md §3)
        params["iterations"] = s["iterations"]
    if s["truncated"]:
        # the whole phantom lies around the ROI: model it (docs/calibration.md, "The exterior model"),
        # out to its far side across the scan axis, as a user who knows the object would: the phantom's box
        # in the ROI grid's frame (z along the protocol's axis), where the exterior grid is cut
        protocol, grabber = demo_setup(s)
        centre_mm = 1000.0 * (np.asarray(grabber["sim_phantom_center_m"]) - np.asarray(protocol["roi_center_m"]))
        lo, hi = make_phantom(s["phantom"], centre_mm).bounds_mm()
        corners = np.array([[(lo, hi)[k >> i & 1][i] for i in range(3)] for k in range(8)])
        across = np.abs(corners @ axis_frame(protocol["axis"]))[:, :2]
        params.update(exterior="on", exterior_half_width_m=float(np.max(across)) * 1e-3)
    return params


DEMO_MARK = ".robot_ct_demo"
"""The file that marks a folder as a demo's output: only such a folder's outputs are replaced by the next run."""
DEMO_OUTPUTS = ("bags", "recon", "summary.json", "scan_protocol.yaml")


def claim_output(out: Path) -> None:
    """Make ``out`` the demo's output folder: a new or empty folder, or one an earlier demo marked
    (:data:`DEMO_MARK`, or its summary.json), whose outputs (:data:`DEMO_OUTPUTS`) are removed first, summary.json included, so a
    failed or interrupted run leaves none of the earlier run's. Any other folder is refused (ValueError): the
    demo never deletes what it did not write."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file")
    earlier_demo = (out / DEMO_MARK).exists() or (out / "summary.json").exists()  # summary.json: before the mark
    if out.is_dir() and any(out.iterdir()) and not earlier_demo:
        raise ValueError(f"--out {out} holds files an earlier demo did not write; give a new or empty folder (the "
                         "demo replaces its own outputs there)")
    for name in DEMO_OUTPUTS:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
    out.mkdir(parents=True, exist_ok=True)
    (out / DEMO_MARK).write_text("robot-ct demo output: the next demo run into this folder replaces its outputs\n")


def run_demo(out="out/demo", *, quick: bool = False, **given) -> int:
    """Run the demo into ``out`` (``given``: views, rows, cols, phantom, method, iterations,
    truncated; None keeps the default); 0 on success, 1 when the graph failed (it says why)."""
    from robot_ct_ros.testing.graph import GraphError, run_scan_graph

    t0 = time.monotonic()
    s = demo_settings(quick=quick, **given)
    out = Path(out)
    claim_output(out)
    protocol, grabber = demo_setup(s)

    def say(msg: str) -> None:
        print(f"[demo {time.monotonic() - t0:6.1f} s] {msg}", flush=True)

    say(f"{s['phantom']} phantom{' (whole, truncated projections)' if s['truncated'] else ' inside the field of view'}"
        f", {s['views']} views, detector {s['rows']}x{s['cols']} binned pixels of 110 um, robot errors "
        f"{s['sigma_mm']} mm / {s['sigma_deg']} deg per move and axis; "
        + ("no correction (method none: the nominal geometry)" if s["method"] == "none" else
           f"correction {s['method']}, "
           + (f"{s['iterations']} iteration(s)" if s["iterations"] else "its schedule's iterations")
           + ", with the arms' accuracy as its prior"))
    try:
        r = run_scan_graph(out, protocol, grabber=grabber,
                           arm_errors={"sim_sigma_mm": s["sigma_mm"], "sim_sigma_deg": s["sigma_deg"]},
                           recon=recon_parameters(s), say=say, quiet=True)
    except GraphError as exc:
        say(f"FAILED: {exc}")
        return 1
    wall = time.monotonic() - t0
    truth = r.report.get("truth") or {}
    summary = {"settings": s, "wall_s": wall, "timings_s": r.timings_s, "frames": r.frames,
               "paths": {"scan_bag": str(r.bag), "corrected_bag": str(r.corrected_bag),
                         "volume_npy": str(r.volume_npy), "volume_tif": str(r.volume_tif),
                         "report_json": str(r.report_json), "report_md": str(r.report_md)},
               "truth": truth}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    say(f"done in {wall:.1f} s (scan {r.timings_s.get('scan_s', 0):.1f} s, correction "
        f"{r.timings_s.get('recon_s', 0):.1f} s)")
    if truth:
        n, c = truth["reprojection_error_nominal_px"], truth["reprojection_error_corrected_px"]
        print(f"  reprojection error vs true geometry (gauge removed): nominal {n['mean']:.3f} px mean "
              f"({n['p95']:.3f} p95) -> corrected {c['mean']:.3f} px ({c['p95']:.3f} p95)")
        print(f"  SSIM vs true-geometry reconstruction: nominal {truth['ssim_nominal']:.4f} -> corrected "
              f"{truth['ssim_corrected']:.4f}")
    print(f"  scan bag       {r.bag}")
    print(f"  corrected bag  {r.corrected_bag}")
    print(f"  volume         {r.volume_npy}, {r.volume_tif}")
    print(f"  report         {r.report_json}, {r.report_md}")
    print(f"  summary        {out / 'summary.json'}")
    return 0
