"""bench/bench_conjugate_modes.py: the harmonic it injects is the one it measures, and k = 1 is the gauge."""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.calibration.constraints import view_angles
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.metrics import roi_points
from robot_ct_ros.ct.trajectory import circular_scan


def test_an_injected_detector_harmonic_is_measured_at_its_amplitude(load_bench):
    bench = load_bench("bench_conjugate_modes")
    nominal = circular_scan(90, 60.0, 150.0, 16, 32, 0.4, 0.4)
    grid = VolumeGrid.centered((8, 16, 16), 0.2)
    pts = roi_points(grid)
    t = view_angles(nominal, grid.center_mm)
    for k, amplitude in ((3, 1.0), (2, 0.5)):
        p = np.zeros((90, 9))
        p[:, 3] = amplitude * nominal.col_pitch_mm * np.cos(k * t + 0.4)
        true = nominal.perturbed(p)
        shift = bench.centre_shift_px(nominal, true, grid, pts)
        assert abs(bench.harmonic_amplitude(shift, t, k) - amplitude) < 0.02 * amplitude
        assert bench.harmonic_amplitude(shift, t, k + 1) < 0.02 * amplitude  # other harmonics stay empty
        assert abs(bench.harmonic_amplitude(bench.centre_shift_px(true, true, grid, pts), t, k)) < 1e-9
    # k = 1: a detector shift that follows the view about the axis is (nearly) a translation, the gauge
    p = np.zeros((90, 9))
    p[:, 3] = nominal.col_pitch_mm * np.cos(t)
    assert bench.harmonic_amplitude(bench.centre_shift_px(nominal, nominal.perturbed(p), grid, pts), t, 1) < 0.1
