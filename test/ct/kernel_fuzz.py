"""Fuzz every numba kernel over random geometries (run by test_kernel_fuzz.py in a subprocess with
NUMBA_BOUNDSCHECK=1 and a fresh NUMBA_CACHE_DIR, so every kernel is compiled with bounds checks).

Geometries: random poses and, half the time, axis-aligned vectors with tiny residues (1e-16 ...),
signed zeros and exactly parallel views; grids smaller than, larger than, taller than and away from
the cone, turned or not. Kernels: forward projector, its adjoint, FDK (filter + back-projection),
the homography warp and the warp-and-score kernel of the calibration, also with degenerate
homographies (singular, huge, points at infinity). Every output must be finite; an IndexError from
a bounds check, a segfault (exit -11) or a non-finite value fails the run.

Usage: python kernel_fuzz.py SEED N_CASES
"""

import sys

import numpy as np

from robot_ct_ros.ct.calibration.kernels import N_SUMS, _warp_score_kernel, detector_homographies, warp_projections
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.projector import back_project, forward_project
from robot_ct_ros.ct.reconstruction import fdk
from scipy.spatial.transform import Rotation

TINY = (0.0, -0.0, 1e-17, -1.2e-16, 1e-12, 3e-9)


def _axis_frame(rng):
    """u, v, w from a signed permutation of the axes, with tiny residues on the zero components."""
    perm = rng.permutation(3)
    signs = rng.choice([-1.0, 1.0], 3)
    R = np.zeros((3, 3))
    R[perm, np.arange(3)] = signs
    R = R * (np.linalg.det(R) or 1.0)  # a proper rotation
    noise = rng.choice(TINY, (3, 3)) * (R == 0)
    R = R + noise
    q, _ = np.linalg.qr(R)  # re-orthonormalise: the residues survive at the 1e-16 level
    return q * np.sign(np.diag(q.T @ R))


def random_geometry(rng) -> ConeGeometry:
    n = int(rng.integers(1, 6))
    rows, cols = int(rng.integers(2, 12)), int(rng.integers(2, 16))
    pitch = float(rng.choice([0.05, 0.3, 1.0]))
    axis_aligned = rng.random() < 0.5
    src, det, us, vs = [], [], [], []
    for i in range(n):
        if axis_aligned:
            R = _axis_frame(rng)
            if rng.random() < 0.3 and i:  # exactly the previous view again, or opposite to it
                R = np.array(R_prev)  # an exactly repeated view
        else:
            R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
        R_prev = R
        u, v, w = R[:, 0], R[:, 1], R[:, 2]
        sod = float(rng.choice([20.0, 128.0, 600.0]))
        sdd = sod * float(rng.choice([1.2, 2.67, 6.0]))
        centre = rng.normal(0.0, 1.0, 3) * float(rng.choice([0.0, 1.0, 30.0]))
        s = centre - sod * w
        d = s + sdd * w + (rng.normal(0.0, 1.0) * pitch * cols) * u * float(rng.random() < 0.3)
        src.append(s), det.append(d), us.append(u), vs.append(v)
    return ConeGeometry(source_mm=src, detector_mm=det, u=us, v=vs, n_rows=rows, n_cols=cols,
                        row_pitch_mm=pitch, col_pitch_mm=pitch * float(rng.choice([1.0, 0.5])))


def random_grid(rng) -> VolumeGrid:
    shape = [int(rng.integers(1, 10)) for _ in range(3)]
    if rng.random() < 0.4:
        shape[int(rng.integers(3))] = int(rng.choice([60, 300]))  # taller / wider than the cone
    vs = float(rng.choice([0.01, 0.2, 2.0, 40.0]))  # 40 mm voxels: a grid far larger than the cone
    centre = rng.normal(0.0, 1.0, 3) * float(rng.choice([0.0, 5.0, 500.0]))
    direction = None if rng.random() < 0.5 else (
        _axis_frame(rng) if rng.random() < 0.5 else Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix())
    if direction is not None and np.linalg.det(direction) < 0:
        direction = direction.copy()
        direction[:, 0] *= -1
    return VolumeGrid.centered(tuple(shape), vs, centre, direction)


def check(name, a):
    a = np.asarray(a)
    if not np.all(np.isfinite(a)):
        raise AssertionError(f"{name}: {int((~np.isfinite(a)).sum())} non-finite values")


def one_case(rng, k):
    geom = random_geometry(rng)
    grid = random_grid(rng)
    vol = rng.random(grid.shape_zyx).astype(np.float32)
    proj = forward_project(vol, grid, geom)
    check("forward_project", proj)
    back = back_project(rng.random((geom.n_views, geom.n_rows, geom.n_cols)).astype(np.float32), geom, grid)
    check("back_project", back)
    # the adjoint identity holds whatever the geometry (a kernel that skipped or doubled rays would not)
    y = rng.random(proj.shape).astype(np.float32)
    lhs, rhs = float(np.vdot(proj.astype(np.float64), y)), float(np.vdot(vol.astype(np.float64),
                                                                        back_project(y, geom, grid)))
    if abs(lhs - rhs) > 1e-3 * max(1.0, abs(lhs), abs(rhs)):
        raise AssertionError(f"adjoint mismatch {lhs} vs {rhs}")
    for truncation in (None, "cylinder") if k % 3 == 0 else (None,):
        try:
            check(f"fdk({truncation})", fdk(proj, geom, grid, truncation=truncation))
        except ValueError:
            pass  # a refusal with a reason is fine; a crash is not
    mask = rng.random(proj.shape) < 0.9
    check("fdk(valid_mask)", fdk(proj, geom, grid, valid_mask=mask, truncation=None))

    # warps: an enlarged virtual detector and the target moved around it, same sources
    virtual = ConeGeometry(source_mm=geom.source_mm, detector_mm=geom.detector_mm, u=geom.u, v=geom.v,
                           n_rows=geom.n_rows + 4, n_cols=geom.n_cols + 4, row_pitch_mm=geom.row_pitch_mm,
                           col_pitch_mm=geom.col_pitch_mm)
    params = np.zeros((geom.n_views, 9))
    params[:, 3:] = rng.normal(0.0, 1.0, (geom.n_views, 6)) * rng.choice([0.0, 0.01, 1.0, 50.0], (geom.n_views, 6))
    params[:, 6:] *= 0.02
    target = geom.perturbed(params)
    H = detector_homographies(virtual, target)
    degenerate = np.stack([np.zeros((3, 3)), np.eye(3) * 1e300, np.diag([1.0, 1.0, 0.0]),
                           np.array([[1.0, 0.0, 1e12], [0.0, 1.0, -1e12], [1e-300, 0.0, 1.0]]),
                           np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1e-300]])])
    # not here: a denormal z (1 / z overflows) or a non-finite homography; see
    # test_kernel_fuzz.py::test_warp_kernels_with_a_non_finite_inverse_depth (a known kernel fault)
    H_all = np.concatenate([H, degenerate])
    images = rng.random((geom.n_views, virtual.n_rows, virtual.n_cols)).astype(np.float32)
    index = np.concatenate([np.arange(geom.n_views), np.zeros(len(degenerate), np.int64)])
    out, valid = warp_projections(images, H_all, index, geom.n_rows, geom.n_cols)
    check("warp_projections", out)
    # warp-and-score: every sample against measured view 0, one basis image (the mean)
    m = H_all.shape[0]
    measured = rng.random((1, geom.n_rows, geom.n_cols)).astype(np.float32)
    basis = np.ones((1, 1, geom.n_rows, geom.n_cols), np.float32)
    weight = (rng.random((1, geom.n_rows, geom.n_cols)) < 0.8).astype(np.float32)
    sums = np.empty((m, N_SUMS + 1), np.float64)
    _warp_score_kernel(images, np.ascontiguousarray(H_all), index, np.zeros(m, np.int64), measured, measured,
                       basis, weight, sums)
    check("_warp_score_kernel", sums)


def main(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    for k in range(n):
        state = rng.bit_generator.state
        try:
            one_case(rng, k)
        except Exception as exc:
            raise SystemExit(f"case {k} (seed {seed}, rng state {state['state']['state']}) failed: "
                             f"{type(exc).__name__}: {exc}") from exc
    print(f"ok {n}")


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]))
