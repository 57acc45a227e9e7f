"""bench/bench_calibration_speed.py: the settings it changes reach the calibration, and its json says so."""

from __future__ import annotations

import json

import pytest


def test_a_changed_fine_volume_reaches_the_calibration_and_is_recorded(load_bench, tmp_path, monkeypatch):
    bench = load_bench("bench_calibration_speed")
    seen = []
    real = bench.calibration.calibrate

    def recording(*args, **kwargs):
        seen.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(bench.calibration, "calibrate", recording)
    out = tmp_path / "speed" / "run.json"
    assert bench.main(["--views", "16", "--det", "24x24", "--vol", "16", "--iterations", "1", "--gdc-iterations", "0",
                       "--no-rtk", "--fine-volume", "fdk+coarse-sirt", "--coarse-passes", "1", "--json", str(out)]) == 0
    assert [(k["fine_volume"], k["coarse_passes"], k["schedule"]) for k in seen] == [("fdk+coarse-sirt", 1, "fast")]
    report = json.loads(out.read_text())
    assert report["settings"]["fine_volume"] == "fdk+coarse-sirt" and report["settings"]["coarse_passes"] == 1
    assert len(report["runs"][0]["iterations"]) == 1


def test_without_changes_the_schedule_decides(load_bench, monkeypatch):
    bench = load_bench("bench_calibration_speed")
    seen = []

    def stop(*args, **kwargs):
        seen.append(kwargs)
        raise RuntimeError("seen enough")

    monkeypatch.setattr(bench.calibration, "calibrate", stop)
    with pytest.raises(RuntimeError, match="seen enough"):
        bench.main(["--views", "16", "--det", "24x24", "--vol", "16", "--gdc-iterations", "0", "--no-rtk"])
    assert len(seen) == 1 and "fine_volume" not in seen[0] and "coarse_passes" not in seen[0]


def test_a_bad_setting_is_a_usage_error_before_any_work(load_bench, capsys):
    bench = load_bench("bench_calibration_speed")
    with pytest.raises(SystemExit) as exc:
        bench.main(["--coarse-passes", "0", "--no-rtk"])
    assert exc.value.code == 2 and "coarse_passes must be >= 1" in capsys.readouterr().err
