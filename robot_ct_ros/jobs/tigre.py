"""TIGRE's per-view cone-beam parameters of a :class:`ConeGeometry` (``robot-ct export --format tigre``).

TIGRE (CERN/TIGRE) builds each view in a local frame with the source on +x (its CUDA
``computeDeltas``, the Python arrays as its ``convert_to_c_geometry`` reads them):

* source ``S = (DSO, 0, 0)``;
* detector pixel (pU, pV) at ``(DSO - DSD, offU, offV) + Q @ (0, dU * (pU - (nU-1)/2), -dV * (pV - (nV-1)/2))``
  with ``Q = Rz(rz) @ Ry(ry) @ Rx(rx)`` (``rollPitchYaw``: roll about z, pitch about y, yaw
  about x, about the detector centre);
* every point then goes to TIGRE's image frame as ``R @ X - offOrigin`` with
  ``R = Rz(alpha) @ Ry(theta) @ Rz(psi)`` (``eulerZYZ``); the image is centred on that frame's
  origin, its axes x, y, z.

Python's arrays, per view i (reversed orders, as TIGRE's Python interface takes them):
``angles[i] = (alpha, theta, psi)`` (rad), ``DSO[i]``, ``DSD[i]`` (mm), ``offOrigin[i] = (z, y, x)``,
``offDetector[i] = (offV, offU)``, ``rotDetector[i] = (rx, ry, rz)`` (rad; TIGRE reads [0] as
yaw, [2] as roll), ``nDetector = (nV, nU)``, ``dDetector = (dV, dU)``, ``sDetector``.

Mapping (exact; :func:`to_tigre`, inverse :func:`from_tigre`): TIGRE's image frame is our world
frame shifted by ``center_mm`` (the bag's ROI centre; TIGRE's x, y, z are our world axes, so a
TIGRE volume is axis-aligned in our world), and ``offOrigin = 0``. pU is our column; TIGRE's
kernels write pixel (pU, pV) at detector row ``nV - 1 - pV``, which is our row, so increasing pV
runs along -v. Per view: R's x axis points from the centre to the
source (``DSO = |s - center|``), its y axis is u made orthogonal to it; then ``DSD = DSO - x_d``
and ``(offU, offV) = (y_d, z_d)`` for the detector centre ``(x_d, y_d, z_d) = R^T (d - center)``,
and ``Q = R^T [w, u, v]``. A circular scan whose detector faces the source with its principal
point on the central ray gets ``theta = psi = 0``, ``rotDetector = 0`` and ``offDetector = 0``
(test/jobs/test_export.py checks HTC2022's ``alpha = angle - 90 deg``).

Limits: a view is refused when its source is at ``center_mm`` (no DSO) or its detector centre is
not farther from the source than the centre (``DSD <= DSO``: TIGRE's projectors crop each ray
assuming the volume lies between source and detector).

Not checked by running TIGRE (none installed here): everything above is read from TIGRE's source
(``computeDeltas``, ``rollPitchYaw``, ``eulerZYZ``, ``_types.pxd``) and tested against a
transcription of it. The projection array's layout is read from the source too, not run: in
``Common/CUDA/Siddon_projection.cu`` (``kernelPixelDetector``), the branch built for Python (not
``IS_FOR_MATLAB_TIGRE``) writes pixel (u, v) of a view at buffer index ``v * nU + u`` and places it
at ``pixelV = nV - 1 - v``, and the Python wrapper (``_Ax.pyx``) presents each view's buffer as
(nV, nU). So TIGRE's Python projection array is our ``proj[view, row, col]`` as it is: no
transpose, no flip of the rows (the MATLAB build's ``u * nV + v`` is the transpose, which
MATLAB's column-major arrays undo). An outside check (tester's ``chk_tigre_py.py``) put the exported
parameters through a transcription of TIGRE's ``computeDeltas_Siddon`` with our row r at buffer row r
(``pixelV = nV - 1 - r``) and compared the pixel and source positions with those of the same geometry
exported as ASTRA vectors: they agree to 1e-13 mm (the other mapping, ``pixelV = r``, is 47 mm off).
Still unverified, for want of TIGRE: the other projector (``ray_interpolated_projection.cu``) and the
back-projectors were not read for the same layout, and no projection of a known object was compared;
check one before feeding our projections to TIGRE.
"""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["to_tigre", "from_tigre", "TIGRE_KEYS"]

TIGRE_KEYS = ("DSO", "DSD", "angles", "offOrigin", "offDetector", "rotDetector", "nDetector", "dDetector",
              "sDetector", "center_mm")


def _rz(a):
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _ry(a):
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rx(a):
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _zyz(R):
    """(alpha, theta, psi) with R = Rz(alpha) Ry(theta) Rz(psi); psi from the residual (exact to rounding)."""
    h = np.hypot(R[:, 0, 2], R[:, 1, 2])
    theta = np.arctan2(h, R[:, 2, 2])
    flat = h < 1e-12  # theta = 0 or pi: alpha carries the rotation about z, psi = 0
    sign = np.where(R[:, 2, 2] >= 0, 1.0, -1.0)
    alpha = np.where(flat, np.arctan2(sign * R[:, 1, 0], sign * R[:, 0, 0]), np.arctan2(R[:, 1, 2], R[:, 0, 2]))
    M = np.einsum("nji,njk->nik", _rz(alpha) @ _ry(theta), R)
    return np.stack([alpha, theta, np.arctan2(M[:, 1, 0], M[:, 0, 0])], axis=1)


def _zyx(Q):
    """(rx, ry, rz) with Q = Rz(rz) Ry(ry) Rx(rx); rx from the residual."""
    rz = np.arctan2(Q[:, 1, 0], Q[:, 0, 0])
    ry = np.arctan2(-Q[:, 2, 0], np.hypot(Q[:, 0, 0], Q[:, 1, 0]))
    M = np.einsum("nji,njk->nik", _rz(rz) @ _ry(ry), Q)
    return np.stack([np.arctan2(M[:, 2, 1], M[:, 1, 1]), ry, rz], axis=1)


def to_tigre(geom: ConeGeometry, center_mm=(0.0, 0.0, 0.0)) -> dict:
    """TIGRE's Python geometry arrays of ``geom`` about ``center_mm`` (module docstring); ValueError
    naming the first view TIGRE cannot represent."""
    c = np.asarray(center_mm, dtype=np.float64).reshape(3)
    a = geom.source_mm - c
    dso = np.linalg.norm(a, axis=1)
    if np.any(dso < 1e-9):
        i = int(np.flatnonzero(dso < 1e-9)[0])
        raise ValueError(f"view {i}: the source is at the volume centre {c.tolist()} mm; TIGRE needs DSO > 0")
    ex = a / dso[:, None]
    ey = geom.u - np.einsum("ij,ij->i", geom.u, ex)[:, None] * ex
    ny = np.linalg.norm(ey, axis=1)
    edge_on = ny < 1e-6  # u along the central ray: build the frame from v instead
    ez_v = geom.v - np.einsum("ij,ij->i", geom.v, ex)[:, None] * ex
    ey = np.where(edge_on[:, None], np.cross(ez_v, ex), ey)
    ey /= np.linalg.norm(ey, axis=1, keepdims=True)
    R = np.stack([ex, ey, np.cross(ex, ey)], axis=2)  # columns: TIGRE's local axes in the world
    dl = np.einsum("nji,nj->ni", R, geom.detector_mm - c)
    dsd = dso - dl[:, 0]
    if np.any(dsd <= dso):
        bad = np.flatnonzero(dsd <= dso)
        i = int(bad[0])
        raise ValueError(f"view {i}: the detector centre is not beyond the volume centre seen from the source "
                         f"(DSD {dsd[i]:.6g} <= DSO {dso[i]:.6g} mm); TIGRE's projectors need the volume between "
                         f"source and detector; {bad.size} of {dso.size} views are so")
    Q = np.einsum("nji,njk->nik", R, geom.local_frames()[:, :, [2, 0, 1]])  # R^T [w, u, v]
    n = geom.n_views
    det_n = np.array([geom.n_rows, geom.n_cols])
    det_d = np.array([geom.row_pitch_mm, geom.col_pitch_mm])
    return {"DSO": dso, "DSD": dsd, "angles": _zyz(R), "offOrigin": np.zeros((n, 3)),
            "offDetector": dl[:, [2, 1]], "rotDetector": _zyx(Q), "nDetector": det_n, "dDetector": det_d,
            "sDetector": det_n * det_d, "center_mm": c}


def from_tigre(params: dict) -> ConeGeometry:
    """The :class:`ConeGeometry` of TIGRE's Python arrays (``center_mm`` = our world position of TIGRE's
    image centre, default the origin), by TIGRE's definitions in the module docstring."""
    ang = np.atleast_2d(np.asarray(params["angles"], dtype=np.float64))
    n = ang.shape[0]

    def per_view(key, k, default=0.0):
        x = np.asarray(params.get(key, default), dtype=np.float64)
        return np.broadcast_to(x, (n,) if k == 1 else (n, k)).copy()

    dso, dsd = per_view("DSO", 1), per_view("DSD", 1)
    off_origin_xyz = per_view("offOrigin", 3)[:, ::-1]
    off_v, off_u = per_view("offDetector", 2).T
    rx, ry, rz = per_view("rotDetector", 3).T
    n_rows, n_cols = (int(x) for x in np.asarray(params["nDetector"]).reshape(2))
    row_pitch, col_pitch = (float(x) for x in np.asarray(params["dDetector"]).reshape(2))
    c = np.asarray(params.get("center_mm", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)
    R = _rz(ang[:, 0]) @ _ry(ang[:, 1]) @ _rz(ang[:, 2])
    RQ = R @ _rz(rz) @ _ry(ry) @ _rx(rx)
    base = c - off_origin_xyz
    src = base + R[:, :, 0] * dso[:, None]
    det = base + np.einsum("nij,nj->ni", R, np.stack([dso - dsd, off_u, off_v], axis=1))
    return ConeGeometry(source_mm=src, detector_mm=det, u=RQ[:, :, 1], v=RQ[:, :, 2], n_rows=n_rows, n_cols=n_cols,
                        row_pitch_mm=row_pitch, col_pitch_mm=col_pitch)
