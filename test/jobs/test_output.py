"""The jobs' chunked volume writer: a tiled OME-TIFF written slab by slab reads back exactly."""

import numpy as np
import pytest
import tifffile

from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.jobs.output import write_ome_tiff


def test_tiled_ome_tiff_written_slab_by_slab_round_trips(tmp_path):
    grid = VolumeGrid.centered((7, 40, 50), (0.045, 0.045, 0.09))  # tiles do not divide the planes
    vol = np.random.default_rng(0).standard_normal(grid.shape_zyx).astype(np.float32)
    slabs = (vol[z0:z0 + 3] for z0 in range(0, 7, 3))  # 3 + 3 + 1 planes, never the volume at once
    path = write_ome_tiff(slabs, grid, tmp_path / "v.ome.tif", tile=(16, 32))
    np.testing.assert_array_equal(tifffile.imread(path), vol)
    with tifffile.TiffFile(path) as tif:
        assert tif.is_ome and tif.is_bigtiff
        assert tif.pages[0].is_tiled and tif.pages[0].tilelength == 16 and tif.pages[0].tilewidth == 32
        assert tif.series[0].axes == "ZYX"
        ome = tif.ome_metadata
    assert 'PhysicalSizeX="0.045"' in ome and 'PhysicalSizeZ="0.09"' in ome and 'PhysicalSizeZUnit="mm"' in ome
    # the whole array in one go (one slab), in float64: converted plane by plane
    path = write_ome_tiff(vol.astype(np.float64), grid, tmp_path / "w.ome.tif", tile=(16, 16))
    np.testing.assert_array_equal(tifffile.imread(path), vol)
    with pytest.raises(ValueError, match="planes"):
        write_ome_tiff([vol[:3]], grid, tmp_path / "x.ome.tif", tile=(16, 16))


def test_the_memory_estimate_covers_the_measured_peaks_and_the_report_s_methods():
    """An outside check measured peaks of 12.6 to 14.8 volumes for calibrate and 25 to 34 for a report of 2 to 6
    methods, where the estimate assumed 8 and 10 (and the same for any number of methods): grids that did not fit
    were passed."""
    from robot_ct_ros.jobs.output import check_memory

    grid = VolumeGrid.centered((100, 100, 100), 0.1)
    volume = 4.0 * 100 ** 3
    est = {job: check_memory(grid, 1, (1, 1), job, available=2 ** 40) / volume for job in ("reconstruct", "calibrate")}
    assert est["reconstruct"] >= 1.6 and est["calibrate"] >= 14.8, est
    report = [check_memory(grid, 1, (1, 1), "report", available=2 ** 40, methods=n) / volume for n in (2, 6)]
    assert report[0] >= 27.6 and report[1] >= 34.0 and report[1] > report[0], report
