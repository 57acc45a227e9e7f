"""robot-ct import rtk: projections with RTK's geometry XML become a scan bag with the same geometry
(RTK's rotation about y, its projection-stack origin) and bit-equal frames; errors in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.cli import main
from robot_ct_ros.ct.trajectory import circular_scan


def _geometry(seed=0, n=8):
    rng = np.random.default_rng(seed)
    return circular_scan(n, 60.0, 150.0, 12, 20, 0.8, 0.7).perturbed(rng.normal(0, [0.3] * 6 + [0.01] * 3, (n, 9)))


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert all(w in err for w in words), err
    return err


def _write_xml(params, path):
    from robot_ct_ros.ct import rtk_bridge

    _, rtk = rtk_bridge._rtk()
    g = rtk_bridge.rtk_geometry_from_parameters(params)
    writer = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    writer.SetFilename(str(path))
    writer.SetObject(g)
    writer.WriteFile()
    return path


def test_rtk_xml_round_trip_through_export(tmp_path, capsys):
    pytest.importorskip("itk")
    g = _geometry()
    proj = np.random.default_rng(1).normal(1, 0.5, (g.n_views,) + g.det_shape).astype(np.float32)
    src = write_scan(tmp_path / "src", proj, g, projection_units="line_integral")
    xml = tmp_path / "g.xml"
    assert main(["export", str(src), "--format", "rtk", "--out", str(xml)]) == 0
    tifffile.imwrite(tmp_path / "p.tif", proj, photometric="minisblack")
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.tif"), "--geometry", str(xml),
                 "--pitch-mm", "0.8,0.7", "--out", str(tmp_path / "bag")]) == 0
    scan = read_scan(tmp_path / "bag")
    assert scan.warnings == [] and scan.units == "line_integral"
    # in the frame the export states beside the XML (this scan turns about the world's z: RTK's frame is the scan's)
    frame = json.loads((tmp_path / "g.rtk_frame.json").read_text())
    m = np.array(frame["world_to_rtk"])
    assert frame["frame"] == "scan"
    assert scan.geom.allclose(read_scan(src).geom.moved(m[:3, :3], m[:3, 3]), atol=1e-9)
    np.testing.assert_array_equal(scan.counts, proj)
    # the pitches are ROW,COL: swapped, the geometry differs
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.tif"), "--geometry", str(xml),
                 "--pitch-mm", "0.7,0.8", "--out", str(tmp_path / "swapped")]) == 0
    assert not read_scan(tmp_path / "swapped").geom.allclose(scan.geom, atol=1e-3)


def test_rtk_convention_rotation_about_y_and_the_stack_origin(tmp_path):
    pytest.importorskip("itk")
    sid, sdd = 500.0, 800.0
    xml = _write_xml([[sid, sdd, a, 0, 0, 0, 0, 0, 0] for a in (0.0, 90.0, 180.0, 270.0)], tmp_path / "g.xml")
    np.save(tmp_path / "p.npy", np.ones((4, 6, 10), np.float32))
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                 "--pitch-mm", "0.5,0.25", "--out", str(tmp_path / "c")]) == 0
    g = read_scan(tmp_path / "c").geom
    t = np.deg2rad([0.0, 90.0, 180.0, 270.0])
    s, c, z = np.sin(t), np.cos(t), np.zeros(4)
    np.testing.assert_allclose(g.source_mm, sid * np.c_[s, z, c], atol=1e-9)  # about +y, from +z towards +x
    np.testing.assert_allclose(g.detector_mm, (sid - sdd) * np.c_[s, z, c], atol=1e-9)
    np.testing.assert_allclose(g.u, np.c_[c, z, -s], atol=1e-12)
    np.testing.assert_allclose(g.v, [[0, 1, 0]] * 4, atol=1e-12)
    # origin (0, 0): pixel (0, 0) sits at RTK's detector position, the grid centre (2.5 rows, 4.5 columns) beyond
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                 "--pitch-mm", "0.5,0.25", "--origin-mm", "0,0", "--out", str(tmp_path / "o")]) == 0
    go = read_scan(tmp_path / "o").geom
    np.testing.assert_allclose(go.pixel_centers_mm(1)[0, 0], g.detector_mm[1], atol=1e-9)
    np.testing.assert_allclose(go.detector_mm, g.detector_mm + 4.5 * 0.25 * g.u + 2.5 * 0.5 * g.v, atol=1e-9)
    assert go.replace(detector_mm=g.detector_mm).allclose(g, atol=1e-12)


def test_rtk_import_errors_are_one_line(tmp_path, capsys, monkeypatch):
    pytest.importorskip("itk")
    xml = _write_xml([[500.0, 800.0, a, 0, 0, 0, 0, 0, 0] for a in (0.0, 90.0, 180.0)], tmp_path / "g.xml")
    np.save(tmp_path / "p.npy", np.ones((4, 6, 10), np.float32))
    p = str(tmp_path / "p.npy")

    def run(*args):
        return main(["import", "rtk", "--projections", p, *args, "--out", str(tmp_path / "bag")])

    assert run("--geometry", str(xml), "--pitch-mm", "0.5") == 2
    _one_line_error(capsys, "holds 4 views", "describes 3")
    assert run("--geometry", str(xml), "--pitch-mm", "0.0005") == 2
    _one_line_error(capsys, "give millimetres")
    with pytest.raises(SystemExit):  # argparse's usage and one error line
        run("--geometry", str(xml), "--pitch-mm", "0.5,0.5,0.5")
    assert "--pitch-mm is ROW,COL in mm, positive, or one value for both" in capsys.readouterr().err.splitlines()[-1]
    assert run("--geometry", str(tmp_path / "none.xml"), "--pitch-mm", "0.5") == 2
    _one_line_error(capsys, "cannot access", "none.xml")
    (tmp_path / "bad.xml").write_text("<?xml version=\"1.0\"?><nothing/>")
    assert run("--geometry", str(tmp_path / "bad.xml"), "--pitch-mm", "0.5") == 2
    _one_line_error(capsys, "bad.xml")
    with pytest.raises(SystemExit):  # argparse: --pitch-mm is required
        run("--geometry", str(xml))
    capsys.readouterr()

    from robot_ct_ros.ct import rtk_bridge

    def no_rtk():
        raise ImportError("No module named 'itk'")
    monkeypatch.setattr(rtk_bridge, "_rtk", no_rtk)
    assert run("--geometry", str(xml), "--pitch-mm", "0.5") == 2
    _one_line_error(capsys, "needs itk-rtk")
    assert not (tmp_path / "bag").exists()


def test_geometries_no_scanner_has_are_refused_and_radians_are_warned(tmp_path, capsys):
    """RTK distances written in metres (a detector far wider than its distance from the source), a curved
    detector (which a scan bag cannot describe) and gantry angles in radians (60 views over 6.3 degrees) were
    imported without a word."""
    pytest.importorskip("itk")
    from robot_ct_ros.ct import rtk_bridge

    np.save(tmp_path / "p.npy", np.ones((60, 6, 10), np.float32))

    def run(xml, name, *extra):
        return main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                     "--pitch-mm", "0.5,0.5", *extra, "--out", str(tmp_path / name)])

    angles = np.linspace(0.0, 360.0, 60, endpoint=False)
    metres = _write_xml([[0.5, 0.8, a, 0, 0, 0, 0, 0, 0] for a in angles], tmp_path / "m.xml")
    assert run(metres, "m") == 2
    _one_line_error(capsys, "spans", "metres")
    assert not (tmp_path / "m").exists()

    _, rtk = rtk_bridge._rtk()
    curved = rtk_bridge.rtk_geometry_from_parameters([[500.0, 800.0, a, 0, 0, 0, 0, 0, 0] for a in angles])
    curved.SetRadiusCylindricalDetector(800.0)
    writer = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    writer.SetFilename(str(tmp_path / "c.xml"))
    writer.SetObject(curved)
    writer.WriteFile()
    assert run(tmp_path / "c.xml", "c") == 2
    _one_line_error(capsys, "cylindrical detector", "800")

    radians = _write_xml([[500.0, 800.0, a, 0, 0, 0, 0, 0, 0] for a in np.deg2rad(angles)], tmp_path / "r.xml")
    assert run(radians, "r") == 0
    out = capsys.readouterr().out
    assert "warning" in out and "radians" in out and "6.2 deg" in out, out
    degrees = _write_xml([[500.0, 800.0, a, 0, 0, 0, 0, 0, 0] for a in angles], tmp_path / "d.xml")
    assert run(degrees, "d") == 0 and "warning" not in capsys.readouterr().out
    # a 1.6 mm pitch written in metres: 1.6 um pixels, warned (it passed the range check without a word)
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(degrees),
                 "--pitch-mm", "0.0016,0.0016", "--out", str(tmp_path / "um")]) == 0
    out = capsys.readouterr().out
    assert "warning" in out and "1.6 um" in out and "metres" in out and "1.6 mm" in out, out
    # a negative origin pair after a space, as RTK's centred origins are: not taken for an option
    assert run(degrees, "o", "--origin-mm", "-1.25,-2.25") == 0
    g, go = read_scan(tmp_path / "d").geom, read_scan(tmp_path / "o").geom
    assert go.allclose(g, atol=1e-9)  # that origin is the centred stack's


def test_an_rtk_parallel_beam_is_refused(tmp_path, capsys):
    """RTK's AddProjection with a source-to-detector distance of 0 is a parallel beam; it was imported as a cone
    beam with its source 2 SID from the detector, and every projection through the bag differed from RTK's."""
    pytest.importorskip("itk")
    np.save(tmp_path / "p.npy", np.ones((12, 6, 10), np.float32))
    xml = _write_xml([[600.0, 0.0, 30.0 * i, 0, 0, 0, 0, 0, 0] for i in range(12)], tmp_path / "par.xml")
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                 "--pitch-mm", "0.5,0.5", "--out", str(tmp_path / "bag")]) == 2
    _one_line_error(capsys, "par.xml", "parallel-beam", "SourceToDetectorDistance 0")
    assert not (tmp_path / "bag").exists()


def test_rtk_distances_in_metres_on_a_small_detector_are_refused(tmp_path, capsys):
    """SID 0.6, SDD 0.9 (metres) on 8 x 8 pixels of 0.2 mm subtend 51 deg, under the 60 deg half-fan that caught
    larger detectors: imported as a cone beam 0.9 mm long. The seed system's 342 mm still imports."""
    pytest.importorskip("itk")
    np.save(tmp_path / "p.npy", np.ones((36, 8, 8), np.float32))

    def run(sid, sdd, name):
        xml = _write_xml([[sid, sdd, 10.0 * i, 0, 0, 0, 0, 0, 0] for i in range(36)], tmp_path / f"{name}.xml")
        return main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                     "--pitch-mm", "0.2,0.2", "--out", str(tmp_path / name)])

    assert run(0.6, 0.9, "m") == 2
    _one_line_error(capsys, "m.xml", "0.9 mm from the detector", "metres")
    assert not (tmp_path / "m").exists()
    assert run(200.0, 342.0, "seed") == 0


@pytest.mark.parametrize("n_views", [4, 9])
def test_radians_are_warned_however_few_the_views(tmp_path, capsys, n_views):
    """The warning for views spanning under 20 deg (gantry angles in radians) was skipped below 10 views."""
    pytest.importorskip("itk")
    np.save(tmp_path / "p.npy", np.ones((n_views, 6, 10), np.float32))
    angles = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)  # radians where RTK's XML has degrees
    xml = _write_xml([[500.0, 800.0, a, 0, 0, 0, 0, 0, 0] for a in angles], tmp_path / "r.xml")
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                 "--pitch-mm", "0.5,0.5", "--out", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert f"the {n_views} views span an arc of {angles[-1]:.1f} deg only" in out and "radians" in out, out
    xml = _write_xml([[500.0, 800.0, a, 0, 0, 0, 0, 0, 0] for a in np.degrees(angles)], tmp_path / "d.xml")
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                 "--pitch-mm", "0.5,0.5", "--out", str(tmp_path / "d")]) == 0
    assert "warning" not in capsys.readouterr().out


def test_check_plausible_warns_two_views_a_few_degrees_apart():
    """scan_arc counts two views a full circle: two views pi (deg) apart passed without the warning."""
    from robot_ct_ros.jobs.importers import check_plausible

    for arc_rad, warned in ((np.deg2rad(np.pi), True), (2 * np.pi, False)):  # views 3.1 deg and 180 deg apart
        said = []
        check_plausible(circular_scan(2, 500.0, 800.0, 6, 10, 0.5, 0.5, arc_rad=arc_rad), "g", said.append)
        assert bool(said) == warned and all("span an arc of 3.1 deg" in m for m in said), said


def test_a_truncated_xml_and_a_corrupt_tiff_are_named_as_such(tmp_path, capsys, caplog):
    """A cut RTK XML read as its first view ('holds 12 views but g.xml describes 1'); a TIFF header with garbage
    behind it read as an empty array ('projections must be 3-D ..., got shape (0,)')."""
    pytest.importorskip("itk")
    xml = _write_xml([[600.0, 900.0, 30.0 * i, 0, 0, 0, 0, 0, 0] for i in range(12)], tmp_path / "g.xml")
    (tmp_path / "cut.xml").write_text(xml.read_text()[:700])
    (tmp_path / "empty.xml").write_text("")
    np.save(tmp_path / "p.npy", np.ones((12, 4, 6), np.float32))
    (tmp_path / "bad.tif").write_bytes(b"II*\x00garbage" * 10)

    def run(proj, geometry):
        return main(["import", "rtk", "--projections", str(tmp_path / proj), "--geometry", str(tmp_path / geometry),
                     "--pitch-mm", "0.2,0.2", "--out", str(tmp_path / "bag")])

    for name in ("cut.xml", "empty.xml"):
        assert run("p.npy", name) == 2
        _one_line_error(capsys, name, "not a well-formed XML file, truncated or corrupt?")
    assert run("bad.tif", "g.xml") == 2
    _one_line_error(capsys, "bad.tif", "cannot read projections", "no readable image")
    assert not [r for r in caplog.records if r.name == "tifffile"]  # its warning went to stderr before our line
    assert not (tmp_path / "bag").exists()


def test_one_pitch_value_is_both_pitches_and_help_says_so(tmp_path, capsys):
    """--pitch-mm 1 was taken as 1,1 without a word in --help, while 1,1,1 was refused as 'ROW,COL'."""
    pytest.importorskip("itk")
    xml = _write_xml([[600.0, 900.0, 45.0 * i, 0, 0, 0, 0, 0, 0] for i in range(8)], tmp_path / "g.xml")
    np.save(tmp_path / "p.npy", np.ones((8, 12, 20), np.float32))
    assert main(["import", "rtk", "--projections", str(tmp_path / "p.npy"), "--geometry", str(xml),
                 "--pitch-mm", "0.5", "--out", str(tmp_path / "bag")]) == 0
    geom = read_scan(tmp_path / "bag").geom
    assert (geom.row_pitch_mm, geom.col_pitch_mm) == (0.5, 0.5)
    with pytest.raises(SystemExit):
        main(["import", "rtk", "--help"])
    helptext = " ".join(capsys.readouterr().out.split())
    assert "between rows and between columns (mm; one value is taken for both)" in helptext
