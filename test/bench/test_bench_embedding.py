"""bench/bench_embedding.py: its variants are valid settings that reach the embedding, its default row is the default."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from robot_ct_ros.ct.calibration import CalibrationSettings, get_method

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_embedding.py"


def test_each_variant_reaches_the_embedding_and_the_default_row_changes_nothing():
    spec = importlib.util.spec_from_file_location("bench_embedding", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    default = get_method("ncc-lle-exact").configs(CalibrationSettings())
    seen = set()
    for label, change in bench.VARIANTS.items():
        configs = get_method("ncc-lle-exact").configs(CalibrationSettings(**change))
        embedding = tuple((c.n_neighbours, c.reg) for c in configs)
        assert ("default" in label) == (embedding == tuple((c.n_neighbours, c.reg) for c in default)), label
        assert f"K {configs[0].n_neighbours}," in label, label
        assert float(label.split("ridge ")[1].split()[0]) == configs[0].reg, label  # the label says what ran
        seen.add(embedding)
    assert len(seen) == len(bench.VARIANTS)  # every row is a different embedding
