"""robot-ct export: a bag's nominal (or a calibration's corrected) geometry as RTK XML and ASTRA
cone_vec, read back into the same geometry; RTK projects through it as we do; clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.cli import main
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.trajectory import circular_scan
from robot_ct_ros.jobs.importers import astra_geometry, read_astra_vectors
from robot_ct_ros.jobs.htc2022 import fan_beam_geometry


def _geometry(seed=0, n=8):
    """A circular scan with per-view errors: every parameter of every view differs."""
    rng = np.random.default_rng(seed)
    return circular_scan(n, 60.0, 150.0, 12, 20, 0.8, 0.7).perturbed(rng.normal(0, [0.3] * 6 + [0.01] * 3, (n, 9)))


@pytest.fixture
def bag(tmp_path):
    g = _geometry()
    return write_scan(tmp_path / "scan", np.ones((g.n_views,) + g.det_shape, np.float32), g,
                      projection_units="line_integral")


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert all(w in err for w in words), err
    return err


def _read_rtk_xml(path):
    from robot_ct_ros.ct import rtk_bridge

    _, rtk = rtk_bridge._rtk()
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(path))
    reader.GenerateOutputInformation()
    return reader.GetOutputObject()


def _interior_volume(grid, seed=0):
    """Random values with a zero border of 3 voxels (RTK's and our Joseph projectors differ only in
    how they treat the volume's outer voxels)."""
    vol = np.zeros(grid.shape_zyx, np.float32)
    inner = tuple(slice(3, s - 3) for s in grid.shape_zyx)
    vol[inner] = np.random.default_rng(seed).random(vol[inner].shape)
    return vol


def _stated_frame(xml):
    """The geometry of the bag in the RTK frame the export wrote beside ``xml`` (world->RTK, 4 x 4)."""
    doc = json.loads((xml.parent / (xml.stem + ".rtk_frame.json")).read_text())
    m = np.array(doc["world_to_rtk"])
    np.testing.assert_allclose(np.array(doc["rtk_to_world"]) @ m, np.eye(4), atol=1e-12)
    return doc, m[:3, :3], m[:3, 3]


@pytest.mark.parametrize("frame", [None, "world"], ids=["auto", "world"])
@pytest.mark.parametrize("one_row", [False, True], ids=["cone", "fan"])
def test_rtk_xml_round_trip_and_rtk_projects_through_it_as_we_do(tmp_path, capsys, one_row, frame):
    pytest.importorskip("itk")
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.rtk_bridge import from_rtk_geometry, rtk_forward_project

    if one_row:
        g = fan_beam_geometry(np.arange(0.0, 360.0, 23.0), 410.66, 553.74, 64, 1.6)
        grid = VolumeGrid.centered((9, 48, 48), 1.0)
    else:
        g = _geometry()
        grid = VolumeGrid.centered((16, 24, 24), 0.5)
    src = write_scan(tmp_path / "scan", np.ones((g.n_views,) + g.det_shape, np.float32), g,
                     projection_units="line_integral")
    world = read_scan(src).geom  # as the bag carries it (metres on the wire)
    xml = tmp_path / "geometry.xml"
    assert main(["export", str(src), "--format", "rtk", "--out", str(xml)]
                + ([] if frame is None else ["--rtk-frame", frame])) == 0
    said = capsys.readouterr().out
    assert "RTK projection stack origin" in said
    # the scan turns about the world's z: auto writes the scan frame; the geometry round-trips in the stated frame
    doc, rot, shift = _stated_frame(xml)
    assert doc["frame"] == (frame or "scan") and f"RTK frame: {doc['frame']}" in said
    if frame == "world":
        np.testing.assert_array_equal(rot, np.eye(3))
        np.testing.assert_array_equal(shift, np.zeros(3))
    else:
        np.testing.assert_allclose(rot @ [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], atol=0.02)
    g = g.moved(rot, shift)
    # the options it prints bring the stack back (the origin was printed x first, and import takes rows first)
    import re

    pitch, origin = re.search(r"--pitch-mm (\S+) --origin-mm=(\S+)\)", said).groups()
    np.save(tmp_path / "p.npy", np.ones((g.n_views,) + g.det_shape, np.float32))
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml), "--pitch-mm",
                 pitch, f"--origin-mm={origin}", "--out", str(tmp_path / "back")]) == 0
    nominal = world.moved(rot, shift)  # in the frame the export states
    assert read_scan(tmp_path / "back").geom.allclose(nominal, atol=1e-9)
    back = from_rtk_geometry(_read_rtk_xml(xml), g.n_rows, g.n_cols, g.row_pitch_mm, g.col_pitch_mm)
    assert back.allclose(nominal, atol=1e-9)
    assert nominal.allclose(g, atol=1e-9)
    vol = _interior_volume(grid)
    ours = forward_project(vol, grid, nominal)
    theirs = rtk_forward_project(vol, grid, back)
    assert ours.max() > 1.0
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=2e-6 * ours.max())


def test_rtk_fdk_of_an_exported_z_axis_scan_is_robot_cts_fdk(tmp_path, capsys):
    """A scan about the world's z went out with RTK's gantry angle the same (270 deg) in every view and the
    rotation in the out-of-plane / in-plane angles: RTK's FDK of it had a correlation of -0.2 with ours. It is
    now written in the scan frame (axis +y, orbit centre at the origin); RTK's FDK on the XML and the bag's
    projections, mapped back through the transform written beside it, is ours on the same voxels."""
    pytest.importorskip("itk")
    from robot_ct_ros.ct import rtk_bridge
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.reconstruction import fdk

    itk, rtk = rtk_bridge._rtk()
    centre = np.array([4.0, -3.0, 2.0])
    g = circular_scan(60, 60.0, 150.0, 24, 40, 0.8, 0.8, center_mm=centre)  # about z, off the origin
    grid = VolumeGrid.centered((24, 24, 24), 0.6, centre)
    zz, yy, xx = np.meshgrid(*[np.arange(24) - 11.5] * 3, indexing="ij")
    vol = ((xx / 8) ** 2 + ((yy - 2) / 5) ** 2 + ((zz + 1) / 7) ** 2 < 1).astype(np.float32)
    vol += ((xx + 4) ** 2 + yy ** 2 + (zz - 3) ** 2 < 6).astype(np.float32)
    proj = forward_project(vol, grid, g)
    src = write_scan(tmp_path / "scan", proj, g, projection_units="line_integral")
    xml = tmp_path / "geometry.xml"

    def rtk_vs_ours(*extra):
        assert main(["export", str(src), "--format", "rtk", "--out", str(xml), *extra]) == 0
        doc, rot, shift = _stated_frame(xml)
        rtk_grid = VolumeGrid.centered((32, 32, 32), 0.5, rot @ centre + shift)  # where RTK's user puts it
        reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
        reader.SetFilename(str(xml))
        reader.GenerateOutputInformation()
        f = rtk.FDKConeBeamReconstructionFilter[itk.Image[itk.F, 3]].New()
        f.SetInput(0, rtk_bridge.volume_to_itk(np.zeros(rtk_grid.shape_zyx, np.float32), rtk_grid))
        f.SetInput(1, rtk_bridge.projections_to_itk(read_scan(src).to_line_integrals()[0], g))
        f.SetGeometry(reader.GetOutputObject())
        f.Update()
        theirs = rtk_bridge.itk_to_volume(f.GetOutput())[0]
        # the same voxels in the world, as the frame file says: origin R^T o + c, direction R^T D
        back = np.array(doc["rtk_to_world"])
        world_grid = VolumeGrid(rtk_grid.shape_zyx, rtk_grid.voxel_size_mm,
                                tuple(back[:3, :3] @ np.array(rtk_grid.origin_mm) + back[:3, 3]),
                                tuple((back[:3, :3] @ rtk_grid.direction_matrix).ravel()))
        ours = fdk(proj, g, world_grid, truncation=None, window="ram-lak")
        return doc, float(np.corrcoef(theirs.ravel(), ours.ravel())[0, 1])

    doc, corr = rtk_vs_ours()
    assert doc["frame"] == "scan" and corr > 0.95, corr
    np.testing.assert_allclose(doc["scan_centre_world_mm"], centre, atol=1e-6)
    np.testing.assert_allclose(doc["scan_axis_world"], [0.0, 0.0, 1.0], atol=1e-9)
    assert "RTK frame: scan" in capsys.readouterr().out
    doc, corr_world = rtk_vs_ours("--rtk-frame", "world")  # the world as it is: RTK's weights go wrong
    assert doc["frame"] == "world" and corr_world < corr - 0.2, (corr, corr_world)


def test_rtk_frame_auto_keeps_a_world_that_already_turns_about_y(tmp_path, capsys):
    """An RTK-style scan (about +y through the origin) is exported as it is, with the identity written."""
    g = circular_scan(12, 60.0, 150.0, 12, 20, 0.8, 0.7, axis=(0.0, 1.0, 0.0))
    src = write_scan(tmp_path / "scan", np.ones((g.n_views,) + g.det_shape, np.float32), g,
                     projection_units="line_integral")
    from robot_ct_ros.jobs.export import rtk_frame

    assert rtk_frame(g)["frame"] == "world"
    assert rtk_frame(g.moved(np.eye(3), [30.0, 0.0, 0.0]))["frame"] == "scan"  # the axis off the origin
    if not _has_itk():
        return
    xml = tmp_path / "g.xml"
    assert main(["export", str(src), "--format", "rtk", "--out", str(xml)]) == 0
    assert "RTK frame: world" in capsys.readouterr().out
    doc, rot, shift = _stated_frame(xml)
    assert doc["frame"] == "world" and np.array_equal(rot, np.eye(3)) and not shift.any()


def _has_itk():
    try:
        import itk  # noqa: F401
    except ImportError:
        return False
    return True


def test_rtk_frame_with_another_format_is_refused(tmp_path, bag, capsys):
    assert main(["export", str(bag), "--format", "astra", "--out", str(tmp_path / "v.npy"),
                 "--rtk-frame", "scan"]) == 2
    _one_line_error(capsys, "--rtk-frame")


@pytest.mark.parametrize("suffix", [".npy", ".txt"])
def test_astra_vectors_round_trip_and_follow_astras_pixel_convention(tmp_path, bag, suffix):
    out = tmp_path / f"vectors{suffix}"
    assert main(["export", str(bag), "--format", "astra", "--out", str(out)]) == 0
    nominal = read_scan(bag).geom
    vec = np.load(out) if suffix == ".npy" else np.loadtxt(out)
    assert vec.shape == (nominal.n_views, 12)
    assert astra_geometry(read_astra_vectors(out), nominal.n_rows, nominal.n_cols).allclose(nominal, atol=1e-9)
    # ASTRA: src, detector centre, u = pixel (0,0) -> (0,1) (next column), v = pixel (0,0) -> (1,0) (next row)
    for i in (0, nominal.n_views - 1):
        px = nominal.pixel_centers_mm(i)
        np.testing.assert_allclose(vec[i, 0:3], nominal.source_mm[i], atol=1e-9)
        np.testing.assert_allclose(vec[i, 3:6], px.mean(axis=(0, 1)), atol=1e-9)
        np.testing.assert_allclose(vec[i, 6:9], px[0, 1] - px[0, 0], atol=1e-9)
        np.testing.assert_allclose(vec[i, 9:12], px[1, 0] - px[0, 0], atol=1e-9)


def test_export_of_a_corrected_geometry(tmp_path, bag, capsys):
    scan = read_scan(bag)
    corrected = scan.geom.perturbed(np.full(9, 0.01))
    calib = tmp_path / "calib"
    # what robot-ct calibrate --out writes (write_correction), with the corrected geometry given
    from types import SimpleNamespace

    from robot_ct_ros.jobs.calibrate import Correction, write_correction

    scan_raw = read_scan(bag, keep_raw=True)
    grid = VolumeGrid.centered((2, 2, 2), 1.0)
    result = SimpleNamespace(geom=corrected, volume=np.zeros(grid.shape_zyx, np.float32))
    write_correction(Correction(scan_raw, grid, result, {"method_used": "test", "iterations_run": 1}), calib,
                     say=lambda m: None)
    corrected_bag = calib / "scan_corrected"
    expected = read_scan(corrected_bag).geom_corrected
    assert not expected.allclose(scan.geom, atol=1e-6)
    for i, where in enumerate((calib, calib / "report.json", corrected_bag)):
        out = tmp_path / f"corrected{i}.npy"
        assert main(["export", str(bag), "--format", "astra", "--corrected", str(where), "--out", str(out)]) == 0
        assert "corrected geometry" in capsys.readouterr().out
        assert astra_geometry(read_astra_vectors(out), 12, 20).allclose(expected, atol=1e-9)
    moved = tmp_path / "moved"
    calib.rename(moved)  # report.json names the old place: the bag next to it is used
    assert main(["export", str(bag), "--format", "astra", "--corrected", str(moved), "--out",
                 str(tmp_path / "m.npy")]) == 0
    assert astra_geometry(read_astra_vectors(tmp_path / "m.npy"), 12, 20).allclose(expected, atol=1e-9)
    # the corrected bag and the report are spared as the bag is; a new file beside them is fine
    mcap = next((moved / "scan_corrected").glob("*.mcap"))
    for out, words in ((mcap, "lies in the corrected bag"), (moved / "report.json", "the calibration's report")):
        before = out.read_bytes()
        assert main(["export", str(bag), "--format", "astra", "--corrected", str(moved), "--out", str(out)]) == 2
        _one_line_error(capsys, words)
        assert out.read_bytes() == before
    assert main(["export", str(bag), "--format", "astra", "--corrected", str(moved), "--out",
                 str(moved / "v.npy")]) == 0

    other = _geometry(seed=1, n=6)
    other_bag = write_scan(tmp_path / "other", np.ones((6, 12, 20), np.float32), other,
                           projection_units="line_integral")
    assert main(["export", str(other_bag), "--format", "astra", "--corrected", str(moved), "--out",
                 str(tmp_path / "x.npy")]) == 2
    _one_line_error(capsys, "other views")
    assert main(["export", str(bag), "--format", "astra", "--corrected", str(bag), "--out",
                 str(tmp_path / "x.npy")]) == 2
    _one_line_error(capsys, "no /ct/geometry_corrected")
    (tmp_path / "r.json").write_text(json.dumps({"method": "none"}))
    assert main(["export", str(bag), "--format", "astra", "--corrected", str(tmp_path / "r.json"), "--out",
                 str(tmp_path / "x.npy")]) == 2
    _one_line_error(capsys, "no corrected_bag")
    assert not (tmp_path / "x.npy").exists()


def test_export_errors_are_one_line(tmp_path, bag, capsys, monkeypatch):
    assert main(["export", str(tmp_path / "missing"), "--format", "astra", "--out", str(tmp_path / "a.npy")]) == 2
    _one_line_error(capsys, "no such bag")
    assert main(["export", str(bag), "--format", "astra", "--out", str(tmp_path)]) == 2
    _one_line_error(capsys, "is a folder")
    assert main(["export", str(bag), "--format", "astra", "--out", str(tmp_path / "no" / "a.npy")]) == 2
    _one_line_error(capsys, "is not a folder")

    from robot_ct_ros.ct import rtk_bridge

    def no_rtk():
        raise ImportError("No module named 'itk'")
    monkeypatch.setattr(rtk_bridge, "_rtk", no_rtk)
    assert main(["export", str(bag), "--format", "rtk", "--out", str(tmp_path / "g.xml")]) == 2
    _one_line_error(capsys, "needs itk-rtk")
    assert not (tmp_path / "g.xml").exists()


# ----------------------------------------------------------------------------------- TIGRE
def _tigre_pixels(p, i, c):
    """TIGRE's pixel positions of view i, transcribed from its CUDA computeDeltas (rollPitchYaw,
    offsets, eulerZYZ, -offOrigin), Python arrays as its convert_to_c_geometry reads them; plus our
    world offset ``c``. Returns (nV, nU, 3) indexed [pV, pU]."""
    nV, nU = (int(x) for x in p["nDetector"])
    dV, dU = (float(x) for x in p["dDetector"])
    DSO, DSD = p["DSO"][i], p["DSD"][i]
    offV, offU = p["offDetector"][i]
    yaw, pitch, roll = p["rotDetector"][i]
    alpha, theta, psi = p["angles"][i]
    oz, oy, ox = p["offOrigin"][i]

    def roll_pitch_yaw(q):
        x, y, z = q
        cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
        return np.array([cr * cp * x + (cr * sp * sy - sr * cy) * y + (cr * sp * cy + sr * sy) * z,
                         sr * cp * x + (sr * sp * sy + cr * cy) * y + (sr * sp * cy - cr * sy) * z,
                         -sp * x + cp * sy * y + cp * cy * z])

    def euler_zyz(q):
        x, y, z = q
        ca, sa, ct, st, cs, ss = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta), np.cos(psi), np.sin(psi)
        return np.array([(ca * ct * cs - sa * ss) * x + (-ca * ct * ss - sa * cs) * y + ca * st * z,
                         (sa * ct * cs + ca * ss) * x + (-sa * ct * ss + ca * cs) * y + sa * st * z,
                         -st * cs * x + st * ss * y + ct * z])

    def place(pu, pv):
        q = roll_pitch_yaw(np.array([0.0, dU * (pu - nU / 2 + 0.5), dV * (nV / 2 - 0.5 - pv)]))
        q = q + np.array([-(DSD - DSO), offU, offV])
        return euler_zyz(q) - np.array([ox, oy, oz]) + c

    origin, du, dv = place(0, 0), place(1, 0) - place(0, 0), place(0, 1) - place(0, 0)
    pu, pv = np.meshgrid(np.arange(nU), np.arange(nV))
    source = euler_zyz(np.array([DSO, 0.0, 0.0])) - np.array([ox, oy, oz]) + c
    return origin + pu[..., None] * du + pv[..., None] * dv, source


def test_tigre_round_trip_and_tigres_own_pixel_formula(tmp_path, bag):
    from robot_ct_ros.jobs.tigre import from_tigre, to_tigre

    out = tmp_path / "geometry.npz"
    assert main(["export", str(bag), "--format", "tigre", "--out", str(out)]) == 0
    scan = read_scan(bag)
    p = dict(np.load(out))
    assert p["angles"].shape == (8, 3) and p["offDetector"].shape == (8, 2) and p["rotDetector"].shape == (8, 3)
    np.testing.assert_allclose(p["center_mm"], scan.scan_center_mm(), atol=0)
    np.testing.assert_array_equal(p["nDetector"], [12, 20])
    assert from_tigre(p).allclose(scan.geom, atol=1e-9)
    for i in (0, 5):  # our row r is TIGRE's pV = nV - 1 - r
        px, src = _tigre_pixels(p, i, p["center_mm"])
        np.testing.assert_allclose(px[::-1], scan.geom.pixel_centers_mm(i), atol=1e-9)
        np.testing.assert_allclose(src, scan.geom.source_mm[i], atol=1e-9)

    # arbitrary TIGRE parameters (offOrigin, every angle, detector tilts): TIGRE -> ours -> TIGRE -> ours
    rng = np.random.default_rng(4)
    n = 6
    q = {"DSO": rng.uniform(400, 600, n), "angles": rng.uniform(-np.pi, np.pi, (n, 3)),
         "offOrigin": rng.normal(0, 5, (n, 3)), "offDetector": rng.normal(0, 10, (n, 2)),
         "rotDetector": rng.normal(0, 0.3, (n, 3)), "nDetector": np.array([5, 7]), "dDetector": np.array([0.4, 0.3]),
         "center_mm": np.array([1.0, -2.0, 3.0])}
    q["DSD"] = q["DSO"] + rng.uniform(200, 400, n)
    g = from_tigre(q)
    for i in range(n):
        px, src = _tigre_pixels(q, i, q["center_mm"])
        np.testing.assert_allclose(px[::-1], g.pixel_centers_mm(i), atol=1e-9)
        np.testing.assert_allclose(src, g.source_mm[i], atol=1e-9)
    assert from_tigre(to_tigre(g, q["center_mm"])).allclose(g, atol=1e-9)
    assert not from_tigre(q | {"rotDetector": q["rotDetector"][:, ::-1]}).allclose(g, atol=1e-3)  # the order matters


def test_tigre_export_of_a_circular_scan_is_tigres_standard_circle(tmp_path):
    angles = np.arange(0.0, 360.0, 30.0)
    g = fan_beam_geometry(angles, 410.66, 553.74, 64, 1.6)
    src = write_scan(tmp_path / "scan", np.ones((g.n_views,) + g.det_shape, np.float32), g,
                     projection_units="line_integral")
    out = tmp_path / "t.npz"
    assert main(["export", str(src), "--format", "tigre", "--out", str(out)]) == 0
    p = np.load(out)
    np.testing.assert_allclose(p["center_mm"], 0.0, atol=1e-9)
    alpha = np.deg2rad(angles - 90.0)
    np.testing.assert_allclose(np.angle(np.exp(1j * (p["angles"][:, 0] - alpha))), 0.0, atol=1e-12)
    np.testing.assert_allclose(p["angles"][:, 1:], 0.0, atol=1e-12)
    np.testing.assert_allclose(p["rotDetector"], 0.0, atol=1e-12)
    np.testing.assert_allclose(p["offDetector"], 0.0, atol=1e-9)
    np.testing.assert_allclose(p["offOrigin"], 0.0, atol=0)
    np.testing.assert_allclose(p["DSO"], 410.66, atol=1e-9)
    np.testing.assert_allclose(p["DSD"], 553.74, atol=1e-9)
    np.testing.assert_allclose(p["dDetector"], [1.6, 1.6], atol=1e-12)


def test_tigre_refuses_a_view_it_cannot_represent(tmp_path, capsys):
    g = _geometry()
    beyond = 2.0 * g.detector_mm[0]  # a volume centre behind view 0's detector
    src = write_scan(tmp_path / "scan", np.ones((g.n_views,) + g.det_shape, np.float32), g,
                     projection_units="line_integral", roi_center_mm=tuple(beyond))
    out = tmp_path / "t.npz"
    assert main(["export", str(src), "--format", "tigre", "--out", str(out)]) == 2
    err = _one_line_error(capsys, "view 0", "DSD", "<= DSO", f"of {g.n_views} views are so")
    assert "{" not in err  # every count filled in
    assert not out.exists()


def test_astra_vectors_in_an_upper_case_npy_file_import_back(tmp_path, bag):
    """Export wrote text into ``vec.NPY`` while import read any ``.npy`` suffix as numpy's format."""
    out = tmp_path / "vec.NPY"
    assert main(["export", str(bag), "--format", "astra", "--out", str(out)]) == 0
    nominal = read_scan(bag).geom
    assert np.load(out).shape == (nominal.n_views, 12)
    assert astra_geometry(read_astra_vectors(out), nominal.n_rows, nominal.n_cols).allclose(nominal, atol=1e-9)


def test_an_out_inside_the_bag_is_refused(tmp_path, bag, capsys):
    """export --out BAG/its.mcap overwrote the bag's own file with the geometry (exit 0): the scan was lost."""
    files = {p: p.read_bytes() for p in bag.iterdir()}
    mcap = next(p for p in files if p.suffix == ".mcap")
    for out in (mcap, bag / "metadata.yaml", bag / "new.npz"):
        assert main(["export", str(bag), "--format", "tigre", "--out", str(out)]) == 2
        _one_line_error(capsys, "lies in the bag", "overwrite")
    assert main(["export", str(mcap), "--format", "astra", "--out", str(mcap)]) == 2  # the bag as its .mcap file
    _one_line_error(capsys, "lies in the bag")
    (tmp_path / "link.npy").symlink_to(mcap)  # a link into the bag writes there too
    assert main(["export", str(bag), "--format", "astra", "--out", str(tmp_path / "link.npy")]) == 2
    _one_line_error(capsys, "lies in the bag")
    assert {p: p.read_bytes() for p in bag.iterdir()} == files
    assert read_scan(bag).n_views == 8
    assert main(["export", str(bag), "--format", "astra", "--out", str(tmp_path / "v.txt")]) == 0


def test_export_of_a_damaged_bag_says_what_the_reader_recovered(tmp_path, capsys):
    """A truncated bag: export wrote the views it could read and said nothing (info and reconstruct warn)."""
    g = _geometry(n=24)
    bag = write_scan(tmp_path / "scan", np.ones((24,) + g.det_shape, np.float32), g, projection_units="line_integral")
    mcap = next(bag.glob("*.mcap"))
    with open(mcap, "r+b") as f:
        f.truncate(mcap.stat().st_size * 2 // 3)
    warned = read_scan(bag).warnings
    assert warned
    assert main(["export", str(bag), "--format", "astra", "--out", str(tmp_path / "v.npy")]) == 0
    out = capsys.readouterr().out
    assert all(f"warning: {w}" in out for w in warned), out


@pytest.mark.parametrize("fmt, name, warned", [("astra", "v.npy", False), ("astra", "v.TXT", False),
                                               ("astra", "v.xml", True), ("tigre", "t.npz", False),
                                               ("tigre", "t.txt", True), ("rtk", "g.Xml", False),
                                               ("rtk", "x.npy", True)])
def test_export_warns_when_the_out_suffix_is_another_formats(tmp_path, bag, capsys, fmt, name, warned):
    """--format tigre --out t.txt wrote a zip, --format rtk --out x.npy an XML, silently."""
    assert main(["export", str(bag), "--format", fmt, "--out", str(tmp_path / name)]) == 0
    out = capsys.readouterr().out
    assert ("warning: --out" in out) == warned, out
    if warned:
        assert {"astra": ".npy or .txt", "tigre": ".npz", "rtk": ".xml"}[fmt] in out


def test_export_of_an_unfinished_calibration_folder_says_so(tmp_path, bag, capsys):
    """A calibrate --out whose run stopped before report.json: 'no .mcap file found (the bag directory holds
    [...])' took it for a bag."""
    half = tmp_path / "calib"
    (half / "scan_corrected").mkdir(parents=True)
    assert main(["export", str(bag), "--format", "astra", "--corrected", str(half), "--out",
                 str(tmp_path / "x.npy")]) == 2
    _one_line_error(capsys, "calibrate folder whose run did not finish", "no report.json",
                    str(half / "scan_corrected"))


@pytest.mark.parametrize("turn_deg, warned", [(0.0, False), (90.0, True), (30.0, True), (180.0, False)])
def test_rtk_export_of_a_detector_turned_in_its_plane_warns_that_rtks_fdk_is_approximate(tmp_path, turn_deg, warned):
    """An outside tester's detector turned 90 degrees in its plane was exported with InPlaneAngle 90 and no
    warning; RTK's FDK of it (ramp-filtered along the rows) correlated 0.644 with the phantom, 0.988 unturned."""
    if not _has_itk():
        pytest.skip("needs itk-rtk")
    from robot_ct_ros.jobs.export import export_geometry

    g = circular_scan(8, 60.0, 150.0, 12, 20, 0.8, 0.8)
    a = np.radians(turn_deg)
    g = g.replace(u=np.cos(a) * g.u + np.sin(a) * g.v, v=-np.sin(a) * g.u + np.cos(a) * g.v)
    src = write_scan(tmp_path / "scan", np.ones((g.n_views,) + g.det_shape, np.float32), g,
                     projection_units="line_integral")
    said = []
    result = export_geometry(src, tmp_path / "g.xml", "rtk", say=said.append)
    assert len([line for line in said if line.startswith("warning: the detector is turned")]) == int(warned), said
    turned = [w for w in result["warnings"] if "turned in its plane" in w]
    assert len(turned) == int(warned), result["warnings"]
    if warned:
        assert f"InPlaneAngle {turn_deg:.1f} deg" in turned[0] and "RTK's FDK ramp-filters along" in turned[0]
        assert "transpose" in turned[0] and "robot-ct reconstruct" in turned[0]
        assert f"warning: {turned[0]}" in said
