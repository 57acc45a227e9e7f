"""What every job writes the same way: strict JSON, volumes, progress lines."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["say", "json_default", "clean_json", "write_json", "write_volume"]


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
    """Write ``obj`` as indented strict JSON; returns the path."""
    path = Path(path)
    path.write_text(json.dumps(clean_json(obj), indent=2, default=json_default))
    return path


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
