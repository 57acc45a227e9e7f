"""Where the bench scripts write: a run without --out never overwrites the published results (docs/results), and
each make bench-* target that publishes names the folder itself."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BENCH_DIR = ROOT / "bench"

OUTPUTS = ("--out", "--json", "--volume-out")  # what a script writes (--results is what bench_guard reads)


def _output_defaults(path):
    """(option, its default's source) of every output option of a bench script's argument parser."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument"
                and node.args and isinstance(node.args[0], ast.Constant) and node.args[0].value in OUTPUTS):
            default = next((k.value for k in node.keywords if k.arg == "default"), None)
            out.append((node.args[0].value, "None" if default is None else ast.unparse(default)))
    return out


def test_no_bench_script_writes_the_published_results_by_default():
    """From an outside check: bench_dask.py wrote docs/results by default (relative to the working folder), so its
    docstring's own cut-down example overwrote the published dask.md; bench_calibration.py did the same."""
    scripts = sorted(BENCH_DIR.glob("bench_*.py"))
    assert scripts
    for script in scripts:
        for option, default in _output_defaults(script):
            assert "docs" not in default and "results" not in default, f"{script.name} {option} default {default}"


def test_the_make_targets_name_the_published_folder():
    """make bench-dask and bench-calibration write docs/results as before: they name it."""
    makefile = (ROOT / "Makefile").read_text()
    for script in ("bench_dask.py", "bench_calibration.py"):
        (line,) = [ln for ln in makefile.splitlines() if f"bench/{script}" in ln]
        assert re.search(r"--out docs/results(\s|$)", line), line
