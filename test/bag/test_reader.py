"""ScanBag.default_grid for a detector turned in its own plane (no ROI in the bag)."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.ct.trajectory import circular_scan


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0)])
def test_default_grid_of_a_portrait_detector_is_the_landscape_one(tmp_path, axis):
    """Columns along the scan axis (a valid right-handed frame, the same rays): the default grid is
    the landscape detector's, not one with its transaxial and axial sizes swapped."""
    g = circular_scan(8, 100.0, 200.0, 16, 40, 0.5, 0.5, axis=axis)
    gp = g.replace(u=g.v, v=-g.u, n_rows=g.n_cols, n_cols=g.n_rows)
    frames = np.full((8, 16, 40), 500.0, np.float32)
    grids = []
    for name, geom, f in (("land", g, frames), ("port", gp, np.ascontiguousarray(frames.transpose(0, 2, 1)))):
        bag = write_scan(tmp_path / name, f, geom, flat=np.full(f.shape[1:], 1000.0, np.float32))
        grids.append(read_scan(bag).default_grid())
    land, port = grids
    assert port.shape_zyx == land.shape_zyx
    assert port.shape_zyx[0] < port.shape_zyx[1]  # 16 rows along the axis, 40 columns across it
    np.testing.assert_allclose(port.voxel_size_mm, land.voxel_size_mm)
    np.testing.assert_allclose(port.center_mm, land.center_mm, atol=1e-9)


def test_positions_in_mm_on_the_wire_are_refused_naming_the_topic(tmp_path, capsys):
    """Positions written in mm on a wire in metres: info said "SDD 500000.0 mm" without a word, and
    reconstruct ended in a memory refusal suggesting a 0.73 mm voxel. The reader refuses a source-to-detector
    distance above 10 m and says the positions look like mm."""
    from robot_ct_ros.bag.format import ScanBagError
    from robot_ct_ros.cli import main

    g = circular_scan(8, 300.0, 500.0, 8, 12, 0.5, 0.5)
    frames = np.full((8, 8, 12), 500.0, np.float32)
    flat = np.full((8, 12), 1000.0, np.float32)
    read_scan(write_scan(tmp_path / "ok", frames, g, flat=flat))  # 0.5 m: fine
    big = g.replace(source_mm=g.source_mm * 1000.0, detector_mm=g.detector_mm * 1000.0)  # mm on the wire
    bag = write_scan(tmp_path / "mm", frames, big, flat=flat)
    with pytest.raises(ScanBagError, match=r"/ct/geometry: source-to-detector distance 500 m .* above 10 m: the "
                                           r"positions look like mm"):
        read_scan(bag)
    for cmd in (["info", str(bag)], ["reconstruct", str(bag), "--out", str(tmp_path / "rec")]):
        assert main(cmd) != 0
        said = capsys.readouterr()
        said = said.out + said.err
        assert "/ct/geometry" in said and "500 m" in said and "look like mm" in said, said
        assert "Traceback" not in said and "memory" not in said, said
    # a corrected geometry in mm is dropped with the reason, the scan kept
    bag2 = write_scan(tmp_path / "corr_mm", frames, g, flat=flat, geom_corrected=big)
    scan = read_scan(bag2)
    assert scan.geom_corrected is None
    assert any("/ct/geometry_corrected ignored" in w and "look like mm" in w for w in scan.warnings), scan.warnings


def _namespaced_copy(src, dst, namespaces):
    """A copy of the bag ``src`` with its contract topics under each of ``namespaces`` (``ros2 bag record -a`` of
    scanners started with ``namespace:=/scanner_a``); /diagnostics stays global, as the nodes publish it."""
    from robot_ct_ros.bag import format as fmt
    from robot_ct_ros.bag.reader import read_raw_messages
    from robot_ct_ros.bag.writer import ScanBagWriter

    raw = read_raw_messages(src)
    with ScanBagWriter(dst, None, flush_every_frame=False) as w:
        for m in raw.messages:
            for ns in namespaces:
                w.write_raw(m.topic if m.topic in fmt.GLOBAL_TOPICS else ns + m.topic, m.msgtype, m.data,
                            m.log_time_ns)
        w.write_msg("/rosout_like", fmt.typestore().types[fmt.STRING](data="x"), raw.messages[-1].log_time_ns,
                    fmt.STRING)  # a topic outside the contract: kept as it is
    return dst


def test_a_scan_recorded_under_a_namespace_is_read_there_and_its_correction_goes_beside_it(tmp_path, tiny_scan):
    """Outside test E #4: ``ros2 bag record -a`` of a scanner run with ``namespace:=/scanner_a`` holds
    /scanner_a/ct/scan_info, /scanner_a/ct/projection, ...; ``robot-ct info`` refused it ("no /ct/scan_info
    message"). Such a bag is read under its one namespace; calibrate's corrected copy adds
    /scanner_a/ct/geometry_corrected, where the reader finds it again."""
    from robot_ct_ros.bag import summarize
    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.jobs.calibrate import calibrate_bag

    geom, frames, flat, dead = tiny_scan
    plain = write_scan(tmp_path / "plain", frames, geom, flat=flat, dead_pixels=dead)
    bag = _namespaced_copy(plain, tmp_path / "ns_bag", ["/scanner_a"])
    ref, scan = read_scan(plain), read_scan(bag)
    assert scan.namespace == "/scanner_a" and ref.namespace == ""
    assert "read the scan recorded under namespace /scanner_a" in scan.warnings
    np.testing.assert_array_equal(scan.counts, ref.counts)
    np.testing.assert_array_equal(scan.geom.source_mm, ref.geom.source_mm)
    np.testing.assert_array_equal(scan.pixel_mask, ref.pixel_mask)  # flat field and dead pixels read there too
    assert "scan_error" not in summarize(bag)

    report = calibrate_bag(bag, tmp_path / "cal", CalibrationSettings(method="none"), say=lambda *a: None).report
    corrected = report["corrected_bag"]
    topics = summarize(corrected)["topics"]
    assert "/scanner_a/ct/geometry_corrected" in topics and "/ct/geometry_corrected" not in topics
    again = read_scan(corrected)
    assert again.namespace == "/scanner_a" and again.geom_corrected is not None
    assert summarize(corrected)["has_geometry_corrected"]
    # the recorded QoS profiles travel with the topics' names as read
    from robot_ct_ros.bag.reader import _under_namespace, read_raw_messages

    raw = read_raw_messages(bag)
    under = _under_namespace(raw, "/scanner_a")
    assert raw.qos and set(under.qos) == {t[len("/scanner_a"):] if t.startswith("/scanner_a/") else t for t in raw.qos}


def test_scans_under_two_namespaces_are_refused_naming_them_unless_one_is_picked(tmp_path, tiny_scan):
    from robot_ct_ros.bag.reader import ScanBagError

    geom, frames, flat, dead = tiny_scan
    plain = write_scan(tmp_path / "plain", frames, geom, flat=flat, dead_pixels=dead)
    bag = _namespaced_copy(plain, tmp_path / "two", ["/scanner_a", "/scanner_b"])
    with pytest.raises(ScanBagError, match="2 namespaces: /scanner_a, /scanner_b; read one of them"):
        read_scan(bag)
    scan = read_scan(bag, namespace="scanner_b")
    assert scan.namespace == "/scanner_b" and scan.n_views == 12
    with pytest.raises(ScanBagError, match="namespace /scanner_c asked for; the bag's scans: /scanner_a, /scanner_b"):
        read_scan(bag, namespace="/scanner_c")


def test_a_file_compressed_bag_file_given_alone_is_named_as_such(tmp_path, tiny_scan, capsys):
    """Outside test E #5: ``robot-ct info file_zstd/file_zstd_0.mcap.zstd`` (rosbag2's file compression: the whole
    MCAP file in a zstd frame) said "no MCAP magic at the start; scanning for chunks; ... recovered 0 messages", as
    for a damaged file. A zstd frame is recognised by its magic and the bag folder asked for."""
    import zstandard

    from robot_ct_ros.bag.reader import ScanBagError, read_raw_messages
    from robot_ct_ros.cli import main

    geom, frames, flat, dead = tiny_scan
    bag = write_scan(tmp_path / "plain", frames, geom, flat=flat)
    mcap = next(bag.glob("*.mcap"))
    zst = tmp_path / "file_zstd_0.mcap.zstd"
    zst.write_bytes(zstandard.ZstdCompressor().compress(mcap.read_bytes()))
    with pytest.raises(ScanBagError, match="a zstd-compressed file .*file compression.*give the bag folder, with its "
                                           "metadata.yaml"):
        read_raw_messages(zst)
    assert main(["info", str(zst)]) == 2
    err = capsys.readouterr().err
    assert "zstd-compressed" in err and "scanning for chunks" not in err, err
    assert len(read_raw_messages(mcap).messages) == 12 + 12 + 2  # a plain MCAP file is read as before


def test_a_detector_on_the_source_or_before_the_centre_is_refused_naming_the_values(tmp_path, capsys):
    """Outside test F findings 1 and 6: a detector centre written as the source (SDD 0) was read without a word,
    and reconstruct and calibrate ended in a ZeroDivisionError traceback in default_grid; a detector between the
    source and the centre of the views (SDD 100 mm, SOD 200 mm: info printed magnification 0.500) was read
    silently too. The reader refuses both, naming the topic, the views affected and the distances."""
    from robot_ct_ros.bag.format import ScanBagError
    from robot_ct_ros.cli import main

    g = circular_scan(8, 200.0, 400.0, 8, 12, 0.8, 0.8)
    frames = np.zeros((8, 8, 12), np.float32)
    frames[:, 2:6, 3:9] = 0.3  # line integrals
    info = {"projection_units": "line_integral"}
    read_scan(write_scan(tmp_path / "ok", frames, g, **info))  # magnification 2: fine
    on_source = g.replace(detector_mm=g.source_mm.copy())
    before = g.replace(detector_mm=0.5 * g.source_mm)  # 100 mm from the source, the centre (origin) 200 mm away
    cases = (("sdd0", on_source, r"/ct/geometry: source-to-detector distance 0 mm in 8 of 8 views"),
             ("before", before, r"/ct/geometry: the detector lies between the source and the centre of the views "
                                r"in 8 of 8 views \(e\.g\. view 0; SDD 100 mm < SOD 200 mm, magnification 0\.50"))
    for name, geom, said_re in cases:
        bag = write_scan(tmp_path / name, frames, geom, **info)
        with pytest.raises(ScanBagError, match=said_re):
            read_scan(bag)
        for cmd in (["info", str(bag)], ["reconstruct", str(bag), "--out", str(tmp_path / f"rec_{name}")],
                    ["calibrate", str(bag), "--out", str(tmp_path / f"cal_{name}")]):
            main(cmd)
            said = capsys.readouterr()
            said = said.out + said.err
            assert "/ct/geometry" in said and ("source-to-detector distance 0 mm" in said
                                               or "magnification 0.50" in said), (cmd, said)
            assert "Traceback" not in said and "ZeroDivisionError" not in said, (cmd, said)
    # half a view's worth: one view with the detector before the centre is named as one view
    one = g.replace(detector_mm=np.where(np.arange(8)[:, None] == 3, 0.5 * g.source_mm, g.detector_mm))
    with pytest.raises(ScanBagError, match=r"in 1 of 8 views \(e\.g\. view 3; SDD 100 mm < SOD 200 mm"):
        read_scan(write_scan(tmp_path / "one", frames, one, **info))
    # a corrected geometry like it is ignored with the reason, the scan kept
    scan = read_scan(write_scan(tmp_path / "corr", frames, g, geom_corrected=before, **info))
    assert scan.geom_corrected is None
    assert any("/ct/geometry_corrected ignored" in w and "magnification 0.50" in w for w in scan.warnings)


def test_line_integrals_declared_as_counts_are_warned_strong_attenuation_is_not(tmp_path):
    """Outside test F finding 3: line integrals of 0.05 to 0.49 written as counts under a flat of 1e4 were read
    without a word and gave a garbage volume. The reader warns when the counts are a tiny fraction of the flat
    almost everywhere (median below 1e-3); a strongly attenuating scan (the carotid simulation behind 13 cm of
    water reads 0.17 of its flat, here down to e^-6 = 0.0025) is not warned."""
    g = circular_scan(8, 200.0, 400.0, 8, 12, 0.8, 0.8)
    rng = np.random.default_rng(1)
    li = rng.uniform(0.05, 0.49, (8, 8, 12)).astype(np.float32)
    flat = np.full((8, 12), 1e4, np.float32)
    scan = read_scan(write_scan(tmp_path / "li_as_counts", li, g, flat=flat))
    said = [w for w in scan.warnings if "of the flat field everywhere" in w]
    assert len(said) == 1 and "are these line integrals? (projection_units" in said[0], scan.warnings
    assert "about 2.7e-05 of the flat field" in said[0], said
    dense = (flat * np.exp(-rng.uniform(1.0, 6.0, (8, 8, 12)))).astype(np.float32)
    assert not [w for w in read_scan(write_scan(tmp_path / "dense", dense, g, flat=flat)).warnings
                if "of the flat field" in w]


def _weak_object_line_integrals(rng, noise: float) -> np.ndarray:
    """(8, 8, 12) line integrals of a weak object (0 to 0.44 across a disc, air 0 around it) plus noise."""
    yy, xx = np.mgrid[:8, :12]
    disc = np.clip(1.0 - ((xx - 5.5) / 4.0) ** 2 - ((yy - 3.5) / 3.0) ** 2, 0.0, None)
    return (0.44 * np.sqrt(disc)[None] + rng.normal(0.0, noise, (8, 8, 12))).astype(np.float32)


def test_sign_flipped_line_integrals_of_a_weak_object_are_warned_noisy_air_is_not(tmp_path):
    """Outside test F finding 4: a weak object's line integrals sign-flipped (0 to -0.44, median 0) passed both
    documented tests (median below -0.1, 5 % below -0.5) and reconstructed to the negated object without a word.
    The reader warns when the negative tail dominates (1st percentile below -0.05 and more than twice the 99th in
    size); the same object unflipped with noise, and noisy air around it, are not warned."""
    g = circular_scan(8, 200.0, 400.0, 8, 12, 0.8, 0.8)
    rng = np.random.default_rng(2)
    li = _weak_object_line_integrals(rng, 0.0)
    flipped = read_scan(write_scan(tmp_path / "neg", -li, g, projection_units="line_integral"))
    said = [w for w in flipped.warnings if "further below 0 than above it" in w]
    assert len(said) == 1 and "sign-flipped" in said[0] and "99th 0)" in said[0], flipped.warnings
    for name, data in (("plain", li), ("noisy", _weak_object_line_integrals(rng, 0.03)),
                       ("air", rng.normal(0.0, 0.05, (8, 8, 12)).astype(np.float32))):
        scan = read_scan(write_scan(tmp_path / name, data, g, projection_units="line_integral"))
        assert not [w for w in scan.warnings if "below 0" in w or "lie below" in w], (name, scan.warnings)
    # a bright object on air (29 % of the rays well below 0, the median 0) is said as such, not as a negative median
    from robot_ct_ros.bag.reader import line_integral_warning

    bright = np.where(np.arange(768).reshape(8, 8, 12) < 223, -1.0, 0.0).astype(np.float32)  # 29.0 %
    said = line_integral_warning(bright, np.ones(bright.shape, bool))
    assert said.startswith("29 % of the usable line integrals lie below -0.5 (their median is 0: most rays see air)")


def test_an_all_zero_line_integral_frame_among_others_is_warned_naming_it(tmp_path):
    """Outside test F finding 5: one line-integral frame all exactly 0 among frames that are not (t3_zeroframe_li)
    was used as a view of air without a word. The reader warns, naming the frame's index and stamp; a scan whose
    frames all hold something (air included, as exact zeros around the object) is not warned."""
    from robot_ct_ros.bag.writer import default_stamps

    g = circular_scan(8, 200.0, 400.0, 8, 12, 0.8, 0.8)
    li = _weak_object_line_integrals(np.random.default_rng(3), 0.0)
    assert not [w for w in read_scan(write_scan(tmp_path / "ok", li, g, projection_units="line_integral")).warnings
                if "hold exactly 0" in w]
    li[5] = 0.0
    scan = read_scan(write_scan(tmp_path / "zero", li, g, projection_units="line_integral"))
    said = [w for w in scan.warnings if "hold exactly 0 in every usable pixel" in w]
    assert len(said) == 1, scan.warnings
    assert "1 line-integral frame(s) of 8 hold exactly 0" in said[0] and "(frame [5], stamps " in said[0], said
    assert str(int(default_stamps(8)[5])) in said[0] and "view of air" in said[0], said
    assert scan.n_views == 8  # kept: only the user knows whether the view saw nothing


@pytest.mark.parametrize("arc_deg", [360.0, 200.0])
def test_default_grid_of_a_detector_tilted_out_of_its_plane_is_about_the_field_of_view(tmp_path, arc_deg):
    """Outside test F finding 8: a detector tilted 25 degrees about its v axis (the ray through its centre still
    through the axis) got a default grid 429 voxels (171 mm) across for a field of view about 25 mm wide: the grid
    was sized from the principal rays (along the detector normal), which miss the axis by SOD sin 25 = 85 mm. It is
    placed and sized from the central rays: the principal ray where the detector holds the principal point, the
    ray through the detector centre where not; the untilted grid is unchanged."""
    from scipy.spatial.transform import Rotation

    g = circular_scan(12, 200.0, 400.0, 48, 64, 0.8, 0.8, arc_rad=np.radians(arc_deg))
    turn = Rotation.from_rotvec(g.v * np.radians(25.0)).as_matrix()
    tilted = g.replace(u=np.einsum("nij,nj->ni", turn, g.u))
    frames = np.full((12, 48, 64), 0.1, np.float32)
    grids = [read_scan(write_scan(tmp_path / name, frames, geom, projection_units="line_integral")).default_grid()
             for name, geom in (("flat", g), ("tilted", tilted))]
    plain, tilt = grids
    assert plain.shape_zyx == (48, 64, 64)  # 25.6 mm across at 0.4 mm: as before
    assert tilt.shape_zyx[0] == 48 and 56 <= tilt.shape_zyx[1] == tilt.shape_zyx[2] <= 64, tilt.shape_zyx
    np.testing.assert_allclose(tilt.voxel_size_mm, plain.voxel_size_mm)
    np.testing.assert_allclose(tilt.center_mm, 0.0, atol=1e-6)  # a short arc too: the central rays meet there
