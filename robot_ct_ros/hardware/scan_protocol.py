"""Scan protocols: what one acquisition does, read from YAML and checked; its trajectory and scan info.

A protocol file (config/scan_protocol_*.yaml) holds a top-level ``scan_protocol`` mapping in SI
units (metres, seconds, degrees for the arc); see :class:`ScanProtocol` for the keys. The
trajectory is the seed system's robotic ROI scan (:func:`robot_ct_ros.ct.trajectory.robotic_roi_scan`)
in the core's units (mm); the scan info is the bag contract's /ct/scan_info
(:func:`robot_ct_ros.bag.format.scan_info_for`). No ROS import.

The protocol lives with the hardware rather than in :mod:`robot_ct_ros.ct` because it is an
acquisition's description (arm trajectory, detector read-out, exposure timing, source settings),
is read from files, and produces the bag contract's scan info: the science core stays free of
file I/O and of the bag format.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import yaml

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.geometry import ConeGeometry, axis_frame
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan

__all__ = ["ScanProtocol", "PROTOCOL_ERRORS"]

PROTOCOL_ERRORS = (OSError, ValueError, TypeError, yaml.YAMLError)
"""What loading a protocol file, or making its trajectory, raises for a bad file."""


@dataclass(frozen=True)
class ScanProtocol:
    """A scan protocol (SI units, as in the YAML file).

    Attributes
    ----------
    name : str
        Recorded in the scan info and the scan status.
    n_views, roi_center_m, axis, fov_diameter_m, start_deg, arc_deg, sdd_m, magnification
        Trajectory (robotic_roi_scan of the seed system): ``n_views`` views over ``arc_deg`` (deg)
        from ``start_deg`` (deg; below 360 the last view at ``start_deg + arc_deg``, a full circle in
        equal steps of ``arc_deg / n_views``) about ``axis`` (unit vector, world frame) through
        ``roi_center_m`` (m, world frame); source at ``sdd_m / magnification`` (m) from the ROI centre; offset
        detector for a field of view of ``fov_diameter_m`` (m).
    n_rows, n_cols, binning, raw_pixel_m
        Detector read-out (the YAML's ``detector`` mapping): ``n_rows`` x ``n_cols`` pixels (0 =
        the full seed detector) of ``raw_pixel_m * binning`` (m).
    exposure_s, settle_s, move_timeout_s, exposure_timeout_s
        Timing (s): exposure per view (must match the pcd_grabber's), wait after both arms are in
        position, limit per move, limit for the detector's answer.
    kvp, power_w
        Source settings (kVp, W), recorded in the scan info (the source is configured on source_control).
    voxel_size_m, roi_size_m
        Reconstruction grid for the scan info (m; 0 = derived by the reader).
    notes : dict
        More entries for the scan info's notes.
    """

    name: str = "protocol"
    n_views: int = 360
    roi_center_m: tuple = (0.4, 0.0, 0.3)
    axis: tuple = (0.0, 0.0, 1.0)
    fov_diameter_m: float = 0.05
    start_deg: float = 0.0
    arc_deg: float = 360.0
    sdd_m: float = 0.3424
    magnification: float = 2.67
    n_rows: int = 0
    n_cols: int = 0
    binning: int = 2
    raw_pixel_m: float = 55e-6
    exposure_s: float = 0.1
    settle_s: float = 0.05
    move_timeout_s: float = 30.0
    exposure_timeout_s: float = 5.0
    kvp: float = 90.0
    power_w: float = 150.0
    voxel_size_m: float = 0.0
    roi_size_m: tuple = (0.0, 0.0, 0.0)
    notes: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict) -> "ScanProtocol":
        """A checked protocol from a mapping (the YAML's content, with or without ``scan_protocol``).

        Raises
        ------
        ValueError
            Not a mapping, unknown keys, or values :meth:`validate` refuses.
        """
        if not isinstance(d, dict):
            raise ValueError("a scan protocol must be a mapping")
        d = dict(d.get("scan_protocol", d))
        det = dict(d.pop("detector", None) or {})
        for k in ("n_rows", "n_cols", "binning", "raw_pixel_m"):
            if k in det:
                d[k] = det.pop(k)
        unknown = (set(d) - set(cls.__dataclass_fields__)) | set(det)
        if unknown:
            raise ValueError(f"unknown scan protocol keys: {', '.join(sorted(unknown))}")
        for k in ("roi_center_m", "axis", "roi_size_m"):
            if k in d:
                d[k] = tuple(float(x) for x in np.broadcast_to(np.asarray(d[k], float), (3,)))
        proto = cls(**d)
        proto.validate()
        return proto

    @classmethod
    def from_yaml(cls, path) -> "ScanProtocol":
        """A checked protocol from a YAML file; raises one of :data:`PROTOCOL_ERRORS`."""
        with open(path) as f:
            return cls.from_dict(yaml.safe_load(f))

    def validate(self) -> None:
        """Raise ValueError unless the protocol can run (views, timing, geometry, field of view)."""
        if self.n_views < 1:
            raise ValueError("n_views must be positive")
        if not (0 < self.exposure_s < self.exposure_timeout_s):
            raise ValueError("need 0 < exposure_s < exposure_timeout_s")
        if self.settle_s < 0 or self.move_timeout_s <= 0:
            raise ValueError("settle_s must be >= 0 and move_timeout_s > 0")
        if self.magnification <= 1 or self.sdd_m <= 0:
            raise ValueError("need sdd_m > 0 and magnification > 1")
        self.geometry()  # raises on an impossible field of view

    def geometry(self) -> ConeGeometry:
        """The nominal geometry of the scan (mm, world frame), one view per protocol view."""
        system = SeedSystem(sdd_mm=self.sdd_m * 1e3, magnification=self.magnification,
                            raw_pixel_mm=self.raw_pixel_m * 1e3, binning=self.binning, n_views=self.n_views)
        return robotic_roi_scan(system, roi_center_mm=np.asarray(self.roi_center_m) * 1e3,
                                fov_diameter_mm=self.fov_diameter_m * 1e3, n_views=self.n_views,
                                binning=self.binning, axis=self.axis, n_rows=self.n_rows or None,
                                n_cols=self.n_cols or None, arc_rad=math.radians(self.arc_deg),
                                start_rad=math.radians(self.start_deg))

    def scan_info(self, geom: ConeGeometry, scan_id: str) -> dict:
        """The /ct/scan_info content of a scan of this protocol with geometry ``geom`` (bag contract)."""
        kw = {}
        if self.voxel_size_m > 0:
            kw["voxel_size_mm"] = self.voxel_size_m * 1e3
        if min(self.roi_size_m) > 0:
            kw["roi_size_mm"] = np.asarray(self.roi_size_m) * 1e3
        notes = {"scan_id": scan_id, "protocol": self.name, "kvp": self.kvp, "power_w": self.power_w,
                 "exposure_s": self.exposure_s, "settle_s": self.settle_s, **self.notes}
        # the grid's orientation stated, z along the protocol's axis: a live reconstruction starts from the first few
        # views, whose short arc tells the axis far less well than the protocol does
        direction = axis_frame(self.axis)
        return fmt.scan_info_for(geom, binning=self.binning, projection_units="counts",
                                 roi_center_mm=np.asarray(self.roi_center_m) * 1e3, notes=notes,
                                 roi_direction=[float(x) for x in direction.reshape(-1)], **kw)
