"""The photon-counting detector model: flat field, counts with Poisson noise, bad pixels, binning."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_ct_ros.ct.geometry import bin_projections
from robot_ct_ros.ct.simulation.phantoms import MU, _rng

__all__ = ["DetectorModel", "simulate_flat", "simulate_counts", "counts_to_line_integrals"]

# ----------------------------------------------------------------------------- detector model
@dataclass(frozen=True)
class DetectorModel:
    """Timepix-like photon-counting detector, read out ``binning`` x ``binning`` binned.

    ``photons_per_pixel``: expected unattenuated counts per *binned* pixel per view (the
    flat field). The design's "4,000 photons per 110 um pixel through 13 cm of water" is
    ``DetectorModel.from_transmitted(4000, 130.0)`` (I0 ~ 49,000). ``flat_field_sigma``:
    relative raw-pixel gain variation (fixed pattern, in flat and projections alike).
    ``flat_frames``: frames averaged into the flat field. ``saturation_counts``: raw counter
    maximum (hot pixels sit there). ``poisson=False`` gives the noiseless expectation. The
    fixed pattern (gain, dead, hot) is drawn from ``seed``; Poisson noise from the ``rng``
    passed to :func:`simulate_counts`.
    """

    photons_per_pixel: float = 4000.0
    binning: int = 2
    chip_size_px: int = 256
    chip_gap_px: int = 2
    dead_pixel_fraction: float = 1e-3
    hot_pixel_fraction: float = 2e-4
    flat_field_sigma: float = 0.03
    flat_frames: int = 20
    saturation_counts: float = 65535.0
    min_valid_fraction: float = 0.5
    poisson: bool = True
    raw_pitch_mm: float = 0.055
    seed: int = 0

    @classmethod
    def from_transmitted(cls, photons_behind: float = 4000.0, water_path_mm: float = 130.0,
                         mu_water: float = MU["water"], **kw) -> "DetectorModel":
        """A model whose flat field gives ``photons_behind`` counts behind ``water_path_mm`` of water."""
        return cls(photons_per_pixel=photons_behind * float(np.exp(mu_water * water_path_mm)), **kw)

    def raw_shape(self, binned_shape) -> tuple[int, int]:
        return (int(binned_shape[0]) * self.binning, int(binned_shape[1]) * self.binning)

    def gap_mask(self, raw_shape) -> np.ndarray:
        """True on raw pixels that fall in a gap between chips, (rows, cols)."""
        period = self.chip_size_px + self.chip_gap_px
        rows = (np.arange(raw_shape[0]) % period) >= self.chip_size_px
        cols = (np.arange(raw_shape[1]) % period) >= self.chip_size_px
        return rows[:, None] | cols[None, :]

    def pixel_maps(self, raw_shape):
        """Fixed pattern of the raw detector from ``seed``: (gain f64, dead bool, hot bool, gap bool)."""
        rng = np.random.default_rng(self.seed)
        gain = np.clip(1.0 + self.flat_field_sigma * rng.standard_normal(raw_shape), 0.05, None)
        u = rng.uniform(size=raw_shape)
        dead = u < self.dead_pixel_fraction
        hot = (u >= self.dead_pixel_fraction) & (u < self.dead_pixel_fraction + self.hot_pixel_fraction)
        return gain, dead, hot, self.gap_mask(raw_shape)

    def valid_raw(self, raw_shape) -> np.ndarray:
        _, dead, hot, gap = self.pixel_maps(raw_shape)
        return ~(dead | hot | gap)

    def valid_mask(self, raw_shape) -> np.ndarray:
        """Binned validity: at least ``min_valid_fraction`` of the bin's raw pixels are good."""
        n_ok = bin_projections(self.valid_raw(raw_shape).astype(np.int32), self.binning)
        return n_ok >= max(1.0, self.min_valid_fraction * self.binning ** 2)


def _poisson(rng, lam, noisy: bool) -> np.ndarray:
    return rng.poisson(lam).astype(np.float64) if noisy else lam


def simulate_flat(raw_shape, model: DetectorModel, rng=None):
    """Binned flat field (mean counts per frame, float32 (rows, cols)) and binned valid mask."""
    rng = _rng(model.seed + 1 if rng is None else rng)
    gain, dead, hot, gap = model.pixel_maps(raw_shape)
    ok = ~(dead | hot | gap)
    i0_raw = model.photons_per_pixel / model.binning ** 2
    F = max(1, int(model.flat_frames))
    flat_raw = _poisson(rng, F * i0_raw * gain, model.poisson) / F
    flat = bin_projections(np.where(ok, flat_raw, 0.0), model.binning).astype(np.float32)
    return flat, model.valid_mask(raw_shape) & (flat > 0)


def simulate_counts(line_integrals_raw: np.ndarray, model: DetectorModel, rng=None, flat=None,
                    return_raw: bool = False):
    """Photon counts of the raw-detector line integrals ``(n_views, rows, cols)``, binned.

    Raw counts are Poisson(I0_raw * gain * exp(-p)) (I0_raw = photons_per_pixel / binning^2),
    clipped at saturation; gap and dead pixels read 0, hot pixels read ``saturation_counts``.
    Binning sums the *valid* raw pixels only (module docstring), flat field likewise.

    Returns ``(counts, flat, valid)``: counts float32 (n_views, rows/b, cols/b) (integer
    valued when ``model.poisson``), flat float32 (rows/b, cols/b) mean counts per frame,
    valid bool (rows/b, cols/b). With ``return_raw`` also the raw counts (with the defects).
    ``flat`` may be passed (from :func:`simulate_flat`) to share one flat over several calls.
    """
    li = np.asarray(line_integrals_raw)
    if li.ndim == 2:
        li = li[None]
    rng = _rng(model.seed + 2 if rng is None else rng)
    raw_shape = li.shape[1:]
    if raw_shape[0] % model.binning or raw_shape[1] % model.binning:
        raise ValueError(f"raw detector shape {raw_shape} is not a multiple of binning {model.binning}")
    gain, dead, hot, gap = model.pixel_maps(raw_shape)
    ok = ~(dead | hot | gap)
    if flat is None:
        flat, valid = simulate_flat(raw_shape, model, rng)
    else:
        flat = np.asarray(flat, np.float32)
        valid = model.valid_mask(raw_shape) & (flat > 0)
    i0_raw = model.photons_per_pixel / model.binning ** 2
    nb = (li.shape[0], raw_shape[0] // model.binning, raw_shape[1] // model.binning)
    counts = np.empty(nb, np.float32)
    raw_out = np.empty(li.shape, np.float32) if return_raw else None
    for v in range(li.shape[0]):  # one view at a time keeps float64 temporaries small
        lam = i0_raw * gain * np.exp(-li[v].astype(np.float64))
        raw = np.minimum(_poisson(rng, lam, model.poisson), model.saturation_counts)
        if raw_out is not None:
            raw_out[v] = np.where(dead | gap, 0.0, np.where(hot, model.saturation_counts, raw))
        counts[v] = bin_projections(np.where(ok, raw, 0.0), model.binning)
    if return_raw:
        return counts, flat, valid, raw_out
    return counts, flat, valid


def counts_to_line_integrals(counts, flat, valid_mask, min_counts: float = 0.5):
    """Line integrals ``log(flat / counts)`` (float32), NaN/inf free.

    Counts are clipped below at ``min_counts`` (photon starvation); pixels outside
    ``valid_mask`` (or with a non-positive flat) are set to 0. Returns ``(line_integrals,
    mask)`` with mask the bool validity actually used, broadcast to the projection frame.
    """
    counts = np.asarray(counts, np.float32)
    flat = np.asarray(flat, np.float32)
    mask = np.asarray(valid_mask, bool) & (flat > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        li = np.log(np.where(flat > 0, flat, 1.0)) - np.log(np.maximum(counts, np.float32(min_counts)))
    li = np.where(mask, li, 0.0).astype(np.float32)
    li[~np.isfinite(li)] = 0.0
    return li, mask
