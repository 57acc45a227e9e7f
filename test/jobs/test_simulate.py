"""robot_ct_ros.jobs.simulate: the phantoms robot-ct simulate offers, and its short scans."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.jobs.simulate import PHANTOMS, make_phantom


@pytest.mark.parametrize("name", PHANTOMS)
def test_each_offered_phantom_is_made_around_the_roi_it_centres_on(name):
    """Every phantom of PHANTOMS exists and holds the origin (the ROI's centre) inside its bounds; the seed
    draws its random details, the same seed the same phantom."""
    lo, hi = (np.asarray(b, float) for b in make_phantom(name, 0).bounds_mm())
    assert np.all(lo < 0.0) and np.all(hi > 0.0)
    np.testing.assert_array_equal(np.asarray(make_phantom(name, 1).bounds_mm()),
                                  np.asarray(make_phantom(name, 1).bounds_mm()))


def test_an_unknown_phantom_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="unknown phantom 'leg'.*carotid"):
        make_phantom("leg")


def test_a_short_scan_from_simulate_reconstructs_as_the_full_circle(tmp_path):
    """``simulate_bag(arc_deg=200)`` spreads the views over 200 degrees (half a turn and more than the fan), and
    its FDK with the true geometry (Parker's weights, no partial-arc warning) matches the full circle's FDK of
    the same phantom (photon noise made negligible); weighted as a full circle it holds about half the
    attenuation."""
    import warnings

    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.reconstruction import estimate_scan_axis, fdk
    from robot_ct_ros.jobs.simulate import simulate_bag

    kw = dict(phantom="mouse", views=60, rows=8, cols=64, sigma_mm=0.0, sigma_deg=0.0, photons=1e8, progress=False,
              say=lambda m: None)
    short = read_scan(simulate_bag(tmp_path / "short", arc_deg=200.0, **kw))
    full = read_scan(simulate_bag(tmp_path / "full", **kw))
    g = short.geom_true
    axis = estimate_scan_axis(g)
    e1 = np.cross(axis, [1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    phi = np.sort(np.degrees(np.arctan2(g.source_mm @ np.cross(axis, e1), g.source_mm @ e1)))
    gaps = np.diff(np.r_[phi, phi[0] + 360.0])
    assert 360.0 - gaps.max() == pytest.approx(200.0, abs=0.01)  # views at 0, 3.39, ... 200 degrees

    grid = short.default_grid()
    li_s, mask_s = short.to_line_integrals()
    li_f, mask_f = full.to_line_integrals()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "does not cover 360 degrees"
        v_short = fdk(li_s, g, grid, valid_mask=mask_s)
    v_full = fdk(li_f, full.geom_true, grid, valid_mask=mask_f)
    with pytest.warns(RuntimeWarning, match="360 degrees"):
        v_plain = fdk(li_s, g, grid, valid_mask=mask_s, short_scan=False)
    inner = np.zeros(grid.shape_zyx, bool)  # the field of view's inner 3/4 (the mouse is wider: truncated data)
    nz, ny, nx = grid.shape_zyx
    inner[:, ny // 8:ny - ny // 8, nx // 8:nx - nx // 8] = True
    assert v_short[inner].mean() == pytest.approx(v_full[inner].mean(), rel=0.01)  # 1e-5 here
    assert np.corrcoef(v_short[inner], v_full[inner])[0, 1] > 0.9  # 0.96: the truncation's artefacts differ
    assert v_plain[inner].mean() < 0.7 * v_full[inner].mean()


def test_a_one_row_detector_of_common_width_simulates(tmp_path):
    """1 x 256 and 1 x 560 were refused ("fine ROI grid ... exceeds max_voxels"): the default phantom voxel was sized
    from the one-row ROI alone while the fine grid adds a margin of millimetres on every side."""
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.cli import main

    assert main(["simulate", "--rows", "1", "--cols", "560", "--views", "4", "--out", str(tmp_path / "fan")]) == 0
    scan = read_scan(tmp_path / "fan")
    assert scan.geom.det_shape == (1, 560) and scan.n_views == 4


def test_bad_sigmas_and_a_fov_beyond_the_detector_name_their_option(tmp_path, capsys):
    """--sigma-mm -1 said 'per_view_sigma must be non-negative' (an internal name, not a usage error);
    --fov-mm 1000 said 'FOV radius must lie in [0, sod)' (a radius, no value, no limit)."""
    from robot_ct_ros.cli import main

    base = ["simulate", "--views", "8", "--rows", "8", "--cols", "16", "--quiet", "--out", str(tmp_path / "bag")]
    for option in ("--sigma-mm", "--sigma-deg"):
        with pytest.raises(SystemExit) as exit_:
            main(base + [option, "-1"])
        assert exit_.value.code == 2
        assert f"argument {option}: {option[2:]} must be >= 0, got '-1'" in capsys.readouterr().err
    for fov in ("1000", "11"):
        assert main(base + ["--fov-mm", fov]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert all(w in err for w in ("--fov-mm", "diameter", f"{fov} mm", "1.32 mm")), err
    assert not (tmp_path / "bag").exists()
