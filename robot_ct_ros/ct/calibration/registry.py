"""The calibration methods, found by name: one table that the CLI, the nodes and the bench read.

A :class:`Method` is an estimator (one pass over all views, the signature of
:func:`robot_ct_ros.ct.calibration.lle.estimator.estimate_views`) with the factory of its coarse
and fine settings. ``"none"`` is the nominal geometry (no estimator). Like ASTRA's algorithms,
a method is chosen by its name; adding one is adding a row to :data:`METHODS`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

from robot_ct_ros.ct.calibration.gdc import default_gdc_configs, estimate_views_gdc
from robot_ct_ros.ct.calibration.lle.estimator import default_lle_configs, estimate_views, narrowed

__all__ = ["Method", "METHODS", "NO_CORRECTION", "get_method", "method_names"]

NO_CORRECTION = "none"
"""The name of "no correction": the nominal geometry, reconstructed."""


@dataclass(frozen=True)
class Method:
    """One calibration method of the registry.

    Attributes
    ----------
    name, summary : str
        Registry name and one line for help texts.
    estimate : callable or None
        ``estimate(measured, nominal, params0, volume, grid, config, valid_mask) -> (params, info)``;
        None for :data:`NO_CORRECTION`.
    configs : callable or None
        ``configs(settings) -> (coarse_config, fine_config)`` from a
        :class:`~robot_ct_ros.ct.calibration.settings.CalibrationSettings`.
    narrow : callable
        ``narrow(config, iteration) -> config``: the search of outer iteration ``iteration`` (0-based).
    fresh_samples : callable
        ``fresh_samples(config, k) -> config``: the config of the k-th extra coarse pass.
    uses_prior : bool
        Whether the estimate is maximum a posteriori under the settings' prior. A method without
        one runs on the data alone: the report's ``prior_sigma`` is none, while its settings keep
        the robots' stated accuracy, which the guard reads.
    samples : bool
        Whether it draws random samples: then ``seed`` changes the estimate and ``ensemble``
        averages runs; otherwise every run is the same and an ensemble runs once.
    lle_settings : tuple of str
        The embedding's settings its ``configs`` read (``lle_neighbours``, ``lle_ridge``); empty for
        a method that embeds no samples. The result's notes name the others, where given, as not applied.
    """

    name: str
    summary: str
    estimate: Callable | None
    configs: Callable | None
    narrow: Callable = lambda config, iteration: config
    fresh_samples: Callable = lambda config, k: config
    uses_prior: bool = False
    samples: bool = False
    lle_settings: tuple = ()


def _lle(weighting: str) -> Callable:
    def configs(settings):
        plan = settings.plan()
        coarse, fine = default_lle_configs(weighting, seed=settings.seed, prior_sigma=settings.prior_sigma,
                                           n_neighbours=settings.lle_neighbours, reg=settings.lle_ridge)
        return coarse, replace(fine, source_positions=plan["fine_source"], n_samples=plan["fine_samples"],
                               draws=plan["fine_draws"])
    return configs


def _reseeded(config, k: int):
    return replace(config, seed=config.seed + 104729 * k)


def _gdc(name: str) -> Callable:
    return lambda settings: default_gdc_configs(name)


METHODS = {m.name: m for m in (
    Method(NO_CORRECTION, "no correction: the nominal geometry", None, None),
    Method("l2-lle", "LLE with L2 weights (Chen et al. 2016)", estimate_views, _lle("l2"), narrowed, _reseeded,
           uses_prior=True, samples=True, lle_settings=("lle_neighbours", "lle_ridge")),
    Method("ncc-lle", "LLE with the published NCC closed-form weights (Li et al.)", estimate_views, _lle("ncc"),
           narrowed, _reseeded, uses_prior=True, samples=True, lle_settings=("lle_neighbours",)),  # no ridge
    Method("ncc-lle-exact", "LLE with the exact NCC-maximising weights", estimate_views, _lle("ncc-exact"),
           narrowed, _reseeded, uses_prior=True, samples=True, lle_settings=("lle_neighbours", "lle_ridge")),
    Method("gdc", "Gauss-Newton on the L2 reprojection error (Sun et al. 2016)", estimate_views_gdc, _gdc("gdc")),
    Method("gdc-log", "the same on Laplacian-of-Gaussian filtered projections (Sun et al. 2021)", estimate_views_gdc,
           _gdc("gdc-log")),
)}
"""Name -> :class:`Method`, in the order help texts list them."""


def method_names(*, include_none: bool = True) -> tuple:
    """The registry's names (``"none"`` first unless ``include_none`` is False)."""
    return tuple(n for n in METHODS if include_none or n != NO_CORRECTION)


def get_method(name: str) -> Method:
    """The :class:`Method` called ``name``.

    Raises
    ------
    ValueError
        No method has that name (the message lists them all).
    """
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown calibration method {name!r}; choose one of {', '.join(METHODS)}") from None
