"""Calibration settings: one typed object for the code, the CLI, the nodes and report.json.

:class:`CalibrationSettings` holds every choice :func:`robot_ct_ros.ct.calibration.calibrate`
makes; the command line builds it from its options, the recon_service and replay nodes from
their ROS parameters (robot_ct_ros.parameters: SI units on ROS, e.g. the prior in m and rad),
and report.json records it (``to_dict``). The evidence behind the defaults is in
docs/calibration.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from robot_ct_ros.ct.calibration.lle.estimator import COARSE_SAMPLES, DRAWS
from robot_ct_ros.parameters import setting, to_dict, validate

__all__ = ["CalibrationSettings", "SCHEDULES", "AUTO_SCHEDULE", "SCHEDULE_FIELDS", "FINE_VOLUMES", "PROJECTION_KINDS",
           "EXTERIOR_MODES", "DEFAULT_PADDING", "DEFAULT_PRIOR_MM", "DEFAULT_PRIOR_DEG", "DEFAULT_PRIOR_SIGMA",
           "prior_sigma_from", "REACH_SETTING"]


REACH_SETTING = "exterior_half_width_mm; on ROS exterior_half_width_m, in m"
"""How the notes name the object's reach: its field (the command line's option) and its ROS parameter, which differ."""


def prior_sigma_from(translation_mm: float, rotation_deg: float):
    """The 9 prior standard deviations (mm x6, rad x3) from one translation and one rotation
    error; None when either is not positive (no prior: the data alone)."""
    if not (translation_mm > 0 and rotation_deg > 0):
        return None
    return (float(translation_mm),) * 6 + (math.radians(rotation_deg),) * 3


DEFAULT_PRIOR_MM = 0.3
DEFAULT_PRIOR_DEG = 0.3
"""The default prior of the MAP estimate: the robots' coordination error per view and axis
(docs/calibration.md §4). Set it to the robots' measured accuracy."""
DEFAULT_PRIOR_SIGMA = prior_sigma_from(DEFAULT_PRIOR_MM, DEFAULT_PRIOR_DEG)


_LOOP = {"iterations": 2, "stop_ncc_gain": 0.0, "exterior_iterations": 15}
_FAST = {"coarse_binning": 4, "fine_binning": 2, "fine_volume": "fdk", "fine_source": "fixed", "fine_samples": 96,
         "fine_draws": 1, "coarse_passes": 1, **_LOOP}
SCHEDULES = {
    "accurate": {"coarse_binning": 2, "fine_binning": 1, "fine_volume": "sirt", "fine_source": "star",
                 "fine_samples": 192, "fine_draws": DRAWS, "coarse_passes": 3, **_LOOP},
    "fast": _FAST,
    "exterior": {**_FAST, "iterations": 8, "stop_ncc_gain": 1e-4, "exterior_iterations": 30},
}
assert all(s["fine_samples"] >= COARSE_SAMPLES for s in SCHEDULES.values())  # lle_neighbours' bound holds everywhere
"""Resolution schedules, and how long the loop runs under each. ``accurate``: estimate on 2x2
binned data, then at full size against a full-size FDK + SIRT volume. ``fast`` (large scans):
4x4 binned (FDK + SIRT), then 2x2 binned against the FDK alone, the source held at the coarse
estimate on the finer level (one ray-cast per view and level) with 96 samples and one sample set
there. ``exterior`` (the exterior model): ``fast``'s levels, 30 SIRT passes of the ROI and
exterior model, and up to 8 outer iterations, each kept only while it raises the model's
projection NCC by ``stop_ncc_gain`` 1e-4 or more. The final volume is the full-size FDK in all
three. The default, ``auto`` (:data:`AUTO_SCHEDULE`), is ``exterior`` where the exterior model
is used and ``accurate`` elsewhere: with the exterior model, ``exterior`` ended below ``accurate``
on the interior neck and on most of the truncation sweep, and close to it on the other strongly
truncated scans measured, in a fraction of its time. Evidence: docs/calibration.md, "Schedules"."""

AUTO_SCHEDULE = "auto"
"""The schedule setting that picks ``exterior`` with the exterior model and ``accurate`` without."""
SCHEDULE_FIELDS = ("coarse_binning", "fine_binning", "fine_volume", "coarse_passes", "iterations", "stop_ncc_gain",
                   "exterior_iterations")
"""The settings that take the schedule's value when left at None."""

FINE_VOLUMES = ("sirt", "fdk+coarse-sirt", "fdk")
"""The volume the finer level registers against on a truncated scan: its own FDK + SIRT, its
FDK plus the coarse level's SIRT correction resampled, or its FDK alone."""

EXTERIOR_MODES = ("off", "on", "auto")
"""Whether the estimation volume models the object outside the ROI (robot_ct_ros.ct.calibration.exterior)."""
FOV_SUPPORT_MODES = ("off", "on", "auto")
"""Whether the estimation volume's FDK is kept to the field of view (ct.field_of_view.field_of_view_mask)."""

PROJECTION_KINDS = ("truncated", "complete", "auto")
"""Whether the projections are truncated (estimation volumes FDK + SIRT) or see the whole object
(FDK alone); ``auto`` decides from the data (:func:`robot_ct_ros.ct.calibration.volume.truncation_level`)."""

DEFAULT_PADDING = 1.25
"""How many times the ROI grid is widened across the scan axis for the estimation volume
(docs/calibration.md, "Estimation volume")."""


def _method_names():
    from robot_ct_ros.ct.calibration.registry import method_names

    return method_names()


def _schedule_names():
    return (AUTO_SCHEDULE, *SCHEDULES)


DASK_PROTOCOLS = ("tcp", "tls", "inproc", "ucx", "ws", "wss")
"""The address schemes of dask.distributed's communication backends (``scheduler`` = ``<scheme>://host:port``)."""


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything the calibration of one scan is set by (units in each field's help).

    ``method`` is a name of the method registry (:mod:`robot_ct_ros.ct.calibration.registry`),
    ``"none"`` for no correction. The prior is the robots' per-view coordination error, the same
    standard deviation on every translation and on every rotation; 0 for either turns it off.
    ``prior_source_mm`` / ``prior_detector_mm`` state one arm's translation error where the two
    arms differ (the source's three translations, the detector's three). Fields left at
    None (:data:`SCHEDULE_FIELDS`: ``coarse_binning``, ``fine_binning``, ``fine_volume``,
    ``coarse_passes``, ``iterations``, ``stop_ncc_gain``, ``exterior_iterations``) take the
    schedule's value; :meth:`resolved` fills them in.

    Raises
    ------
    ValueError
        A field outside its bounds or choices (the message names the field), or ``coarse_binning``
        below ``fine_binning`` under a schedule the run may take (``auto``: ``accurate`` and,
        unless ``exterior`` is off, ``exterior``), a level left off taking the schedule's.
    """

    method: str = setting("ncc-lle-exact", "calibration method, or none for the nominal geometry",
                          choices=_method_names)
    iterations: int | None = setting(None, "outer iterations at most (fewer when one moves the views less than "
                                     "stop_update_px; off: the schedule's, 2, or 8 under exterior)", minimum=1,
                                     maximum=100, ros_none=0, kind=int)
    schedule: str = setting(AUTO_SCHEDULE, "resolution schedule: accurate (2x binned, then full size with SIRT), fast "
                            "(4x then 2x binned: large scans) or exterior (fast's levels, more SIRT passes and "
                            "iterations: the exterior model); auto: exterior where the exterior model is used, "
                            "else accurate", choices=_schedule_names)
    stop_update_px: float = setting(0.05, "stop after an iteration that moves the views less than this "
                                    "(gauge-aligned mean; 0: always run every iteration)", unit="px", minimum=0.0)
    prior_translation_mm: float = setting(DEFAULT_PRIOR_MM, "the robots' per-view translation error, prior of the "
                                          "MAP estimate (0: no prior, the data alone)", unit="mm", minimum=0.0,
                                          ros_name="prior_sigma_translation_m", ros_scale=1e-3, ros_unit="m")
    prior_rotation_deg: float = setting(DEFAULT_PRIOR_DEG, "the robots' per-view rotation error, prior of the MAP "
                                        "estimate (0: no prior)", unit="deg", minimum=0.0,
                                        ros_name="prior_sigma_rotation_rad", ros_scale=math.pi / 180, ros_unit="rad")
    prior_source_mm: float | None = setting(None, "the source arm's own per-view translation error, where the arms "
                                            "differ (off or 0: the prior's translation error)", unit="mm", minimum=0.0,
                                            ros_name="prior_sigma_source_m", ros_scale=1e-3, ros_unit="m",
                                            ros_none=0.0, kind=float)
    prior_detector_mm: float | None = setting(None, "the detector arm's own per-view translation error, where the "
                                              "arms differ (off or 0: the prior's translation error)", unit="mm", minimum=0.0,
                                              ros_name="prior_sigma_detector_m", ros_scale=1e-3, ros_unit="m",
                                              ros_none=0.0, kind=float)
    drift_order: int | None = setting(None, "fit every parameter with a polynomial of this degree in time (a slowly "
                                      "drifting geometry); off: independent per-view errors", minimum=0,
                                      ros_none=-1, kind=int)
    seed: int = setting(0, "sampling seed of the LLE methods (another seed, another estimate of the same scan)",
                        minimum=0)
    ensemble: int = setting(1, "average this many runs with different sampling seeds (LLE methods)", minimum=1,
                            maximum=100)
    lle_neighbours: int | None = setting(None, "LLE methods: how many samples each view's projection is embedded "
                                         "in (off: the method's own, 24 for l2-lle and ncc-lle-exact, 16 for "
                                         "ncc-lle; at most the coarse level's samples)", minimum=2,
                                         maximum=COARSE_SAMPLES, ros_none=0, kind=int)
    lle_ridge: float | None = setting(None, "l2-lle and ncc-lle-exact: ridge added to the embedding's Gram matrix, "
                                      "times its trace / K (off: the method's own, 1e-5; the ncc-lle closed form "
                                      "has none)", minimum=1e-12, maximum=1.0, ros_none=0.0, kind=float)
    padding: float = setting(DEFAULT_PADDING, "widening of the ROI grid across the scan axis for the estimation "
                             "volume", minimum=1.0, maximum=20.0)
    projections: str = setting("truncated", "truncated (interior scan: FDK + SIRT estimation volumes) or complete "
                               "(the object inside the field of view: FDK alone); auto: decide from the data",
                               choices=PROJECTION_KINDS)
    fov_support: str = setting("auto", "zero the estimation volume's FDK outside the field of view (voxels whose "
                               "measured rays do not cover every direction: the square grid's corners); auto: where "
                               "the detector's edges see air (truncation level at most "
                               "calibration.volume.TRUNCATED_ABOVE), so the object lies inside it",
                               choices=FOV_SUPPORT_MODES)
    sirt_iterations: int = setting(15, "SIRT iterations of each estimation volume of a truncated scan", minimum=0,
                                   maximum=1000)
    coarse_binning: int | None = setting(None, "binning of the coarse level (off: the schedule's)", minimum=1,
                                         maximum=16, ros_none=0, kind=int)
    fine_binning: int | None = setting(None, "binning of the finer level (off: the schedule's)", minimum=1, maximum=16,
                                       ros_none=0, kind=int)
    fine_volume: str | None = setting(None, "volume the finer level registers against (off: the schedule's)",
                                      choices=FINE_VOLUMES, ros_none="", kind=str)
    coarse_passes: int | None = setting(None, "coarse passes of the first iteration at most (off: the schedule's)",
                                        minimum=1, maximum=20, ros_none=0, kind=int)
    coarse_tol_px: float = setting(0.1, "the coarse passes stop when one moves the views less than this", unit="px",
                                   minimum=0.0)
    undo_inconsistent: bool = setting(False, "undo an iteration that lowers the data consistency, and stop")
    stop_ncc_gain: float | None = setting(None, "from the second iteration on, undo an iteration that raises the "
                                          "estimation model's projection NCC by less than this, and stop (0: never; "
                                          "off: the schedule's, 1e-4 under exterior, else 0)", minimum=0.0,
                                          maximum=1.0, ros_none=-1.0, kind=float)
    exterior: str = setting("auto", "model the object outside the ROI with a coarse grid reconstructed with it (strongly "
                            "truncated interior scans); auto: when the truncation level exceeds "
                            "calibration.volume.EXTERIOR_ABOVE and the object's reach is stated "
                            "(exterior_half_width_mm; on ROS exterior_half_width_m) or guessed (exterior_reach_guess)",
                            choices=EXTERIOR_MODES)
    exterior_voxel_mm: float = setting(0.5, "voxel of the exterior grid", unit="mm", minimum=0.01, maximum=10.0,
                                       ros_name="exterior_voxel_m", ros_scale=1e-3, ros_unit="m")
    exterior_half_width_mm: float = setting(0.0, "how far the object reaches from the ROI centre across the scan axis, "
                                            "the exterior grid's reach (0: not stated; see exterior_reach_guess)",
                                            unit="mm", minimum=0.0, ros_name="exterior_half_width_m", ros_scale=1e-3,
                                            ros_unit="m")
    exterior_reach_guess: bool = setting(True, "where the object's reach is not stated and the exterior is modelled "
                                         "(on, or auto on a strongly truncated scan), the reach whose model best "
                                         "predicts views it was not built from; off: on reaches up to the sources and "
                                         "auto keeps the ROI model")
    exterior_iterations: int | None = setting(None, "ordered-subsets SIRT passes of the ROI and exterior model (off: "
                                              "the schedule's, 30 under exterior, else 15)", minimum=1, maximum=1000,
                                              ros_none=0, kind=int)
    exterior_subsets: int = setting(10, "ordered subsets of that SIRT (more than the views: one view each)", minimum=1,
                                    maximum=1000)
    guard: bool = setting(True, "keep the nominal geometry where the correction moves the views further than the "
                          "robots' stated accuracy (the prior) explains")
    guard_max_ratio: float = setting(1.5, "the scan keeps its nominal geometry when the correction moves the views this "
                                     "many times as far as the stated accuracy does", minimum=1.0)
    guard_max_ratio_unmodelled: float = setting(1.0, "the same limit (the stricter of the two applies) for a strongly "
                                                "truncated scan whose object outside the ROI was not modelled: there the ROI model's data term is "
                                                "biased, and a correction larger than the robots' own errors is not "
                                                "credited", minimum=0.1)
    guard_min_ncc: float = setting(0.5, "the scan keeps its nominal geometry when the estimation model explains the "
                                   "data this poorly: the final projection NCC of its reprojection against the data",
                                   minimum=0.0, maximum=1.0)
    guard_min_ncc_unmodelled: float = setting(0.7, "the same floor (the stricter of the two applies) for a strongly "
                                              "truncated scan whose object outside the ROI was not modelled: there corrections whose model explained the "
                                              "data at about 0.5 have made the geometry worse", minimum=0.0, maximum=1.0)
    guard_min_ncc_exterior: float = setting(0.85, "the same floor (the stricter of the two applies) for a scan whose "
                                            "object outside the ROI was modelled (exterior model): on small interior scans of wide objects, "
                                            "corrections whose model explained the data at 0.64 to 0.82 made the "
                                            "geometry worse", minimum=0.0, maximum=1.0)
    guard_view_quantile: float = setting(0.999, "a view moved beyond guard_max_ratio times this quantile of the "
                                         "stated accuracy's displacements keeps its nominal geometry", minimum=0.5,
                                         maximum=1.0)
    scheduler: str = setting("", "where estimation and FDK run: empty = in this process (default, no cluster); "
                             "local = a Dask LocalCluster of dask_workers processes; tcp://host:8786 = that Dask "
                             "scheduler (needs pip install dask distributed; docs/distributed.md)")
    dask_workers: int = setting(2, "worker processes of the local Dask cluster (scheduler=local)", minimum=1,
                                maximum=1024)
    dask_threads: int = setting(0, "numba threads of each local Dask worker (scheduler=local; 0: the cores shared "
                                "out among the workers)", minimum=0, maximum=1024)

    def __post_init__(self):
        validate(self)
        for name in ("prior_source_mm", "prior_detector_mm"):
            value = getattr(self, name)
            if value == 0:  # 0 is off, as on ROS (ros_none) and within the range the command line states (>= 0)
                object.__setattr__(self, name, None)
            elif value is not None and not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive (or off: the same as prior_translation_mm); got {value!r}")
        # the binnings under each schedule that may run: a named one, or both of auto's (the exterior one only where
        # the exterior model may be used), so that a run does not fail once it has chosen its schedule
        auto = self.schedule == AUTO_SCHEDULE
        runs = (self.schedule,) if not auto else ("accurate",) + (("exterior",) if self.exterior != "off" else ())
        for name in runs:
            coarse = SCHEDULES[name]["coarse_binning"] if self.coarse_binning is None else self.coarse_binning
            fine = SCHEDULES[name]["fine_binning"] if self.fine_binning is None else self.fine_binning
            if coarse < fine:
                which = (f"the schedule's {name!r} value" if not auto else f"the value of schedule {name!r}, which "
                         f"auto runs {'with' if name == 'exterior' else 'without'} the exterior model")
                raise ValueError(f"coarse_binning ({coarse}) must be at least fine_binning ({fine}): the coarse level "
                                 f"is the more binned one (a field left off takes {which})")
        scheme, sep, where = self.scheduler.partition("://")
        if self.scheduler not in ("", "local") and not (sep and where and scheme in DASK_PROTOCOLS):
            raise ValueError(f"scheduler must be empty (in-process), local or a Dask scheduler address such as "
                             f"tcp://host:8786 (protocol one of {', '.join(DASK_PROTOCOLS)}); got {self.scheduler!r}")

    @property
    def prior_sigma(self):
        """The prior's 9 standard deviations (mm x6: source, detector; rad x3), or None without a
        prior (``prior_translation_mm`` or ``prior_rotation_deg`` 0)."""
        sigma = prior_sigma_from(self.prior_translation_mm, self.prior_rotation_deg)
        if sigma is None:
            return None
        src = self.prior_translation_mm if self.prior_source_mm is None else float(self.prior_source_mm)
        det = self.prior_translation_mm if self.prior_detector_mm is None else float(self.prior_detector_mm)
        return (src,) * 3 + (det,) * 3 + sigma[6:]

    def schedule_for(self, exterior: bool = False) -> str:
        """The schedule that runs: ``schedule``, or for ``auto`` ``exterior`` when the exterior
        model is used (``exterior`` True) and ``accurate`` when not."""
        if self.schedule != AUTO_SCHEDULE:
            return self.schedule
        return "exterior" if exterior else "accurate"

    def plan(self, exterior: bool = False) -> dict:
        """The schedule's values (:meth:`schedule_for`) with this object's overrides: coarse_binning,
        fine_binning, fine_volume, coarse_passes, iterations, stop_ncc_gain, exterior_iterations,
        fine_source, fine_samples, fine_draws."""
        p = dict(SCHEDULES[self.schedule_for(exterior)])
        for k in SCHEDULE_FIELDS:
            if getattr(self, k) is not None:
                p[k] = getattr(self, k)
        return p

    def resolved(self, exterior: bool = False) -> "CalibrationSettings":
        """A copy with the schedule named and every field it sets filled in (:meth:`plan`): what
        a run with or without the exterior model uses, and what its result records."""
        p = self.plan(exterior)
        return replace(self, schedule=self.schedule_for(exterior), **{k: p[k] for k in SCHEDULE_FIELDS})

    def iterations_text(self) -> str:
        """The outer iterations for a progress line, before the model is known: one number, or the
        ROI model's and the exterior model's where they differ."""
        roi, ext = (self.plan(exterior)["iterations"] for exterior in (False, True))
        return str(roi) if roi == ext else f"{roi} ({ext} with the exterior model)"

    def replace(self, **changes) -> "CalibrationSettings":
        """A copy with ``changes`` (validated)."""
        return replace(self, **changes)

    def with_prior(self, translation_mm: float, rotation_deg: float, *, source_mm: float | None = None,
                   detector_mm: float | None = None) -> "CalibrationSettings":
        """A copy with the prior: every translation ``translation_mm`` unless an arm's own is given."""
        return replace(self, prior_translation_mm=float(translation_mm), prior_rotation_deg=float(rotation_deg),
                       prior_source_mm=None if source_mm is None else float(source_mm),
                       prior_detector_mm=None if detector_mm is None else float(detector_mm))

    def without_prior(self) -> "CalibrationSettings":
        return self.with_prior(0.0, 0.0)

    def to_dict(self) -> dict:
        """Field name -> value, as report.json records it."""
        return to_dict(self)
