"""Estimation blocks and FDK slabs as Dask tasks on a LocalCluster give the in-process results."""

import subprocess
import sys

import numpy as np
import pytest

from robot_ct_ros.ct.calibration import calibrate
from robot_ct_ros.ct.calibration.distributed import (DaskExecutor, DaskUnavailable, InProcess, SchedulerUnreachable,
                                                     executor_for,
                                                     slab_bounds, view_blocks)
from robot_ct_ros.ct.calibration.gdc import default_gdc_configs, estimate_views_gdc
from robot_ct_ros.ct.calibration.lle.estimator import default_lle_configs, estimate_views
from robot_ct_ros.ct.calibration.model import VolumeParts
from robot_ct_ros.ct.calibration.settings import CalibrationSettings
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.reconstruction import fdk
from robot_ct_ros.ct.simulation import robot_coordination
from robot_ct_ros.ct.trajectory import circular_scan

pytest.importorskip("distributed")


def _scan(n_views=20, n_det=32):
    """A small circular scan of a few balls with robot errors, one view without usable pixels."""
    nominal = circular_scan(n_views, 60.0, 150.0, n_det, n_det, 32.0 / n_det, 32.0 / n_det)
    grid = VolumeGrid.centered((24, 24, 24), 12.0 / 24)
    z, y, x = np.meshgrid(*(np.arange(24) - 11.5,) * 3, indexing="ij")
    phantom = np.zeros(grid.shape_zyx, np.float32)
    for (cz, cy, cx), r, mu in (((0, 0, 0), 9.0, 0.02), ((3, -2, 4), 3.0, 0.03), ((-4, 3, -2), 2.5, -0.01)):
        phantom[(z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 < r * r] += mu
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=3).sample(n_views))
    measured = forward_project(phantom, grid, true)
    mask = np.ones(measured.shape, bool)
    mask[:, 5, 7] = False  # a dead pixel
    mask[13] = False       # a view that cannot be estimated
    return nominal, grid, measured, mask, fdk(measured, nominal, grid, valid_mask=mask)


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes, one thread each (closed after the module's tests)."""
    with DaskExecutor("local", workers=2, threads=1) as ex:
        yield ex


def test_blocks_and_slabs_are_whole_chunks_and_cover_everything():
    assert view_blocks(20, 4, 4) == [(0, 4), (4, 8), (8, 12), (12, 20)]
    assert view_blocks(21, 8, 10) == [(0, 8), (8, 16), (16, 21)]
    assert view_blocks(5, 8, 3) == [(0, 5)]
    assert slab_bounds(24, 5) == [(0, 4), (4, 9), (9, 14), (14, 19), (19, 24)]
    grid = VolumeGrid.centered((6, 4, 5), (0.5, 0.6, 0.7), (1.0, -2.0, 3.0), np.eye(3)[[1, 0, 2]] * [1, -1, 1])
    slab = grid.slab(2, 5)
    assert slab.shape_zyx == (3, 4, 5)
    np.testing.assert_allclose(slab.index_to_world((1, 2, 0)), grid.index_to_world((1, 2, 2)))


@pytest.mark.parametrize("method", ["ncc-lle-exact", "gdc"])
def test_estimation_on_two_worker_processes_equals_the_in_process_pass(cluster, method):
    nominal, grid, measured, mask, vol = _scan()
    if method == "gdc":
        estimate, cfg = estimate_views_gdc, default_gdc_configs("gdc")[0]
    else:  # with the prior: the independent fraction's median is taken over all views
        estimate = estimate_views
        cfg = default_lle_configs("ncc-exact", seed=5, prior_sigma=(0.3,) * 6 + (0.005,) * 3)[0]
    from dataclasses import replace

    cfg = replace(cfg, chunk_views=4)  # 5 chunks: blocks on both workers
    params0 = np.zeros((nominal.n_views, 9))
    p_in, info_in = InProcess().estimate(estimate, measured, nominal, params0, vol, grid, cfg, mask)
    p_dask, info_dask = cluster.estimate(estimate, measured, nominal, params0, vol, grid, cfg, mask)
    assert len(info_dask["blocks"]) > 1
    # equal to float rounding: a CI run once differed by 1.5e-9 relative in a distance (another process's
    # float32 sums); another seed moves these parameters by up to 0.17
    np.testing.assert_allclose(p_dask, p_in, rtol=0, atol=1e-6)
    assert info_dask["skipped_views"] == info_in["skipped_views"] == [13]
    for key in ("best_distance", "chosen_distance", "independent_fraction", "cost", "accepted"):
        if key in info_in:
            np.testing.assert_allclose(info_dask[key], info_in[key], rtol=1e-6, err_msg=key)
    assert np.abs(p_in).max() > 0  # the views moved


def test_fdk_slabs_and_a_volume_of_parts_on_the_cluster(cluster):
    nominal, grid, measured, mask, vol = _scan()
    np.testing.assert_allclose(cluster.fdk(measured, nominal, grid, valid_mask=mask), vol, rtol=0,
                               atol=1e-5 * np.abs(vol).max())
    # the exterior model's two grids travel to the workers as one scattered object
    coarse = VolumeGrid.centered((6, 6, 6), 2.0)
    parts = VolumeParts(((vol, grid), (np.zeros(coarse.shape_zyx, np.float32), coarse)))
    cfg = default_gdc_configs("gdc")[1]
    params0 = np.zeros((nominal.n_views, 9))
    p_in, _ = InProcess().estimate(estimate_views_gdc, measured, nominal, params0, parts, grid, cfg, mask[0])
    p_dask, _ = cluster.estimate(estimate_views_gdc, measured, nominal, params0, parts, grid, cfg, mask[0])
    np.testing.assert_allclose(p_dask, p_in, rtol=0, atol=1e-6)


def test_the_loop_with_scheduler_local_equals_the_in_process_loop():
    nominal, grid, measured, mask, _ = _scan(n_views=16)
    kw = dict(method="ncc-lle", iterations=1, schedule="fast", projections="complete", fdk_kwargs={"window": "hann"})
    said = []
    ref = calibrate(measured, nominal, grid, valid_mask=mask, **kw)
    out = calibrate(measured, nominal, grid, valid_mask=mask, scheduler="local", dask_workers=2, dask_threads=1,
                    progress=said.append, **kw)
    assert any("dask" in s for s in said)
    # the slabs' FDK equals fdk to float32 rounding, which the estimation carries on: a CI run once
    # differed by 1.3e-7 mm / deg
    np.testing.assert_allclose(out.params, ref.params, rtol=0, atol=1e-5)
    np.testing.assert_allclose(out.volume, ref.volume, rtol=0, atol=1e-5 * np.abs(ref.volume).max())


def test_the_default_path_imports_no_dask_and_a_scheduler_without_dask_says_what_to_install(monkeypatch):
    code = ("import sys; import robot_ct_ros.cli; from robot_ct_ros.ct.calibration.distributed import executor_for; "
            "from robot_ct_ros.ct.calibration.settings import CalibrationSettings; "
            "ex = executor_for(CalibrationSettings()); print(type(ex).__name__, "
            "any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.split() == ["InProcess", "False"]
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(DaskUnavailable, match="pip install dask distributed"):
        executor_for(CalibrationSettings(scheduler="tcp://127.0.0.1:8786"))
    for address in ("127.0.0.1:8786", "foo://x", "tcp://"):  # no protocol, one Dask lacks, no host
        with pytest.raises(ValueError, match="scheduler"):
            CalibrationSettings(scheduler=address)
    assert CalibrationSettings(scheduler="tls://10.0.0.2:8786").scheduler == "tls://10.0.0.2:8786"


def test_fdk_on_the_cluster_of_a_portrait_detector(cluster):
    """Columns along the scan axis (the same rays, the data transposed): filtered with the rows along
    the source motion, as fdk does (filtering across it gave an empty volume)."""
    nominal, grid, measured, mask, vol = _scan()
    portrait = nominal.replace(u=nominal.v, v=-nominal.u, n_rows=nominal.n_cols, n_cols=nominal.n_rows)
    lp = np.ascontiguousarray(measured[:, :, ::-1].transpose(0, 2, 1))
    mp = np.ascontiguousarray(mask[:, :, ::-1].transpose(0, 2, 1))
    np.testing.assert_allclose(cluster.fdk(lp, portrait, grid, valid_mask=mp), vol, rtol=0,
                               atol=1e-4 * np.abs(vol).max())


def _server(answer: bytes | None):
    """A TCP server on a free local port that answers every connection with ``answer`` (an HTTP server's reply), or
    with nothing, holding the connection open (None); its address."""
    import socket
    import threading

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held = []

    def serve():
        while True:
            conn, _ = srv.accept()
            held.append(conn)
            if answer is not None:
                conn.recv(65536)
                conn.sendall(answer)
    threading.Thread(target=serve, daemon=True).start()
    return f"tcp://127.0.0.1:{srv.getsockname()[1]}"


def _executor_within(settings, seconds: float):
    """executor_for(settings) on a thread: its outcome (the exception it raised), or None while it still waits."""
    import threading

    out = []

    def run():
        try:
            out.append(executor_for(settings))
        except BaseException as exc:  # noqa: BLE001 - the outcome under test
            out.append(exc)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    return out[0] if out else None


def test_an_http_server_for_a_scheduler_is_named_as_no_dask_scheduler():
    """From an outside check: --scheduler naming an HTTP server (the dashboard's port, 8787) ended in 'out of memory
    (Unable to allocate 3.07 EiB)': its reply was read as a message length. Now it says that the address does not
    answer as a Dask scheduler."""
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        http = _server(b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\n\r\n")
        err = _executor_within(CalibrationSettings(scheduler=http), 30.0)
        assert isinstance(err, SchedulerUnreachable) and "does not answer as a Dask scheduler" in str(err), err
        assert "8787" in str(err)


def test_a_scheduler_address_that_never_answers_times_out():
    """From an outside check: a server that accepts the connection and never answers held the run forever
    (distributed.Client times out only the connection). Now it ends after twice Dask's connect timeout, saying so."""
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        err = _executor_within(CalibrationSettings(scheduler=_server(None)), 30.0)
        assert err is not None, "still waiting for an answer"
        assert isinstance(err, SchedulerUnreachable) and "no answer as a Dask scheduler within 2 s" in str(err), err
        assert "distributed.comm.timeouts.connect" in str(err)


def test_a_scheduler_address_connects_and_a_worker_address_is_refused():
    import distributed

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                                  dashboard_address=":0") as lc:
        with DaskExecutor(lc.scheduler_address) as ex:
            assert ex.n_threads() == 1
        worker = next(iter(lc.scheduler_info["workers"]))
        with pytest.raises(SchedulerUnreachable, match="answers as a Dask [Ww]orker, not as a scheduler"):
            DaskExecutor(worker)


def test_a_scheduler_no_worker_joins_is_named_so():
    """An outside check: a scheduler without workers ended the run after the connect timeout with "cannot access: No
    valid workers found", naming neither the scheduler nor the workers."""
    import dask
    import distributed

    with distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp://", dashboard_address=":0") as lc:
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
            with pytest.raises(SchedulerUnreachable, match="has no workers .*dask worker tcp://"):
                DaskExecutor(lc.scheduler_address)


def test_fdk_on_the_cluster_says_as_fdk_does_when_it_puts_nothing_into_the_grid(cluster):
    """A grid beyond every view's cone: fdk warns, and the cluster's fdk did not (the same calibration said less on
    Dask than in process)."""
    from robot_ct_ros.ct.reconstruction import FDKWarning

    nominal, grid, measured, mask, _ = _scan()
    far = VolumeGrid.centered(grid.shape_zyx, grid.voxel_size_mm, (0.0, 0.0, 500.0))
    for run in (fdk, cluster.fdk):
        with pytest.warns(FDKWarning, match="put nothing into the grid"):
            assert not run(measured, nominal, far, valid_mask=mask).any()


def test_tasks_the_cluster_lost_are_one_clear_error_and_a_task_s_own_error_is_itself(cluster):
    """A worker or the scheduler lost mid-run ended calibrate with 40 lines of Dask traceback ending in
    FutureCancelledError (an outside check); it is ClusterLost now, a one-line refusal on the command line. An error
    raised inside a task is not a lost cluster."""
    import time

    from robot_ct_ros.ct.calibration.distributed import ClusterLost

    lost = cluster.client.submit(time.sleep, 30, pure=False)
    cluster.client.cancel([lost])
    with pytest.raises(ClusterLost, match="lost the test's tasks mid-run"):
        cluster._gather([lost], "the test's tasks")
    with pytest.raises(ValueError, match="invalid literal") as err:  # int("x") in a worker
        cluster._gather([cluster.client.submit(int, "x", pure=False)], "the test's tasks")
    assert not isinstance(err.value, ClusterLost)


def test_the_local_clusters_processes_leave_ctrl_c_to_this_one(cluster):
    """Ctrl-C reaches every process of the terminal's group: each worker printed its own KeyboardInterrupt traceback
    (and the cluster's atexit hook another) before the one line. They start with SIGINT ignored; this process keeps
    its handler and closes the cluster in order."""
    import signal

    dispositions = cluster.client.run(signal.getsignal, signal.SIGINT)
    assert dispositions and all(d == signal.SIG_IGN for d in dispositions.values()), dispositions
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
