"""bench/bench_embedding.py: its variants are valid settings that reach the embedding; its default row is unchanged."""

from __future__ import annotations

from robot_ct_ros.ct.calibration import CalibrationSettings, get_method


def test_each_variant_reaches_the_embedding_and_the_default_row_changes_nothing(load_bench):
    bench = load_bench("bench_embedding")
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
