"""The whole graph on simulated hardware (robot_ct_ros.testing.graph): scan -> record -> online correction.

A small interior scan (24 views, 64 x 128 detector, an object inside the field of view, robot
errors of 0.1 mm / 0.05 deg per move and axis) runs through every node on one executor; the
recon_service corrects it online as soon as the scan is done. Checks: every frame is recorded
and gets a corrected geometry; the corrected geometry is closer to the true one
(/ct/geometry_true, gauge removed) than the nominal one; and calibrating the recorded bag
offline (robot-ct calibrate, same method) gives the same corrected geometry (calibration is
deterministic)."""

from __future__ import annotations

import json

import numpy as np

from robot_ct_ros.bag import read_scan
from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.jobs.calibrate import calibrate_bag
from robot_ct_ros.ct.metrics import reprojection_error, roi_points
from robot_ct_ros.testing.graph import run_scan_graph

N = 24
PROTOCOL = {"name": "e2e", "n_views": N, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.005,
            "detector": {"n_rows": 64, "n_cols": 128, "binning": 2, "raw_pixel_m": 0.000055},
            "exposure_s": 0.02, "settle_s": 0.01, "move_timeout_s": 10.0, "exposure_timeout_s": 2.0}
GRABBER = {"sim_phantom": "mouse", "sim_voxel_size_m": 0.0005, "sim_region_size_m": [0.003, 0.003, 0.1],
           "sim_roi_size_m": [0.004, 0.004, 0.004], "sim_roi_voxel_size_m": 0.000025}
METHOD, ITERATIONS = "ncc-lle-exact", 2


def test_scan_record_correct_and_replay_offline(tmp_path):
    lines = []
    r = run_scan_graph(tmp_path / "run", PROTOCOL, grabber=GRABBER,
                       arm_errors={"sim_sigma_mm": 0.1, "sim_sigma_deg": 0.05},
                       recon={"method": METHOD, "iterations": ITERATIONS}, say=lines.append, quiet=True,
                       scan_timeout_s=120.0, recon_timeout_s=600.0)
    assert r.frames == N
    assert any("scan done" in s for s in lines) and any(s.startswith("recon: iteration 2/2") for s in lines)

    # the recorder's bag holds the whole scan, with the true geometry of the simulation
    scan = read_scan(r.bag)
    assert scan.n_views == N and scan.geom_true is not None and not scan.warnings
    stamps = [int(s) for s in scan.stamps_ns]

    # the online correction: one corrected geometry per recorded frame, on the topic and in the bag
    assert sorted(r.corrected) == stamps
    online = read_scan(r.corrected_bag)
    assert [int(s) for s in online.stamps_ns] == stamps and online.geom_corrected is not None
    src = np.array([r.corrected[s][0] for s in stamps])
    np.testing.assert_allclose(src, online.geom_corrected.source_mm, atol=1e-6)
    assert r.volume_npy.exists() and r.volume_tif.exists() and r.report_md.exists()
    assert json.loads(r.report_json.read_text())["n_views"] == N
    assert set(r.slices) == {"axial", "sagittal", "coronal"}

    # closer to the truth than the nominal geometry (reprojection error with the gauge removed)
    grid = scan.default_grid()
    pts = roi_points(grid)
    err_nominal = reprojection_error(scan.geom, scan.geom_true, pts)["mean_px"]
    err_corrected = reprojection_error(online.geom_corrected, scan.geom_true, pts)["mean_px"]
    assert err_corrected < 0.9 * err_nominal, (err_nominal, err_corrected)
    truth = r.report["truth"]
    assert truth["reprojection_error_corrected_px"]["mean"] == err_corrected
    assert 0 < truth["ssim_nominal"] <= 1 and 0 < truth["ssim_corrected"] <= 1  # 24 views: too few to rank by SSIM

    # offline, from the recorded bag: the same corrected geometry
    report = calibrate_bag(r.bag, tmp_path / "offline", CalibrationSettings(method=METHOD, iterations=ITERATIONS),
                           say=lambda s: None).report
    offline = read_scan(report["corrected_bag"]).geom_corrected
    np.testing.assert_allclose(offline.source_mm, online.geom_corrected.source_mm, rtol=0, atol=1e-9)
    np.testing.assert_allclose(offline.detector_mm, online.geom_corrected.detector_mm, rtol=0, atol=1e-9)
    np.testing.assert_allclose(offline.u, online.geom_corrected.u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(offline.v, online.geom_corrected.v, rtol=0, atol=1e-12)
