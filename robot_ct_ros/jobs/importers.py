"""Import of a projection stack with RTK or ASTRA geometry into a scan bag (``robot-ct import rtk|astra``).

Projections (:func:`read_stack`): a ``.npy`` array or a TIFF stack (``tifffile``), shape (views,
rows, cols), i.e. our ``proj[view, row, col]`` (RTK's numpy view of its projection stack). For
ASTRA, ``layout="astra"`` takes ASTRA's 3-D projection data (rows, views, cols) instead; a 2-D
array is a fan-beam sinogram (views, cols) and becomes a one-row detector.

Values are line integrals -log(I/I0), stored unchanged (float32, ``projection_units =
"line_integral"``), or raw counts (``counts=True``) with a flat field ``flat`` and optionally a dark
frame ``dark`` (2-D frames, or stacks averaged over their first axis). The bag stores counts and
a flat field itself (docs/bag-format.md), so raw data are kept as counts rather than converted:
frames ``I - D`` and flat field ``F - D`` (float32); the reader then forms
``log((F - D) / max(I - D, 0.5)) = -log((I - D) / (F - D))``. As the bag's contract has it, a
count of 0 (``I - D = 0``: photon starvation) is a measurement and is stored as 0 (the reader
warns of 0 counts under a bright flat); a pixel with ``I - D < 0`` is stored as NaN (unusable in
that frame) and one with ``F - D <= 0`` is unusable in every frame (the reader masks a
non-positive flat). Dark-corrected counts in [0, 0.5) meet the bag's photon-starvation floor of
0.5. Fewer than 4 frames with a usable pixel are refused before anything is written: no reader
accepts such a bag (docs/bag-format.md, Pairing).

RTK (:func:`rtk_geometry`): the ``rtk.ThreeDCircularProjectionGeometry`` XML, read with
itk-rtk's ``ThreeDCircularProjectionGeometryXMLFileReader`` (itk-rtk is a test dependency:
without it the import says so). RTK's circular geometry rotates about the world **y** axis: at
gantry angle theta (no offsets, no tilt) the source is at ``SID * (sin theta, 0, cos theta)``,
the detector's u (first image index) is ``(cos theta, 0, -sin theta)`` and v is ``+y`` (checked
with RTK in test/jobs/test_import_rtk.py). The views keep RTK's world frame; a bag may rotate
about any axis. The XML holds no detector size, so the pitch (``row_pitch_mm, col_pitch_mm``)
must be given and the stack's origin may be: ``origin_mm = (row, col)`` is the physical
coordinate of pixel (0, 0) in RTK's projection frame (ITK's image origin, second and first
component). The default is RTK's usual centred stack, origin ``(-(n_rows-1)/2 * row_pitch,
-(n_cols-1)/2 * col_pitch)``, whose physical (0, 0) is the pixel-grid centre (what
``robot-ct export --format rtk`` assumes); another origin moves our detector centre to the
world point of the grid centre. RTK's parallel beam (``SourceToDetectorDistance`` 0) and its
cylindrical detector are refused: a bag describes flat-panel cone and fan beams only.

ASTRA (:func:`astra_geometry`): ``cone_vec`` rows of 12 numbers ``(src, d, u, v)`` (mm; d the
detector centre, u and v one column and one row step, :meth:`ConeGeometry.from_astra_vec`) or
``fanflat_vec`` rows of 6 ``(srcX, srcY, dX, dY, uX, uY)``: a fan in the plane z = 0 on a one-row
detector with v = +z and a row pitch ``row_pitch_mm`` (default the column pitch; it only sets
the slice thickness). ``.npy`` or text (``numpy.loadtxt``; ``#`` comments). ASTRA's parallel-beam
``parallel3d_vec`` / ``parallel_vec`` rows have the same columns, a unit ray direction first: they are
refused (:func:`check_not_parallel`).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry
from robot_ct_ros.jobs.output import say as _say

__all__ = ["read_stack", "read_frame", "dark_corrected", "rtk_geometry", "read_astra_vectors", "astra_geometry",
           "check_not_parallel", "import_rtk", "import_astra", "check_view_count", "LAYOUTS"]

LAYOUTS = ("views-first", "astra")
"""Projection array layouts: (views, rows, cols), or ASTRA's 3-D (rows, views, cols)."""
MIN_PITCH_MM = 1e-3
MAX_PITCH_MM = 10.0
FINEST_DETECTOR_PITCH_MM = 5e-3
"""A pixel pitch below this (finer than X-ray detectors' pixels) is warned on import: metres given for mm, most
likely (1.6 mm written 0.0016); accepted, since an optically magnified detector may quote a finer one."""


def _load(path, what: str) -> np.ndarray:
    path = Path(path)
    with open(path, "rb"):  # a missing or unreadable file is an OSError with its name
        pass
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix in (".tif", ".tiff"):
            import logging

            import tifffile

            log = logging.getLogger("tifffile")
            level = log.level
            # its warnings and errors about a damaged file (logged at ERROR: "invalid page offset") would precede our
            # one-line error, which says what it read
            log.setLevel(logging.CRITICAL + 1)
            try:
                arr = tifffile.imread(path)
            finally:
                log.setLevel(level)
            if arr.size == 0:  # tifffile reads a TIFF header with garbage behind it as no page at all
                raise ValueError(f"{path}: cannot read {what} (the TIFF file holds no readable image: corrupt or "
                                 "truncated?)")
        else:
            raise ValueError(f"{path}: {what} must be a .npy or .tif/.tiff file")
    except ValueError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise ValueError(f"{path}: cannot read {what} ({' '.join(str(exc).split())})") from None
    except Exception as exc:  # tifffile raises its own errors for what is no TIFF
        raise ValueError(f"{path}: cannot read {what} ({type(exc).__name__}: {' '.join(str(exc).split())})") \
            from None
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{path}: {what} must be numeric, got dtype {arr.dtype}")
    return arr


def read_stack(path, layout: str = "views-first", *, allow_2d: bool = False) -> np.ndarray:
    """The projection stack at ``path`` as (views, rows, cols) (module docstring); a 2-D array
    (views, cols) only with ``allow_2d`` (a fan-beam sinogram: one row)."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; one of {', '.join(LAYOUTS)}")
    arr = _load(path, "projections")
    if arr.ndim == 2 and allow_2d:
        return arr[:, None, :]
    if arr.ndim != 3:
        raise ValueError(f"{path}: projections must be 3-D ({'rows, views, cols' if layout == 'astra' else 'views, rows, cols'})"
                         f"{' or a 2-D sinogram (views, cols)' if allow_2d else ''}, got shape {arr.shape}")
    return arr.transpose(1, 0, 2) if layout == "astra" else arr


def read_frame(path, shape, what: str) -> np.ndarray:
    """A 2-D frame (rows, cols) of ``shape``; a 3-D stack is averaged over its first axis."""
    arr = _load(path, what).astype(np.float64)
    if arr.ndim == 3:
        arr = arr.mean(axis=0)
    elif arr.ndim == 1 and shape[0] == 1:
        arr = arr[None]
    if arr.shape != tuple(shape):
        raise ValueError(f"{path}: the {what} is {arr.shape} pixels but the projections are {tuple(shape)}")
    return arr


def dark_corrected(counts, flat, dark=None) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``I - D`` (NaN where < 0: unusable; 0 kept, a measurement) and flat field ``F - D`` as float32
    (module docstring)."""
    counts = np.asarray(counts, np.float64)
    flat = np.asarray(flat, np.float64)
    d = 0.0 if dark is None else np.asarray(dark, np.float64)
    frames = counts - d
    frames = np.where(frames >= 0, frames, np.nan).astype(np.float32)
    return frames, (flat - d).astype(np.float32)


def _check_pitch(pitch_mm: float, what: str) -> float:
    pitch = float(pitch_mm)
    if not np.isfinite(pitch) or pitch <= 0:
        raise ValueError(f"{what} must be positive, got {pitch:g} mm")
    if pitch < MIN_PITCH_MM or pitch > MAX_PITCH_MM:
        raise ValueError(f"{what} is {pitch:g} mm, outside {MIN_PITCH_MM:g}..{MAX_PITCH_MM:g} mm; give millimetres")
    return pitch


# ---------------------------------------------------------------------------------- RTK
def rtk_geometry(xml_path, n_rows: int, n_cols: int, row_pitch_mm: float, col_pitch_mm: float,
                 origin_mm=None) -> ConeGeometry:
    """The views of RTK's geometry XML on an ``n_rows`` x ``n_cols`` detector (module docstring)."""
    xml_path = Path(xml_path)
    with open(xml_path, "rb"):
        pass
    row_pitch_mm = _check_pitch(row_pitch_mm, "the row pitch")
    col_pitch_mm = _check_pitch(col_pitch_mm, "the column pitch")
    try:
        from robot_ct_ros.ct import rtk_bridge
        _, rtk = rtk_bridge._rtk()
    except ImportError:
        raise ValueError("import rtk needs itk-rtk to read RTK's XML (pip install itk-rtk, see "
                         "requirements-test.txt); import astra does not") from None
    import xml.etree.ElementTree as ET

    try:  # ITK's reader stops silently at a cut: a truncated file would read as its first few views
        ET.parse(xml_path)
    except ET.ParseError as exc:
        raise ValueError(f"{xml_path}: not a well-formed XML file, truncated or corrupt? ({exc})") from None
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(xml_path))
    try:
        reader.GenerateOutputInformation()
    except Exception as exc:  # ITK raises RuntimeError with a multi-line message
        first = next((ln.strip() for ln in str(exc).splitlines() if ln.strip().startswith(("Desc", "what"))), "")
        raise ValueError(f"{xml_path}: not an RTK ThreeDCircularProjectionGeometry XML file"
                         f"{' (' + first + ')' if first else ''}") from None
    rtk_geom = reader.GetOutputObject()
    if len(rtk_geom.GetGantryAngles()) == 0:
        raise ValueError(f"{xml_path}: the RTK geometry holds no projection (is it RTK's "
                         "ThreeDCircularProjectionGeometry XML?)")
    radius = float(rtk_geom.GetRadiusCylindricalDetector())
    if radius != 0.0:  # RTK's curved detector: a flat-panel geometry would misplace every column but the centre
        raise ValueError(f"{xml_path}: a cylindrical detector (RadiusCylindricalDetector {radius:g} mm); a scan bag "
                         "describes flat detectors only")
    sdd = np.asarray(rtk_geom.GetSourceToDetectorDistances(), np.float64)
    if np.any(sdd == 0.0):  # RTK's parallel beam: read back as a cone, its source would sit 2 SID from the detector
        view = int(np.argmax(sdd == 0.0))
        raise ValueError(f"{xml_path}: a parallel-beam geometry (SourceToDetectorDistance 0 in view {view}, RTK's "
                         "parallel convention); a scan bag describes cone and fan beams only")
    geom = rtk_bridge.from_rtk_geometry(rtk_geom, n_rows, n_cols, row_pitch_mm, col_pitch_mm)
    if origin_mm is not None:
        o_row, o_col = (float(x) for x in origin_mm)
        dc = o_col + 0.5 * (n_cols - 1) * col_pitch_mm  # physical coordinate of the grid centre
        dr = o_row + 0.5 * (n_rows - 1) * row_pitch_mm
        geom = geom.replace(detector_mm=geom.detector_mm + dc * geom.u + dr * geom.v)
    return geom


# -------------------------------------------------------------------------------- ASTRA
def read_astra_vectors(path) -> np.ndarray:
    """ASTRA vector rows (n, 12) or (n, 6) from ``.npy`` or text."""
    path = Path(path)
    with open(path, "rb"):
        pass
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: cannot read ASTRA vectors (the file is empty)")
    try:
        with warnings.catch_warnings():  # loadtxt warns of a file without numbers: the error below says so
            warnings.simplefilter("ignore", UserWarning)
            vec = np.load(path, allow_pickle=False) if path.suffix.lower() == ".npy" else np.loadtxt(path, ndmin=2)
    except (ValueError, EOFError) as exc:  # EOFError: a .npy cut inside its header
        raise ValueError(f"{path}: cannot read ASTRA vectors ({' '.join(str(exc).split())})") from None
    vec = np.asarray(vec, dtype=np.float64)
    if vec.size == 0:
        raise ValueError(f"{path}: cannot read ASTRA vectors (the file holds no numbers)")
    if vec.ndim == 1 and vec.size in (6, 12):
        vec = vec[None]
    if vec.ndim != 2 or vec.shape[1] not in (6, 12):
        raise ValueError(f"{path}: ASTRA vectors must have 12 (cone_vec) or 6 (fanflat_vec) columns, got shape "
                         f"{vec.shape}")
    if not np.all(np.isfinite(vec)):
        raise ValueError(f"{path}: ASTRA vectors contain NaN or infinite values")
    return vec


UNIT_SOURCE_TOL = 1e-4
"""check_not_parallel: how far from 1 (mm) the first vector's length may be in every view to be a unit ray
direction; a float32 file rounds a unit vector's length by some 1e-7."""


def check_not_parallel(vectors, source) -> None:
    """Refuse ASTRA ``parallel3d_vec`` (``parallel_vec``) rows, which have ``cone_vec``'s (``fanflat_vec``'s)
    columns: their first three (two) numbers are a unit ray direction where ``cone_vec`` has the source
    position. A "source" exactly 1 mm from the origin in every view (within :data:`UNIT_SOURCE_TOL`) is that
    direction, wherever the detector stands: no scanner has its focal spot on a 1 mm sphere. ``source``: the
    vectors' file."""
    vec = np.asarray(vectors, np.float64)
    k = 3 if vec.shape[1] == 12 else 2
    length = np.linalg.norm(vec[:, :k], axis=1)
    if np.all(np.abs(length - 1.0) <= UNIT_SOURCE_TOL):
        par, cone = ("parallel3d_vec", "cone_vec") if k == 3 else ("parallel_vec", "fanflat_vec")
        raise ValueError(f"{source}: these look like ASTRA {par} (parallel-beam) vectors: the source column is a unit "
                         f"vector (length 1 in every view), a ray direction rather than a {cone} source position; a "
                         "scan bag describes cone and fan beams only")


def astra_geometry(vectors, n_rows: int, n_cols: int, row_pitch_mm: float | None = None,
                   source: str = "ASTRA vectors") -> ConeGeometry:
    """The :class:`ConeGeometry` of ASTRA ``cone_vec`` (n, 12) or ``fanflat_vec`` (n, 6) rows (module docstring).
    ``source``: what the errors name (the vectors' file)."""
    vec = np.asarray(vectors, dtype=np.float64)
    n = vec.shape[0]
    if vec.shape[1] == 6:
        if n_rows != 1:
            raise ValueError(f"{source}: fanflat_vec describes a one-row detector but the projections have "
                             f"{n_rows} rows")
        cu = np.linalg.norm(vec[:, 4:6], axis=1)
        if np.any(cu == 0):
            raise ValueError(f"{source}: fanflat_vec: a zero detector vector u in view {int(np.argmin(cu))}")
        col_pitch = _check_pitch(cu[0], f"{source}: the column pitch |u|")
        row_pitch = col_pitch if row_pitch_mm is None else _check_pitch(row_pitch_mm, "--row-pitch-mm")
        z = np.zeros(n)
        vec = np.stack([vec[:, 0], vec[:, 1], z, vec[:, 2], vec[:, 3], z, vec[:, 4], vec[:, 5], z,
                        z, z, np.full(n, row_pitch)], axis=1)
    for k, what in ((6, "column pitch |u|"), (9, "row pitch |v|")):
        p = np.linalg.norm(vec[:, k:k + 3], axis=1)
        for view in (int(np.argmin(p)), int(np.argmax(p))):
            _check_pitch(p[view], f"{source}: the {what} in view {view}")
        if np.ptp(p) > 1e-9 * p.max():  # ConeGeometry, as a scan bag, holds one pitch
            raise ValueError(f"{source}: the {what} varies between views ({p.min():g} mm in view "
                             f"{int(np.argmin(p))}, {p.max():g} mm in view {int(np.argmax(p))}); a scan bag holds "
                             "one pitch")
    u, v = vec[:, 6:9], vec[:, 9:12]
    cosang = np.abs(np.einsum("ij,ij->i", u, v)) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
    if np.any(cosang > 1e-6):
        raise ValueError(f"{source}: u and v are not orthogonal in view {int(np.argmax(cosang))}")
    return ConeGeometry.from_astra_vec(vec, n_rows, n_cols)


# ------------------------------------------------------------------------------- import
def check_view_count(n_usable: int, n_frames: int, source) -> None:
    """Refuse a scan of fewer than ``MIN_VIEWS`` frames with a usable pixel before its bag is written: every
    reader refuses such a bag (docs/bag-format.md, Pairing). ``source``: the projections' file."""
    from robot_ct_ros.bag.reader import MIN_VIEWS

    if n_usable < MIN_VIEWS:
        held = f"{n_frames} views" if n_usable == n_frames else \
            f"{n_usable} of its {n_frames} frames with a usable pixel"
        raise ValueError(f"{source} holds {held}; a scan needs at least {MIN_VIEWS} (no reader would accept the bag)")


def _write(out, proj, geom: ConeGeometry, *, counts: bool, flat, dark, notes: dict, say, source) -> Path:
    """The bag at ``out``; ``source``: the projections' path, as the refusals name it."""
    from robot_ct_ros.bag import scan_info_for, write_scan

    shape = geom.det_shape
    if counts:
        if flat is None:
            raise ValueError("--counts needs --flat (the flat field, a frame or a stack averaged)")
        flat_frame = read_frame(flat, shape, "flat field")
        dark_frame = None if dark is None else read_frame(dark, shape, "dark frame")
        frames, flat_frame = dark_corrected(proj, flat_frame, dark_frame)
        units = "counts"
        with np.errstate(invalid="ignore"):  # a frame needs a positive count to be a view (bag.reader)
            usable = (frames > 0) & (flat_frame > 0)[None]
        if not usable.any():  # refused before anything is written: such a bag would be no scan at all
            dark_text = " minus the dark frame" if dark_frame is not None else ""
            raise ValueError("no usable pixel: " + (
                f"the flat field{dark_text} is at or below 0 everywhere" if not np.any(flat_frame > 0)
                else f"every projection value{dark_text} is at or below 0") + " (are --flat and --dark swapped, or "
                "the projections not raw counts?)")
    else:
        if flat is not None or dark is not None:
            raise ValueError("--flat and --dark go with --counts (raw counts); without it the projections are "
                             "line integrals")
        frames, flat_frame, units = np.asarray(proj, np.float32), None, "line_integral"
    if not counts:  # line integrals: a frame with no finite value is no view either
        usable = np.isfinite(frames)
    empty = int((~usable.any(axis=(1, 2))).sum())
    check_view_count(geom.n_views - empty, geom.n_views, source)
    info = scan_info_for(geom, projection_units=units, notes=notes)
    write_scan(out, frames, geom, info=info, flat=flat_frame)
    bad = int(np.isnan(frames).sum()) if counts else 0
    say(f"wrote {out}: {geom.n_views} views, {geom.n_rows} x {geom.n_cols} detector of {geom.row_pitch_mm:g} x "
        f"{geom.col_pitch_mm:g} mm, {units}"
        f"{f' ({bad} pixel values below the dark, or not finite, marked unusable)' if bad else ''}"
        + (f"; warning: {empty} frames have no usable pixel and will not be views" if empty else ""))
    if counts:
        from robot_ct_ros.bag.reader import zero_counts_warning

        warnings_ = counts_warnings(frames, flat_frame)
        zero = zero_counts_warning(frames, flat_frame, np.isfinite(frames) & (flat_frame > 0)[None])
        for warning in warnings_ + ([zero] if zero else []):  # the reader repeats the last on every read
            say(f"warning: {warning}")
    else:  # the reader warns the same on every read (robot-ct info, reconstruct)
        from robot_ct_ros.bag.reader import line_integral_warning

        warning = line_integral_warning(frames, usable)
        if warning:
            say(f"warning: {warning}")
    return Path(out)


BRIGHTER_THAN_FLAT_SHARE = 0.05
"""counts_warnings: the share of usable pixels that may count more than the flat field beyond Poisson noise."""


def counts_warnings(frames: np.ndarray, flat: np.ndarray) -> list[str]:
    """What looks wrong in dark-corrected counts ``frames`` (views, rows, cols; NaN unusable) and flat field
    ``flat`` (rows, cols): flat pixels unusable in every frame (not finite, or at or below the dark), and
    more than :data:`BRIGHTER_THAN_FLAT_SHARE` of the usable pixels counting more than the flat field by over
    3 standard deviations of its noise, Poisson or 2 % if larger (negative line integrals: a flat field from
    another exposure or tube current, or saturated counts)."""
    out = []
    flat = np.asarray(flat, np.float64)
    not_finite, dark_above = int((~np.isfinite(flat)).sum()), int((np.isfinite(flat) & (flat <= 0)).sum())
    if not_finite or dark_above:
        out.append(f"the flat field has {not_finite} pixels that are NaN or infinite and {dark_above} at or below "
                   "the dark frame: those pixels are unusable in every frame")
    ok = np.isfinite(frames) & (np.isfinite(flat) & (flat > 0))[None]
    if ok.any():
        f = np.broadcast_to(flat, frames.shape)[ok]
        # Poisson noise of photon counts, or 2 % where the counts are scaled (an integrating detector's ADU)
        brighter = float(np.mean(frames[ok] > f + 3.0 * np.maximum(np.sqrt(f), 0.02 * f)))
        if brighter > BRIGHTER_THAN_FLAT_SHARE:
            out.append(f"{100 * brighter:.0f} % of the usable pixels count more than the flat field beyond its noise "
                       "(negative line integrals): is the flat field from this exposure and tube current, or are the "
                       "projections saturated?")
    return out


MAX_HALF_FAN_DEG = 60.0
"""The widest half angle a detector may subtend from the source: beyond it the distances are not in
millimetres, or the vectors not a cone or fan beam's (a parallel-beam vector file has the same columns)."""
MIN_SDD_MM = 10.0
"""The shortest source-to-detector distance accepted: no X-ray scanner has its focal spot within 10 mm of the
detector (the tube's housing and the object lie between), while a real scanner's distances written in metres
(0.1 to 2 m) fall below it, on a detector too small for :data:`MAX_HALF_FAN_DEG` to catch them (an ASTRA
parallel-beam file, a unit ray direction where the source stands, is refused before: :func:`check_not_parallel`)."""


def check_plausible(geom: ConeGeometry, source: str, say=_say) -> None:
    """Refuse a geometry no scanner has (the source on or behind the detector plane, a detector wider than
    ``MAX_HALF_FAN_DEG`` allows from the source, a source closer than ``MIN_SDD_MM`` to the detector), naming
    the likely mix-up; warn where the views span less
    than 20 degrees, however few the views (angles in radians where degrees were meant). ``source``: the
    geometry's file. Warn, too, of a pixel finer than :data:`FINEST_DETECTOR_PITCH_MM` (metres for mm)."""
    from robot_ct_ros.ct.scan_weights import scan_arc

    sdd = np.asarray(geom.sdd_mm, np.float64)
    if np.any(~(sdd > 0)):
        view = int(np.argmin(sdd))
        raise ValueError(f"{source}: view {view} has its source {sdd[view]:g} mm from the detector plane, on it or "
                         "behind it (a parallel-beam geometry, or the source and detector swapped?)")
    half_width = 0.5 * np.hypot(geom.n_cols * geom.col_pitch_mm, geom.n_rows * geom.row_pitch_mm)
    half_fan = float(np.degrees(np.arctan(half_width / sdd.min())))
    if half_fan > MAX_HALF_FAN_DEG:
        raise ValueError(f"{source}: the detector's half diagonal ({half_width:g} mm) spans {half_fan:.1f} deg from the "
                         f"source at {sdd.min():g} mm (more than {MAX_HALF_FAN_DEG:g}): are the distances in metres, "
                         "or the vectors a parallel beam's (ASTRA parallel_vec / parallel3d_vec have the same "
                         "columns as fanflat_vec / cone_vec)?")
    if sdd.min() < MIN_SDD_MM:
        view = int(np.argmin(sdd))
        raise ValueError(f"{source}: view {view} has its source {sdd[view]:g} mm from the detector, closer than any "
                         f"scanner ({MIN_SDD_MM:g} mm): are the distances in metres, or the vectors a parallel beam's "
                         "(ASTRA parallel_vec / parallel3d_vec have the same columns as fanflat_vec / cone_vec)?")
    pitch_mm = min(geom.row_pitch_mm, geom.col_pitch_mm)
    if pitch_mm < FINEST_DETECTOR_PITCH_MM:
        say(f"warning: a detector pixel of {pitch_mm * 1000:g} um, finer than X-ray detectors' "
            f"({FINEST_DETECTOR_PITCH_MM * 1000:g} um and up): metres where mm were meant? ({pitch_mm:g} m would be "
            f"{pitch_mm * 1000:g} mm)")
    if geom.n_views > 2:
        arc = float(np.degrees(scan_arc(geom)[0]))
    elif geom.n_views == 2:  # scan_arc counts 2 views a full circle: the angle between their viewing directions
        arc = float(np.degrees(np.arccos(np.clip(geom.w[0] @ geom.w[1], -1.0, 1.0))))
    else:  # one view spans no arc to judge
        arc = 360.0
    if arc < 20.0:
        say(f"warning: the {geom.n_views} views span an arc of {arc:.1f} deg only (angles written in radians "
            "where degrees were meant, as RTK's XML has them?)")


def _same_views(n_proj: int, n_geom: int, proj_path, geom_path):
    if n_proj != n_geom:
        raise ValueError(f"{proj_path} holds {n_proj} views but {geom_path} describes {n_geom}")


def import_rtk(projections, geometry_xml, out, *, pitch_mm, origin_mm=None, counts: bool = False, flat=None,
               dark=None, say=_say) -> Path:
    """Write projections with RTK's geometry XML as a scan bag at ``out`` (a new directory).

    ``pitch_mm`` = (row, col) pitch; ``origin_mm`` = (row, col) origin of RTK's stack (default
    centred); module docstring.
    """
    out = Path(out)
    if out.exists():
        raise ValueError(f"{out} exists already; a bag is never overwritten")
    proj = read_stack(projections)
    geom = rtk_geometry(geometry_xml, proj.shape[1], proj.shape[2], pitch_mm[0], pitch_mm[1], origin_mm)
    _same_views(proj.shape[0], geom.n_views, projections, geometry_xml)
    check_view_count(geom.n_views, geom.n_views, projections)
    check_plausible(geom, geometry_xml, say)
    notes = {"generator": "robot-ct import rtk", "projections": Path(projections).name,
             "geometry": f"{Path(geometry_xml).name} (RTK ThreeDCircularProjectionGeometry, rotation about y)",
             "rtk_projection_origin_mm": None if origin_mm is None else [float(x) for x in origin_mm][::-1]}
    return _write(out, proj, geom, counts=counts, flat=flat, dark=dark, notes=notes, say=say,
                  source=projections)


def import_astra(projections, vectors, out, *, layout: str = "views-first", row_pitch_mm=None, counts: bool = False,
                 flat=None, dark=None, say=_say) -> Path:
    """Write projections with ASTRA ``cone_vec``/``fanflat_vec`` vectors as a scan bag at ``out``."""
    out = Path(out)
    if out.exists():
        raise ValueError(f"{out} exists already; a bag is never overwritten")
    vec = read_astra_vectors(vectors)
    check_not_parallel(vec, vectors)
    proj = read_stack(projections, layout, allow_2d=vec.shape[1] == 6)
    _same_views(proj.shape[0], vec.shape[0], projections, vectors)
    check_view_count(proj.shape[0], proj.shape[0], projections)
    if row_pitch_mm is not None and vec.shape[1] == 12:
        raise ValueError("--row-pitch-mm is for fanflat_vec only; cone_vec's v holds the row pitch")
    geom = astra_geometry(vec, proj.shape[1], proj.shape[2], row_pitch_mm, source=f"ASTRA vectors {vectors}")
    check_plausible(geom, vectors, say)
    notes = {"generator": "robot-ct import astra", "projections": Path(projections).name, "layout": layout,
             "geometry": f"{Path(vectors).name} (ASTRA {'cone_vec' if vec.shape[1] == 12 else 'fanflat_vec'})"}
    return _write(out, proj, geom, counts=counts, flat=flat, dark=dark, notes=notes, say=say,
                  source=projections)
