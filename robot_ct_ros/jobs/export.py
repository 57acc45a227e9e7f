"""Export of a scan's per-view geometry for other CT toolkits: RTK XML, ASTRA ``cone_vec``, TIGRE.

:func:`export_geometry` writes the nominal geometry of a scan bag (/ct/geometry), or the
corrected geometry of a calibration (:func:`corrected_geometry`), in millimetres, one view per
paired frame in stamp order (the order of the bag's frames as :func:`read_scan` returns them):

* ``rtk``: an ``rtk.ThreeDCircularProjectionGeometry`` XML file, written by RTK's own
  ``ThreeDCircularProjectionGeometryXMLFileWriter`` from
  :func:`robot_ct_ros.ct.rtk_bridge.to_rtk_geometry` (exact vector form). It needs itk-rtk,
  which is a test dependency only; without it the export says so. The XML holds no detector
  size: RTK's projection stack must have spacing (col_pitch, row_pitch, 1) mm and origin
  (-(n_cols-1)/2 * col_pitch, -(n_rows-1)/2 * row_pitch, 0) mm (its physical (0, 0) is the
  centre of the pixel grid), and its numpy view is our ``proj[view, row, col]``.
  RTK's FDK, Parker and displaced-detector weights assume the orbit turns about RTK's y axis
  through its origin (they work from the gantry angles); a scan about another axis, written as it
  is, would put the whole rotation into the out-of-plane and in-plane angles with one gantry angle
  for every view, and RTK's FDK of it is meaningless. So the XML is written in an RTK frame
  (``--rtk-frame``, :func:`rtk_frame`): ``scan``: the scan axis (:func:`estimate_scan_axis`, the
  sign along the detector's rows v) turned onto +y by the smallest rotation R, the centre c of the
  sources' orbit (:func:`estimate_scan_centre`, RTK's isocentre) at the origin,
  ``x_rtk = R (x_world - c)``; ``world``: the bag's world as it is; ``auto`` (default): ``world``
  where the scan axis is already within 1 degree of the world's +-y and passes within 2 % of the
  orbit's radius of the origin, else ``scan``. The frame is printed and written beside the XML as
  ``<out stem>.rtk_frame.json`` (the 4 x 4 world->RTK and RTK->world matrices and how a volume
  RTK reconstructs maps back into the world: the same voxels, origin ``R^T o + c``, direction
  ``R^T D``). ``robot-ct import rtk`` of the XML gives the geometry in that RTK frame. A detector
  turned in its plane gets a warning (:func:`rtk_in_plane_note`): RTK's FDK filters along the rows.
* ``astra``: ASTRA's ``cone_vec`` vectors, one row of 12 numbers per view:
  ``(srcX, srcY, srcZ, dX, dY, dZ, uX, uY, uZ, vX, vY, vZ)``: the source, the detector centre, the
  vector from detector pixel (0, 0) to (0, 1) (one column step, ``u * col_pitch``) and from
  (0, 0) to (1, 0) (one row step, ``v * row_pitch``), i.e.
  :meth:`~robot_ct_ros.ct.geometry.ConeGeometry.to_astra_vec`. ASTRA's detector has
  ``n_rows`` rows and ``n_cols`` columns; its 3-D projection data are ``proj.transpose(1, 0, 2)``
  (rows, views, columns). ``.npy`` writes a float64 array (n_views, 12), any other suffix a text
  file (``numpy.savetxt``, 17 significant digits, a ``#`` header with the detector size).
* ``tigre``: an ``.npz`` of TIGRE's Python geometry arrays per view (``DSO``, ``DSD``, ``angles``
  (n, 3) ZYZ, ``offOrigin``, ``offDetector``, ``rotDetector``) with ``nDetector``, ``dDetector``,
  ``sDetector`` and ``center_mm``, our world position of TIGRE's origin (the bag's ROI centre):
  :mod:`robot_ct_ros.jobs.tigre` states the exact mapping and the views it refuses.

A suffix other than the format's (rtk ``.xml``, astra ``.npy`` or ``.txt``, tigre ``.npz``) gets a warning;
the reader's warnings on a damaged bag are said as ``warning: ...`` (the views it recovered are exported).
The output file must lie outside the bag (and the corrected bag, and be no calibration's report.json):
writing into a bag's folder or over its ``.mcap`` would destroy the scan being exported.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry
from robot_ct_ros.jobs.output import refuse_out_in_bag
from robot_ct_ros.jobs.output import say as _say

__all__ = ["FORMATS", "RTK_FRAMES", "corrected_geometry", "export_geometry", "rtk_frame", "rtk_frame_path",
           "rtk_in_plane_note", "write_astra_vectors", "write_rtk_frame", "write_rtk_xml"]

FORMATS = ("rtk", "astra", "tigre")
SUFFIXES = {"rtk": (".xml",), "astra": (".npy", ".txt"), "tigre": (".npz",)}
"""The suffixes of each format's files (case aside); :func:`export_geometry` warns on another (the file
is written as the format says, whatever its name: an XML named .npy would mislead whoever opens it)."""
WRITES = {"rtk": "RTK's geometry XML", "astra": "text", "tigre": "an .npz archive"}
"""What each format writes to a file of an unexpected suffix (astra: text, as for .txt)."""
RTK_IN_PLANE_WARN_DEG = 3.0
"""An RTK export whose detector is turned in its plane (RTK's InPlaneAngle) farther than this from 0 or 180 degrees
in some view gets a warning (:func:`rtk_in_plane_note`): RTK's FDK ramp-filters along the projections' rows as they
are, while ours filters along the source motion beyond the same 3 degrees
(:data:`robot_ct_ros.ct.virtual_detector.DEFAULT_TOL_DEG`)."""


def _read(bag):
    from robot_ct_ros.bag.reader import read_scan

    return read_scan(bag)


def _corrected_paths(path) -> tuple[Path | None, Path]:
    """(report.json or None, corrected bag) of a calibration output ``path`` (:func:`corrected_geometry`)."""
    path = Path(path)
    report = path / "report.json" if path.is_dir() and (path / "report.json").exists() else path
    if report.suffix != ".json":
        inner = sorted(p.name for p in path.glob("*_corrected") if p.is_dir()) if path.is_dir() else []
        if inner and not any(path.glob("*.mcap")):  # calibrate writes the bag, the volume, then report.json
            raise ValueError(f"{path} looks like a robot-ct calibrate folder whose run did not finish (no "
                             f"report.json): run calibrate again, or pass its corrected bag ({path / inner[0]}) "
                             "if robot-ct info reads it whole")
        return None, path
    try:
        rep = json.loads(report.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{report}: not a JSON report ({exc})") from None
    name = rep.get("corrected_bag") if isinstance(rep, dict) else None
    if not name:
        raise ValueError(f"{report}: no corrected_bag in it; is it a report of robot-ct calibrate?")
    bag = Path(name)
    if not bag.exists():  # the output folder was moved: the bag sits next to report.json
        bag = report.parent / bag.name
    return report, bag


def _check_out_spares(out: Path, bag: Path, what: str) -> None:
    """Refuse an ``out`` that is the bag's file or lies in its folder: the export would overwrite the scan it
    reads (:func:`~robot_ct_ros.jobs.output.refuse_out_in_bag`)."""
    refuse_out_in_bag(out, bag, what, "give a file outside it")


def corrected_geometry(path, nominal_scan=None, *, say=None) -> ConeGeometry:
    """The corrected geometry of a calibration output.

    ``path`` is the folder ``robot-ct calibrate --out`` wrote, its ``report.json`` (whose
    ``corrected_bag`` names the bag with /ct/geometry_corrected), or such a corrected bag itself.
    With ``nominal_scan`` (a :class:`~robot_ct_ros.bag.reader.ScanData`), the corrected bag must
    hold the same views (same stamps) and the same projections. ``say``: where the reader's warnings on the
    corrected bag go (``warning: ...``; those the nominal scan has too are left out, said with it).
    """
    _, bag = _corrected_paths(path)
    scan = _read(bag)
    said = set(nominal_scan.warnings) if nominal_scan is not None else set()  # the nominal bag's: said with it
    for w in scan.warnings if say is not None else ():
        if w not in said:
            say(f"warning: {bag.name}: {w}")
    if scan.geom_corrected is None:
        raise ValueError(f"{bag}: no /ct/geometry_corrected covering every frame")
    if nominal_scan is not None and not np.array_equal(scan.stamps_ns, nominal_scan.stamps_ns):
        raise ValueError(f"{bag} holds other views than {nominal_scan.path} ({scan.n_views} and "
                         f"{nominal_scan.n_views} frames, stamps differ)")
    if nominal_scan is not None and not np.array_equal(scan.counts, nominal_scan.counts, equal_nan=True):
        # simulated scans of one protocol share stamps: the frames tell whose correction this is
        raise ValueError(f"{bag} is the correction of another scan than {nominal_scan.path} (same stamps, other "
                         "projections)")
    return scan.geom_corrected


RTK_FRAMES = ("auto", "scan", "world")
"""``--rtk-frame`` choices (module docstring)."""
AUTO_WORLD_AXIS_DEG = 1.0
"""``auto`` keeps the world where the scan axis is within this of the world's +-y ..."""
AUTO_WORLD_CENTRE_FRACTION = 0.02
"""... and passes this fraction of the orbit's radius or less from the world's origin."""


def _turn_onto_y(a) -> np.ndarray:
    """The smallest rotation taking the unit vector ``a`` (``a[1] > -1``) onto +y."""
    a = np.asarray(a, dtype=np.float64)
    a = a / np.linalg.norm(a)
    v = np.cross(a, [0.0, 1.0, 0.0])
    c = float(a[1])
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def rtk_frame(geom: ConeGeometry, frame: str = "auto", fallback_centre_mm=(0.0, 0.0, 0.0)) -> dict:
    """The RTK frame the XML of ``geom`` is written in (module docstring): a dict with ``frame`` (``scan`` or
    ``world``, what ``auto`` chose), ``rotation`` R (3 x 3) and ``centre_mm`` c (``x_rtk = R (x_world - c)``),
    ``world_to_rtk`` and ``rtk_to_world`` (4 x 4), ``axis`` (the scan axis in the world), ``axis_deg`` (its angle
    to the world's +-y) and ``axis_offset_mm`` (its distance from the world's origin). ``fallback_centre_mm``:
    the centre where the geometry tells none (a single view)."""
    from robot_ct_ros.ct.scan_weights import estimate_scan_axis, estimate_scan_centre

    if frame not in RTK_FRAMES:
        raise ValueError(f"unknown --rtk-frame {frame!r}; one of {', '.join(RTK_FRAMES)}")
    a = np.asarray(estimate_scan_axis(geom), dtype=np.float64)
    a = a / np.linalg.norm(a)  # along the rows' v: RTK's in-plane angle about 0
    if a[1] < -0.5:  # a world about -y (its rows pointing down) keeps its orientation: in-plane about 180 deg
        a = -a
    c = estimate_scan_centre(geom, a)
    c = np.asarray(fallback_centre_mm if c is None else c, dtype=np.float64)
    axis_deg = float(np.degrees(np.arccos(min(1.0, abs(a[1])))))
    offset = float(np.linalg.norm(c - np.dot(c, a) * a))  # the world origin's distance from the axis line
    radius = float(np.median(np.linalg.norm(np.cross(geom.source_mm - c, a), axis=1)))
    if frame == "auto":
        frame = ("world" if axis_deg <= AUTO_WORLD_AXIS_DEG and offset <= AUTO_WORLD_CENTRE_FRACTION * radius
                 else "scan")
    if frame == "world":
        R, c = np.eye(3), np.zeros(3)
    else:
        R = _turn_onto_y(a)
    w2r = np.eye(4)
    w2r[:3, :3], w2r[:3, 3] = R, -R @ c
    r2w = np.eye(4)
    r2w[:3, :3], r2w[:3, 3] = R.T, c
    return {"frame": frame, "rotation": R, "centre_mm": c, "world_to_rtk": w2r, "rtk_to_world": r2w, "axis": a,
            "axis_deg": axis_deg, "axis_offset_mm": offset}


def rtk_in_plane_note(geom_rtk: ConeGeometry) -> str | None:
    """A warning for the RTK export of ``geom_rtk`` (the geometry in its RTK frame) when some view's detector is
    turned in its plane (RTK's InPlaneAngle, degrees) more than :data:`RTK_IN_PLANE_WARN_DEG` from 0 or 180; else
    None. RTK's FDK ramp-filters along each projection's rows, which then do not follow the source's motion: its
    FDK of the export is approximate (an outside check, a detector turned 90 degrees: correlation 0.644 with the
    phantom, 0.988 unturned), while the geometry itself is exact (its forward projector, iterative methods)."""
    from robot_ct_ros.ct.rtk_bridge import _rtk_vector_parameters  # pure numpy, no itk

    in_plane = np.degrees(_rtk_vector_parameters(geom_rtk)[:, 6])  # RTK's InPlaneAngle per view (AddProjection)
    off = np.abs((in_plane + 90.0) % 180.0 - 90.0)  # from the nearer of 0 and 180 degrees
    worst = int(np.argmax(off))
    if off[worst] <= RTK_IN_PLANE_WARN_DEG:
        return None
    return (f"the detector is turned in its plane (RTK's InPlaneAngle {in_plane[worst] % 360.0:.1f} deg in view "
            f"{worst}, {off[worst]:.1f} deg from 0 or 180): RTK's FDK ramp-filters along the projections' rows, "
            f"which here do not follow the source's motion, so RTK's FDK of this export is approximate (the "
            f"geometry itself is exact); for RTK's FDK, turn the projections so that their rows run across the scan "
            f"axis (a detector turned 90 deg: transpose each frame and export that geometry), or reconstruct with "
            f"robot-ct reconstruct, whose FDK filters along the source's motion")


def rtk_frame_path(out) -> Path:
    """Where the RTK frame of an XML ``out`` is written: ``<stem>.rtk_frame.json`` beside it."""
    out = Path(out)
    return out.with_name(out.stem + ".rtk_frame.json")


def write_rtk_frame(frame: dict, path, xml, frame_id: str = "world") -> Path:
    """The RTK frame (:func:`rtk_frame`) of the XML ``xml`` as JSON at ``path``."""
    doc = {
        "format": "robot_ct_ros.rtk_frame/1",
        "xml": Path(xml).name,
        "frame": frame["frame"],
        "world_frame_id": frame_id,
        "units": "mm",
        "world_to_rtk": frame["world_to_rtk"].tolist(),
        "rtk_to_world": frame["rtk_to_world"].tolist(),
        "scan_axis_world": frame["axis"].tolist(),
        "scan_centre_world_mm": frame["centre_mm"].tolist(),
        "meaning": "x_rtk = world_to_rtk @ [x_world, 1] (R = its 3 x 3 block, c = scan_centre_world_mm: "
                   "x_rtk = R (x_world - c)); RTK's y axis is the scan axis, its origin the orbit's centre",
        "volume_to_world": "a volume RTK reconstructs with origin o and direction D (identity by default) is the "
                           "same voxels in the world with origin R^T o + c and direction R^T D (rtk_to_world "
                           "applied to the image's placement; no resampling)",
    }
    Path(path).write_text(json.dumps(doc, indent=1) + "\n")
    return Path(path)


def write_rtk_xml(geom: ConeGeometry, path) -> Path:
    """RTK's geometry XML of ``geom`` at ``path`` (needs itk-rtk; module docstring)."""
    try:
        from robot_ct_ros.ct import rtk_bridge
        _, rtk = rtk_bridge._rtk()
    except ImportError:
        raise ValueError("--format rtk needs itk-rtk (pip install itk-rtk, see requirements-test.txt); "
                         "--format astra does not") from None
    rtk_geom = rtk_bridge.to_rtk_geometry(geom)  # kept referenced: the writer holds a raw pointer to it
    writer = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    writer.SetFilename(str(path))
    writer.SetObject(rtk_geom)
    writer.WriteFile()
    del writer, rtk_geom
    return Path(path)


def write_astra_vectors(geom: ConeGeometry, path) -> Path:
    """ASTRA ``cone_vec`` rows of ``geom`` at ``path`` (.npy, else text; module docstring)."""
    vec = geom.to_astra_vec()
    path = Path(path)
    if path.suffix.lower() == ".npy":  # as import reads it
        with open(path, "wb") as f:  # np.save(path) would append ".npy" to "vec.NPY"
            np.save(f, vec)
    else:
        np.savetxt(path, vec, fmt="%.17g",
                   header=f"ASTRA cone_vec, mm: srcX srcY srcZ dX dY dZ uX uY uZ vX vY vZ; "
                          f"detector {geom.n_rows} rows x {geom.n_cols} columns")
    return path


def write_tigre(geom: ConeGeometry, path, center_mm) -> Path:
    """TIGRE's geometry arrays of ``geom`` about ``center_mm`` as an .npz at ``path`` (:mod:`robot_ct_ros.jobs.tigre`)."""
    from robot_ct_ros.jobs.tigre import to_tigre

    params = to_tigre(geom, center_mm)  # refused views raise before the file is created
    with open(path, "wb") as f:
        np.savez(f, **params)
    return Path(path)


def export_geometry(bag, out, fmt: str = "rtk", *, corrected=None, rtk_frame_choice: str | None = None,
                    say=_say) -> dict:
    """Write the geometry of the scan bag ``bag`` as ``fmt`` (``rtk``, ``astra`` or ``tigre``) to the file ``out``.

    ``corrected``: a calibration output (see :func:`corrected_geometry`) whose corrected geometry
    is written instead of the bag's nominal one. ``rtk_frame_choice``: ``auto`` (None), ``scan`` or ``world``,
    the frame of an RTK XML (module docstring; refused with another format). Returns what was written (paths,
    detector, the RTK projection stack's origin and spacing, the RTK frame) and ``warnings``: every warning said
    (``warning: ...``), among them, for RTK, a detector turned in its plane (:func:`rtk_in_plane_note`).
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; one of {', '.join(FORMATS)}")
    if rtk_frame_choice is not None and fmt != "rtk":
        raise ValueError(f"--rtk-frame is the frame of an RTK XML; --format {fmt} writes the bag's world frame")
    if rtk_frame_choice is not None and rtk_frame_choice not in RTK_FRAMES:
        raise ValueError(f"unknown --rtk-frame {rtk_frame_choice!r}; one of {', '.join(RTK_FRAMES)}")
    warnings = []

    def tell(line: str) -> None:  # every warning said is also kept in the result
        if line.startswith("warning: "):
            warnings.append(line[len("warning: "):])
        say(line)

    out = Path(out)
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder; give a file name")
    if not out.parent.is_dir():
        raise ValueError(f"cannot write {out}: {out.parent} is not a folder")
    _check_out_spares(out, Path(bag), "the bag")
    if out.suffix.lower() not in SUFFIXES[fmt]:
        tell(f"warning: --out {out.name}: --format {fmt} writes {WRITES[fmt]}, whose files end in "
            f"{' or '.join(SUFFIXES[fmt])}; the name says otherwise")
    if corrected is not None:
        report, corrected_bag = _corrected_paths(corrected)
        _check_out_spares(out, corrected_bag, "the corrected bag")
        if report is not None and out.resolve() == report.resolve():
            raise ValueError(f"--out {out} is the calibration's report; give another file")
    scan = _read(bag)
    for w in scan.warnings:  # a damaged bag gives fewer views: the reader never drops data silently
        tell(f"warning: {w}")
    geom = scan.geom if corrected is None else corrected_geometry(corrected, scan, say=tell)
    which = "nominal" if corrected is None else "corrected"
    frame = None
    if fmt == "rtk":
        frame = rtk_frame(geom, rtk_frame_choice or "auto", scan.scan_center_mm())
        frame_json = rtk_frame_path(out)
        _check_out_spares(frame_json, Path(bag), "the bag")
        geom_rtk = geom.moved(frame["rotation"], -frame["rotation"] @ frame["centre_mm"])
        write_rtk_xml(geom_rtk, out)
        write_rtk_frame(frame, frame_json, out, scan.frame_id)
        turned = rtk_in_plane_note(geom_rtk)
    elif fmt == "tigre":
        try:
            write_tigre(geom, out, scan.scan_center_mm())
        except ValueError as exc:
            raise ValueError(f"--format tigre: {which} geometry, {exc}") from None
    else:
        write_astra_vectors(geom, out)
    from robot_ct_ros.ct.rtk_bridge import rtk_stack_origin_spacing  # pure numpy, no itk

    origin, spacing = rtk_stack_origin_spacing(geom)
    result = {"path": str(out), "format": fmt, "geometry": which, "n_views": geom.n_views,
              "n_rows": geom.n_rows, "n_cols": geom.n_cols, "row_pitch_mm": geom.row_pitch_mm,
              "col_pitch_mm": geom.col_pitch_mm, "rtk_projection_origin_mm": origin,
              "rtk_projection_spacing_mm": spacing}
    if frame is not None:
        result.update({"rtk_frame": frame["frame"], "world_to_rtk": frame["world_to_rtk"].tolist(),
                       "rtk_to_world": frame["rtk_to_world"].tolist(), "rtk_frame_path": str(frame_json)})
    detector = (f"detector {geom.n_rows} x {geom.n_cols} pixels of {geom.row_pitch_mm:g} x {geom.col_pitch_mm:g} mm "
                "(rows x columns)")
    if fmt == "rtk":
        o = result["rtk_projection_origin_mm"]
        detector += f"; RTK projection stack origin ({o[0] + 0.0:g}, {o[1] + 0.0:g}, 0) mm, spacing " \
                    f"({geom.col_pitch_mm:g}, {geom.row_pitch_mm:g}, 1) (x along columns; robot-ct import rtk " \
                    f"takes rows first: --pitch-mm {geom.row_pitch_mm:g},{geom.col_pitch_mm:g} " \
                    f"--origin-mm={o[1] + 0.0:g},{o[0] + 0.0:g})"
    say(f"wrote {out}: {which} geometry of {geom.n_views} views as {fmt}, {detector}")
    if frame is not None:
        say(_frame_line(frame, scan.frame_id, frame_json))
        if turned:
            tell(f"warning: {turned}")
    result["warnings"] = warnings
    return result


def _frame_line(frame: dict, frame_id: str, path: Path) -> str:
    """What the export says of the RTK frame it wrote (one line, then the matrix where it is not the identity)."""
    def vec(x):
        return "(" + ", ".join(f"{v + 0.0:.6g}" for v in x) + ")"

    a = frame["axis"]
    if frame["frame"] == "world":
        return (f"RTK frame: world ({frame_id} as it is; the scan axis {vec(a)} is {frame['axis_deg']:.3g} deg off "
                f"+-y and passes {frame['axis_offset_mm']:.3g} mm from the origin); identity written to {path.name}")
    c = frame["centre_mm"]
    rows = "; ".join(vec(np.append(r, t)) for r, t in zip(frame["world_to_rtk"][:3, :3], frame["world_to_rtk"][:3, 3]))
    return (f"RTK frame: scan (RTK's gantry angle follows the views): the scan axis {vec(a)} of {frame_id} is RTK's +y "
            f"and the orbit's centre {vec(c)} mm its origin, x_rtk = R (x_world - c), world->RTK rows [{rows}]; "
            f"a volume RTK reconstructs (origin o, direction D) is in the world at origin R^T o + c, direction R^T D; "
            f"written to {path.name} (--rtk-frame world keeps the world, whose axis is {frame['axis_deg']:.3g} deg "
            f"off +-y)")
