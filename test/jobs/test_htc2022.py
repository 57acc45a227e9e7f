"""robot-ct import htc2022: a HTC2022 .mat becomes a 1-row line-integral scan bag with the
documented fan-beam geometry; bad files are refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from robot_ct_ros.bag import read_scan
from robot_ct_ros.cli import main
from robot_ct_ros.jobs.htc2022 import fan_beam_geometry, read_htc2022

REAL = Path("/work/shared/realdata/htc2022")
REAL_FULL = REAL / "htc2022_01a_full.mat"
REAL_FBP = REAL / "htc2022_01a_recon_fbp.mat"


def _parameters(n_det=40, angles=(0.0, 0.5, 1.0, 1.5, 2.0, 360.0)) -> dict:
    """A cut-down ``parameters`` struct: the real file's fields and values where it is present."""
    if REAL_FULL.exists():
        real = scipy.io.loadmat(REAL_FULL, squeeze_me=True, struct_as_record=False)["CtDataFull"].parameters
        params = {f: getattr(real, f) for f in real._fieldnames}
    else:
        params = {"geometryType": "Cone", "distanceSourceOrigin": 410.66, "distanceSourceDetector": 553.74,
                  "distanceUnit": "mm", "pixelSizePost": 0.2, "effectivePixelSizePost": 0.2 * 410.66 / 553.74}
    params.update(angles=np.asarray(angles, float), numberImages=len(angles), numDetectorsPost=n_det)
    return params


def _sinogram(n_views: int, n_det: int) -> np.ndarray:
    """The real file's first views (central detectors; the last a repeat of the first), else a smooth synthetic one."""
    if REAL_FULL.exists():
        real = scipy.io.loadmat(REAL_FULL, squeeze_me=True, struct_as_record=False)["CtDataFull"].sinogram
        c0 = (real.shape[1] - n_det) // 2
        sino = np.array(real[:n_views, c0:c0 + n_det])
    else:
        t = np.linspace(-1, 1, n_det)
        sino = np.array([np.clip(1 - (t - 0.1 * np.sin(k)) ** 2, 0, None) for k in range(n_views)])
    sino[-1] = sino[0]
    return sino


def write_htc_mat(path, *, n_det=40, angles=(0.0, 0.5, 1.0, 1.5, 2.0, 360.0), sinogram=None, drop=(), **changes):
    params = _parameters(n_det, angles)
    for name in drop:
        params.pop(name)
    params.update(changes)
    sino = _sinogram(len(angles), n_det) if sinogram is None else sinogram
    scipy.io.savemat(path, {"CtDataFull": {"type": "full", "sinogram": sino, "parameters": params}})
    return Path(path), sino, params


def test_import_writes_a_one_row_line_integral_bag_with_the_documented_geometry(tmp_path, capsys):
    mat, sino, params = write_htc_mat(tmp_path / "scan_full.mat")
    bag = tmp_path / "bag"
    assert main(["import", "htc2022", str(mat), "--out", str(bag)]) == 0
    assert "repeated last angle dropped" in capsys.readouterr().out
    scan = read_scan(bag)
    assert scan.warnings == []
    assert scan.units == "line_integral" and scan.flat is None
    assert scan.n_views == 5 and scan.geom.det_shape == (1, 40)  # the repeated 360 degree view is dropped
    np.testing.assert_array_equal(scan.counts[:, 0, :], sino[:5].astype(np.float32))  # stored unchanged
    assert scan.valid_mask.all()
    dso, dsd, pitch = params["distanceSourceOrigin"], params["distanceSourceDetector"], params["pixelSizePost"]
    assert scan.geom.col_pitch_mm == pytest.approx(pitch, abs=1e-12)
    assert scan.geom.allclose(fan_beam_geometry(params["angles"][:5], dso, dsd, 40, pitch), atol=1e-9)
    # the conventions, stated independently: ASTRA's fanflat -> fanflat_vec conversion in the plane z = 0
    t = np.deg2rad(params["angles"][:5])
    vec = scan.geom.to_astra_vec()
    np.testing.assert_allclose(vec[:, [0, 1]], np.c_[np.sin(t), -np.cos(t)] * dso, atol=1e-9)
    np.testing.assert_allclose(vec[:, [3, 4]], np.c_[-np.sin(t), np.cos(t)] * (dsd - dso), atol=1e-9)
    np.testing.assert_allclose(vec[:, [6, 7]], np.c_[np.cos(t), np.sin(t)] * pitch, atol=1e-12)
    np.testing.assert_allclose(vec[:, [2, 5, 8]], 0.0, atol=1e-12)
    np.testing.assert_allclose(scan.geom.v, [[0.0, 0.0, 1.0]] * 5, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", scan.geom.w, scan.geom.source_mm - scan.geom.detector_mm) > 0)
    assert np.cross(scan.geom.source_mm[0], scan.geom.source_mm[1])[2] > 0  # counter-clockwise about +z
    assert scan.info["notes"]["dropped_repeated_last_angle"] is True


def test_a_last_angle_that_is_no_repeat_is_kept(tmp_path):
    mat, sino, _ = write_htc_mat(tmp_path / "part.mat", angles=(0.0, 10.0, 20.0, 30.0, 40.0))
    d = read_htc2022(mat)
    assert not d.dropped_last and d.sinogram.shape == (5, 40)


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert all(w in err for w in words), err
    return err


def test_bad_files_are_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "never"

    def refused(path, *words):
        assert main(["import", "htc2022", str(path), "--out", str(out)]) == 2
        _one_line_error(capsys, *words)
        assert not out.exists()

    text = tmp_path / "notes.mat"
    text.write_text("not a MATLAB file\n")
    refused(text, "not a MATLAB .mat file")
    refused(tmp_path / "missing.mat", "cannot access", "missing.mat")
    other = tmp_path / "recon.mat"
    scipy.io.savemat(other, {"reconFullFbp": np.zeros((4, 4))})
    refused(other, "no HTC2022 struct", "reconFullFbp")
    refused(write_htc_mat(tmp_path / "nopitch.mat", drop=("pixelSizePost",))[0], "lacks pixelSizePost")
    refused(write_htc_mat(tmp_path / "ndet.mat", numDetectorsPost=41)[0], "numDetectorsPost is 41", "40 columns")
    refused(write_htc_mat(tmp_path / "nangles.mat", sinogram=np.ones((4, 40)))[0], "6 angles", "4 rows")
    refused(write_htc_mat(tmp_path / "dist.mat", distanceSourceOrigin=600.0)[0], "must be smaller")
    refused(write_htc_mat(tmp_path / "unit.mat", distanceUnit="cm")[0], "only mm")
    exists = tmp_path / "exists"
    exists.mkdir()
    assert main(["import", "htc2022", str(write_htc_mat(tmp_path / "ok.mat")[0]), "--out", str(exists)]) == 2
    _one_line_error(capsys, "exists already")


def _correlations(measured, projected):
    def corr(a, b):
        a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
        return float(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
    # the residual after removing each detector column's mean over the angles (the round disc) carries
    # the holes, which tell the conventions apart
    return corr(measured, projected), corr(measured - measured.mean(0), projected - projected.mean(0))


@pytest.mark.skipif(not (REAL_FULL.exists() and REAL_FBP.exists()), reason="shared HTC2022 data not present")
def test_real_htc2022_geometry_reprojects_the_datasets_own_reconstruction(tmp_path):
    """Our forward projection of the dataset's FBP (ASTRA's image axes = world x, y; row 0 at the
    largest y; 512 pixels of effectivePixelSizePost) along the imported geometry matches the measured
    sinogram, and clearly less so with the opposite rotation sense."""
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.projector import forward_project

    bag = tmp_path / "bag01a"
    assert main(["import", "htc2022", str(REAL_FULL), "--out", str(bag)]) == 0
    scan = read_scan(bag)
    assert scan.n_views == 720 and scan.geom.det_shape == (1, 560)
    fbp = scipy.io.loadmat(REAL_FBP, squeeze_me=True)["reconFullFbp"]
    eff = scan.info["voxel_size_m"][0] * 1e3
    grid = VolumeGrid((3, 512, 512), (eff, eff, eff), (-255.5 * eff, -255.5 * eff, -eff))
    vol = np.ascontiguousarray(np.broadcast_to(fbp[::-1], grid.shape_zyx), np.float32)
    measured = scan.counts[:, 0, :].astype(np.float64)
    full, residual = _correlations(measured, forward_project(vol, grid, scan.geom)[:, 0, :])
    d = read_htc2022(REAL_FULL)
    mirrored = fan_beam_geometry(-d.angles_deg, d.dso_mm, d.dsd_mm, 560, d.pitch_mm)
    full_m, residual_m = _correlations(measured, forward_project(vol, grid, mirrored)[:, 0, :])
    print(f"correlation {full:.4f} (residual {residual:.3f}); opposite rotation sense {full_m:.4f} "
          f"(residual {residual_m:.3f})")
    assert full > 0.995 and residual > 0.6
    assert full_m < full and residual_m < residual - 0.25


def test_fewer_than_four_views_are_refused_before_writing(tmp_path, capsys):
    """A 2-view file was imported (exit 0) into a bag that every reader refuses (a scan needs 4 paired views)."""
    out = tmp_path / "bag"
    mat = write_htc_mat(tmp_path / "two.mat", angles=(0.0, 0.5))[0]
    assert main(["import", "htc2022", str(mat), "--out", str(out)]) == 2
    _one_line_error(capsys, "two.mat holds 2 views", "at least 4")
    sino = _sinogram(5, 40)
    sino[1:3] = np.nan  # 3 of 4 views left (the repeated last dropped), one of them with no finite value
    mat = write_htc_mat(tmp_path / "nan.mat", angles=(0.0, 0.5, 1.0, 1.5, 360.0), sinogram=sino)[0]
    assert main(["import", "htc2022", str(mat), "--out", str(out)]) == 2
    _one_line_error(capsys, "2 of its 4 frames with a usable pixel", "at least 4")
    assert not out.exists()


@pytest.mark.parametrize("compressed", [False, True])
def test_a_truncated_mat_file_is_called_truncated(tmp_path, capsys, compressed):
    """A .mat file cut short (an incomplete copy) was reported as 'not a MATLAB .mat file'; its MAT 5 header
    tells it is one, and its first data element's byte count that it is cut."""
    path = write_htc_mat(tmp_path / "whole.mat")[0]
    if compressed:
        mat = {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
        scipy.io.savemat(path, mat, do_compression=True)
    whole = path.read_bytes()
    for n_bytes, words in ((len(whole) // 2, ("truncated", f"the file has {len(whole) // 2}")), (130, ("truncated",))):
        cut = tmp_path / f"cut{n_bytes}.mat"
        cut.write_bytes(whole[:n_bytes])
        assert main(["import", "htc2022", str(cut), "--out", str(tmp_path / "bag")]) == 2
        err = _one_line_error(capsys, cut.name, "a MATLAB .mat file", *words)
        assert "not a MATLAB" not in err
