"""Per-view 9-DOF geometry calibration of a cone-beam scan (docs/calibration.md; Li et al., arXiv 2406.18063).

Where things are:

* :mod:`.settings` — :class:`CalibrationSettings`, the one settings object;
* :mod:`.registry` — the methods by name (``none``, ``l2-lle``, ``ncc-lle``, ``ncc-lle-exact``,
  ``gdc``, ``gdc-log``);
* :mod:`.loop` — :func:`calibrate`, the alternating loop;
* :mod:`.volume` — the estimation volume the views are registered against;
* :mod:`.constraints` — gauge (magnification hold), drift model, conjugate modes;
* :mod:`.ensemble` — averaging runs with different sampling seeds;
* :mod:`.lle` — the LLE estimator: ``weights`` (L2, NCC, exact NCC, MAP), ``sampling``,
  ``estimator``;
* :mod:`.gdc` — the GDC and GDC-LoG baselines;
* :mod:`.kernels` — numba kernels: detector homographies, warps, sample scores;
* :mod:`.masks` — which pixels count.

The evidence for the design choices is in docs/calibration.md.
"""

from robot_ct_ros.ct.calibration.constraints import fit_drift
from robot_ct_ros.ct.calibration.ensemble import ENSEMBLE_SEED_STEP, average_estimates
from robot_ct_ros.ct.calibration.loop import calibrate
from robot_ct_ros.ct.calibration.registry import METHODS, NO_CORRECTION, Method, get_method, method_names
from robot_ct_ros.ct.calibration.result import CalibrationResult, IterationRecord
from robot_ct_ros.ct.calibration.settings import (DEFAULT_PADDING, DEFAULT_PRIOR_SIGMA, SCHEDULES,
                                                  CalibrationSettings, prior_sigma_from)

__all__ = ["calibrate", "CalibrationSettings", "CalibrationResult", "IterationRecord", "METHODS", "Method",
           "NO_CORRECTION", "get_method", "method_names", "SCHEDULES", "DEFAULT_PADDING", "DEFAULT_PRIOR_SIGMA",
           "prior_sigma_from", "average_estimates", "ENSEMBLE_SEED_STEP", "fit_drift"]
