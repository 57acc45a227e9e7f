"""Calibration reports: figures like the NCC-LLE paper's and a metrics table (Markdown + JSON).

:func:`write_report` takes the outcome of several calibration methods on one scan and
writes into ``out_dir`` (``<name>`` prefixes every file):

* ``<name>_slices.png``: zoomed ROI axial and sagittal slices, one column per method
  (e.g. "none" = nominal geometry first, "true geometry" last), one grey window for all; the
  axial row alone when the ROI is one slice thick (a fan-beam scan: no sagittal extent);
* ``<name>_rmse.png``: projection RMSE per outer iteration, one curve per method (when none ran
  an iteration, e.g. ``none`` alone, the panel says so);
* ``<name>_param_error.png`` (truth known): per-view error of the source shift, detector
  shift and detector rotation after removing the gauge (:func:`metrics.remove_gauge`);
* ``<name>.md`` and ``<name>.json``: the table from :func:`summarize`.

Metrics (all from :mod:`robot_ct_ros.ct.metrics`): gauge-aligned reprojection error of ROI
points (mean, p95, px), SSIM against the reconstruction with the true geometry, edge
sharpness, fibrous-cap thickness for a plaque phantom, the model NCC (how well the last
iteration's estimation volume reprojects to the data: the guard's first test), outer
iterations, wall time.
Figures use matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.jobs.output import write_json
from robot_ct_ros.ct.metrics import cap_thickness_mm, edge_sharpness, remove_gauge, reprojection_error, roi_points, ssim

__all__ = ["COLUMNS", "summarize", "markdown_table", "method_notes", "unguarded_error", "plot_slices", "plot_cap_slabs",
           "plot_rmse", "gauge_aligned_param_error", "plot_param_error", "write_report"]

COLUMNS = (
    ("method", "method", "{}"),
    ("reproj_mean_px", "reproj. error mean (px)", "{:.3f}"),
    ("reproj_p95_px", "reproj. error p95 (px)", "{:.3f}"),
    ("unguarded_mean_px", "before the guard, mean (px)", "{:.3f}"),
    ("ssim", "SSIM vs true-geom. recon", "{:.4f}"),
    ("sharpness", "edge sharpness", "{:.4f}"),
    ("cap_um", "cap thickness (um)", "{:.1f}"),
    ("model_ncc", "model NCC", "{:.3f}"),
    ("iterations", "iterations", "{}"),
    ("wall_s", "wall time (s)", "{:.1f}"),
)


def _unpack(result):
    """(geom, volume, history, wall_s) from a CalibrationResult or a (geom, volume, history[, wall_s]) tuple."""
    if hasattr(result, "geom") and hasattr(result, "volume"):
        return result.geom, result.volume, tuple(getattr(result, "history", ()) or ()), getattr(result, "wall_s", None)
    items = tuple(result)
    if len(items) not in (3, 4):
        raise ValueError("a result is a CalibrationResult or (geom, volume, history[, wall_s])")
    geom, volume, history = items[:3]
    return geom, volume, tuple(history or ()), (items[3] if len(items) == 4 else None)


def _history(history, key: str = "projection_rmse") -> list[float]:
    """One field of each iteration's record (an IterationRecord or its dict), NaN where missing."""
    out = []
    for h in history:
        v = h.get(key) if isinstance(h, dict) else getattr(h, key, None)
        out.append(float("nan") if v is None else float(v))
    return out


def _finite_or_none(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def summarize(results: dict, grid: VolumeGrid, truth=None, points_mm=None, reconstruct=None,
              reconstruct_cap=None, nominal: ConeGeometry | None = None) -> list[dict]:
    """One row per method: the metrics of the table (None where a metric does not apply).

    ``truth`` = (true geometry, volume reconstructed with it, phantom or None); without it only
    sharpness, iterations and wall time are filled. ``points_mm`` for the reprojection error
    default to :func:`metrics.roi_points` of ``grid``. With ``reconstruct(geom) -> volume``
    the SSIM compares the reconstruction with each estimate moved into the true gauge
    (:func:`metrics.remove_gauge`): calibration cannot know where the object is, only its
    shape, and a voxel of global offset would otherwise dominate the SSIM. A row whose
    geometry is the true one keeps its own volume.

    The cap thickness (a plaque phantom) is measured in that gauge-aligned reconstruction
    (without ``reconstruct``, in the volume as given), or, with
    ``reconstruct_cap(geom, method) -> (volume, grid)``, in a reconstruction made for it alone
    from the gauge-aligned geometry (``method``: the row's key in ``results``, for a caller that
    keeps the volumes): typically a fine grid around the cap from the unbinned
    detector, as a cap thinner than the calibration's binned pixels needs.

    With ``truth`` and the ``nominal`` geometry the calibrations started from, a result whose guard
    changed anything (``params_unguarded``) also gets the mean reprojection error its estimate had
    before the guard (``unguarded_mean_px``): what the guard refused.
    """
    true_geom, true_vol, phantom = (tuple(truth) + (None,) * 3)[:3] if truth is not None else (None, None, None)
    pts = roi_points(grid) if points_mm is None else np.asarray(points_mm, float)
    cap = getattr(phantom, "cap", None)
    rows = []
    for method, result in results.items():
        geom, volume, history, wall = _unpack(result)
        row = {"method": str(method), "reproj_mean_px": None, "reproj_p95_px": None, "ssim": None,
               "unguarded_mean_px": None, "sharpness": _finite_or_none(edge_sharpness(volume)), "cap_um": None,
               "iterations": len(history), "wall_s": _finite_or_none(wall),
               "projection_rmse": _history(history), "projection_ncc": _history(history, "projection_ncc"),
               "model_ncc": _finite_or_none(_history(history, "projection_ncc")[-1]) if history else None}
        if true_geom is not None:
            err = reprojection_error(geom, true_geom, pts)
            row["reproj_mean_px"], row["reproj_p95_px"] = err["mean_px"], err["p95_px"]
            before = unguarded_error(result, nominal, true_geom, pts) if nominal is not None else None
            row["unguarded_mean_px"] = None if before is None else before["mean_px"]
        aligned_geom, aligned = geom, volume
        if true_geom is not None and not geom.allclose(true_geom, atol=1e-9):
            # (the true geometry itself needs no move, and no second reconstruction)
            aligned_geom = remove_gauge(geom, true_geom, pts)
            if reconstruct is not None:
                aligned = reconstruct(aligned_geom)
        if true_vol is not None:
            row["ssim"] = _finite_or_none(ssim(aligned, true_vol))
        if cap is not None:
            cap_vol, cap_grid = (aligned, grid) if reconstruct_cap is None else reconstruct_cap(aligned_geom, method)
            row["cap_um"] = _finite_or_none(1000.0 * cap_thickness_mm(cap_vol, cap_grid, cap))
        rows.append(row)
    return rows


def markdown_table(rows: list[dict], columns=COLUMNS) -> str:
    """The rows as a GitHub Markdown table ("-" where a metric does not apply)."""
    cols = [c for c in columns if c[0] == "method" or any(r.get(c[0]) is not None for r in rows)]
    lines = ["| " + " | ".join(c[1] for c in cols) + " |", "| " + " | ".join("---" for _ in cols) + " |"]
    for r in rows:
        cells = []
        for key, _, fmt in cols:
            v = r.get(key)
            cells.append("-" if v is None else fmt.format(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- figures
def unguarded_error(result, nominal: ConeGeometry, true_geom: ConeGeometry, points_mm) -> dict | None:
    """The reprojection error (metrics.reprojection_error) of a calibration's estimate before its guard
    changed anything (``params_unguarded`` relative to ``nominal``), or None where the guard changed nothing."""
    unguarded = getattr(result, "params_unguarded", None)
    return None if unguarded is None else reprojection_error(nominal.perturbed(unguarded), true_geom, points_mm)


def method_notes(results: dict, nominal: ConeGeometry, true_geom: ConeGeometry, points_mm) -> dict:
    """Each calibrated method's notes (the guard's verdict, skipped views, models used), and where the
    guard kept views at their nominal geometry, the error of the estimate before it, against
    ``true_geom`` on ``points_mm`` (None: a measured scan, no such error): {method: [note, ...]} for the methods
    that have any."""
    notes = {}
    for method, result in results.items():
        lines = list(getattr(result, "notes", ()))
        e = None if true_geom is None else unguarded_error(result, nominal, true_geom, points_mm)
        if e is not None:
            lines.append(f"before the guard {e['mean_px']:.3f} px mean, {e['p95_px']:.3f} px p95")
        if lines:
            notes[method] = lines
    return notes


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _slices(volume, grid: VolumeGrid, center_mm, half_mm):
    """Zoomed axial (y, x at the centre z) and sagittal (z, y at the centre x) slices and their extents."""
    vol = np.asarray(volume, np.float32)
    ax = grid.axes_mm()
    c = grid.direction_matrix.T @ np.asarray(center_mm, float)  # the grid's own frame, as axes_mm
    idx = [int(np.clip(np.argmin(np.abs(ax[a] - c[a])), 0, len(ax[a]) - 1)) for a in range(3)]
    sel = [np.flatnonzero(np.abs(ax[a] - c[a]) <= half_mm[a] + 1e-9) for a in range(3)]
    sel = [s if s.size else np.arange(len(ax[a])) for a, s in enumerate(sel)]
    axial = vol[idx[2]][np.ix_(sel[1], sel[0])]
    sagittal = vol[:, :, idx[0]][np.ix_(sel[2], sel[1])]
    h = 0.5 * np.asarray(grid.voxel_size_mm, float)  # extents run over the voxels' edges (one voxel: not empty)
    ext_ax = (ax[0][sel[0][0]] - h[0], ax[0][sel[0][-1]] + h[0], ax[1][sel[1][-1]] + h[1], ax[1][sel[1][0]] - h[1])
    ext_sag = (ax[1][sel[1][0]] - h[1], ax[1][sel[1][-1]] + h[1], ax[2][sel[2][-1]] + h[2], ax[2][sel[2][0]] - h[2])
    return axial, sagittal, ext_ax, ext_sag


def plot_slices(path, results: dict, grid: VolumeGrid, *, center_mm=None, zoom: float = 0.6, reference=None,
                title: str = "") -> Path:
    """Axial (top) and sagittal (bottom) zoomed ROI slices, one column per method; the axial row alone
    when the sagittal slice would be one voxel tall (a one-slice grid: it showed a blank panel)."""
    plt = _plt()
    center = grid.center_mm if center_mm is None else np.asarray(center_mm, float)
    half = 0.5 * zoom * grid.extent_mm
    vols = {m: np.asarray(_unpack(r)[1]) for m, r in results.items()}
    ref = vols[next(iter(vols))] if reference is None else np.asarray(reference)
    a0, s0, _, _ = _slices(ref, grid, center, half)
    sagittal = s0.shape[0] > 1
    both = np.concatenate([a0.ravel(), s0.ravel()]) if sagittal else a0.ravel()
    lo, hi = np.percentile(both, [0.5, 99.5])
    n, rows = len(vols), 2 if sagittal else 1
    fig, axes = plt.subplots(rows, n, figsize=(2.3 * n + 0.4, 4.9 if sagittal else 2.7), squeeze=False)
    for k, (m, v) in enumerate(vols.items()):
        a, s, ea, es = _slices(v, grid, center, half)
        axes[0, k].imshow(a, cmap="gray", vmin=lo, vmax=hi, extent=ea, interpolation="nearest")
        if sagittal:
            axes[1, k].imshow(s, cmap="gray", vmin=lo, vmax=hi, extent=es, interpolation="nearest", aspect="auto")
        axes[0, k].set_title(m, fontsize=9)
        for r in range(rows):
            axes[r, k].set_xticks([])
            axes[r, k].set_yticks([])
    axes[0, 0].set_ylabel("axial (x-y)" if sagittal else "axial (x-y), one slice", fontsize=9)
    if sagittal:
        axes[1, 0].set_ylabel("sagittal (y-z)", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_cap_slabs(path, volumes: dict, grid: VolumeGrid, cap, *, reference=None, title: str = "") -> Path:
    """Axial slabs around a fibrous cap, one per method: each volume averaged along z (the
    vessel axis of :class:`~robot_ct_ros.ct.simulation.CapGeometry`), as
    :func:`metrics.cap_thickness_mm` averages its lines (a single fine slice is mostly noise);
    one grey window (``reference``'s, default the first); the measured profile line in red."""
    plt = _plt()
    slabs = {m: np.asarray(v, np.float32).mean(axis=0) for m, v in volumes.items()}
    ref = next(iter(slabs.values())) if reference is None else np.asarray(reference, np.float32).mean(axis=0)
    lo, hi = np.percentile(ref, [1, 99])
    x, y = grid.axes_mm()[:2]
    d = np.asarray(cap.direction)
    p0 = np.asarray(cap.lumen_point_mm) - 0.6 * d
    p1 = np.asarray(cap.lumen_point_mm) + (cap.thickness_mm + 0.5 * cap.core_depth_mm) * d
    fig, axes = plt.subplots(1, len(slabs), figsize=(2.3 * len(slabs) + 0.4, 2.9), squeeze=False)
    for ax, (m, img) in zip(axes[0], slabs.items()):
        ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, extent=(x[0], x[-1], y[-1], y[0]), interpolation="nearest")
        ax.plot([p0[0], p1[0]], [p0[1], p1[1]], "r-", lw=0.6)
        ax.set_title(m, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _save(fig, path) -> Path:
    """Lay out, write (110 dpi PNG) and close a figure."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return Path(path)


def _color(k: int):
    return f"C{k % 10}"


def _wrap(title: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(title, width)) if title else ""


def plot_rmse(path, results: dict, *, initial_rmse: float | None = None, title: str = "") -> Path:
    """Projection RMSE after each outer iteration, per method (iteration 0 = nominal, if given); when no
    method ran an iteration (``none`` alone, or only fixed geometries), the panel says so (it was empty). A method
    whose guard changed its estimate (kept the nominal geometry for some views or all) is labelled so: the
    iterations plotted are the estimate's, not the result's."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.4, 3.9))
    for k, (m, r) in enumerate(results.items()):
        rmse = _history(_unpack(r)[2])
        if not rmse:
            continue
        x = np.arange(1, len(rmse) + 1)
        if initial_rmse is not None:
            x, rmse = np.concatenate([[0], x]), [initial_rmse] + rmse
        guarded = getattr(r, "params_unguarded", None) is not None  # its iterations: the estimate's, not the result's
        ax.plot(x, rmse, "o-", color=_color(k), label=f"{m} (estimate: the guard changed it)" if guarded else m)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_xlabel("outer iteration (0 = nominal geometry)" if initial_rmse is not None else "outer iteration")
    ax.set_ylabel("projection RMSE (masked)")
    ax.grid(alpha=0.3)
    if not ax.lines:
        ax.text(0.5, 0.5, "no outer iterations to plot:\nno calibration method ran one"
                + ("" if initial_rmse is None else f"\n(nominal geometry: projection RMSE {initial_rmse:.4g})"),
                ha="center", va="center", transform=ax.transAxes, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    if title:
        ax.set_title(_wrap(title, 60), fontsize=9)
    return _save(fig, path)


def gauge_aligned_param_error(geom: ConeGeometry, true_geom: ConeGeometry, points_mm) -> np.ndarray:
    """(n, 9) parameters taking the true geometry to the estimate after removing the gauge."""
    return remove_gauge(geom, true_geom, points_mm).params_relative_to(true_geom)


def plot_param_error(path, results: dict, true_geom: ConeGeometry, points_mm, *, title: str = "") -> Path:
    """Per-view error (gauge removed) of source shift |s| (mm), detector shift |d| (mm), rotation (deg)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(12.0, 3.4))
    for q, (m, r) in enumerate(results.items()):
        e = gauge_aligned_param_error(_unpack(r)[0], true_geom, points_mm)
        x = np.arange(e.shape[0])
        for k, (sl, scale) in enumerate(((slice(0, 3), 1.0), (slice(3, 6), 1.0), (slice(6, 9), 180 / np.pi))):
            axes[k].plot(x, np.linalg.norm(e[:, sl], axis=1) * scale, ".-", ms=3, lw=0.8, color=_color(q),
                         label=m)
    for k, lab in enumerate(("source shift error (mm)", "detector shift error (mm)", "detector rotation error (deg)")):
        axes[k].set_xlabel("view")
        axes[k].set_ylabel(lab)
        axes[k].grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


# ----------------------------------------------------------------------------- report
def write_report(out_dir, results: dict, grid: VolumeGrid, truth=None, nominal: ConeGeometry | None = None, *,
                 name: str = "report", title: str = "", points_mm=None, slice_center_mm=None, zoom: float = 0.6,
                 initial_rmse: float | None = None, notes: dict | None = None, reconstruct=None,
                 reconstruct_cap=None, figures: bool = True, notes_per_method: dict | None = None) -> dict:
    """Write the figures and the table of one scan's calibration results; returns their paths.

    ``results`` maps method name to a :class:`~robot_ct_ros.ct.calibration.CalibrationResult`
    or a ``(geom, volume, history[, wall_s])`` tuple, in the column order of the figures.
    ``truth`` = (true geometry, reconstruction with it, phantom or None). ``nominal``: if
    given and no "none" entry exists, the nominal geometry is added to the parameter-error
    plot as "none"; with ``truth`` the table also gives the error before the guard
    (:func:`summarize`). ``initial_rmse`` is plotted at iteration 0. ``notes`` go into the JSON.
    ``reconstruct``, ``reconstruct_cap``: see :func:`summarize`. ``figures`` False: the table alone.
    ``notes_per_method`` ({method: [note, ...]}, :func:`method_notes`) go below the table and into the JSON.
    Returned dict: paths under keys "slices", "rmse", "param_error" (truth known; with figures),
    "markdown", "json", and the table "rows".
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pts = roi_points(grid) if points_mm is None else np.asarray(points_mm, float)
    rows = summarize(results, grid, truth, pts, reconstruct=reconstruct, reconstruct_cap=reconstruct_cap,
                     nominal=nominal)
    true_geom, true_vol = (truth[0], truth[1]) if truth is not None else (None, None)
    paths = {"rows": rows}
    if figures:
        paths["slices"] = plot_slices(out / f"{name}_slices.png", results, grid, center_mm=slice_center_mm, zoom=zoom,
                                      reference=true_vol, title=title)
        paths["rmse"] = plot_rmse(out / f"{name}_rmse.png", results, initial_rmse=initial_rmse, title=title)
    if figures and true_geom is not None:
        geoms = dict(results)
        if nominal is not None and "none" not in geoms:
            geoms = {"none": (nominal, np.zeros(grid.shape_zyx, np.float32), ())} | geoms
        paths["param_error"] = plot_param_error(out / f"{name}_param_error.png", geoms, true_geom, pts, title=title)
    md = (f"## {title or name}\n\n" + markdown_table(rows) + "\n"
          + "".join(f"- {m}: {'; '.join(lines)}\n" for m, lines in (notes_per_method or {}).items())
          + ("\n" if notes_per_method else "")
          + "".join(f"![{k}]({Path(paths[k]).name})\n" for k in ("slices", "rmse", "param_error") if k in paths))
    paths["markdown"] = out / f"{name}.md"
    paths["markdown"].write_text(md)
    paths["json"] = out / f"{name}.json"
    write_json(paths["json"], {"name": name, "title": title, "rows": rows, "notes": notes or {},
                               "method_notes": notes_per_method or {}})
    return paths
