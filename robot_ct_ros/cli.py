"""robot-ct: the jobs that need no ROS plumbing (simulate, reconstruct, report, benchmark)."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robot-ct", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="simulate a robotic interior scan on simulated hardware and reconstruct it")
    demo.add_argument("--out", default="out/demo", help="output folder")
    args = parser.parse_args(argv)
    if args.command == "demo":
        from robot_ct_ros.demo import run_demo

        return run_demo(args)
    return 2


if __name__ == "__main__":
    sys.exit(main())
