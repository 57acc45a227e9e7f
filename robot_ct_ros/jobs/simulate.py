"""The simulation job: a seed-system robotic ROI scan of a phantom, recorded as a scan bag."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from robot_ct_ros.jobs.output import say as _say

__all__ = ["simulate_bag", "make_phantom", "PHANTOMS"]

PHANTOMS = ("mouse", "battery", "carotid")
"""The phantoms ``robot-ct simulate`` offers (robot_ct_ros.ct.simulation)."""


def make_phantom(name: str, seed: int = 0):
    """The phantom ``name`` (one of :data:`PHANTOMS`) that :func:`simulate_bag` scans, in its world frame (mm):
    the ROI it centres on is the origin."""
    from robot_ct_ros.ct import simulation as sim

    factories = {"mouse": sim.mouse_phantom, "battery": sim.battery_phantom, "carotid": sim.carotid_plaque_phantom}
    if name not in factories:
        raise ValueError(f"unknown phantom {name!r}; choose from {', '.join(PHANTOMS)}")
    return factories[name](seed=seed)


def simulate_bag(out, *, phantom: str = "carotid", views: int = 360, rows: int = 272, cols: int = 636,
                 binning: int = 2, sigma_mm: float = 0.1, sigma_deg: float = 0.1, seed: int = 0,
                 drift_mm: float = 0.0, drift_deg: float = 0.0, photons: float | None = None,
                 fov_mm: float | None = None, sim_voxel_mm: float | None = None, arc_deg: float = 360.0,
                 chunk_views: int = 8, progress: bool = True, say=_say) -> Path:
    """Simulate a seed-system robotic ROI scan of a phantom and record it as a scan bag at ``out``.

    The nominal geometry (/ct/geometry) is :func:`robotic_roi_scan`; the frames are
    simulated along it perturbed by independent per-view robot errors (``sigma_mm`` on the
    6 translations, ``sigma_deg`` on the 3 rotations) plus, optionally, a detector that drifts
    linearly by ``drift_mm`` (its 3 translations) and ``drift_deg`` (its 3 rotations) over the
    scan; the bag keeps the true geometry on /ct/geometry_true. Frames are photon counts
    (``photons`` per binned pixel per frame unattenuated; default: 4,000 behind 13 cm of
    water) with flat field and dead pixels. ``arc_deg`` below 360 takes a short scan: the views
    span that arc, the first at 0 and the last at ``arc_deg`` (reconstructed with Parker's weights
    where it exceeds half a turn plus the fan, :func:`robot_ct_ros.ct.reconstruction.short_scan_weights`).
    """
    if not 0.0 < float(arc_deg) <= 360.0:
        raise ValueError(f"the scan's arc must lie in (0, 360] degrees, got {arc_deg}")
    from tqdm import tqdm

    from robot_ct_ros.bag import ScanBagWriter, default_stamps, scan_info_for
    from robot_ct_ros.ct import simulation as sim
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.trajectory import SeedSystem, fov_radius_mm, robotic_roi_scan

    system = SeedSystem()
    pitch = system.raw_pixel_mm * binning
    if fov_mm is None:
        fov_mm = 0.999 * 2 * fov_radius_mm(0.5 * cols * pitch, system.sod_mm, system.sdd_mm)
    largest_mm = 2 * fov_radius_mm(cols * pitch, system.sod_mm, system.sdd_mm)  # offset by half its width
    if not 0 < fov_mm <= largest_mm:
        raise ValueError(f"--fov-mm is the field of view's diameter: {fov_mm:g} mm is more than the "
                         f"{largest_mm:.2f} mm that {cols} columns of {pitch:g} mm reach (the detector offset by half "
                         "its width)")
    nominal = robotic_roi_scan(system, n_views=views, binning=binning, n_rows=rows, n_cols=cols,
                               fov_diameter_mm=fov_mm, arc_rad=np.radians(float(arc_deg)))
    model = sim.robot_coordination(sigma_mm, sigma_deg, seed=seed)
    if drift_mm or drift_deg:
        model = model + sim.detector_drift(drift_mm / max(views - 1, 1), drift_deg / max(views - 1, 1), kind="linear")
    errors = model.sample(views)
    true = nominal.perturbed(errors)
    ph = make_phantom(phantom, seed)
    det = (sim.DetectorModel.from_transmitted(4000.0, 130.0, binning=binning, seed=seed) if photons is None
           else sim.DetectorModel(photons_per_pixel=photons, binning=binning, seed=seed))
    voxel = pitch / system.magnification
    axial = rows * pitch / system.magnification
    roi = VolumeGrid.centered((max(1, round(axial / voxel)), max(1, round(fov_mm / voxel)),
                               max(1, round(fov_mm / voxel))), voxel)
    say(f"{phantom} phantom, {views} views, detector {rows}x{cols} at {pitch * 1000:.0f} um (binning {binning}), "
        f"FOV {fov_mm:.2f} mm, robot errors {sigma_mm} mm / {sigma_deg} deg"
        + (f", detector drift {drift_mm} mm / {drift_deg} deg over the scan" if drift_mm or drift_deg else "")
        + f", seed {seed}")
    gproj = sim.raw_geometry(true, binning)
    def outer_voxel_mm(fine_mm: float) -> float:  # the coarse grid outside the ROI
        return max(0.4, 4 * fine_mm)

    if sim_voxel_mm is None:  # half the reconstruction voxel, coarser when the ROI would need > 200^3 voxels
        sim_voxel_mm = max(0.5 * voxel, float(np.prod(roi.extent_mm)) ** (1 / 3) / 200)
        # the fine grid is the ROI plus a margin and a blend of outer voxels on every side (sim.scan_volumes):
        # on a thin ROI (a fan beam's one row) that margin, not the ROI, sets its size
        while np.prod((roi.extent_mm + 2.0 * (0.5 + 3.0 * outer_voxel_mm(sim_voxel_mm))) / sim_voxel_mm) > 0.8 * 400 ** 3:
            sim_voxel_mm *= 1.1
    outer_mm = outer_voxel_mm(sim_voxel_mm)
    say(f"phantom voxelised at {sim_voxel_mm * 1000:.1f} um in the ROI, {outer_mm:.2f} mm outside")
    try:
        parts = sim.scan_volumes(ph, gproj, sim_voxel_mm, roi_grid=roi, outer_voxel_size_mm=outer_mm)
    except ValueError as exc:
        if "exceeds max_voxels" not in str(exc):
            raise
        raise ValueError(f"{exc}: the phantom voxel {sim_voxel_mm * 1000:.1f} um is too fine for this field of view; "
                         "give a coarser --sim-voxel-mm") from None
    rng = np.random.default_rng(seed)
    raw_shape = (rows * binning, cols * binning)
    flat, valid = sim.simulate_flat(raw_shape, det, rng)
    info = scan_info_for(nominal, binning=binning, projection_units="counts", roi_center_mm=roi.center_mm,
                         roi_size_mm=roi.extent_mm, voxel_size_mm=roi.voxel_size_mm, phantom=phantom,
                         notes={"simulated": True, "seed": seed, "photons_per_pixel": det.photons_per_pixel,
                                "robot_error_sigma_mm": sigma_mm, "robot_error_sigma_deg": sigma_deg,
                                "detector_drift_mm": drift_mm, "detector_drift_deg": drift_deg,
                                "generator": "robot-ct simulate"})
    stamps = default_stamps(views)
    t0 = int(stamps[0]) - 1_000_000
    out = Path(out)
    if out.exists():
        raise ValueError(f"{out} exists already; a bag is never overwritten")
    with ScanBagWriter(out, info, start_ns=t0) as w:
        w.write_flat(flat, t0)
        w.write_dead_pixels(~valid, t0)
        bar = tqdm(total=views, desc="simulate", unit="view", disable=not progress, file=sys.stdout)
        for v0 in range(0, views, chunk_views):
            sel = np.arange(v0, min(views, v0 + chunk_views))
            li = sim.project_parts(parts, gproj.subset(sel))
            counts = sim.simulate_counts(li, det, rng, flat=flat)[0]
            for k, i in enumerate(sel):
                w.write_frame(counts[k], nominal, int(stamps[i]), int(i), true=true)
            bar.update(len(sel))
        bar.close()
    say(f"wrote {out} ({views} frames)")
    return out
