"""Import of the Helsinki Tomography Challenge 2022 (HTC2022) fan-beam data into a scan bag.

A HTC2022 ``*_full.mat`` (MATLAB 5) holds one struct, ``CtDataFull`` (``CtDataLimited`` in the
limited-angle files), with ``sinogram`` (angles x detectors, -log(I/I0) line integrals, flat and
dark corrected by the authors) and ``parameters`` (``distanceSourceOrigin``,
``distanceSourceDetector`` in mm, ``angles`` in degrees, ``numDetectorsPost`` detectors of
``pixelSizePost`` mm after the authors' binning, ...). The scan is the central row of a flat
panel: a circular fan beam.

The bag written (:func:`import_htc2022`) follows docs/bag-format.md, like ``robot-ct simulate``'s:

* frames: 1 x ``numDetectorsPost`` pixels, the sinogram rows unchanged (float32), with
  ``projection_units = "line_integral"`` (no flat field: the values already are -log(I/I0));
* ``/ct/geometry``: the nominal circular fan beam below, one view per angle;
* stamps: :func:`robot_ct_ros.bag.writer.default_stamps` (synthetic, in angle order);
* ``scan_info``: the dataset's reference reconstruction grid (512 x 512 pixels of
  ``effectivePixelSizePost`` about the rotation centre, one voxel thick) and the file's
  parameters under ``notes``.

Geometry (:func:`fan_beam_geometry`), world frame in mm, rotation axis = world +z through the
origin, fan plane z = 0. At the dataset's angle theta:

* source at ``DSO * (sin theta, -cos theta, 0)``;
* detector centre at ``(DSD - DSO) * (-sin theta, cos theta, 0)``;
* u (increasing sinogram column) ``= (cos theta, sin theta, 0)``, v ``= +z``, so w = u x v
  points from the detector towards the source.

Increasing theta turns the source counter-clockwise seen from +z (a positive rotation about
+z). This is ASTRA's ``fanflat`` geometry (which the HTC2022 authors used) with ASTRA's image x,
y as world x, y (image row 0 at the largest y). It was checked on the data: our forward
projection of the dataset's own FBP reconstruction (``*_recon_fbp.mat``, placed so) correlates
with the measured sinogram at 0.998 for 01a and 02a (0.714 and 0.967 after removing each detector
column's mean over the angles, i.e. the disc), against 0.996 and 0.942 (0.30 and -0.10) with the
opposite rotation sense (test/jobs/test_htc2022.py checks 01a when the shared real data are present).

The angles run 0 to 360 degrees in 0.5 degree steps: the last repeats the first. It is
**dropped** (720 views over a full turn), so a full turn is not weighted twice; a last angle that
is not a repeat of the first (modulo 360 degrees) is kept. A file with fewer than 4 views (with a finite
value) is refused: no reader accepts such a bag.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry
from robot_ct_ros.jobs.output import say as _say

__all__ = ["HtcData", "read_htc2022", "fan_beam_geometry", "import_htc2022", "REQUIRED_PARAMETERS",
           "RECON_SHAPE"]

REQUIRED_PARAMETERS = ("distanceSourceOrigin", "distanceSourceDetector", "angles", "numDetectorsPost",
                       "pixelSizePost")
"""The fields of ``parameters`` the import needs."""
RECON_SHAPE = 512
"""The dataset's reference reconstructions are 512 x 512 pixels of ``effectivePixelSizePost``."""


@dataclass(frozen=True)
class HtcData:
    """A HTC2022 scan read from its .mat file: sinogram (views, detectors) float64 with the
    duplicate last angle dropped, angles (deg), distances and pitch (mm), all parameters (dict)."""

    path: Path
    sinogram: np.ndarray
    angles_deg: np.ndarray
    dso_mm: float
    dsd_mm: float
    pitch_mm: float
    parameters: dict
    dropped_last: bool

    @property
    def effective_pixel_mm(self) -> float:
        """The detector pitch at the rotation centre (pitch / magnification)."""
        return self.pitch_mm * self.dso_mm / self.dsd_mm


def _plain(value):
    """A JSON-friendly copy of a loadmat value (numbers, strings, lists)."""
    if isinstance(value, np.ndarray):
        return value.tolist() if value.size <= 16 else f"array {value.shape}"
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (int, float, str, bool)):
        return value
    return str(value)


def _number(params, name: str, path: Path) -> float:
    try:
        x = float(np.asarray(getattr(params, name)).reshape(()))
    except (TypeError, ValueError):
        raise ValueError(f"{path}: parameters.{name} is not a single number") from None
    if not (np.isfinite(x) and x > 0):
        raise ValueError(f"{path}: parameters.{name} must be positive, got {x}")
    return x


MI_COMPRESSED = 15
"""The MAT 5 data type of a zlib-compressed element, not padded to 8 bytes."""


def _mat_damage(path) -> str | None:
    """Why a file with a MATLAB 5 header cannot be read, where its layout tells: cut inside a data element
    (each top-level element is an 8-byte tag of type and byte count, padded to 8 bytes unless compressed),
    or else damaged; None for a file without a MATLAB 5 header (no .mat file, or v7.3's HDF5)."""
    import struct

    data = Path(path).read_bytes()
    order = {b"IM": "<", b"MI": ">"}.get(data[126:128])
    if not data.startswith(b"MATLAB 5.0 MAT-file") or order is None:
        return None
    pos, size = 128, len(data)
    while pos < size:
        if pos + 8 > size:
            return f"truncated: it ends inside the tag of a data element at byte {pos}"
        dtype, nbytes = struct.unpack(order + "II", data[pos:pos + 8])
        if dtype >> 16:  # a small data element: type, size and data in 8 bytes
            pos += 8
            continue
        end = pos + 8 + nbytes + (0 if dtype == MI_COMPRESSED else -nbytes % 8)
        if end > size:
            return (f"truncated: its data element at byte {pos} needs {end} bytes, the file has {size} "
                    "(an incomplete copy or download?)")
        pos = end
    return "damaged: its layout is whole but its data do not read"


def read_htc2022(path) -> HtcData:
    """Read and check a HTC2022 ``*_full.mat`` (or ``*_limited.mat``); see the module docstring.

    Raises ``ValueError`` (one line) for a file that is no MATLAB file, holds no HTC2022 struct,
    lacks a field, or whose sizes disagree; ``OSError`` when it cannot be read.
    """
    import scipy.io

    path = Path(path)
    with open(path, "rb"):  # a missing or unreadable file is an OSError with its name
        pass
    try:
        mat = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except Exception as exc:  # scipy raises ValueError, TypeError, ... for what is not a .mat file
        why = ' '.join(str(exc).split()) or type(exc).__name__
        damage = _mat_damage(path)
        if damage is not None:
            raise ValueError(f"{path}: a MATLAB .mat file, {damage}"
                             + (f" ({why})" if damage.startswith("damaged") else "")) from None
        raise ValueError(f"{path}: not a MATLAB .mat file ({why})") from None
    structs = [k for k, v in mat.items() if not k.startswith("__") and hasattr(v, "_fieldnames")
               and "sinogram" in v._fieldnames and "parameters" in v._fieldnames]
    if not structs:
        names = ", ".join(k for k in mat if not k.startswith("__")) or "nothing"
        raise ValueError(f"{path}: no HTC2022 struct (CtDataFull with sinogram and parameters); the file holds {names}")
    data = mat["CtDataFull"] if "CtDataFull" in structs else mat[structs[0]]
    params = data.parameters
    fields = getattr(params, "_fieldnames", None)
    if fields is None:
        raise ValueError(f"{path}: {structs[0]}.parameters is not a struct")
    missing = [f for f in REQUIRED_PARAMETERS if f not in fields]
    if missing:
        raise ValueError(f"{path}: {structs[0]}.parameters lacks {', '.join(missing)}")
    unit = getattr(params, "distanceUnit", "mm")
    if isinstance(unit, str) and unit.strip().lower() not in ("mm", ""):
        raise ValueError(f"{path}: distanceUnit is {unit!r}; only mm is supported")
    try:
        sino = np.asarray(data.sinogram, dtype=np.float64)
        angles = np.atleast_1d(np.asarray(params.angles, dtype=np.float64))
    except (TypeError, ValueError):
        raise ValueError(f"{path}: sinogram and parameters.angles must be numeric arrays") from None
    if sino.ndim == 1:  # squeeze_me turns a one-view sinogram into a vector
        sino = sino[None]
    n_det = int(_number(params, "numDetectorsPost", path))
    dso = _number(params, "distanceSourceOrigin", path)
    dsd = _number(params, "distanceSourceDetector", path)
    pitch = _number(params, "pixelSizePost", path)
    if sino.ndim != 2:
        raise ValueError(f"{path}: sinogram must be 2-D (angles x detectors), got shape {sino.shape}")
    if angles.ndim != 1 or angles.size != sino.shape[0]:
        raise ValueError(f"{path}: {angles.size} angles but the sinogram has {sino.shape[0]} rows "
                         f"(shape {sino.shape})")
    if sino.shape[1] != n_det:
        raise ValueError(f"{path}: numDetectorsPost is {n_det} but the sinogram has {sino.shape[1]} columns")
    if not np.all(np.isfinite(angles)):
        raise ValueError(f"{path}: angles contain NaN or infinite values")
    if dso >= dsd:
        raise ValueError(f"{path}: distanceSourceOrigin {dso} mm must be smaller than distanceSourceDetector {dsd} mm")
    dropped = False
    if angles.size > 1 and abs(np.remainder(angles[-1] - angles[0] + 180.0, 360.0) - 180.0) < 1e-6:
        angles, sino, dropped = angles[:-1], sino[:-1], True
    if angles.size < 1:
        raise ValueError(f"{path}: the sinogram holds no view")
    parameters = {f: _plain(getattr(params, f)) for f in fields}
    return HtcData(path, sino, angles, dso, dsd, pitch, parameters, dropped)


def fan_beam_geometry(angles_deg, dso_mm: float, dsd_mm: float, n_cols: int, pitch_mm: float,
                      n_rows: int = 1) -> ConeGeometry:
    """The nominal circular fan-beam geometry of the module docstring (ASTRA ``fanflat``, about +z)."""
    t = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    s, c, z = np.sin(t), np.cos(t), np.zeros_like(t)
    odd = dsd_mm - dso_mm
    return ConeGeometry(source_mm=np.stack([dso_mm * s, -dso_mm * c, z], axis=1),
                        detector_mm=np.stack([-odd * s, odd * c, z], axis=1),
                        u=np.stack([c, s, z], axis=1), v=np.stack([z, z, np.ones_like(t)], axis=1),
                        n_rows=n_rows, n_cols=n_cols, row_pitch_mm=pitch_mm, col_pitch_mm=pitch_mm)


def import_htc2022(mat_path, out, *, say=_say) -> Path:
    """Write the HTC2022 scan ``mat_path`` as a scan bag at ``out`` (a new directory); returns ``out``.

    Frames are the sinogram rows as line integrals on a 1-row detector, with the nominal
    geometry of :func:`fan_beam_geometry` (module docstring).
    """
    from robot_ct_ros.bag import scan_info_for, write_scan

    out = Path(out)
    if out.exists():
        raise ValueError(f"{out} exists already; a bag is never overwritten")
    from robot_ct_ros.jobs.importers import check_view_count

    d = read_htc2022(mat_path)
    n_views, n_det = d.sinogram.shape
    check_view_count(int(np.isfinite(d.sinogram).any(axis=1).sum()), n_views, d.path)  # the reader's pairing
    geom = fan_beam_geometry(d.angles_deg, d.dso_mm, d.dsd_mm, n_det, d.pitch_mm)
    eff = d.effective_pixel_mm
    info = scan_info_for(geom, projection_units="line_integral", roi_center_mm=(0.0, 0.0, 0.0),
                         roi_size_mm=(RECON_SHAPE * eff, RECON_SHAPE * eff, eff), voxel_size_mm=eff,
                         notes={"source": "HTC2022 (Helsinki Tomography Challenge 2022)", "file": d.path.name,
                                "generator": "robot-ct import htc2022",
                                "geometry": "circular fan beam about +z, ASTRA fanflat convention",
                                "dropped_repeated_last_angle": d.dropped_last,
                                "parameters": d.parameters})
    frames = d.sinogram.astype(np.float32)[:, None, :]
    write_scan(out, frames, geom, info=info)
    say(f"wrote {out}: {n_views} views{' (repeated last angle dropped)' if d.dropped_last else ''}, "
        f"1 x {n_det} detector of {d.pitch_mm:g} mm, SOD {d.dso_mm:g} mm, SDD {d.dsd_mm:g} mm")
    return out
