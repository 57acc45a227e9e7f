"""A recording process interrupted mid-scan leaves a readable bag (SIGINT: clean close; SIGKILL: recovered)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from robot_ct_ros.bag import read_scan

REPO = Path(__file__).resolve().parents[2]

WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from robot_ct_ros.bag import ScanBagWriter, scan_info_for
    from robot_ct_ros.bag.writer import default_stamps
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=200, n_rows=8, n_cols=12, fov_diameter_mm=0.5)
    stamps = default_stamps(200)
    with ScanBagWriter(sys.argv[1], scan_info_for(geom)) as w:
        w.write_flat(np.full((8, 12), 1000.0, np.float32), int(stamps[0]) - 1)
        for i in range(200):
            w.write_frame(np.full((8, 12), float(i + 1), np.float32), geom, int(stamps[i]), i)
            print(f"frame {i}", flush=True)  # printed after the frame is on disk
            time.sleep(0.05)
""")


def _record_until(tmp_path, n_frames: int, sig) -> tuple[Path, int]:
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    bag = tmp_path / "bag"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, str(script), str(bag)], stdout=subprocess.PIPE, text=True, env=env)
    last = -1
    try:
        for line in proc.stdout:
            last = int(line.split()[1])
            if last + 1 >= n_frames:
                proc.send_signal(sig)
                break
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    return bag, last + 1


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_interrupted_recording_is_readable(tmp_path, sig, check_bag):
    bag, written = _record_until(tmp_path, 6, sig)
    assert written >= 6
    scan = read_scan(bag)
    assert scan.n_views >= written  # every frame reported as written survived
    np.testing.assert_array_equal(scan.counts[:, 0, 0], np.arange(1, scan.n_views + 1, dtype=np.float32))
    assert any("200 views" in w for w in scan.warnings), (scan.warnings, scan.recovered, scan.info)
    if sig == signal.SIGINT:  # KeyboardInterrupt: the writer closed the bag normally
        assert not scan.recovered and (bag / "metadata.yaml").exists()
        assert check_bag(bag)["/ct/projection"] == scan.n_views
    else:  # killed: no metadata.yaml, no MCAP summary; recovered from the chunks on disk
        assert scan.recovered and not (bag / "metadata.yaml").exists()
