"""Where the loop's heavy steps run: in this process (the default), or as Dask tasks on a cluster.

Per-view estimation is independent given the volume (every view draws its samples from its own
generator and nothing couples the views: :func:`~robot_ct_ros.ct.calibration.lle.estimator.estimate_views`),
and FDK back-projection splits into slabs of the grid's z planes. An executor runs both:

* :class:`InProcess` calls the estimator and :func:`~robot_ct_ros.ct.reconstruction.fdk` here,
  on numba's threads. It imports no dask, and needs none installed.
* :class:`DaskExecutor` (``dask.distributed``, imported only when it is made) estimates blocks
  of views as tasks and back-projects slabs as tasks. The volume is sent once per estimation
  pass (``client.scatter(..., broadcast=True)``), the filtered projections once per FDK; the
  measured projections once per level while the same arrays come back (a cache keyed by the
  array), and with every task only its views' geometry, parameters and ROI support.

Blocks are whole multiples of the estimator's ``chunk_views``, and the per-view values of the
blocks' ``info`` are joined and summarised as one pass would
(:func:`~robot_ct_ros.ct.calibration.masks.summarise_views`), skipped views by their index in
the whole scan: the result is the in-process one. How to point it at a cluster, and what it sends:
docs/distributed.md.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

import numpy as np

from robot_ct_ros.ct.calibration.masks import roi_support_mask, summarise_views
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid

__all__ = ["InProcess", "DaskExecutor", "DaskUnavailable", "SchedulerUnreachable", "ClusterLost", "executor_for", "check_scheduler",
           "connect_timeout_s", "view_blocks", "slab_bounds", "join_infos", "transfer_bytes", "LOCAL"]

LOCAL = "local"
"""The ``scheduler`` setting that starts a ``LocalCluster`` of worker processes on this machine."""


class DaskUnavailable(ValueError):
    """A scheduler was asked for, but dask.distributed is not installed."""


class SchedulerUnreachable(ValueError):
    """A scheduler address that does not answer as a Dask scheduler (nothing listens, another service such as an
    HTTP server or the dashboard's port, a worker's address) or not within Dask's connect timeout, or a scheduler
    that no worker joins within that timeout."""


class ClusterLost(ValueError):
    """The Dask cluster lost what a run had sent it (a worker or the scheduler stopped mid-run): the data
    scattered to it cannot be recovered, and the run stops; nothing of it is written."""


def connect_timeout_s() -> float:
    """Dask's ``distributed.comm.timeouts.connect`` (30 s unless configured; the environment variable
    ``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT`` sets it), in seconds: how long a scheduler address may take
    to answer."""
    import dask
    from dask.utils import parse_timedelta

    return float(parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"), "s"))


def check_scheduler(distributed, address: str, timeout_s: float) -> None:
    """Ask ``address`` who it is (Dask's ``identity`` call), within ``timeout_s`` for the connection and the
    answer together. ``distributed.Client`` times out only the connection: a server that accepts and never
    answers held it forever, and an HTTP server's reply was read as the length of a message (an allocation of
    exabytes). Raises :class:`SchedulerUnreachable` with the reason."""
    import asyncio

    hint = "give the scheduler's port (8786 by default), not its dashboard's (8787) or another service's"

    async def identity():
        args = distributed.Security().get_connection_args("client")
        async with distributed.rpc(address, timeout=timeout_s, connection_args=args) as scheduler:
            return await scheduler.identity()
    try:
        info = asyncio.run(asyncio.wait_for(identity(), 2 * timeout_s))  # Dask's own timeouts say more, first
    except TimeoutError as exc:
        raise SchedulerUnreachable(f"scheduler {address}: no answer as a Dask scheduler within {2 * timeout_s:g} s "
                                   f"({str(exc) or 'it accepted the connection, nothing came back'}; twice Dask's "
                                   f"distributed.comm.timeouts.connect, {timeout_s:g} s); {hint}") from None
    except OSError as exc:  # refused, unreachable, the address unknown
        raise SchedulerUnreachable(f"scheduler {address}: cannot reach it: {exc}; {hint}") from None
    except Exception as exc:  # noqa: BLE001 - an answer in another protocol (e.g. HTTP) fails in any way
        raise SchedulerUnreachable(f"scheduler {address}: does not answer as a Dask scheduler (its answer is not "
                                   f"Dask's protocol: {type(exc).__name__}: {str(exc)[:120]}); {hint}") from None
    kind = info.get("type") if isinstance(info, dict) else None
    if kind != "Scheduler":
        kind = str(kind).lower() if kind else "peer of unknown type"
        raise SchedulerUnreachable(f"scheduler {address}: answers as a Dask {kind}, not as a scheduler; {hint}")


class InProcess:
    """Estimation and FDK in this process (numba threads): the default, no cluster, no dask."""

    description = "in-process"

    def estimate(self, estimate, measured, nominal: ConeGeometry, params, volume, grid: VolumeGrid, config,
                 valid_mask):
        """``estimate(measured, nominal, params, volume, grid, config, valid_mask)`` (a registry estimator)."""
        return estimate(measured, nominal, params, volume, grid, config, valid_mask)

    def fdk(self, line_integrals, geom: ConeGeometry, grid: VolumeGrid, **kwargs) -> np.ndarray:
        """:func:`~robot_ct_ros.ct.reconstruction.fdk` with these arguments."""
        from robot_ct_ros.ct.reconstruction import fdk

        return fdk(line_integrals, geom, grid, **kwargs)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def executor_for(settings) -> "InProcess | DaskExecutor":
    """The executor a :class:`~robot_ct_ros.ct.calibration.settings.CalibrationSettings` asks for:
    in-process for ``scheduler=""``, else a :class:`DaskExecutor` on that scheduler (``"local"``:
    a ``LocalCluster`` of ``dask_workers`` processes with ``dask_threads`` numba threads each)."""
    if not settings.scheduler:
        return InProcess()
    return DaskExecutor(settings.scheduler, workers=settings.dask_workers, threads=settings.dask_threads)


@contextlib.contextmanager
def _workers_ignore_sigint():
    """Start the local cluster's processes with SIGINT ignored (Python then installs no KeyboardInterrupt handler in
    them), so that Ctrl-C, which the terminal sends to every process of the group, reaches only this one: it closes
    the cluster in order. Each worker printed its own traceback first, and the cluster's atexit hook another."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise DaskUnavailable("a Dask scheduler was asked for (scheduler / --scheduler), but dask.distributed is not "
                              "installed: pip install dask distributed (or leave scheduler empty: in-process)") from exc
    return distributed


def view_blocks(n_views: int, chunk_views: int, n_blocks: int) -> list:
    """(start, stop) of at most ``n_blocks`` consecutive blocks of views, each a whole number of
    ``chunk_views`` chunks (the last one the rest), as even as that allows."""
    chunk = max(1, int(chunk_views))
    n_chunks = -(-n_views // chunk)
    k = max(1, min(int(n_blocks), n_chunks))
    edges = [min(n_views, (n_chunks * i // k) * chunk) for i in range(k + 1)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def slab_bounds(nz: int, n_slabs: int) -> list:
    """(z0, z1) of at most ``n_slabs`` slabs of ``nz`` planes, as even as possible."""
    k = max(1, min(int(n_slabs), nz))
    edges = [nz * i // k for i in range(k + 1)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def join_infos(infos: list, blocks: list) -> dict:
    """One ``info`` from those of consecutive blocks of views: per-view values joined step by step and
    summarised (:func:`~robot_ct_ros.ct.calibration.masks.summarise_views`), ``skipped_views`` (already
    indices in the whole scan) joined, the other entries the first block's."""
    out = dict(infos[0])
    per_view = {}
    for key, (reducer, empty, steps) in infos[0].get("per_view", {}).items():
        joined = [np.concatenate([np.asarray(i["per_view"][key][2][s]) for i in infos]) for s in range(len(steps))]
        per_view[key] = (reducer, empty, joined)
    out["per_view"] = per_view
    out.update(summarise_views(per_view))
    out["skipped_views"] = sorted(v for i in infos for v in i.get("skipped_views", ()))
    out["blocks"] = [tuple(b) for b in blocks]
    return out


def transfer_bytes(n_views: int, det_shape, grid_shape_zyx, *, per_view_mask: bool = True,
                   roi_support: bool = True) -> dict:
    """What a :class:`DaskExecutor` sends over the network, in bytes, for a scan of ``n_views`` views
    of ``det_shape`` (rows, cols) pixels and a volume of ``grid_shape_zyx`` voxels (float32):

    * ``volume_per_worker``: the volume, to every worker once per estimation pass;
    * ``measured_per_view``: a view's projection (float32) and, with ``per_view_mask``, its valid
      pixels (bool): once per level while the loop passes the same arrays;
    * ``per_view_per_pass``: a view's ROI support (bool, with ``roi_support``), geometry (four
      3-vectors), parameters and index (float64 / int64) with its task, and its parameters back;
    * ``filtered_per_worker``: the filtered projections, to every worker once per FDK (a displaced
      detector widens their rows), and ``volume_back``: the slabs of the FDK volume back.
    """
    rows, cols = (int(x) for x in det_shape)
    px = rows * cols
    voxels = int(np.prod([int(x) for x in grid_shape_zyx]))
    return {"volume_per_worker": 4 * voxels, "measured_per_view": 4 * px + (px if per_view_mask else 0),
            "per_view_per_pass": (px if roi_support else 0) + 12 * 8 + 9 * 8 + 8 + 9 * 8,
            "filtered_per_worker": 4 * n_views * px, "volume_back": 4 * voxels}


def _use_threads(threads: int) -> None:
    """Numba's threads in this task's thread (a worker's setting; 0: leave them)."""
    if threads > 0:
        import numba

        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


def _estimate_block(estimate, measured, nominal, params, volume, grid, config, valid_mask, support, view_ids,
                    threads):
    _use_threads(threads)
    return estimate(measured, nominal, params, volume, grid, config, valid_mask, support_mask=support,
                    view_ids=view_ids)


def _backproject_slab(filtered, geom, grid, threads):
    from robot_ct_ros.ct.reconstruction import fdk_backproject

    _use_threads(threads)
    return fdk_backproject(filtered, geom, grid)


class DaskExecutor:
    """Estimation blocks and FDK slabs as ``dask.distributed`` tasks.

    ``scheduler``: ``"local"`` starts a ``LocalCluster`` of ``workers`` processes, one task at a
    time each, whose tasks run numba on ``threads`` threads (0: the cores shared out); an address
    (``tcp://host:8786``) connects to that scheduler, whose workers keep their own numba settings
    (docs/distributed.md). ``blocks_per_worker`` sets how many blocks of views (slabs of the
    grid) each worker thread gets per pass, for balance.

    Raises
    ------
    DaskUnavailable
        dask.distributed is not installed.
    SchedulerUnreachable
        the address does not answer as a Dask scheduler within Dask's connect timeout
        (:func:`connect_timeout_s`).
    """

    def __init__(self, scheduler: str = LOCAL, *, workers: int = 2, threads: int = 0, blocks_per_worker: int = 2,
                 client=None):
        distributed = _import_distributed()
        self._cluster = None
        self._own_client = client is None
        self.threads = 0
        if client is not None:
            self.client = client
        elif scheduler == LOCAL:
            threads = int(threads) or max(1, (os.cpu_count() or 1) // max(1, int(workers)))
            self.threads = threads
            env = {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                   "MKL_NUM_THREADS": "1"}
            import dask

            # dask's nannies fix glibc's MALLOC_TRIM_THRESHOLD_ in their workers, which also fixes the mmap
            # threshold: every large temporary array is then mapped and page-faulted anew, and the estimation
            # runs slower in such a worker than in a plain process; the workers keep glibc's adaptive default
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}), \
                    _workers_ignore_sigint():
                self._cluster = distributed.LocalCluster(n_workers=int(workers), threads_per_worker=1,
                                                         processes=True, dashboard_address=":0", env=env)
            self.client = distributed.Client(self._cluster)
        else:
            timeout_s = connect_timeout_s()
            check_scheduler(distributed, scheduler, timeout_s)
            self.client = distributed.Client(scheduler, timeout=timeout_s)
            if not self.client.nthreads():  # a scheduler with no worker: the first task waited, then "No valid workers"
                try:
                    self.client.wait_for_workers(1, timeout=timeout_s)
                except (TimeoutError, OSError):
                    self.client.close()
                    raise SchedulerUnreachable(f"the Dask scheduler at {scheduler} has no workers (none joined within "
                                               f"{timeout_s:g} s): start some, e.g. dask worker {scheduler}") from None
        self.blocks_per_worker = max(1, int(blocks_per_worker))
        self._cache = {}  # (id(array), start, stop) -> (array, future): the measured views of a level
        self.description = f"dask ({scheduler}, {self.n_threads()} worker thread(s))"

    def n_threads(self) -> int:
        """Worker threads of the cluster now (tasks that run at once)."""
        return max(1, sum(self.client.nthreads().values()))

    def _scattered_blocks(self, array, blocks):
        """Futures of ``array[a:b]`` per block, sent once while ``array`` is the same object."""
        keys = [(id(array), a, b) for a, b in blocks]
        missing = [k for k in keys if k not in self._cache]
        if missing:
            if len(self._cache) > 8 * len(keys):  # another scan's levels: drop the old ones
                self._cache.clear()
            futures = self.client.scatter([np.ascontiguousarray(array[a:b]) for _, a, b in missing], hash=False)
            self._cache.update({k: (array, f) for k, f in zip(missing, futures)})
        return [self._cache[k][1] for k in keys]

    def _gather(self, futures, what: str):
        """The tasks' results; :class:`ClusterLost` where the cluster lost them (a worker or the scheduler gone: the
        futures cancelled, the connection closed), not Dask's traceback. An error raised inside a task is raised as
        it is."""
        from concurrent.futures import CancelledError

        try:
            return self.client.gather(futures)
        except (CancelledError, OSError) as exc:  # FutureCancelledError, CommClosedError among them
            reason = " ".join(str(exc).split()) or type(exc).__name__
            raise ClusterLost(f"the Dask cluster lost {what} mid-run ({reason}): a worker or the scheduler stopped, and "
                              f"the data sent to it are gone; run again ({self.description})") from exc

    def estimate(self, estimate, measured, nominal: ConeGeometry, params, volume, grid: VolumeGrid, config,
                 valid_mask):
        """``estimate`` over blocks of views as tasks; the same parameters and info as one call."""
        n = nominal.n_views
        params = np.asarray(params, np.float64).reshape(n, 9)
        fraction = getattr(config, "roi_support_fraction", None)
        # the ROI support's margin-or-exact choice is the whole scan's: made here, for all views
        support = None if fraction is None else roi_support_mask(nominal, params, grid, fraction)
        blocks = view_blocks(n, getattr(config, "chunk_views", 8), self.blocks_per_worker * self.n_threads())
        meas_f = self._scattered_blocks(measured, blocks)
        per_view_mask = valid_mask is not None and np.ndim(valid_mask) == 3
        mask_f = self._scattered_blocks(valid_mask, blocks) if per_view_mask else [valid_mask] * len(blocks)
        vol_f = self.client.scatter(volume, broadcast=True, hash=False)
        futures = [self.client.submit(_estimate_block, estimate, m, nominal.subset(np.arange(a, b)), params[a:b],
                                      vol_f, grid, config, mk, None if support is None else support[a:b],
                                      np.arange(a, b), self.threads, pure=False)
                   for (a, b), m, mk in zip(blocks, meas_f, mask_f)]
        results = self._gather(futures, "the views' estimation")
        self.client.cancel([vol_f])
        out = np.concatenate([p for p, _ in results], axis=0)
        return out, join_infos([i for _, i in results], blocks)

    def fdk(self, line_integrals, geom: ConeGeometry, grid: VolumeGrid, *, center_mm=None, **kwargs) -> np.ndarray:
        """:func:`~robot_ct_ros.ct.reconstruction.fdk`: the projections filtered here, sent once, and
        back-projected onto slabs of the grid's z planes as tasks."""
        from robot_ct_ros.ct.reconstruction import fdk_filter_motion_rows  # rows along the motion, as fdk
        from robot_ct_ros.ct.reconstruction import scan_centre, warn_if_empty

        if center_mm is None:  # as fdk
            center_mm = scan_centre(geom, kwargs.get("axis"), grid.center_mm)
        q, q_geom = fdk_filter_motion_rows(line_integrals, geom, center_mm=center_mm, **kwargs)
        q_f = self.client.scatter(q, broadcast=True, hash=False)
        g_f = self.client.scatter(q_geom, broadcast=True, hash=False)
        slabs = slab_bounds(grid.shape_zyx[0], self.blocks_per_worker * self.n_threads())
        futures = [self.client.submit(_backproject_slab, q_f, g_f, grid.slab(a, b), self.threads, pure=False)
                   for a, b in slabs]
        vol = np.concatenate(self._gather(futures, "the back-projection"), axis=0)
        self.client.cancel([q_f, g_f])
        warn_if_empty(vol, q, geom)
        return vol

    def close(self) -> None:
        self._cache.clear()
        if self._own_client:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
