"""robot-ct import astra: projections with ASTRA cone_vec / fanflat_vec vectors become a scan bag with
the same geometry and bit-equal frames; raw counts keep their flat and dark correction; bad inputs
are refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.cli import main
from robot_ct_ros.ct.trajectory import circular_scan
from robot_ct_ros.jobs.htc2022 import fan_beam_geometry


def _geometry(seed=0, n=8):
    """A circular scan with per-view errors: every parameter of every view differs."""
    rng = np.random.default_rng(seed)
    return circular_scan(n, 60.0, 150.0, 12, 20, 0.8, 0.7).perturbed(rng.normal(0, [0.3] * 6 + [0.01] * 3, (n, 9)))


def _proj(shape, seed=1):
    return np.random.default_rng(seed).normal(1.0, 0.5, shape).astype(np.float32)


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert all(w in err for w in words), err
    return err


@pytest.mark.parametrize("vec_suffix,proj_suffix,layout", [(".txt", ".tif", "views-first"), (".npy", ".npy", "astra")])
def test_cone_vec_round_trip(tmp_path, capsys, vec_suffix, proj_suffix, layout):
    g = _geometry()
    proj = _proj((g.n_views,) + g.det_shape)
    src = write_scan(tmp_path / "src", proj, g, projection_units="line_integral")
    vec = tmp_path / f"v{vec_suffix}"
    assert main(["export", str(src), "--format", "astra", "--out", str(vec)]) == 0
    stored = proj.transpose(1, 0, 2) if layout == "astra" else proj  # ASTRA's 3-D data: (rows, views, cols)
    p = tmp_path / f"p{proj_suffix}"
    np.save(p, stored) if proj_suffix == ".npy" else tifffile.imwrite(p, stored, photometric="minisblack")
    bag = tmp_path / "bag"
    args = ["import", "astra", "--projections", str(p), "--vectors", str(vec), "--out", str(bag)]
    assert main(args + (["--layout", "astra"] if layout == "astra" else [])) == 0
    assert "8 views, 12 x 20 detector" in capsys.readouterr().out
    scan, nominal = read_scan(bag), read_scan(src)
    assert scan.warnings == [] and scan.units == "line_integral"
    assert scan.geom.allclose(nominal.geom, atol=1e-9)
    assert scan.geom.allclose(g, atol=1e-9)
    np.testing.assert_array_equal(scan.counts, proj)  # bit-equal
    if layout == "astra":  # the default layout is views-first: the same file is then refused (12 rows != 8 views)
        assert main(args[:-2] + ["--out", str(tmp_path / "bag2")]) == 2
        _one_line_error(capsys, "holds 12 views", "describes 8")


def test_fanflat_vec_is_a_one_row_fan_in_the_plane_z0(tmp_path):
    angles = np.arange(0.0, 360.0, 30.0)
    g = fan_beam_geometry(angles, 410.66, 553.74, 40, 0.2)
    vec6 = g.to_astra_vec()[:, [0, 1, 3, 4, 6, 7]]  # ASTRA fanflat_vec: src, detector centre, u (2-D)
    sino = _proj((len(angles), 40))
    np.save(tmp_path / "v.npy", vec6)
    np.save(tmp_path / "s.npy", sino)
    base = ["import", "astra", "--projections", str(tmp_path / "s.npy"), "--vectors", str(tmp_path / "v.npy")]
    assert main(base + ["--out", str(tmp_path / "a")]) == 0
    scan = read_scan(tmp_path / "a")
    assert scan.geom.allclose(g, atol=1e-9)  # v = +z, row pitch = column pitch
    np.testing.assert_array_equal(scan.counts[:, 0], sino)
    assert main(base + ["--row-pitch-mm", "1.5", "--out", str(tmp_path / "b")]) == 0
    g2 = read_scan(tmp_path / "b").geom
    assert g2.row_pitch_mm == pytest.approx(1.5, abs=1e-12) and g2.replace(row_pitch_mm=0.2).allclose(g, atol=1e-9)


@pytest.mark.parametrize("with_dark", [True, False])
def test_raw_counts_keep_flat_and_dark_and_mark_dead_pixels(tmp_path, capsys, with_dark):
    """Counts are stored dark-corrected with their flat field; a pixel below the dark is unusable (NaN). A count of
    exactly 0 (I - D = 0: photon starvation) was stored as NaN, against the bag's contract that 0 is a measurement;
    it is now stored as 0, usable at the 0.5-count floor, and the import and the reader warn of it."""
    g = _geometry()
    rng = np.random.default_rng(3)
    shape = g.det_shape
    dark = rng.uniform(90, 110, (5,) + shape) if with_dark else None  # a stack: averaged
    d = dark.mean(axis=0) if with_dark else 0.0
    flat = rng.uniform(3000, 4000, (3,) + shape)
    f = flat.mean(axis=0)
    counts = d + (f - d) * np.exp(-rng.uniform(0, 3, (g.n_views,) + shape))
    counts[2, 3, 4] = d[3, 4] if with_dark else 0.0  # I - D = 0: photon starvation, a measurement
    counts[5, 1, 1] = (d[1, 1] if with_dark else 0.0) - 5.0  # below the dark
    flat[:, 7, 9] = d[7, 9] if with_dark else 0.0  # F - D = 0: a dead pixel in every frame
    np.save(tmp_path / "p.npy", counts)
    tifffile.imwrite(tmp_path / "flat.tif", flat.astype(np.float32), photometric="minisblack")
    f = flat.astype(np.float32).astype(np.float64).mean(axis=0)
    args = ["import", "astra", "--projections", str(tmp_path / "p.npy"), "--vectors", str(tmp_path / "v.txt"),
            "--counts", "--flat", str(tmp_path / "flat.tif"), "--out", str(tmp_path / "bag")]
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    if with_dark:
        np.save(tmp_path / "dark.npy", dark)
        args += ["--dark", str(tmp_path / "dark.npy")]
    assert main(args) == 0
    assert "warning: 1 usable pixels in 1 frames (first [2]) read 0 counts" in capsys.readouterr().out
    scan = read_scan(tmp_path / "bag")
    assert scan.units == "counts"
    assert scan.counts[2, 3, 4] == 0.0 and scan.valid_mask[2, 3, 4]  # stored 0, not NaN
    assert any("read 0 counts" in w for w in scan.warnings), scan.warnings
    expected_valid = ((counts - d) >= 0) & ((f - d) > 0)[None]
    assert expected_valid[2, 3, 4] and not expected_valid[5, 1, 1] and not expected_valid[:, 7, 9].any()
    np.testing.assert_array_equal(scan.valid_mask, expected_valid)
    li, mask = scan.to_line_integrals()
    with np.errstate(divide="ignore", invalid="ignore"):
        ref = -np.log(np.maximum(counts - d, 0.5) / (f - d))
    np.testing.assert_array_equal(mask, expected_valid)
    np.testing.assert_allclose(li[mask], ref[mask], rtol=0, atol=2e-6)
    np.testing.assert_array_equal(scan.flat, (f - d).astype(np.float32))


def test_import_errors_are_one_line(tmp_path, capsys):
    g = _geometry()
    np.save(tmp_path / "p.npy", _proj((g.n_views,) + g.det_shape))
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    p, v = str(tmp_path / "p.npy"), str(tmp_path / "v.txt")

    def run(*args, out="bag"):
        return main(["import", "astra", *args, "--out", str(tmp_path / out)])

    np.savetxt(tmp_path / "v6.txt", g.to_astra_vec()[:6])
    assert run("--projections", p, "--vectors", str(tmp_path / "v6.txt")) == 2
    _one_line_error(capsys, "holds 8 views", "describes 6")
    np.savetxt(tmp_path / "v7.txt", g.to_astra_vec()[:, :7])
    assert run("--projections", p, "--vectors", str(tmp_path / "v7.txt")) == 2
    _one_line_error(capsys, "12 (cone_vec) or 6 (fanflat_vec) columns")
    np.savetxt(tmp_path / "vm.txt", g.to_astra_vec() * 1e-3)  # metres
    assert run("--projections", p, "--vectors", str(tmp_path / "vm.txt")) == 2
    _one_line_error(capsys, "give millimetres")
    # a zero u, and a pitch that changes between views: the file and the view named
    zero_u, varies = g.to_astra_vec(), g.to_astra_vec()
    zero_u[5, 6:9] = 0.0
    varies[7, 9:12] *= 1.01
    np.savetxt(tmp_path / "vu0.txt", zero_u)
    np.savetxt(tmp_path / "vpv.txt", varies)
    assert run("--projections", p, "--vectors", str(tmp_path / "vu0.txt")) == 2
    _one_line_error(capsys, "vu0.txt", "column pitch |u| in view 5 must be positive")
    assert run("--projections", p, "--vectors", str(tmp_path / "vpv.txt")) == 2
    _one_line_error(capsys, "vpv.txt", "row pitch |v| varies between views", "in view 7")
    assert run("--projections", str(tmp_path / "missing.npy"), "--vectors", v) == 2
    _one_line_error(capsys, "cannot access", "missing.npy")
    assert run("--projections", p, "--vectors", str(tmp_path / "missing.txt")) == 2
    _one_line_error(capsys, "cannot access", "missing.txt")
    np.save(tmp_path / "p4.npy", np.zeros((2, 8, 12, 20), np.float32))
    assert run("--projections", str(tmp_path / "p4.npy"), "--vectors", v) == 2
    _one_line_error(capsys, "must be 3-D", "(2, 8, 12, 20)")
    (tmp_path / "p.txt").write_text("1 2 3")
    assert run("--projections", str(tmp_path / "p.txt"), "--vectors", v) == 2
    _one_line_error(capsys, ".npy or .tif")
    (tmp_path / "bad.tif").write_bytes(b"not a tiff at all")
    assert run("--projections", str(tmp_path / "bad.tif"), "--vectors", v) == 2
    _one_line_error(capsys, "cannot read projections")
    assert run("--projections", p, "--vectors", v, "--counts") == 2
    _one_line_error(capsys, "--counts needs --flat")
    assert run("--projections", p, "--vectors", v, "--flat", p) == 2
    _one_line_error(capsys, "go with --counts")
    np.save(tmp_path / "f.npy", np.ones((12, 19)))
    assert run("--projections", p, "--vectors", v, "--counts", "--flat", str(tmp_path / "f.npy")) == 2
    _one_line_error(capsys, "flat field is (12, 19) pixels", "(12, 20)")
    assert run("--projections", p, "--vectors", v, "--row-pitch-mm", "0.5") == 2
    _one_line_error(capsys, "fanflat_vec only")
    assert not (tmp_path / "bag").exists()
    (tmp_path / "bag").mkdir()
    assert run("--projections", p, "--vectors", v) == 2
    _one_line_error(capsys, "exists already")


def test_raw_counts_with_no_usable_pixel_are_refused_before_writing(tmp_path, capsys):
    """A dark frame equal to the flat (or --flat and --dark swapped) once wrote a bag with no usable pixel and
    exited 0; info then called it no scan. The import refuses in one line and writes nothing."""
    g = _geometry()
    shape = g.det_shape
    flat = np.full(shape, 3000.0)
    counts = np.full((g.n_views,) + shape, 1000.0)
    np.save(tmp_path / "p.npy", counts)
    np.save(tmp_path / "flat.npy", flat)
    np.save(tmp_path / "dark.npy", flat)
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    args = ["import", "astra", "--projections", str(tmp_path / "p.npy"), "--vectors", str(tmp_path / "v.txt"),
            "--counts", "--flat", str(tmp_path / "flat.npy"), "--dark", str(tmp_path / "dark.npy"), "--out"]
    assert main(args + [str(tmp_path / "bag")]) == 2
    _one_line_error(capsys, "no usable pixel", "the flat field minus the dark frame is at or below 0 everywhere")
    assert not (tmp_path / "bag").exists()
    np.save(tmp_path / "dark.npy", np.full(shape, 2000.0))  # above every count, below the flat
    assert main(args + [str(tmp_path / "bag2")]) == 2
    _one_line_error(capsys, "no usable pixel", "every projection value minus the dark frame is at or below 0")


def test_parallel_beam_vectors_and_a_source_on_the_detector_are_refused(tmp_path, capsys):
    """ASTRA parallel_vec / parallel3d_vec files have fanflat_vec's / cone_vec's columns; read as a cone beam,
    the ray direction became a source 1 mm from the centre. A source on the detector plane likewise."""
    g = _geometry()
    np.save(tmp_path / "p.npy", _proj((g.n_views,) + g.det_shape))
    vec = g.to_astra_vec()
    parallel = vec.copy()
    parallel[:, 0:3] = g.w  # parallel3d_vec: a unit ray direction where cone_vec has the source,
    parallel[:, 3:6] = 0.0  # and the detector centred on the origin, as ASTRA's parallel3d geometry converts
    on_detector = vec.copy()
    on_detector[:, 0:3] = vec[:, 3:6]
    for name, v, words in (("par", parallel, ("parallel",)), ("on", on_detector, ("detector plane",))):
        np.save(tmp_path / f"{name}.npy", v)
        assert main(["import", "astra", "--projections", str(tmp_path / "p.npy"), "--vectors",
                     str(tmp_path / f"{name}.npy"), "--out", str(tmp_path / name)]) == 2
        _one_line_error(capsys, *words)
        assert not (tmp_path / name).exists()


def test_raw_counts_brighter_than_their_flat_or_a_dead_flat_are_warned(tmp_path, capsys):
    """A flat field from another exposure (every line integral negative) and saturated counts above the flat
    were imported without a word; a dead flat pixel was counted as 'pixel values <= dark'."""
    g = _geometry()
    rng = np.random.default_rng(4)
    flat = np.full(g.det_shape, 3000.0)
    counts = rng.poisson(flat * np.exp(-rng.uniform(0, 2, (g.n_views,) + g.det_shape))).astype(np.float64)
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())

    def run(name, proj, flat_field):
        np.save(tmp_path / f"{name}.npy", proj)
        np.save(tmp_path / f"{name}_flat.npy", flat_field)
        assert main(["import", "astra", "--projections", str(tmp_path / f"{name}.npy"), "--vectors",
                     str(tmp_path / "v.txt"), "--counts", "--flat", str(tmp_path / f"{name}_flat.npy"), "--out",
                     str(tmp_path / name)]) == 0
        return capsys.readouterr().out

    assert "warning" not in run("good", counts, flat)
    out = run("other_exposure", counts, flat / 4.0)  # the flat of a quarter of the tube current
    assert "warning" in out and "more than the flat field" in out, out
    saturated = np.where(rng.random(counts.shape) < 0.3, 65535.0, counts)
    assert "more than the flat field" in run("saturated", saturated, flat)
    dead = flat.copy()
    dead[1, 2], dead[3, 4] = np.nan, 0.0
    out = run("dead", counts, dead)
    assert "1 pixels that are NaN or infinite and 1 at or below the dark" in out, out


def test_a_frame_of_line_integrals_with_no_finite_value_is_warned(tmp_path, capsys):
    """An all-NaN frame of line integrals was imported without a word (info said so only later)."""
    g = _geometry()
    proj = _proj((g.n_views,) + g.det_shape)
    proj[2] = np.nan
    np.save(tmp_path / "p.npy", proj)
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    assert main(["import", "astra", "--projections", str(tmp_path / "p.npy"), "--vectors", str(tmp_path / "v.txt"),
                 "--out", str(tmp_path / "bag")]) == 0
    assert "warning: 1 frames have no usable pixel" in capsys.readouterr().out


def test_metres_and_parallel_beam_vectors_on_a_small_detector_are_refused(tmp_path, capsys):
    """On a detector of 8 x 8 pixels of 0.2 mm, distances in metres (SDD 0.55) and ASTRA parallel3d_vec rows (a unit
    ray direction where the source stands: SDD 1) subtend less than 60 deg and were imported as cone beams; a source
    closer than 10 mm to the detector is now refused. The HTC2022 scanner's own geometry still imports."""
    angles = np.arange(0.0, 360.0, 10.0)
    t, n, p = np.deg2rad(angles), 8, 0.2
    np.save(tmp_path / "p.npy", _proj((angles.size, n, n)))
    z = np.zeros_like(t)
    parallel = np.stack([-np.sin(t), np.cos(t), z, z, z, z, p * np.cos(t), p * np.sin(t), z, z, z, p + z], axis=1)
    htc = fan_beam_geometry(angles, 410.66, 553.74, n, p, n_rows=n).to_astra_vec()
    metres = htc.copy()
    metres[:, :6] *= 1e-3

    def run(name, vec):
        np.savetxt(tmp_path / f"{name}.txt", vec)
        return main(["import", "astra", "--projections", str(tmp_path / "p.npy"), "--vectors",
                     str(tmp_path / f"{name}.txt"), "--out", str(tmp_path / name)])

    for name, vec, words in (("par", parallel, ("parallel3d_vec", "unit vector")),
                             ("m", metres, ("0.55374 mm", "metres", "parallel"))):
        assert run(name, vec) == 2
        _one_line_error(capsys, f"{name}.txt", *words)
        assert not (tmp_path / name).exists()
    assert run("htc", htc) == 0


def test_fewer_than_four_views_are_refused_before_writing(tmp_path, capsys):
    """3 views (or 8 frames of which 5 hold no finite value) were imported, exit 0, into a bag no reader accepts."""
    g = _geometry()
    proj = _proj((g.n_views,) + g.det_shape)
    np.save(tmp_path / "p3.npy", proj[:3])
    np.savetxt(tmp_path / "v3.txt", g.to_astra_vec()[:3])
    proj[3:] = np.nan
    np.save(tmp_path / "pnan.npy", proj)
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    for p, v, words in (("p3", "v3", ("p3.npy holds 3 views",)), ("pnan", "v", ("3 of its 8 frames", "usable"))):
        assert main(["import", "astra", "--projections", str(tmp_path / f"{p}.npy"), "--vectors",
                     str(tmp_path / f"{v}.txt"), "--out", str(tmp_path / p)]) == 2
        _one_line_error(capsys, *words, "at least 4")
        assert not (tmp_path / p).exists()


def test_empty_or_cut_vector_files_are_one_line_errors(tmp_path, capsys):
    """A 0-byte vectors .npy gave a traceback (EOFError), exit 1; an empty .txt printed numpy's UserWarning
    before the error. Each is now one line naming the file, and no warning."""
    import warnings

    g = _geometry()
    np.save(tmp_path / "p.npy", _proj((g.n_views,) + g.det_shape))
    np.save(tmp_path / "v.npy", g.to_astra_vec())
    (tmp_path / "empty.npy").write_bytes(b"")
    (tmp_path / "empty.txt").write_text("")
    (tmp_path / "comments.txt").write_text("# cone_vec\n\n")
    (tmp_path / "cut.npy").write_bytes((tmp_path / "v.npy").read_bytes()[:8])  # cut inside the header
    for name, words in (("empty.npy", ("empty",)), ("empty.txt", ("empty",)), ("comments.txt", ("no numbers",)),
                        ("cut.npy", ("cannot read ASTRA vectors",))):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a warning would escape as an exception: no one-line error
            assert main(["import", "astra", "--projections", str(tmp_path / "p.npy"), "--vectors",
                         str(tmp_path / name), "--out", str(tmp_path / "bag")]) == 2
        _one_line_error(capsys, name, *words)
        assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("detector_mm", [50.0, 214.16])
def test_parallel_beam_vectors_off_the_origin_are_refused(tmp_path, capsys, detector_mm):
    """parallel3d_vec (parallel_vec) rows whose detector centre is 50 or 214 mm from the origin were imported as a
    cone beam with its source 1 mm from the origin, exit 0: only a detector through the origin was caught. A unit
    first vector in every view (a ray direction) is now refused as parallel-beam vectors, wherever the detector."""
    g = _geometry()
    np.save(tmp_path / "p.npy", _proj((g.n_views,) + g.det_shape))
    par = g.to_astra_vec()
    par[:, 0:3] = g.w.astype(np.float32)  # a unit ray direction, rounded as a float32 file holds it
    par[:, 3:6] = -detector_mm * g.w
    angles = np.arange(0.0, 360.0, 45.0)
    fan = fan_beam_geometry(angles, 410.66, 553.74, 20, 0.2).to_astra_vec()[:, [0, 1, 3, 4, 6, 7]]
    fan[:, 0:2] /= np.linalg.norm(fan[:, 0:2], axis=1)[:, None]  # parallel_vec: the ray direction in the plane
    fan[:, 2:4] *= detector_mm / np.linalg.norm(fan[:, 2:4], axis=1)[:, None]
    np.save(tmp_path / "s.npy", _proj((angles.size, 20)))
    for name, vec, proj, words in (("par3d", par, "p", ("parallel3d_vec", "cone_vec")),
                                   ("par2d", fan, "s", ("parallel_vec", "fanflat_vec"))):
        np.save(tmp_path / f"{name}.npy", vec)
        assert main(["import", "astra", "--projections", str(tmp_path / f"{proj}.npy"), "--vectors",
                     str(tmp_path / f"{name}.npy"), "--out", str(tmp_path / name)]) == 2
        _one_line_error(capsys, f"{name}.npy", "parallel-beam", *words)
        assert not (tmp_path / name).exists()


def test_counts_or_sign_flipped_line_integrals_are_warned(tmp_path, capsys):
    """Raw counts given without --counts (thousands) and sign-flipped line integrals were imported as line
    integrals without a word, and info said 100 % valid. The import and every read now warn; the data are kept."""
    from robot_ct_ros.bag.reader import summarize

    g = _geometry()
    li = np.random.default_rng(5).uniform(0.2, 0.5, (g.n_views,) + g.det_shape).astype(np.float32)  # a faint object
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    for name, proj, words in (("good", li, None), ("counts", 4900 * np.exp(-li) + 100, "look like raw counts"),
                              ("flipped", -li, "sign-flipped"), ("noisy", _proj(li.shape), None)):
        np.save(tmp_path / f"{name}.npy", proj.astype(np.float32))
        assert main(["import", "astra", "--projections", str(tmp_path / f"{name}.npy"), "--vectors",
                     str(tmp_path / "v.txt"), "--out", str(tmp_path / name)]) == 0
        out = capsys.readouterr().out
        warnings = summarize(tmp_path / name)["warnings"]
        if words is None:
            assert "warning" not in out and warnings == [], (out, warnings)
        else:
            assert "warning: " in out and words in out, out
            assert len(warnings) == 1 and words in warnings[0], warnings
            np.testing.assert_array_equal(read_scan(tmp_path / name).counts, proj.astype(np.float32))


def test_a_cut_tiff_and_an_all_nan_stack_are_one_line_errors_with_the_full_path(tmp_path, capsys, caplog):
    """A TIFF cut short printed tifffile's own 'invalid page offset' log line (logged at ERROR, which the
    silenced level let through) before the one-line error; an all-NaN stack's refusal named the file
    without its folder, while every other refusal gives the path as given."""
    g = _geometry()
    proj = _proj((g.n_views,) + g.det_shape)
    np.savetxt(tmp_path / "v.txt", g.to_astra_vec())
    tifffile.imwrite(tmp_path / "p.tif", proj)  # one page per view
    data = (tmp_path / "p.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(data[: len(data) * 2 // 3])
    np.save(tmp_path / "nan.npy", np.full_like(proj, np.nan))

    def run(proj_name):
        return main(["import", "astra", "--projections", str(tmp_path / proj_name), "--vectors",
                     str(tmp_path / "v.txt"), "--out", str(tmp_path / "bag")])

    assert run("cut.tif") == 2
    _one_line_error(capsys, str(tmp_path / "cut.tif"), "cannot read projections")
    assert not [r for r in caplog.records if r.name == "tifffile"], [r.getMessage() for r in caplog.records]
    assert run("nan.npy") == 2
    _one_line_error(capsys, f"{tmp_path / 'nan.npy'} holds 0 of its 8 frames with a usable pixel")
    assert not (tmp_path / "bag").exists()
