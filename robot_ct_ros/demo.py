"""The main job on simulated hardware, end to end (grows with the project).

Current slice: the nominal and the robot-perturbed geometry of a 360-view scan of the seed
system (source-to-detector 342.4 mm, magnification 2.67, 110 µm binned pixels), written as JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry


def _seed_circular_geometry(n_views: int = 360) -> ConeGeometry:
    sdd_mm, magnification = 342.4, 2.67
    sod_mm = sdd_mm / magnification
    angles = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)
    radial = np.stack([np.cos(angles), np.sin(angles), np.zeros(n_views)], axis=1)
    tangential = np.stack([-np.sin(angles), np.cos(angles), np.zeros(n_views)], axis=1)
    return ConeGeometry(source_mm=sod_mm * radial, detector_mm=-(sdd_mm - sod_mm) * radial,
                        u=tangential, v=np.tile([0.0, 0.0, 1.0], (n_views, 1)),
                        n_rows=272, n_cols=636, row_pitch_mm=0.11, col_pitch_mm=0.11)


def run_demo(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    nominal = _seed_circular_geometry()
    rng = np.random.default_rng(0)
    errors = np.concatenate([rng.normal(0, 0.3, (nominal.n_views, 6)),
                             rng.normal(0, np.deg2rad(0.3), (nominal.n_views, 3))], axis=1)
    true = nominal.perturbed(errors)
    shift_px = np.abs(true.project_points([0.0, 0.0, 0.0]) - nominal.project_points([0.0, 0.0, 0.0]))
    print(f"[demo] {nominal.n_views} views, detector {nominal.n_rows}x{nominal.n_cols} at "
          f"{nominal.col_pitch_mm * 1000:.0f} µm, magnification {nominal.magnification().mean():.2f}")
    print(f"[demo] robot errors move the ROI centre by {shift_px.mean():.2f} px on average "
          f"(max {shift_px.max():.2f} px)")
    (out / "geometry_nominal.json").write_text(nominal.to_json())
    (out / "geometry_true.json").write_text(true.to_json())
    (out / "summary.json").write_text(json.dumps({"mean_shift_px": float(shift_px.mean())}, indent=2))
    print(f"[demo] wrote {out}/geometry_nominal.json, geometry_true.json, summary.json")
    return 0
