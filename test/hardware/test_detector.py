"""Simulated photon-counting detector: scene, true-pose projection, beam fraction, faults."""

import threading
import time

import numpy as np
import pytest

from robot_ct_ros.ct.geometry import bin_projections
from robot_ct_ros.ct.hand_eye import HandEye, tool_goals_from_geometry
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.simulation import DetectorModel, raw_geometry
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan
from robot_ct_ros.hardware.detector import (DetectorConfig, DetectorError, DetectorSettings, DetectorTimeout,
                                            SimulatedDetector, SimulatedDetectorSettings, TruePoses, build_scene,
                                            make_detector, make_phantom)
from robot_ct_ros.parameters import from_ros_values, ros_defaults

CENTER = (400.0, 0.0, 300.0)
CFG = DetectorConfig(n_rows=12, n_cols=16, binning=2, raw_pixel_mm=0.5)


def _model(**kw):
    kw.setdefault("poisson", False)
    return DetectorModel(photons_per_pixel=5000.0, binning=2, raw_pitch_mm=0.5, chip_size_px=10, chip_gap_px=1,
                         dead_pixel_fraction=0.02, hot_pixel_fraction=0.01, seed=3, **kw)


@pytest.fixture(scope="module")
def scene():
    return build_scene(make_phantom("mouse", CENTER), 1.0, supersample=1)


def _geom(n=4):
    system = SeedSystem(raw_pixel_mm=CFG.raw_pixel_mm, binning=CFG.binning)
    return robotic_roi_scan(system, roi_center_mm=CENTER, fov_diameter_mm=8.0, n_views=n,
                            n_rows=CFG.n_rows, n_cols=CFG.n_cols)


def _detector(scene, poses, fraction=1.0, **kw):
    model = kw.pop("model", _model())
    det = SimulatedDetector(CFG, model, scene, HandEye(), lambda: poses, lambda t0, t1: fraction, **kw)
    det.connect()
    return det


def test_scene_parts_and_fine_roi():
    phantom = make_phantom("mouse", CENTER)
    one = build_scene(phantom, 1.0, supersample=1)
    assert len(one.parts) == 1
    two = build_scene(phantom, 1.0, roi_size_mm=4.0, roi_voxel_size_mm=0.5, roi_center_mm=CENTER, supersample=1)
    assert len(two.parts) == 2
    (coarse, cg), (fine, fg) = two.parts
    assert fg.voxel_size_mm == (0.5, 0.5, 0.5) and cg.voxel_size_mm == (1.0, 1.0, 1.0)
    # the fine box replaces the coarse voxels it covers: the total attenuation is about the same
    total_one = one.parts[0][0].sum() * 1.0
    total_two = coarse.sum() * 1.0 + fine.sum() * 0.125
    assert abs(total_two - total_one) < 0.02 * total_one
    cut = build_scene(phantom, 1.0, region_center_mm=CENTER, region_size_mm=(10.0, 10.0, 10.0), supersample=1)
    assert cut.parts[0][1].shape_zyx == (10, 10, 10)
    with pytest.raises(ValueError):
        make_phantom("teapot")


def test_frame_matches_the_true_geometry_projection(scene):
    geom = _geom()
    S, D = tool_goals_from_geometry(geom, HandEye())
    det = _detector(scene, (S[1], D[1]))
    flat, bad = det.flat_field()
    assert flat.shape == bad.shape == CFG.shape and bad.any() and not bad.all()
    frame = det.acquire(0.01)
    assert frame.counts.shape == CFG.shape and frame.counts.dtype == np.float32
    assert frame.start_ns < frame.stamp_ns < frame.end_ns
    assert frame.info["geometry"].allclose(geom.subset([1]), atol=1e-6)
    # noiseless model: counts = sum over valid raw pixels of I0 * gain * exp(-line integral)
    model = det.model
    gain, dead, hot, gap = model.pixel_maps(CFG.raw_shape)
    li = sum(forward_project(v, g, raw_geometry(geom.subset([1]), 2)) for v, g in scene.parts)[0]
    expect = bin_projections(np.where(dead | hot | gap, 0.0, 5000.0 / 4 * gain * np.exp(-li)), 2)
    np.testing.assert_allclose(frame.counts, expect, rtol=1e-4)
    assert np.all(frame.counts[~bad] < flat[~bad])  # the mouse attenuates every ray of this small ROI


def test_beam_fraction_scales_the_flux_and_dark_frames(scene):
    geom = _geom()
    S, D = tool_goals_from_geometry(geom, HandEye())
    full = _detector(scene, (S[0], D[0]), 1.0).acquire(0.01).counts
    half = _detector(scene, (S[0], D[0]), 0.5).acquire(0.01).counts
    dark_det = _detector(scene, (S[0], D[0]), 0.0)
    dark = dark_det.acquire(0.01)
    _, bad = dark_det.flat_field()
    np.testing.assert_allclose(half, 0.5 * full, rtol=1e-5)
    assert dark.info["beam_fraction"] == 0.0 and np.all(dark.counts == 0.0)
    noisy = _detector(scene, (S[0], D[0]), 1.0, model=_model(poisson=True), seed=1).acquire(0.01).counts
    assert np.all(noisy == np.round(noisy)) and not np.allclose(noisy, full)
    assert abs(noisy[~bad].mean() / full[~bad].mean() - 1) < 0.05


def test_true_pose_errors_move_the_image(scene):
    geom = _geom()
    S, D = tool_goals_from_geometry(geom, HandEye())
    a = _detector(scene, (S[2], D[2])).acquire(0.01)
    D_err = D[2].copy()
    D_err[:3, 3] += 2.0 * geom.u[2]  # detector 2 mm along u: the image moves by 2 binned pixels
    b = _detector(scene, (S[2], D_err)).acquire(0.01)
    assert not np.allclose(a.counts, b.counts)
    np.testing.assert_allclose(b.info["geometry"].detector_mm[0] - a.info["geometry"].detector_mm[0],
                               2.0 * geom.u[2], atol=1e-9)


def test_faults_timeout_no_poses_not_connected(scene):
    geom = _geom()
    S, D = tool_goals_from_geometry(geom, HandEye())
    det = _detector(scene, (S[0], D[0]), fail="timeout", hang_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(DetectorTimeout):
        det.acquire(0.01)
    assert time.monotonic() - t0 < 5.0
    # a disconnect releases a hanging acquisition at once
    det2 = _detector(scene, (S[0], D[0]), fail="timeout", hang_s=60.0)
    errors = []
    th = threading.Thread(target=lambda: errors.append(pytest.raises(DetectorError, det2.acquire, 0.01)))
    th.start()
    time.sleep(0.1)
    det2.disconnect()
    th.join(5.0)
    assert not th.is_alive() and errors
    with pytest.raises(DetectorError, match="poses unknown"):
        _detector(scene, None).acquire(0.01)
    with pytest.raises(DetectorError, match="not connected"):
        SimulatedDetector(CFG, _model(), scene, HandEye(), lambda: None, lambda a, b: 1.0).acquire(0.01)
    with pytest.raises(ValueError, match="disagree"):
        SimulatedDetector(DetectorConfig(12, 16, 1, 0.5), _model(), scene, HandEye(), lambda: None, lambda a, b: 1.0)


def test_read_out_waits_briefly_for_late_true_poses(scene):
    geom = _geom()
    S, D = tool_goals_from_geometry(geom, HandEye())
    box = {"poses": None}
    det = _detector(scene, None, pose_wait_s=5.0)
    det._true_poses = lambda: box["poses"]
    timer = threading.Timer(0.1, lambda: box.update(poses=(S[0], D[0])))
    timer.start()
    frame = det.acquire(0.01)
    timer.join()
    assert frame.info["geometry"].allclose(geom.subset([0]), atol=1e-6)


def test_settings_are_the_grabber_parameters_and_refuse_bad_values():
    # names and defaults of the pcd_grabber's parameters (config/pcd_grabber.yaml)
    assert ros_defaults(DetectorSettings) == {"driver": "simulated", "n_rows": 272, "n_cols": 636, "binning": 2,
                                              "raw_pixel_m": 55e-6, "exposure_s": 0.1, "exposure_timeout_s": 5.0,
                                              "frame_id": "pcd_detector", "world_frame": "world",
                                              "publish_true_geometry": True, "min_valid_pixel_fraction": 0.5}
    sim = ros_defaults(SimulatedDetectorSettings)
    assert sim["phantom"] == "carotid" and sim["phantom_center_m"] == [0.4, 0.0, 0.3]
    assert sim["region_center_m"] is None and sim["mount_error.detector_rotvec_rad"] == [0.0, 0.0, 0.0]
    assert set(sim) == {
        "phantom", "phantom_center_m", "region_center_m", "phantom_seed", "voxel_size_m", "region_size_m",
        "roi_size_m", "roi_voxel_size_m", "supersample", "photons_per_pixel", "chip_size_px", "chip_gap_px",
        "dead_pixel_fraction", "hot_pixel_fraction", "flat_field_sigma", "flat_frames", "poisson", "seed", "fail",
        "readout_s", "pose_max_age_s", "mount_error.source_translation_m", "mount_error.detector_translation_m",
        "mount_error.detector_rotvec_rad"}
    assert sim["photons_per_pixel"] == 49000.0 and sim["fail"] == "none" and sim["roi_voxel_size_m"] == 5e-5
    assert DetectorSettings(raw_pixel_m=5e-4, binning=2).config == DetectorConfig(272, 636, 2, 0.5)
    with pytest.raises(ValueError, match="exposure_s must be >= 0"):
        DetectorSettings(exposure_s=-0.1)
    with pytest.raises(ValueError, match="need 0 < exposure_s < exposure_timeout_s"):
        DetectorSettings(exposure_s=6.0)
    with pytest.raises(ValueError, match="n_rows must be a whole number"):
        DetectorSettings(n_rows=12.5)
    with pytest.raises(ValueError, match="phantom must be one of"):
        SimulatedDetectorSettings(phantom="teapot")
    with pytest.raises(ValueError, match="region_center_m needs 3"):
        from_ros_values(SimulatedDetectorSettings, {"region_center_m": [0.4, 0.0]})
    with pytest.raises(ValueError, match="roi_size_m: every item must be >= 0"):
        SimulatedDetectorSettings(roi_size_m=(0.01, -0.01, 0.01))
    with pytest.raises(ValueError, match="voxel sizes must be positive"):
        SimulatedDetectorSettings(voxel_size_m=0.0)
    # ROS lists in, tuples out; an empty list is "unset" for the optional region centre
    s = from_ros_values(SimulatedDetectorSettings, {"region_center_m": [], "roi_size_m": [0.01, 0.01, 0.01],
                                                    "mount_error.source_translation_m": [0.0, 1e-3, 0.0]})
    assert s.region_center_m is None and s.roi_size_m == (0.01, 0.01, 0.01)
    assert s.source_mount_error_m == (0.0, 1e-3, 0.0)


def test_true_poses_go_stale():
    clock = {"ns": 10 * 10 ** 9}
    poses = TruePoses(lambda: clock["ns"], max_age_s=1.0)
    S, D = np.eye(4), 2 * np.eye(4)
    poses.update("source", clock["ns"], S)
    assert poses() is None and len(poses) == 1  # the detector arm unknown
    poses.update("detector", clock["ns"] - 5 * 10 ** 8, D)
    got = poses()
    assert got is not None and got[0] is S and got[1] is D
    clock["ns"] += 6 * 10 ** 8  # the detector pose is now 1.1 s old
    assert poses() is None


def test_make_detector_from_settings():
    settings = DetectorSettings(n_rows=12, n_cols=16, binning=2, raw_pixel_m=5e-4, exposure_s=0.05,
                                exposure_timeout_s=2.0)
    sim = SimulatedDetectorSettings(phantom="mouse", phantom_center_m=tuple(np.array(CENTER) * 1e-3),
                                    voxel_size_m=1e-3, photons_per_pixel=5000.0, chip_size_px=10, chip_gap_px=1,
                                    seed=3, detector_mount_error_m=(0.0, 0.0, 1e-3))
    geom = _geom()
    S, D = tool_goals_from_geometry(geom, HandEye())
    det = make_detector(settings, sim, HandEye(), lambda: (S[1], D[1]), lambda a, b: 1.0, time.monotonic_ns)
    assert isinstance(det, SimulatedDetector) and det.config == CFG
    assert det.model.photons_per_pixel == 5000.0 and det.model.raw_pitch_mm == 0.5 and det.fail == "none"
    assert det.pose_wait_s == pytest.approx(0.975) and len(det.scene.parts) == 1
    # the true mounts carry the mount error: the detector sits 1 mm off along its normal
    true = det.true_geometry(S[1], D[1])
    np.testing.assert_allclose(true.detector_mm[0] - geom.detector_mm[1],
                               np.cross(geom.u[1], geom.v[1]), atol=1e-6)
    with pytest.raises(ValueError, match="not available"):
        make_detector(DetectorSettings(driver="real"), sim, HandEye(), lambda: None, lambda a, b: 1.0,
                      time.monotonic_ns)


def test_valid_pixel_fraction_counts_as_robot_ct_info():
    """Valid: not in the unusable-pixel map, finite flat > 0 and, for a frame, a finite non-negative count."""
    from robot_ct_ros.hardware.detector import valid_pixel_fraction

    flat = np.ones((2, 4), np.float32)
    bad = np.zeros((2, 4), bool)
    assert valid_pixel_fraction(flat, bad) == 1.0
    bad[0, 0] = True
    flat[0, 1] = 0.0
    flat[0, 2] = np.nan
    assert valid_pixel_fraction(flat, bad) == 5 / 8
    counts = np.zeros((2, 4), np.float32)  # a dark frame's zeros are valid
    counts[1, 0], counts[1, 1] = np.nan, -1.0
    assert valid_pixel_fraction(flat, bad, counts) == 3 / 8
