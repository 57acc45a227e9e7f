"""The in-process scan graph harness (robot_ct_ros.testing.graph): its orchestrator settings."""

from __future__ import annotations

import pytest

from robot_ct_ros.testing.graph import ARM_REPORT_TIMEOUT_S, GraphError, run_scan_graph

PROTOCOL = {"name": "harness", "n_views": 4, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.002,
            "detector": {"n_rows": 16, "n_cols": 32, "binning": 2, "raw_pixel_m": 0.000055},
            "exposure_s": 0.02, "settle_s": 0.01, "move_timeout_s": 10.0, "exposure_timeout_s": 2.0}


def test_the_harness_tolerates_a_shared_thread_and_passes_orchestrator_settings(tmp_path):
    # one thread serves every node here, so the harness is more patient with the arms than a robot's 1 s
    assert ARM_REPORT_TIMEOUT_S > 1.0
    # and an orchestrator setting given to the harness reaches the node: arms that must report every
    # microsecond are never reporting, and the sequencer refuses to start the scan
    with pytest.raises(GraphError, match="source arm not reporting; detector arm not reporting"):
        run_scan_graph(tmp_path, PROTOCOL, orchestrator={"arm_report_timeout_s": 1e-6}, quiet=True,
                       say=lambda s: None, startup_timeout_s=10.0, recon={"auto_run": False})
