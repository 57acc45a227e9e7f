"""Write the sample scan bags of this folder, each through the command line that makes such a bag.

* ``htc2022_01a``: ``robot-ct import htc2022 htc2022_01a_full.mat`` — real measured fan-beam data
  (Helsinki Tomography Challenge 2022, phantom 01a: 720 views on a 1 x 560 detector, line integrals;
  University of Helsinki Industrial Mathematics CT Laboratory, Meaney et al., Zenodo 6984868 /
  8041800; cite the dataset when you use it). Needs the .mat file (``--data``).
* ``sim_mouse_80``: ``robot-ct simulate --phantom mouse --views 80 --rows 64 --cols 128`` — a
  small simulated robotic interior scan with per-view robot errors of 0.1 mm / 0.1 deg and its true
  geometry on /ct/geometry_true (the demo's detector, fewer views: 3 MB at most).

Each bag must stay at most ``MAX_BYTES``; one that is larger is removed and reported. Existing bags
are replaced.

    .venv/bin/python bags/make_bags.py                      # both bags into bags/
    .venv/bin/python bags/make_bags.py --only htc2022_01a --data /path/to/htc2022
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from robot_ct_ros.cli import main as robot_ct  # noqa: E402

MAX_BYTES = 3_000_000
DATA = Path("/work/shared/realdata/htc2022")
BAGS = {
    "htc2022_01a": lambda data, out: ["import", "htc2022", str(data / "htc2022_01a_full.mat"), "--out", str(out)],
    "sim_mouse_80": lambda data, out: ["simulate", "--phantom", "mouse", "--views", "80", "--rows", "64",
                                          "--cols", "128", "--sigma-mm", "0.1", "--sigma-deg", "0.1", "--seed", "0",
                                          "--quiet", "--out", str(out)],
}


def size_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.environ.get("HTC2022_DATA", str(DATA)),
                    help="folder holding htc2022_01a_full.mat (or set HTC2022_DATA)")
    ap.add_argument("--only", default=",".join(BAGS), help="comma-separated bag names")
    ap.add_argument("--out", default=str(HERE))
    args = ap.parse_args(argv)
    out_dir = Path(args.out)
    status = 0
    for name in (n.strip() for n in args.only.split(",") if n.strip()):
        if name not in BAGS:
            ap.error(f"unknown bag {name!r}; choose from {', '.join(BAGS)}")
        out = out_dir / name
        if out.exists():
            shutil.rmtree(out)
        cmd = BAGS[name](Path(args.data), out)
        print("robot-ct " + " ".join(cmd), flush=True)
        rc = robot_ct(cmd)
        if rc != 0:
            print(f"{name}: robot-ct failed ({rc})", flush=True)
            status = 1
            continue
        size = size_bytes(out)
        if size > MAX_BYTES:
            shutil.rmtree(out)
            print(f"{name}: {size / 1e6:.2f} MB is more than {MAX_BYTES / 1e6:g} MB; removed", flush=True)
            status = 1
        else:
            print(f"{name}: {size / 1e6:.2f} MB", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
