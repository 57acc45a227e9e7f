"""`robot-ct demo --quick` end to end in a subprocess: it finishes and leaves the documented outputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_demo_quick(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "robot_ct_ros.cli", "demo", "--quick", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "reprojection error vs true geometry" in proc.stdout and "scan bag" in proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    for key in ("scan_bag", "corrected_bag", "volume_npy", "volume_tif", "report_json", "report_md"):
        assert Path(summary["paths"][key]).exists(), key
    assert summary["frames"] == 12 and summary["truth"]["reprojection_error_nominal_px"]["mean"] > 0
    # the correction's prior is the simulated arms' accuracy (0.1 mm, 0.05 deg per axis at the TCP), not
    # the default, carried to the focal spot and the detector centre through the default mounts (120 and
    # 80 mm levers, test_hand_eye checks the figures against the simulated arm): the error across the beam
    report = json.loads(Path(summary["paths"]["report_json"]).read_text())
    across_mm = [np.hypot(0.1, np.deg2rad(0.05) * lever) for lever in (120.0, 80.0)]
    assert report["prior_sigma"] == pytest.approx([across_mm[0]] * 3 + [across_mm[1]] * 3 + [np.deg2rad(0.05)] * 3)


def test_a_truncated_demo_models_the_phantom_around_the_roi():
    """--truncated scans the whole phantom through the field of view: the correction models the
    object outside the ROI (the exterior model), out to the phantom's far side; a scan inside the
    field of view does not."""
    from robot_ct_ros.testing.demo import demo_settings, recon_parameters

    truncated = recon_parameters(demo_settings(truncated=True))
    assert truncated["exterior"] == "on"
    # the 25 mm wide mouse, its spine (6.6 mm off its centre) in the ROI: its far side 17 mm away
    assert truncated["exterior_half_width_m"] == pytest.approx(0.017, abs=1e-4)  # a ROS parameter: SI
    assert "exterior" not in recon_parameters(demo_settings())


def test_the_demo_replaces_only_its_own_outputs(tmp_path, capsys):
    """demo --out DIR deleted DIR/bags and DIR/recon whatever they held (robot-ct demo --out . in the repository
    would have taken the sample bags), and a failed run kept the earlier run's summary.json."""
    from robot_ct_ros.cli import main
    from robot_ct_ros.testing.demo import DEMO_MARK, claim_output

    mine = tmp_path / "lab"
    (mine / "bags" / "my_scan").mkdir(parents=True)
    (mine / "bags" / "my_scan" / "data.mcap").write_bytes(b"x")
    assert main(["demo", "--out", str(mine), "--quick"]) == 2
    assert "holds files an earlier demo did not write" in capsys.readouterr().err
    assert (mine / "bags" / "my_scan" / "data.mcap").exists()
    earlier = tmp_path / "demo"
    (earlier / "recon").mkdir(parents=True)
    (earlier / "summary.json").write_text("{}")  # an earlier demo's, from before the mark
    claim_output(earlier)
    assert (earlier / DEMO_MARK).exists() and not (earlier / "summary.json").exists()
    assert not (earlier / "recon").exists()
    with pytest.raises(SystemExit):
        main(["demo", "--views", "3"])  # a bag with fewer than 4 views is no scan: refused before any work
    assert "at least 4 views" in capsys.readouterr().err


def test_the_exterior_reach_is_measured_across_the_protocols_scan_axis(monkeypatch):
    """Review N4: the reach was the phantom's extent along x and y whatever the protocol's axis; it is its extent
    across the axis, in the ROI grid's frame (geometry.axis_frame), the one the exterior grid is cut in."""
    from robot_ct_ros.ct.geometry import axis_frame
    from robot_ct_ros.hardware.detector import make_phantom
    from robot_ct_ros.testing import demo

    s = demo.demo_settings(truncated=True)
    setup = demo.demo_setup
    protocol, grabber = setup(s)
    centre_mm = 1000.0 * (np.asarray(grabber["sim_phantom_center_m"]) - np.asarray(protocol["roi_center_m"]))
    lo, hi = make_phantom(s["phantom"], centre_mm).bounds_mm()
    corners = np.array([[(lo, hi)[k >> i & 1][i] for i in range(3)] for k in range(8)])
    for axis in ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]):
        monkeypatch.setattr(demo, "demo_setup", lambda s, axis=axis: ({**setup(s)[0], "axis": axis}, setup(s)[1]))
        expected = np.max(np.abs(corners @ axis_frame(axis))[:, :2])
        assert demo.recon_parameters(s)["exterior_half_width_m"] == pytest.approx(expected * 1e-3), axis
    assert expected != pytest.approx(np.max(np.abs(corners)[:, :2]))  # the axes differ in what they give
