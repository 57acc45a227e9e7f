"""Simulation of a robotic interior CT scan: phantoms, photon-counting detector, geometric errors.

Units and conventions are those of :mod:`robot_ct_ros.ct.geometry` (world mm, radians,
``volume[k, j, i]`` = (z, y, x), ``proj[view, row, col]``). Attenuation coefficients are
linear attenuation in 1/mm at an effective energy of about 70 keV (see :data:`MU`).

Phantoms
    A :class:`Phantom` is an ordered list of analytic :class:`Primitive` objects in world
    mm (ellipsoids, finite elliptic cylinders / annuli / annular sectors, boxes and
    Archimedean spirals). Primitives are *painted* in order: mode ``"set"`` replaces the
    value inside the primitive, mode ``"add"`` adds to it. :func:`voxelize` evaluates the
    painting on ``supersample**3`` points per voxel (numba, parallel over z-slices) and
    averages them. Spirals (thin foils) are anti-aliased along their normal: each sample
    takes the fraction of a sample-sized window that the foil covers, so a 15 um copper
    foil keeps its mass on a 40 um grid.

Detector
    :class:`DetectorModel` is a Timepix-like photon-counting detector read out ``binning``
    x ``binning`` binned. Raw pixels lie on chips of ``chip_size_px`` with ``chip_gap_px``
    insensitive pixels between chips (gaps start after the first chip at raw index 0).
    Dead pixels and chip gaps count 0; hot pixels saturate. The bad-pixel map (gaps, dead,
    hot) is known, as it is for a calibrated detector, and binning sums only the valid raw
    pixels of a bin, for the projections and for the flat field alike. The flat-field ratio
    of a partly bad bin is therefore unbiased (equivalent to scaling by the number of valid
    raw pixels) while its counts stay honest Poisson counts; a binned pixel with fewer than
    ``min_valid_fraction`` valid raw pixels is masked.

Geometric errors
    :class:`GeometryErrorModel` samples per-view 9-DOF parameters (geometry.py convention,
    apply with ``geom.perturbed(params)``): independent per-view errors (robot
    coordination), slow drift (detector creep) and static offsets.

Scan simulation
    :func:`simulate_scan` voxelises the phantom finer than the reconstruction (avoids the
    inverse crime), optionally as two parts (a fine ROI grid and a coarse grid for the
    rest of the irradiated object, which only feeds truncation), forward projects with
    :func:`robot_ct_ros.ct.projector.forward_project` onto the *raw* detector (one ray per
    raw pixel, so a binned pixel integrates binning**2 rays), applies the detector model
    and bins (or takes a ``projector``: :func:`ellipsoid_line_integrals`, the exact line integrals
    of additive ellipsoids, for scans too large to voxelise at their resolution). The geometry passed in is the readout (binned) geometry that reconstruction
    uses; the raw geometry is ``raw_geometry(geom, binning)``.
"""


from robot_ct_ros.ct.simulation.analytic import ellipsoid_line_integrals
from robot_ct_ros.ct.simulation.detector import (DetectorModel, counts_to_line_integrals, simulate_counts,
                                                 simulate_flat)
from robot_ct_ros.ct.simulation.errors import (GeometryErrorModel, SumOfErrorModels, detector_drift,
                                               robot_coordination, static_misalignment)
from robot_ct_ros.ct.simulation.phantoms import (MU, CapGeometry, Phantom, Primitive, battery_phantom, box,
                                                 interior_neck_phantom,
                                                 carotid_plaque_phantom, ellipsoid, elliptic_cylinder, mouse_phantom,
                                                 spiral, voxelize)
from robot_ct_ros.ct.simulation.scan import (SimulatedScan, irradiated_bounds_mm, project_parts, raw_geometry,
                                             scan_volumes, simulate_scan)

__all__ = ["MU", "Primitive", "Phantom", "CapGeometry", "ellipsoid", "elliptic_cylinder", "box", "spiral", "voxelize",
           "mouse_phantom", "battery_phantom", "carotid_plaque_phantom", "interior_neck_phantom", "DetectorModel", "simulate_flat",
           "simulate_counts", "counts_to_line_integrals", "ellipsoid_line_integrals", "GeometryErrorModel", "SumOfErrorModels",
           "robot_coordination", "detector_drift", "static_misalignment", "raw_geometry", "irradiated_bounds_mm",
           "scan_volumes", "SimulatedScan", "project_parts", "simulate_scan"]
