"""bench/ holds scripts, not a package: each test loads the script it checks by its path."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCH_DIR = ROOT / "bench"
# the project's shared folder sits beside the repository (../shared); /work/shared on the project's machines
HTC2022 = next((p for p in (ROOT.parent / "shared" / "realdata" / "htc2022", Path("/work/shared/realdata/htc2022"))
                if p.is_dir()), Path("/work/shared/realdata/htc2022"))


@pytest.fixture
def load_bench():
    """``load_bench("bench_guard")``: bench/bench_guard.py executed as a fresh module."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, BENCH_DIR / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    return load


@pytest.fixture
def htc2022_01a():
    """The shared HTC2022 folder, for a test that reads phantom 01a (its sinogram and the dataset's FBP); the test
    is skipped where they are absent."""
    if not all((HTC2022 / f"htc2022_01a_{kind}.mat").exists() for kind in ("full", "recon_fbp")):
        pytest.skip("shared HTC2022 data not present")
    return HTC2022
