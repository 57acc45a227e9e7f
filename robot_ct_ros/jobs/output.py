"""What every job writes the same way: strict JSON, volumes, progress lines."""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

__all__ = ["say", "fdk_warnings", "refuse_out_in_bag", "refuse_other_job", "json_default", "clean_json", "write_json",
           "write_volume", "write_ome_tiff", "prepare_out", "available_memory_bytes", "check_memory", "MEMORY_FACTORS",
           "GRID_OPTIONS"]

MEMORY_FACTORS = {"reconstruct": (2.0, 3.0), "calibrate": (16.0, 8.0), "report": (26.0, 8.0)}
"""Rough peak memory of each job, as (volumes, projection stacks): FDK holds its volume and its copy for
the files, the line integrals, their mask and the filtered projections; the calibration also holds its
padded estimation volumes (FDK, SIRT) and reprojections; the comparison also keeps every method's volume and
its figures, :data:`REPORT_VOLUMES_PER_METHOD` more per method. The factors are peaks measured (resident memory
on grids inside the field of view, by an outside check), rounded up: smaller ones passed grids that did not fit."""
REPORT_VOLUMES_PER_METHOD = 2.0

GRID_OPTIONS = {"command line": ("--shape {},{},{}", "--voxel-mm {:.4g}", 1.0),
                "ROS parameters": ("roi_shape:=[{},{},{}]", "voxel_size_m:={:.4g}", 1e-3)}
"""How a user sets the grid, by where the job was started (the command line, or the recon_service's and
replay's parameters): (shape, voxel size, voxel unit per mm), the hints of :func:`check_memory`'s refusal."""


def prepare_out(out, *, must_not_exist: bool = False, what: str = "--out") -> Path:
    """The output folder ``out`` made absolute, created and checked writable before any work is done;
    ``what`` names it in the messages (the command-line option, or a node's parameter).

    Raises
    ------
    ValueError
        ``out`` names a file, cannot be created (read-only place, missing permission), is not
        writable, or (``must_not_exist``) exists already; the message says which.
    """
    import os
    import tempfile

    path = Path(out).expanduser().absolute()
    if must_not_exist and path.exists():
        raise ValueError(f"{out} exists already; it is never overwritten")
    if path.exists() and not path.is_dir():
        raise ValueError(f"{what} {out} is a file, not a folder")
    parent = path if must_not_exist is False else path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ValueError(f"cannot create {out}: a part of the path is a file") from None
    except OSError as exc:
        raise ValueError(f"cannot create {out}: {exc.strerror or exc}") from None
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise ValueError(f"cannot write into {parent}: {exc.strerror or exc}") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write into {parent}: permission denied")
    return path


def available_memory_bytes() -> int:
    """Memory available to a new allocation without swapping (Linux: MemAvailable), else the free pages."""
    import os

    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: never refuse


def _gib(n: float) -> str:
    return f"{n / 2 ** 30:.1f} GiB" if n >= 2 ** 29 else f"{n / 2 ** 20:.0f} MiB"


def check_memory(grid, n_views: int, det_shape, job: str, available: int | None = None, *,
                 options: str = "command line", methods: int = 1, shape_given: bool = False) -> int:
    """Refuse, before anything is allocated, a job whose grid and projections cannot fit in memory.

    Returns the estimate in bytes. Raises ValueError naming the estimate, what is available, and
    the largest grid (same aspect) or the voxel size that would fit, written as the settings of
    ``options`` (a key of :data:`GRID_OPTIONS`). ``methods``: the report's number of methods compared.
    ``shape_given``: the grid's shape was set, so a voxel size alone would not change it (no such hint).
    """
    kv, kp = MEMORY_FACTORS[job]
    if job == "report":
        kv += REPORT_VOLUMES_PER_METHOD * max(0, int(methods) - 1)
    nz, ny, nx = (int(v) for v in grid.shape_zyx)
    vol = 4.0 * nx * ny * nz
    proj = 4.0 * int(n_views) * int(det_shape[0]) * int(det_shape[1])
    need = kv * vol + kp * proj
    avail = available_memory_bytes() if available is None else int(available)
    if need <= avail:
        return int(need)
    room = avail - kp * proj
    if room <= 0:
        raise ValueError(f"not enough memory: the {n_views} projections alone need about {_gib(kp * proj)} for "
                         f"{job}, {_gib(avail)} are available")
    scale = (room / (kv * vol)) ** (1.0 / 3.0)
    fit = [max(1, int(n * scale)) for n in (nx, ny, nz)]
    voxel = [float(v) / scale for v in grid.voxel_size_mm]
    shape_hint, voxel_hint, per_mm = GRID_OPTIONS[options]
    voxel_text = "" if shape_given else f", or the same field of view with {voxel_hint.format(max(voxel) * per_mm)}"
    raise ValueError(f"not enough memory: a {nx} x {ny} x {nz} grid needs about {_gib(need)} for {job} "
                     f"({_gib(vol)} per volume), {_gib(avail)} are available; at most about "
                     f"{shape_hint.format(*fit)} would fit{voxel_text}")


@contextmanager
def fdk_warnings(say_=None):
    """``with fdk_warnings(say) as seen:`` collects the :class:`~robot_ct_ros.ct.reconstruction.FDKWarning` raised
    inside (what FDK only approximates on this geometry), each kind once (the first; messages that differ in their
    figures only, one per iteration's geometry, are one kind), in ``seen`` and said as
    ``warning: ...``: the reports keep them, where the command line ignores numpy's RuntimeWarnings.
    Python's warning filters are the process's: while the block runs, warnings other threads raise are held and
    go on when it ends; those raised in Dask worker processes (``scheduler``) do not reach it."""
    from robot_ct_ros.ct.scan_weights import FDKWarning

    seen: list[str] = []
    log: list = []
    try:
        with warnings.catch_warnings(record=True) as log:
            warnings.simplefilter("always", FDKWarning)
            yield seen
    finally:
        kinds = set()
        for w in log:
            if not issubclass(w.category, FDKWarning):  # goes on, through the filters in force, as if not caught
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
                continue
            text = str(w.message)
            kind = re.sub(r"\d+(\.\d+)?", "#", text)
            if kind not in kinds:
                kinds.add(kind)
                seen.append(text)
                if say_ is not None:
                    say_(f"warning: {text}")


def say(message: str) -> None:
    """The default progress printer of the jobs (one line, flushed)."""
    print(f"[robot-ct] {message}", flush=True)


def json_default(o):
    """JSON for what the jobs' reports hold besides plain types: numpy values and arrays, paths."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def clean_json(obj):
    """``obj`` with every non-finite float replaced by None (strict JSON has no NaN)."""
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean_json(v) for v in obj]
    return obj


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented strict JSON, whole or not at all (a temporary file renamed); returns the path."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(clean_json(obj), indent=2, default=json_default))
    os.replace(tmp, path)
    return path


REPORT_FILES = ("report.json", "report.md")
"""A job's report, written after every other output: a folder without report.json holds an unfinished run."""


def refuse_out_in_bag(out, bag, what: str = "the input bag", suffix: str = "give a folder outside it") -> None:
    """Refuse an ``out`` that is the bag's file or lies in its folder (a bag folder, or the folder of an .mcap file
    with its metadata.yaml): the job would write into the scan it reads."""
    out_r, bag_r = Path(out).resolve(), Path(bag).resolve()  # through links, which may point into the bag
    folder = bag_r if bag_r.is_dir() else bag_r.parent if (bag_r.parent / "metadata.yaml").is_file() else None
    if out_r == bag_r or (folder is not None and (out_r == folder or folder in out_r.parents)):
        raise ValueError(f"--out {out} lies in {what} {bag}: writing it would overwrite the bag; {suffix}")


def report_job(report: dict) -> str | None:
    """Which job wrote a report.json: its ``job`` (calibrate, reconstruct), ``report`` for the comparison report
    (its table ``rows``), None when it is none of ours."""
    if not isinstance(report, dict):
        return None
    return report.get("job") or ("report" if "rows" in report else None)


def refuse_other_job(out, job: str, option: str = "--out") -> None:
    """A folder holds one job's results: refuse ``out`` where report.json is another job's (``calibrate``,
    ``reconstruct``, ``report``). Their files would mix: a report replacing a calibration's report.json, the
    corrected bag and volume left without the report that describes them, a report's figures beside a calibration.
    ``option``: what the user sets the folder with, named in the refusal."""
    previous = Path(out) / "report.json"
    if not previous.is_file():
        return
    try:
        earlier = report_job(json.loads(previous.read_text()))
    except ValueError:
        return
    if earlier is not None and earlier != job:
        raise ValueError(f"{out} holds the results of robot-ct {earlier}; give {job} its own {option} folder")


def start_output(out) -> Path:
    """Make the folder ``out`` and remove the reports a previous run left there, before a job rewrites its other
    files: interrupted or failed, the job then leaves no report.json that would vouch for a mix of two runs."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name in REPORT_FILES:
        (out / name).unlink(missing_ok=True)
    return out


def write_volume(volume: np.ndarray, grid, out, stem: str = "volume") -> list[str]:
    """``<stem>.npy`` and ``<stem>.tif`` (float32 z-stack, ImageJ spacing in mm) plus ``<stem>_grid.json``
    (the :class:`~robot_ct_ros.ct.geometry.VolumeGrid`) in ``out``; returns the three paths."""
    import tifffile

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    vol = np.ascontiguousarray(volume, dtype=np.float32)
    np.save(out / f"{stem}.npy", vol)
    vx, vy, vz = grid.voxel_size_mm
    tifffile.imwrite(out / f"{stem}.tif", vol, imagej=True, resolution=(1.0 / vx, 1.0 / vy),
                     metadata={"spacing": vz, "unit": "mm", "axes": "ZYX"})
    write_json(out / f"{stem}_grid.json", grid.to_dict())
    return [str(out / f"{stem}.npy"), str(out / f"{stem}.tif"), str(out / f"{stem}_grid.json")]


def write_ome_tiff(volume, grid, path, *, tile: tuple[int, int] = (256, 256), compression=None) -> Path:
    """Write a float32 volume on ``grid`` as a tiled BigTIFF OME-TIFF (axes ZYX, voxel size in mm), slab by slab.

    ``volume`` is the (nz, ny, nx) array, or an iterable of consecutive z slabs (k, ny, nx) that
    add up to ``grid.shape_zyx`` (e.g. back-projected one after another). The tiles are taken from
    one slab at a time and written as they come: no second copy of the volume is made (a slab that
    is not float32 is converted on its own), and a volume that is never whole in memory can be
    written as it is computed. Viewers (Fiji/Bio-Formats, napari, QuPath) read tiles on demand.
    ``tile`` (rows, cols) must be multiples of 16; ``compression`` is tifffile's (None, "zlib", ...).
    Returns the path.

    Raises
    ------
    ValueError
        The slabs do not add up to the grid's shape, or a slab's plane is not ``(ny, nx)``.
    """
    import tifffile

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    nz, ny, nx = (int(n) for n in grid.shape_zyx)
    th, tw = (int(t) for t in tile)
    slabs = [volume] if isinstance(volume, np.ndarray) else volume
    written = [0]

    def tiles():
        for slab in slabs:
            slab = np.asarray(slab)
            if slab.ndim != 3 or slab.shape[1:] != (ny, nx):
                raise ValueError(f"a slab of shape {slab.shape} does not fit the grid's planes ({ny}, {nx})")
            written[0] += slab.shape[0]  # counted first: the writer stops drawing after the last tile
            if written[0] > nz:
                raise ValueError(f"the slabs hold more than the grid's {nz} planes")
            for k in range(slab.shape[0]):
                plane = slab[k].astype(np.float32, copy=False)
                for y0 in range(0, ny, th):
                    for x0 in range(0, nx, tw):
                        yield np.ascontiguousarray(plane[y0:y0 + th, x0:x0 + tw])

    vx, vy, vz = (float(v) for v in grid.voxel_size_mm)
    metadata = {"axes": "ZYX", "PhysicalSizeX": vx, "PhysicalSizeXUnit": "mm", "PhysicalSizeY": vy,
                "PhysicalSizeYUnit": "mm", "PhysicalSizeZ": vz, "PhysicalSizeZUnit": "mm"}
    try:
        with tifffile.TiffWriter(path, bigtiff=True, ome=True) as tif:
            tif.write(tiles(), shape=(nz, ny, nx), dtype=np.float32, tile=(th, tw), compression=compression,
                      metadata=metadata)
    except (StopIteration, RuntimeError, ValueError) as exc:
        if written[0] == nz:
            raise
        raise ValueError(f"the slabs hold {written[0]} planes, the grid {nz}") from exc
    if written[0] != nz:
        raise ValueError(f"the slabs hold {written[0]} planes, the grid {nz}")
    return path
