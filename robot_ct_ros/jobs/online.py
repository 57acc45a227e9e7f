"""When the recon_service starts a correction: after the scan (auto_run) and, optionally, every N
frames during it. Plain state, no ROS: the node feeds it scan/status messages and frame counts."""

from __future__ import annotations

import time
from dataclasses import dataclass

from robot_ct_ros.parameters import setting, validate

__all__ = ["RunPlanner", "JobGridSettings", "ServiceSettings"]


class RunPlanner:
    """Decides which correction to start next.

    ``auto_run``: a scan/status "done" for a scan id not corrected yet asks for a whole-scan run
    once every frame it announced has arrived (or ``wait_s`` later). ``every_n_views`` > 0: while
    the scan runs (until it is done or aborted, or a whole-scan run started), every N paired frames
    ask for a partial run.
    """

    def __init__(self, auto_run: bool, every_n_views: int, wait_s: float = 5.0, clock=time.monotonic):
        self.auto_run, self.every, self.wait_s, self.clock = bool(auto_run), int(every_n_views), wait_s, clock
        self.pending: tuple[str, int, float] | None = None  # (scan_id, frames, deadline)
        self.done_ids: set[str] = set()
        self.over_ids: set[str] = set()  # scans reported done or aborted: no partial run after them
        self.full_started = False
        self.next_partial = self.every
        self.shortfall: tuple[int, int] | None = None  # (announced, paired) of the last whole-scan run started short

    def new_scan(self) -> None:
        """A new collection started (a new /ct/scan_info)."""
        self.next_partial, self.full_started = self.every, False

    def on_status(self, status: dict) -> None:
        """A scan/status message (the scan_orchestrator's JSON, decoded)."""
        sid = str(status.get("scan_id", ""))
        if status.get("state") in ("done", "aborted"):
            self.over_ids.add(sid)
        if not self.auto_run or status.get("state") != "done":
            return
        if sid in self.done_ids or (self.pending and self.pending[0] == sid):
            return
        self.pending = (sid, int(status.get("frames", 0)), self.clock() + self.wait_s)

    def next_run(self, n_paired: int, scan_id: str) -> str | None:
        """"full", "partial" or None, given the frames paired so far (call when no run is busy)."""
        if self.pending is not None:
            sid, frames, deadline = self.pending
            if n_paired >= frames or self.clock() > deadline:
                self.pending = None
                self.done_ids.add(sid)
                self.shortfall = (frames, n_paired) if n_paired < frames else None
                return "full"
            return None
        if self.every > 0 and n_paired >= self.next_partial and not self.full_started and scan_id not in self.over_ids:
            self.next_partial = (n_paired // self.every + 1) * self.every
            return "partial"
        return None


@dataclass(frozen=True)
class JobGridSettings:
    """What a correction a node runs reconstructs on and reports, the same for the recon_service and replay: the
    grid (the command line's ``--voxel-mm`` and ``--shape``) and the error against a simulated scan's true
    geometry."""

    voxel_size_m: float = setting(0.0, "voxel size (0: scan_info's, else pitch / magnification)", unit="m",
                                  minimum=0.0, maximum=0.01)
    roi_shape: tuple = setting((0, 0, 0), "reconstruction grid nx, ny, nz (zeros: scan_info's ROI or the field of "
                               "view)", unit="voxels", minimum=0)
    evaluate_truth: bool = setting(True, "simulated scans: error against /ct/geometry_true in the report")

    def __post_init__(self):
        validate(self)
        if 0 in self.roi_shape and any(self.roi_shape):  # a zero among sizes is no grid, not "the default"
            raise ValueError(f"roi_shape must be three positive sizes, or all zeros for the scan's own grid; got "
                             f"{list(self.roi_shape)}")

    @property
    def shape_xyz(self):
        """``roi_shape``, or None for the scan's default grid."""
        return tuple(self.roi_shape) if min(self.roi_shape) > 0 else None

    @property
    def voxel_mm(self):
        """``voxel_size_m`` in mm, or None for the scan's default."""
        return self.voxel_size_m * 1e3 if self.voxel_size_m > 0 else None


@dataclass(frozen=True)
class ServiceSettings(JobGridSettings):
    """The recon_service's own parameters (the calibration's are CalibrationSettings; the grid's JobGridSettings)."""

    output_dir: str = setting("recon_out", "folder of the correction's outputs")
    auto_run: bool = setting(True, "correct when scan/status says the scan is done")
    every_n_views: int = setting(0, "also correct every N frames during the scan (0: off)", minimum=0)
    stream: bool = setting(False, "streaming correction: estimate each view as it arrives against a running "
                           "volume, in a worker process, and publish it on /ct/geometry_live (the whole-scan run "
                           "still follows)")
    stream_warmup_views: int = setting(8, "streaming: views back-projected into the first volume before any is "
                                       "estimated", minimum=1)
    stream_nice: int = setting(10, "streaming: niceness increment of the worker process (0: the node's priority)",
                               minimum=0, maximum=19)
    stream_threads: int = setting(1, "streaming: numba threads of the worker process (1 leaves the other cores to the "
                                  "scan; 0: numba's default, every core)", minimum=0, maximum=1024)
    bag_path: str = setting("", "correct this bag instead of the collected topics (empty: the topics)")
