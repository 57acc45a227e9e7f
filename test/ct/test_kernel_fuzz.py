"""Fuzz every numba kernel under NUMBA_BOUNDSCHECK=1 (test/ct/kernel_fuzz.py, in a subprocess so that the
variable takes effect and no kernel compiled without bounds checks is reused from the cache)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
LIMIT = """
import resource, runpy, sys
resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))  # a runaway allocation fails here, not the machine
sys.argv = [sys.argv[0]] + sys.argv[1:]
"""


def _run(tmp_path, code_or_script, *args, timeout=600):
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"),
               PYTHONPATH=str(REPO), PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, "-c", code_or_script, *args], capture_output=True, text=True,
                          env=env, timeout=timeout, cwd=tmp_path)


def test_every_kernel_over_random_geometries_stays_in_bounds_and_finite(tmp_path):
    """60 random cases: projector, adjoint (and the adjoint identity), FDK, warp, warp-and-score."""
    code = LIMIT + f"sys.path.insert(0, {str(HERE)!r})\nimport kernel_fuzz\nkernel_fuzz.main(1, 60)\n"
    proc = _run(tmp_path, code)
    assert proc.returncode == 0 and "ok 60" in proc.stdout, \
        f"exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"


def test_warp_kernels_with_a_non_finite_inverse_depth(tmp_path):
    code = LIMIT + """
import numpy as np
from robot_ct_ros.ct.calibration.kernels import N_SUMS, _warp_score_kernel, warp_projections
img = np.random.default_rng(0).random((1, 10, 12)).astype(np.float32)
for h in (np.diag([0.0, 0.0, 1e-320]), np.full((3, 3), np.nan), np.full((3, 3), np.inf)):
    out, valid = warp_projections(img, h[None], [0], 6, 8)
    assert np.isfinite(out).all() and not valid.any()
    sums = np.empty((1, N_SUMS + 1))
    m = img[:, :6, :8].copy()
    _warp_score_kernel(img, np.ascontiguousarray(h[None]), np.zeros(1, np.int64), np.zeros(1, np.int64), m, m,
                       np.ones((1, 1, 6, 8), np.float32), np.ones((1, 6, 8), np.float32), sums)
    assert np.isfinite(sums).all(), sums
print("ok")
"""
    proc = _run(tmp_path, code, timeout=300)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr[-2000:]
