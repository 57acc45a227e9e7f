"""When the recon_service starts corrections (RunPlanner, no ROS)."""

from robot_ct_ros.jobs.online import RunPlanner, ServiceSettings


class Clock:
    t = 0.0

    def __call__(self):
        return self.t


def test_a_done_scan_runs_once_when_its_frames_are_in_or_after_the_wait():
    clock = Clock()
    p = RunPlanner(auto_run=True, every_n_views=0, wait_s=5.0, clock=clock)
    assert p.next_run(10, "s1") is None
    p.on_status({"state": "done", "scan_id": "s1", "frames": 12})
    assert p.next_run(10, "s1") is None          # two frames still on their way
    assert p.next_run(12, "s1") == "full"
    p.on_status({"state": "done", "scan_id": "s1", "frames": 12})
    assert p.next_run(12, "s1") is None          # that scan is corrected already
    p.on_status({"state": "done", "scan_id": "s2", "frames": 30})
    clock.t = 6.0
    assert p.next_run(20, "s2") == "full"        # frames lost: it runs on what arrived


def test_partial_runs_every_n_frames_until_the_scan_is_over():
    p = RunPlanner(auto_run=False, every_n_views=8)
    assert p.next_run(7, "s") is None
    assert p.next_run(9, "s") == "partial" and p.next_run(9, "s") is None
    assert p.next_run(17, "s") == "partial"
    p.on_status({"state": "aborted", "scan_id": "s"})
    assert p.next_run(40, "s") is None
    p.new_scan()
    assert p.next_run(8, "t") == "partial"
    p.full_started = True
    assert p.next_run(30, "t") is None
    p.on_status({"state": "done", "scan_id": "t", "frames": 30})  # auto_run off: nothing
    assert p.next_run(30, "t") is None


def test_service_settings_defaults_and_units():
    s = ServiceSettings()
    assert s.shape_xyz is None and s.voxel_mm is None
    s = ServiceSettings(voxel_size_m=5e-5, roi_shape=(64, 64, 32))
    assert s.shape_xyz == (64, 64, 32) and abs(s.voxel_mm - 0.05) < 1e-12


def test_a_zero_among_the_roi_sizes_is_refused_not_taken_for_the_default():
    """roi_shape [0, 10, 10] silently became the scan's default grid; only all zeros mean that."""
    import pytest

    for shape in ((0, 10, 10), (64, 64, 0)):
        with pytest.raises(ValueError, match="roi_shape must be three positive sizes"):
            ServiceSettings(roi_shape=shape)
    assert ServiceSettings(roi_shape=(0, 0, 0)).shape_xyz is None
