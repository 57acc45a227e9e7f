"""CalibrationSettings (one typed object for code, CLI and ROS) and the method registry."""

import math

import pytest

from robot_ct_ros.ct.calibration import (METHODS, NO_CORRECTION, SCHEDULES, CalibrationSettings, get_method,
                                         method_names)
from robot_ct_ros.parameters import from_ros_values, ros_defaults, specs, to_dict


def test_every_field_is_described_and_the_defaults_are_valid():
    s = CalibrationSettings()
    for spec in specs(s):
        assert spec.help and spec.ros_name, spec.name
        spec.check(getattr(s, spec.name))
    assert s.prior_sigma == pytest.approx((0.3,) * 6 + (math.radians(0.3),) * 3)
    assert to_dict(s)["method"] == "ncc-lle-exact" and to_dict(s)["drift_order"] is None


@pytest.mark.parametrize("change, message", [
    ({"method": "fdk"}, "method must be one of none, l2-lle"),
    ({"iterations": 0}, "iterations must be >= 1"),
    ({"iterations": 2.5}, "iterations must be a whole number"),
    ({"padding": 0.9}, "padding must be >= 1"),
    ({"stop_update_px": float("nan")}, "stop_update_px must be finite"),
    ({"schedule": "fastest"}, "schedule must be one of auto, accurate, fast, exterior"),
    ({"prior_translation_mm": -0.1}, "prior_translation_mm must be >= 0"),
    ({"ensemble": 0}, "ensemble must be >= 1"),
    ({"drift_order": -2}, "drift_order must be >= 0"),
    ({"coarse_passes": 0}, "coarse_passes must be >= 1"),
    ({"projections": "yes"}, "projections must be one of truncated, complete, auto"),
])
def test_bad_values_are_refused_naming_the_field(change, message):
    with pytest.raises(ValueError, match=message):
        CalibrationSettings(**change)
    with pytest.raises(ValueError, match=message):
        CalibrationSettings().replace(**change)


def test_ros_parameters_are_si_and_round_trip():
    ros = ros_defaults(CalibrationSettings)
    assert ros["prior_sigma_translation_m"] == pytest.approx(0.3e-3)
    assert ros["prior_sigma_rotation_rad"] == pytest.approx(math.radians(0.3))
    assert ros["drift_order"] == -1 and ros["coarse_passes"] == 0 and ros["fine_volume"] == ""  # ROS has no None
    back = from_ros_values(CalibrationSettings, ros)
    for k, v in to_dict(CalibrationSettings()).items():
        assert to_dict(back)[k] == (pytest.approx(v) if isinstance(v, float) else v), k
    s = from_ros_values(CalibrationSettings, {"prior_sigma_translation_m": 0.0005, "prior_sigma_rotation_rad": 0.01,
                                              "drift_order": 3})
    assert s.prior_sigma == pytest.approx((0.5,) * 6 + (0.01,) * 3) and s.drift_order == 3
    assert from_ros_values(CalibrationSettings, {"prior_sigma_translation_m": 0.0}).prior_sigma is None
    with pytest.raises(ValueError, match="whole number"):
        from_ros_values(CalibrationSettings, {"iterations": 1.5})


def test_lengths_cross_the_ros_boundary_in_metres():
    """Review I4: the exterior grid's voxel and reach were ROS parameters in mm (exterior_voxel_mm); at ROS
    interfaces lengths are in metres (the design's SI rule), as the prior's are. The core and the CLI keep mm."""
    units = {s.ros_name: s.ros_unit for s in specs(CalibrationSettings) if s.ros}
    assert not [n for n, u in units.items() if u in ("mm", "um", "deg") or n.endswith(("_mm", "_um", "_deg"))], units
    ros = ros_defaults(CalibrationSettings)
    assert ros["exterior_voxel_m"] == pytest.approx(0.5e-3) and ros["exterior_half_width_m"] == 0.0
    s = from_ros_values(CalibrationSettings, {"exterior_voxel_m": 0.001, "exterior_half_width_m": 0.03})
    assert s.exterior_voxel_mm == 1.0 and s.exterior_half_width_mm == 30.0


def test_the_auto_schedule_runs_exterior_with_the_exterior_model_and_accurate_without():
    s = CalibrationSettings()
    assert s.schedule == "auto" and s.iterations is None and s.stop_ncc_gain is None and s.exterior_iterations is None
    roi, ext = s.resolved(exterior=False), s.resolved(exterior=True)
    assert (roi.schedule, roi.iterations, roi.stop_ncc_gain, roi.exterior_iterations) == ("accurate", 2, 0.0, 15)
    assert (ext.schedule, ext.iterations, ext.stop_ncc_gain, ext.exterior_iterations) == ("exterior", 8, 1e-4, 30)
    assert ext.plan() == SCHEDULES["exterior"] and ext.plan()["fine_binning"] == SCHEDULES["fast"]["fine_binning"]
    # a value the user gives wins over the schedule's, and a named schedule does not change with the model
    given = s.replace(iterations=3, stop_ncc_gain=0.0, exterior_iterations=20).resolved(exterior=True)
    assert (given.schedule, given.iterations, given.stop_ncc_gain, given.exterior_iterations) == ("exterior", 3, 0.0, 20)
    assert s.replace(schedule="fast").resolved(exterior=True).schedule == "fast"
    assert s.replace(schedule="fast").resolved(exterior=True).iterations == 2
    assert s.iterations_text() == "2 (8 with the exterior model)" and s.replace(iterations=4).iterations_text() == "4"
    # on ROS, unset is 0 (iterations, exterior_iterations) and -1 (stop_ncc_gain, where 0 turns the rule off)
    ros = ros_defaults(CalibrationSettings)
    assert ros["iterations"] == 0 and ros["exterior_iterations"] == 0 and ros["stop_ncc_gain"] == -1.0
    back = from_ros_values(CalibrationSettings, {"stop_ncc_gain": 0.0, "iterations": 0})
    assert back.stop_ncc_gain == 0.0 and back.iterations is None


def test_the_registry_names_every_method_once_and_none_is_no_correction():
    assert method_names()[0] == NO_CORRECTION and set(method_names()) == set(METHODS)
    assert {s.name: s for s in specs(CalibrationSettings)}["method"].choices == method_names()
    assert get_method("none").estimate is None
    assert all(m.estimate is not None and m.configs is not None for n, m in METHODS.items() if n != NO_CORRECTION)
    with pytest.raises(ValueError, match="unknown calibration method 'fdk'; choose one of none, l2-lle"):
        get_method("fdk")
    # the LLE methods draw samples and use the prior; the GDC baselines do neither
    assert {n for n, m in METHODS.items() if m.samples} == {"l2-lle", "ncc-lle", "ncc-lle-exact"}
    assert {n for n, m in METHODS.items() if m.uses_prior} == {"l2-lle", "ncc-lle", "ncc-lle-exact"}


def test_the_lle_configs_follow_the_settings():
    coarse, fine = get_method("ncc-lle-exact").configs(CalibrationSettings(seed=7, schedule="fast"))
    assert coarse.weighting == fine.weighting == "ncc-exact" and coarse.seed == 7
    assert fine.source_positions == "fixed" and fine.draws == 1  # the fast schedule's finer level
    assert coarse.prior_sigma == pytest.approx((0.3,) * 6 + (math.radians(0.3),) * 3)
    assert get_method("l2-lle").configs(CalibrationSettings().without_prior())[0].prior_sigma is None


def test_the_embeddings_neighbours_and_ridge_follow_the_settings():
    """Off, each LLE method keeps its own K and ridge; set, every LLE method's two levels take them,
    through the code and ROS (0 there is off); a ridge that is not positive is refused."""
    for name, (k, reg) in {"ncc-lle-exact": (24, 1e-5), "l2-lle": (24, 1e-5), "ncc-lle": (16, 1e-3)}.items():
        for cfg in get_method(name).configs(CalibrationSettings()):
            assert (cfg.n_neighbours, cfg.reg) == (k, pytest.approx(reg)), name
        for cfg in get_method(name).configs(CalibrationSettings(lle_neighbours=12, lle_ridge=1e-3)):
            assert (cfg.n_neighbours, cfg.reg) == (12, pytest.approx(1e-3)), name
    ros = from_ros_values(CalibrationSettings, {"lle_neighbours": 0, "lle_ridge": 0.0})
    assert ros.lle_neighbours is None and ros.lle_ridge is None
    assert from_ros_values(CalibrationSettings, {"lle_ridge": 1e-4}).lle_ridge == pytest.approx(1e-4)
    for bad in (0.0, -1e-3, float("nan")):
        with pytest.raises(ValueError, match="lle_ridge"):
            CalibrationSettings(lle_ridge=bad)
    with pytest.raises(ValueError, match="lle_neighbours must be >= 2"):
        CalibrationSettings(lle_neighbours=1)


def test_each_arm_may_state_its_own_translation_error():
    """Two robots, two accuracies: the source's three translations and the detector's three take
    their arm's sigma, through the code, ROS and the command line; off, both take the prior's."""
    s = CalibrationSettings().with_prior(0.5, 0.01, detector_mm=0.2)
    assert s.prior_sigma == pytest.approx((0.5,) * 3 + (0.2,) * 3 + (math.radians(0.01),) * 3)
    assert get_method("ncc-lle-exact").configs(s)[0].prior_sigma == pytest.approx(s.prior_sigma)
    assert CalibrationSettings(prior_source_mm=0.1).prior_sigma[:6] == pytest.approx((0.1,) * 3 + (0.3,) * 3)
    assert CalibrationSettings(prior_source_mm=0.1).without_prior().prior_sigma is None  # 0 still turns it off
    ros = from_ros_values(CalibrationSettings, {"prior_sigma_source_m": 0.0004, "prior_sigma_detector_m": 0.0})
    assert ros.prior_source_mm == pytest.approx(0.4) and ros.prior_detector_mm is None
    assert ros_defaults(CalibrationSettings)["prior_sigma_detector_m"] == 0.0  # ROS has no None
    for bad in (-1.0, float("inf")):  # 0 is off (test_a_zero_per_arm_prior_is_off_as_on_ros)
        with pytest.raises(ValueError, match="prior_detector_mm"):
            CalibrationSettings(prior_detector_mm=bad)


def test_yes_no_fields_take_bools_only_and_numbers_are_stored_as_their_fields_keep_them():
    """guard="false" was stored and counted as true; iterations=2.0 was stored as a float and crashed the loop;
    numpy's np.int64(3) was refused as 'not a number'."""
    import numpy as np

    for name in ("guard", "exterior_reach_guess", "undo_inconsistent"):
        for value in ("false", "off", 0, None):
            with pytest.raises(ValueError, match=name):
                CalibrationSettings(**{name: value})
    assert CalibrationSettings(guard=np.bool_(False)).guard is False
    s = CalibrationSettings(iterations=2.0, seed=np.int64(3), padding=np.float32(1.5), ensemble=np.int32(2))
    assert (s.iterations, s.seed, s.ensemble) == (2, 3, 2) and all(
        type(x) is int for x in (s.iterations, s.seed, s.ensemble))
    assert s.padding == 1.5 and type(s.padding) is float
    assert s.replace(seed=np.int64(4)).seed == 4 and type(s.replace(seed=np.int64(4)).seed) is int
    with pytest.raises(ValueError, match="whole number"):
        CalibrationSettings(iterations=2.5)


def test_settings_a_method_ignores_are_named_in_its_notes():
    """--method none --ensemble 3 --drift-order 1 and gdc --ensemble 2 ran without a word, while report.json's
    settings said ensemble 3 and 2."""
    import numpy as np

    from robot_ct_ros.ct.calibration import calibrate
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.trajectory import circular_scan

    geom = circular_scan(8, 60.0, 150.0, 8, 12, 1.0, 1.0)
    li = np.random.default_rng(0).random((8, 8, 12)).astype(np.float32)
    grid = VolumeGrid.centered((4, 6, 6), 1.0)
    none = calibrate(li, geom, grid, CalibrationSettings(method="none", ensemble=3, drift_order=1))
    assert any("no correction (none): ensemble 3, drift_order 1 did not apply" in n for n in none.notes), none.notes
    assert calibrate(li, geom, grid, CalibrationSettings(method="none")).notes == ()
    from robot_ct_ros.ct.calibration.loop import _unused_settings

    assert "ensemble 2 did not apply: gdc draws no samples" in _unused_settings(
        get_method("gdc"), CalibrationSettings(method="gdc", ensemble=2))
    assert _unused_settings(get_method("ncc-lle-exact"), CalibrationSettings(ensemble=2)) == ""
    # settings that another setting or the method leaves unused were accepted, recorded and ignored without a word
    for method, settings, words in (
            ("ncc-lle-exact", dict(prior_translation_mm=0.0, prior_source_mm=0.5), "prior_source_mm 0.5 did not apply"),
            ("ncc-lle-exact", dict(exterior="off", exterior_half_width_mm=30.0, exterior_reach_guess=False),
             "exterior_half_width_mm 30.0, exterior_reach_guess False did not apply: exterior is off"),
            ("gdc", dict(lle_neighbours=8), "lle_neighbours 8 did not apply"),
            ("ncc-lle", dict(lle_ridge=1e-3), "lle_ridge 0.001 did not apply"),
            # a deterministic method's seed, its prior (the guard's reference only), SIRT with FDK volumes
            ("gdc", dict(seed=7), "seed 7 did not apply: gdc draws no samples"),
            ("gdc-log", dict(prior_translation_mm=0.1), "prior_translation_mm 0.1 did not apply to the estimate"),
            ("ncc-lle-exact", dict(projections="complete", sirt_iterations=5), "sirt_iterations 5 did not apply")):
        assert words in _unused_settings(get_method(method), CalibrationSettings(method=method, **settings))
    for method, settings in (("ncc-lle-exact", dict(lle_ridge=1e-3, prior_source_mm=0.5, exterior_voxel_mm=0.25,
                                                    seed=7, sirt_iterations=5)),
                             ("ncc-lle", dict(lle_neighbours=8)), ("gdc", {})):  # each of these is used
        assert _unused_settings(get_method(method), CalibrationSettings(method=method, **settings)) == ""


def test_a_coarse_level_finer_than_the_fine_one_is_refused():
    """--coarse-binning 2 --fine-binning 4 ran with its "coarse" level finer than its "fine" one. lle_neighbours
    beyond the coarse level's samples failed during the run, unnamed ("need 2 <= n_neighbours <= n_samples")."""
    from robot_ct_ros.ct.calibration.lle.estimator import COARSE_SAMPLES

    CalibrationSettings(lle_neighbours=COARSE_SAMPLES)
    with pytest.raises(ValueError, match="lle_neighbours"):
        CalibrationSettings(lle_neighbours=COARSE_SAMPLES + 1)
    with pytest.raises(ValueError, match="coarse_binning"):
        CalibrationSettings(coarse_binning=2, fine_binning=4)
    with pytest.raises(ValueError, match="coarse_binning"):  # the schedule's coarse level (2) under accurate
        CalibrationSettings(fine_binning=4).resolved(False)
    one_level = CalibrationSettings(coarse_binning=1, exterior="off")  # (exterior: its fine level is 2)
    assert one_level.resolved(False).plan()["fine_binning"] == 1
    # a named schedule's level is known at once: refused where the settings are made (a node's start), not at the run
    for named in (dict(schedule="fast", coarse_binning=1), dict(schedule="accurate", fine_binning=4)):
        with pytest.raises(ValueError, match="coarse_binning"):
            CalibrationSettings(**named)


def test_binnings_either_schedule_of_auto_refuses_are_refused_when_the_settings_are_made():
    """Under schedule auto the binnings were checked only once a run had chosen its schedule, after the data were
    read and the truncation measured (the command line and the recon_service accepted --fine-binning 4 and the run
    failed, on the ROI model only). Both schedules auto may run are checked where the settings are made now."""
    for changes, schedule in ((dict(fine_binning=4), "accurate"), (dict(fine_binning=3), "accurate"),
                              (dict(coarse_binning=1), "exterior"),
                              (dict(coarse_binning=1, exterior="on"), "exterior")):
        with pytest.raises(ValueError, match=rf"coarse_binning \(\d\) must be at least fine_binning .*'{schedule}'"):
            CalibrationSettings(**changes)
    CalibrationSettings(coarse_binning=1, exterior="off")  # exterior off: auto never runs the exterior schedule
    CalibrationSettings(coarse_binning=1, fine_binning=1)
    CalibrationSettings(fine_binning=2, coarse_binning=4)


def test_a_zero_per_arm_prior_is_off_as_on_ros():
    """--prior-source-mm 0 passed the command line's range (>= 0) and was then refused by the settings ("must be
    positive"), a second, contradicting message; ROS already read 0 as off. 0 is off everywhere now."""
    s = CalibrationSettings(prior_source_mm=0.0, prior_detector_mm=0)
    assert s.prior_source_mm is None and s.prior_detector_mm is None
    assert s.prior_sigma == CalibrationSettings().prior_sigma
    with pytest.raises(ValueError, match="prior_source_mm"):
        CalibrationSettings(prior_source_mm=-1.0)
