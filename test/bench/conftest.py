"""bench/ holds scripts, not a package: each test loads the script it checks by its path."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

BENCH_DIR = Path(__file__).resolve().parents[2] / "bench"


@pytest.fixture
def load_bench():
    """``load_bench("bench_guard")``: bench/bench_guard.py executed as a fresh module."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, BENCH_DIR / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    return load
