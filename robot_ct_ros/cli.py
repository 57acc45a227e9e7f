"""robot-ct: one command line over the jobs (simulate, inspect, reconstruct, calibrate, compare, demo, import, export).

  robot-ct simulate --phantom carotid --views 360 --out scan_bag
  robot-ct info scan_bag
  robot-ct reconstruct scan_bag --out out/recon
  robot-ct calibrate scan_bag --method ncc-lle-exact --iterations 2 --out out/calib
  robot-ct report scan_bag --methods none,ncc-lle-exact,gdc-log --out out/report
  robot-ct demo --out out/demo
  robot-ct import htc2022 htc2022_01a_full.mat --out scan_bag
  robot-ct import rtk --projections proj.tif --geometry geometry.xml --pitch-mm 0.2,0.2 --out scan_bag
  robot-ct import astra --projections proj.npy --vectors cone_vec.txt --out scan_bag
  robot-ct export scan_bag --format rtk --out geometry.xml
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import warnings
from pathlib import Path

import numpy as np

from robot_ct_ros.parameters import specs

OPTION_ALIASES = {"stop_update_px": ("--stop-px",)}
"""Shorter spellings of settings options (the first is shown in the help)."""
PRIOR_FIELDS = ("prior_translation_mm", "prior_rotation_deg")  # one option: --prior-sigma MM,DEG


# ------------------------------------------------------------------------------ argument types
def _checked(spec):
    """An argparse type for one settings field: parsed as the field's type and checked against its
    bounds and choices (robot_ct_ros.parameters.SettingSpec.check), the field named in the error. A field
    whose default is None (shown as ``[off]``) also takes ``off``: None, as if the option were left out."""
    label = spec.name.replace("_", " ")

    def parse(text: str):
        if spec.default is None and text.strip().lower() == "off":
            return None
        try:
            value = spec.kind(text) if spec.kind is not int else int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{label} must be a {'whole ' if spec.kind is int else ''}"
                                             f"{'number' if spec.kind in (int, float) else spec.kind.__name__}, "
                                             f"got {text!r}") from None
        try:
            spec.check(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc).replace(spec.name, label, 1)) from None
        return value
    return parse


def _prior_sigma(text: str):
    """``MM,DEG`` -> (translation mm, rotation deg); ``none`` -> (0, 0): no prior, as is 0 for either."""
    if text.strip().lower() == "none":
        return 0.0, 0.0
    try:
        mm, deg = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("prior sigma is MM,DEG (e.g. 0.3,0.3) or none") from None
    if not (mm >= 0 and deg >= 0 and np.isfinite(mm) and np.isfinite(deg)):
        raise argparse.ArgumentTypeError("prior sigmas must be >= 0 and finite (0 for either: no prior)")
    return mm, deg


def _shape(text: str):
    try:
        parts = [int(x) for x in text.lower().replace("x", ",").split(",") if x]
    except ValueError:
        parts = []
    if len(parts) != 3 or min(parts) < 1:
        raise argparse.ArgumentTypeError("shape is NX,NY,NZ (or NXxNYxNZ), positive whole numbers")
    return tuple(parts)


def _pair(what: str, positive: bool):
    """``ROW,COL`` (or one number for both) -> (row, col) floats, in mm."""
    def parse(text: str):
        try:
            parts = [float(x) for x in text.split(",")]
        except ValueError:
            parts = []
        if len(parts) == 1:
            parts *= 2
        if len(parts) != 2 or not all(np.isfinite(parts)) or (positive and min(parts) <= 0):
            raise argparse.ArgumentTypeError(f"{what} is ROW,COL in mm{', positive' if positive else ''}, or one "
                                             f"value for both (e.g. 0.2,0.2 or 0.2), got {text!r}")
        return tuple(parts)
    return parse


def _positive(what: str, kind=float):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
        if not (value > 0 and np.isfinite(value)):
            raise argparse.ArgumentTypeError(f"{what} must be positive")
        return value
    return parse


def _non_negative(what: str):
    def parse(text: str):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
        if not (value >= 0 and np.isfinite(value)):
            raise argparse.ArgumentTypeError(f"{what} must be >= 0, got {text!r}")
        return value
    return parse


def _arc_deg(text: str) -> float:
    value = _positive("arc-deg")(text)
    if value > 360.0:
        raise argparse.ArgumentTypeError(f"arc-deg must be at most 360, got {text!r}")
    return value


# ------------------------------------------------------------------------------ settings options
def add_settings_arguments(p: argparse.ArgumentParser, skip=("method",)) -> None:
    """One option per field of :class:`~robot_ct_ros.ct.calibration.settings.CalibrationSettings`
    (``--field-name``, help, unit and bounds from the field), plus ``--prior-sigma MM,DEG``."""
    from robot_ct_ros.ct.calibration import CalibrationSettings

    group = p.add_argument_group("calibration settings (defaults in brackets)")
    for s in specs(CalibrationSettings):
        if s.name in skip or s.name in PRIOR_FIELDS:
            continue
        names = ("--" + s.name.replace("_", "-"),) + OPTION_ALIASES.get(s.name, ())
        unit = f" ({s.unit})" if s.unit else ""
        default = "off" if s.default is None else s.default
        if s.kind is bool:  # --name / --no-name
            group.add_argument(*names, dest=s.name, action=argparse.BooleanOptionalAction, default=None,
                               help=f"{s.help} [{'on' if s.default else 'off'}]")
            continue
        metavar = "{" + ",".join(s.choices) + "}" if s.choices else s.name.upper()
        group.add_argument(*names, dest=s.name, type=_checked(s), default=None, metavar=metavar,
                           help=f"{s.help}{unit} [{default}]")
    d = CalibrationSettings()
    group.add_argument("--prior-sigma", type=_prior_sigma, default=None, metavar="MM,DEG",
                       help="the robots' per-view coordination error (translations in mm, rotations in deg), the "
                            f"prior of the MAP estimate; none (or 0 for either): the data alone "
                            f"[{d.prior_translation_mm:g},{d.prior_rotation_deg:g}]")


def settings_from_args(args, **fixed):
    """The :class:`CalibrationSettings` of the parsed options (defaults where an option is absent)."""
    from robot_ct_ros.ct.calibration import CalibrationSettings

    kwargs = {s.name: getattr(args, s.name) for s in specs(CalibrationSettings)
              if getattr(args, s.name, None) is not None}
    if getattr(args, "prior_sigma", None) is not None:
        kwargs["prior_translation_mm"], kwargs["prior_rotation_deg"] = args.prior_sigma
    return CalibrationSettings(**(kwargs | fixed))


# ------------------------------------------------------------------------------ commands
def _cmd_simulate(args) -> int:
    from robot_ct_ros.jobs.output import prepare_out
    from robot_ct_ros.jobs.simulate import simulate_bag

    simulate_bag(prepare_out(args.out, must_not_exist=True), phantom=args.phantom, views=args.views, rows=args.rows, cols=args.cols,
                 binning=args.binning, sigma_mm=args.sigma_mm, sigma_deg=args.sigma_deg, seed=args.seed,
                 drift_mm=args.drift_mm, drift_deg=args.drift_deg,
                 photons=args.photons, fov_mm=args.fov_mm, sim_voxel_mm=args.sim_voxel_mm, arc_deg=args.arc_deg,
                 progress=not args.quiet)
    return 0


def _share_percent(fraction: float, digits: int = 2) -> str:
    """``fraction`` (0 to 1) as a percentage with ``digits`` decimals, more where that would round a share short of
    the whole to 100 (or a share above none to 0): 5 invalid pixels of 184320 read 99.997, not 100.00; beyond 9
    decimals, ``> 99.999999999`` (``< 0.000000001``)."""
    pct = 100.0 * float(fraction)
    for d in range(digits, 10):
        text = f"{pct:.{d}f}"
        if (fraction >= 1.0 or float(text) < 100.0) and (fraction <= 0.0 or float(text) > 0.0):
            return text
    return f"> {100 - 10.0 ** -9:.9f}" if pct > 50 else f"< {10.0 ** -9:.9f}"


def _cmd_info(args) -> int:
    from robot_ct_ros.bag import summarize
    from robot_ct_ros.jobs.output import json_default

    s = summarize(args.bag)
    if args.json:
        print(json.dumps(s, indent=2, default=json_default))
        return 0 if "scan_error" not in s else 1
    print(f"bag        {s['path']} (read with {s['reader']}{', RECOVERED' if s['recovered'] else ''})")
    if "duration_s" in s:
        print(f"duration   {s['duration_s']:.2f} s")
    for t, d in s["topics"].items():
        print(f"topic      {t:<28} {d['type']:<36} {d['messages']:>6} msgs")
    if "scan_error" in s:
        print(f"NOT A USABLE SCAN: {s['scan_error']}")
        return 1
    info = s["scan_info"]
    print(f"format     {info['format']}, projection units {info['projection_units']}, binning {info['binning']}")
    arc = s["arc_deg"]
    print(f"views      {s['paired_views']} paired frames, "
          + ("a full circle" if arc >= 360.0 else f"an arc of {arc:.1f} deg (a short scan: FDK uses Parker's weights)"
             if arc > 180.0 else f"an arc of {arc:.1f} deg, at most half a turn: FDK is approximate"))
    print(f"detector   {s['detector']}")
    print(f"geometry   SDD {s['source_to_detector_mm']:.1f} mm, magnification {s['magnification']:.3f}, "
          f"centre {np.round(s['scan_center_mm'], 3).tolist()} mm")
    print(f"pixels     {_share_percent(s['valid_pixel_fraction'])} % valid")
    print(f"extras     corrected geometry: {'yes' if s['has_geometry_corrected'] else 'no'}, "
          f"true geometry: {'yes' if s['has_geometry_true'] else 'no'}")
    if info.get("phantom"):
        print(f"phantom    {info['phantom']}")
    if "opposed_rays" in s:
        o = s["opposed_rays"]
        print(f"centre     opposed rays not checked: {o['not_checked']}" if "not_checked" in o else
              f"centre     opposed rays agree best with every detector shifted {o['best_shift_px']:+.3f} px "
              f"({o['best_shift_mm']:+.4f} mm) along u: the stated centre of rotation's error as the data see it")
        if o.get("by_ray_distance"):
            parts = ", ".join(f"within {100 * float(f):.0f} % {v:+.3f} px" for f, v in o["by_ray_distance"].items())
            print(f"centre     by the rays' distance from the centre: {parts} "
                  f"(one geometry explains the scan where these agree)")
    for w in s["warnings"]:
        print(f"warning    {w}")
    return 0


def _paths(args):
    """(bag, out) made absolute, ``out`` created and checked writable before any work: the reports then
    name files independently of the current directory, and a bad ``--out`` is refused at once."""
    from pathlib import Path

    from robot_ct_ros.jobs.output import prepare_out

    return Path(args.bag).expanduser().absolute(), prepare_out(args.out)


def _cmd_reconstruct(args) -> int:
    from robot_ct_ros.jobs.reconstruct import reconstruct_bag

    bag, out = _paths(args)
    reconstruct_bag(bag, out, geometry=args.geometry, voxel_mm=args.voxel_mm, shape_xyz=args.shape)
    return 0


def _cmd_calibrate(args) -> int:
    from robot_ct_ros.jobs.calibrate import calibrate_bag

    bag, out = _paths(args)
    calibrate_bag(bag, out, settings_from_args(args), voxel_mm=args.voxel_mm, shape_xyz=args.shape)
    return 0


def _cmd_report(args) -> int:
    from robot_ct_ros.ct.calibration import get_method
    from robot_ct_ros.jobs.report import report_bag

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:  # refused before anything is created
        get_method(m)
    settings = settings_from_args(args)
    bag, out = _paths(args)
    report_bag(bag, out, methods, settings, voxel_mm=args.voxel_mm, shape_xyz=args.shape)  # checks the memory
    return 0


def _cmd_import(args) -> int:
    from robot_ct_ros.jobs.output import prepare_out

    if args.source == "htc2022":
        from robot_ct_ros.jobs.htc2022 import import_htc2022

        import_htc2022(args.file, prepare_out(args.out, must_not_exist=True))
        return 0
    from robot_ct_ros.jobs import importers

    raw = dict(counts=args.counts, flat=args.flat, dark=args.dark)
    if not args.counts and (args.flat or args.dark):
        raise ValueError("--flat and --dark go with --counts (raw counts); without it the projections are line "
                         "integrals")
    for name in ("projections", "geometry", "vectors", "flat", "dark"):  # a missing input is refused before --out
        path = getattr(args, name, None)
        if path is not None:
            with open(path, "rb"):
                pass
    if args.source == "rtk":
        importers.import_rtk(args.projections, args.geometry, prepare_out(args.out, must_not_exist=True),
                             pitch_mm=args.pitch_mm, origin_mm=args.origin_mm, **raw)
    else:
        importers.import_astra(args.projections, args.vectors, prepare_out(args.out, must_not_exist=True),
                               layout=args.layout, row_pitch_mm=args.row_pitch_mm, **raw)
    return 0


def _cmd_export(args) -> int:
    from pathlib import Path

    from robot_ct_ros.jobs.export import export_geometry

    export_geometry(Path(args.bag).expanduser().absolute(), Path(args.out).expanduser().absolute(), args.format,
                    corrected=args.corrected, rtk_frame_choice=args.rtk_frame)
    return 0


def _cmd_demo(args) -> int:
    from robot_ct_ros.testing.demo import run_demo

    return run_demo(args.out, quick=args.quick, views=args.views, rows=args.rows, cols=args.cols,
                    phantom=args.phantom, method=args.method, iterations=args.iterations, truncated=args.truncated)


def _import_layouts():
    from robot_ct_ros.jobs.importers import LAYOUTS

    return LAYOUTS


def build_parser() -> argparse.ArgumentParser:
    from robot_ct_ros.ct.calibration import method_names
    from robot_ct_ros.testing.demo import DEFAULTS as DEMO
    from robot_ct_ros.jobs.reconstruct import GEOMETRIES
    from robot_ct_ros.jobs.report import REPORT_METHODS
    from robot_ct_ros.jobs.simulate import PHANTOMS

    parser = argparse.ArgumentParser(prog="robot-ct", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    whole = _positive("a count", int)

    def scan_views(text: str) -> int:  # a bag with fewer views is no scan (bag.reader.MIN_VIEWS)
        from robot_ct_ros.bag.reader import MIN_VIEWS

        n = whole(text)
        if n < MIN_VIEWS:
            raise argparse.ArgumentTypeError(f"a scan needs at least {MIN_VIEWS} views, got {n}")
        return n

    p = sub.add_parser("demo", help="scan, record and correct a simulated robotic interior scan end to end")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--quick", action="store_true", help="a tiny run: 12 views, 32 x 64 detector, 1 iteration")
    p.add_argument("--views", type=scan_views, default=None, help=f"number of views (default {DEMO['views']})")
    p.add_argument("--rows", type=whole, default=None, help=f"detector rows, binned (default {DEMO['rows']})")
    p.add_argument("--cols", type=whole, default=None, help=f"detector columns, binned (default {DEMO['cols']})")
    p.add_argument("--phantom", choices=PHANTOMS, default=None, help=f"simulated object (default {DEMO['phantom']})")
    p.add_argument("--method", choices=method_names(), default=None,
                   help=f"calibration method (default {DEMO['method']}; none: no correction)")
    p.add_argument("--iterations", type=whole, default=None,
                   help="outer calibration iterations (default: the calibration's, 2, or 8 with the exterior model)")
    p.add_argument("--truncated", action="store_true",
                   help="interior scan of the whole phantom (truncated projections) instead of an object inside "
                        "the field of view")

    p = sub.add_parser("simulate", help="simulate a robotic ROI scan of a phantom into a scan bag")
    p.add_argument("--phantom", choices=PHANTOMS, default="carotid", help="simulated object (default carotid)")
    p.add_argument("--views", type=scan_views, default=360, help="number of views (default 360)")
    p.add_argument("--rows", type=whole, default=272, help="detector rows after binning (default 272)")
    p.add_argument("--cols", type=whole, default=636, help="detector columns after binning (default 636)")
    p.add_argument("--binning", type=whole, default=2, help="readout binning of the 55 um pixels (default 2)")
    p.add_argument("--sigma-mm", type=_non_negative("sigma-mm"), default=0.1,
                   help="robot error per view, translations (mm; default 0.1)")
    p.add_argument("--sigma-deg", type=_non_negative("sigma-deg"), default=0.1,
                   help="robot error per view, detector rotations (deg; default 0.1)")
    p.add_argument("--drift-mm", type=float, default=0.0,
                   help="detector drift over the whole scan, linear, each of its translations (mm; default 0)")
    p.add_argument("--drift-deg", type=float, default=0.0,
                   help="detector drift over the whole scan, linear, each of its rotations (deg; default 0)")
    p.add_argument("--photons", type=_positive("photons"), default=None,
                   help="unattenuated counts per binned pixel per frame (default: 4,000 behind 13 cm of water)")
    p.add_argument("--fov-mm", type=_positive("fov-mm"), default=None,
                   help="field-of-view diameter (default: the centred detector's)")
    p.add_argument("--sim-voxel-mm", type=_positive("sim-voxel-mm"), default=None,
                   help="voxel of the phantom in the ROI (default: half the reconstruction voxel, at most 200^3 voxels)")
    p.add_argument("--arc-deg", type=_arc_deg, default=360.0,
                   help="the arc the views spread over (deg, default 360); below 360 a short scan, the first view at "
                        "0 and the last at the arc (Parker's weights from half a turn plus the fan)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, help="output bag directory (must not exist)")

    p = sub.add_parser("import", help="write another lab's scan data as a scan bag")
    isub = p.add_subparsers(dest="source", required=True)
    q = isub.add_parser("htc2022", help="a Helsinki Tomography Challenge 2022 *_full.mat (fan beam, 1-row detector; "
                                        "geometry conventions: robot_ct_ros/jobs/htc2022.py)")
    q.add_argument("file", help="the .mat file (struct CtDataFull with sinogram and parameters)")
    q.add_argument("--out", required=True, help="output bag directory (must not exist)")
    for name, helptext in (("rtk", "projections with an RTK ThreeDCircularProjectionGeometry XML (needs itk-rtk)"),
                           ("astra", "projections with ASTRA cone_vec (n x 12) or fanflat_vec (n x 6) vectors")):
        q = isub.add_parser(name, help=f"{helptext}; conventions: robot_ct_ros/jobs/importers.py")
        q.add_argument("--projections", required=True, metavar="P",
                       help="a .npy or TIFF stack of line integrals (or raw counts with --counts)"
                            + (", (views, rows, cols)" if name == "rtk" else ""))
        if name == "rtk":
            q.add_argument("--geometry", required=True, metavar="G.xml", help="RTK's geometry XML")
            q.add_argument("--pitch-mm", type=_pair("--pitch-mm", True), required=True, metavar="ROW,COL",
                           help="detector pixel pitch between rows and between columns (mm; one value is taken "
                                "for both); RTK's XML holds none")
            q.add_argument("--origin-mm", type=_pair("--origin-mm", False), default=None, metavar="ROW,COL",
                           help="RTK projection stack origin, physical position of pixel (0, 0) (mm; default "
                                "centred: -(n-1)/2 * pitch; one value is taken for both); rows first, so RTK's "
                                "origin (x, y, 0) is y,x here")
        else:
            q.add_argument("--vectors", required=True, metavar="V", help="ASTRA vectors, .npy or text")
            q.add_argument("--layout", choices=_import_layouts(), default="views-first",
                           help="views-first: (views, rows, cols) [default]; astra: ASTRA's 3-D (rows, views, cols)")
            q.add_argument("--row-pitch-mm", type=_positive("--row-pitch-mm"), default=None,
                           help="fanflat_vec: the one row's height (mm; default the column pitch)")
        q.add_argument("--counts", action="store_true", help="P holds raw counts: needs --flat")
        q.add_argument("--flat", default=None, metavar="F", help="flat field with --counts (a frame, or a stack averaged)")
        q.add_argument("--dark", default=None, metavar="D", help="dark frame with --counts (a frame, or a stack averaged)")
        q.add_argument("--out", required=True, help="output bag directory (must not exist)")

    p = sub.add_parser("export", help="write a bag's geometry (or a calibration's corrected one) for RTK, ASTRA or TIGRE")
    p.add_argument("bag")
    p.add_argument("--format", choices=("rtk", "astra", "tigre"), required=True,
                   help="rtk: RTK ThreeDCircularProjectionGeometry XML (needs itk-rtk); astra: cone_vec rows of 12 "
                        "numbers per view (.npy, else text); tigre: TIGRE's per-view arrays (.npz; "
                        "robot_ct_ros/jobs/tigre.py)")
    p.add_argument("--corrected", default=None, metavar="DIR_OR_REPORT",
                   help="write the corrected geometry of this calibration output (robot-ct calibrate's --out folder, "
                        "its report.json, or a corrected bag) instead of the bag's nominal one")
    p.add_argument("--rtk-frame", choices=("auto", "scan", "world"), default=None,
                   help="--format rtk: the frame of the XML. scan: the scan axis is RTK's +y and the orbit's centre "
                        "its origin, so that RTK's gantry angle follows the views (its FDK needs that); world: the "
                        "bag's world as it is; auto (default): world where the scan already turns about the world's "
                        "+-y through the origin, else scan. The frame is printed and written beside the XML "
                        "(<stem>.rtk_frame.json: the 4x4 world->RTK matrix)")
    p.add_argument("--out", required=True, help="output file")

    p = sub.add_parser("info", help="summarise a bag (topics, scan, pairing, damage)")
    p.add_argument("bag")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")

    for name, helptext in (("reconstruct", "FDK of a scan bag with its geometry"),
                           ("calibrate", "correct the per-view geometry of a scan bag offline and reconstruct"),
                           ("report", "compare calibration methods on a scan bag: slice, RMSE and parameter-error "
                                      "figures and a table")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("bag")
        p.add_argument("--out", required=True, help="output folder")
        p.add_argument("--voxel-mm", type=_positive("voxel-mm"), default=None,
                       help="voxel size (default: scan_info or pitch/M)")
        p.add_argument("--shape", type=_shape, default=None, help="grid NX,NY,NZ (default: scan_info ROI or FOV)")
        if name == "reconstruct":
            p.add_argument("--geometry", choices=GEOMETRIES, default="auto",
                           help="auto: /ct/geometry_corrected when present")
            continue
        if name == "calibrate":
            p.add_argument("--method", default=None, choices=method_names(), metavar="METHOD",
                           help=f"one of {', '.join(method_names())} (none: no correction; default ncc-lle-exact)")
        else:
            p.add_argument("--methods", default=",".join(REPORT_METHODS),
                           help="comma-separated: none (nominal geometry) and calibration methods "
                                f"(default {','.join(REPORT_METHODS)}); the bag's corrected and true "
                                "geometries are added when it holds them")
        add_settings_arguments(p)
    return parser


def _negative_lists_attached(argv: list[str]) -> list[str]:
    """``--origin-mm -25,-10`` as ``--origin-mm=-25,-10``: argparse takes a value that starts with '-' for an
    option unless it is a single negative number, and RTK's centred origins are negative pairs."""
    out, i = [], 0
    while i < len(argv):
        if (argv[i].startswith("--") and "=" not in argv[i] and i + 1 < len(argv)
                and re.fullmatch(r"-[\d.][^\s]*,[^\s]*", argv[i + 1])):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``), raised in the main thread so that a command cleans up as after Ctrl-C."""


_stop_signal: list = []
"""The stop signals (SIGINT, SIGTERM) this command received: the exception a signal raises inside a C extension
comes out as that extension's error (rclpy's take_message: "RuntimeError: Unable to convert call argument"), and
is then reported as the stop it was."""


def _raise_terminated(signum, frame):
    _stop_signal.append(signum)
    raise Terminated()


def _raise_interrupted(signum, frame):
    _stop_signal.append(signum)
    raise KeyboardInterrupt()


def main(argv: list[str] | None = None) -> int:
    import signal
    import threading

    on_main = threading.current_thread() is threading.main_thread()
    _stop_signal.clear()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if on_main else None
    # Ctrl-C as Python's default handler takes it, recorded; an ignored SIGINT (a background job) stays ignored
    previous_int = (signal.signal(signal.SIGINT, _raise_interrupted)
                    if on_main and signal.getsignal(signal.SIGINT) is signal.default_int_handler else None)
    try:
        return _main(argv)
    finally:
        if on_main:
            signal.signal(signal.SIGTERM, previous)
            if previous_int is not None:
                signal.signal(signal.SIGINT, previous_int)


def _main(argv: list[str] | None = None) -> int:
    try:  # building the parser imports the settings (numba): a signal may come that early
        args = build_parser().parse_args(_negative_lists_attached(list(sys.argv[1:] if argv is None else argv)))
    except KeyboardInterrupt:
        return _failed(None)
    commands = {"demo": _cmd_demo, "simulate": _cmd_simulate, "info": _cmd_info, "reconstruct": _cmd_reconstruct,
                "calibrate": _cmd_calibrate, "report": _cmd_report, "import": _cmd_import,
                "export": _cmd_export}
    out = Path(args.out) if isinstance(getattr(args, "out", None), str) else None
    created = out if out is not None and not out.exists() else None  # removed again if the command leaves it empty
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # numpy's on masked pixels; the jobs report what counts
            code = commands[args.command](args)
    except BaseException:
        _remove_if_empty(created)  # a refused or stopped command leaves no empty --out behind
        return _failed(args.command, out)
    if code:
        _remove_if_empty(created)
    return code


def _remove_if_empty(folder) -> None:
    try:
        if folder is not None and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    except OSError:
        pass


def _stdout_closed() -> bool:
    """Whether standard output's reader has gone (a pipe closed); if so, output goes to the null device from now
    on, so that the interpreter's last flush does not fail again."""
    import os
    import select

    try:
        fd = sys.stdout.fileno()
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        if not any(events & select.POLLERR for _, events in poll.poll(0)):  # a pipe without a reader: POLLERR
            return False
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
        return True
    except (OSError, ValueError, AttributeError):  # no file descriptor (captured output), or no poll here
        return False


def _failed(command: str | None, out: Path | None = None) -> int:
    """The exit status and one line for the exception being handled (no traceback for the expected ones);
    ``command`` None: before the command was known; ``out`` the command's output folder, if any."""
    prog = "robot-ct" if command is None else f"robot-ct {command}"
    from robot_ct_ros.bag import ScanBagError

    import signal

    try:
        if _stop_signal and not isinstance(sys.exc_info()[1], KeyboardInterrupt):
            # the stop raised inside a C extension, which turned it into its own error
            raise (Terminated if _stop_signal[0] == signal.SIGTERM else KeyboardInterrupt)() from None
        raise
    except (ScanBagError, ValueError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the job's own cleanup has run; no traceback
        terminated = isinstance(exc, Terminated)
        left = f" ({out} holds no complete result of this run)" if out is not None and out.exists() else ""
        print(f"{prog}: {'terminated (SIGTERM)' if terminated else 'interrupted'}{left}", file=sys.stderr)
        return 143 if terminated else 130
    except MemoryError as exc:  # the estimate before allocating was too optimistic
        print(f"{prog}: out of memory ({exc or 'allocation failed'}); use a smaller --shape or a "
              "larger --voxel-mm", file=sys.stderr)
        return 2
    except BrokenPipeError as exc:
        if _stdout_closed():  # `robot-ct info BAG | head -1`: the reader went away, as Unix tools take it
            return 141
        print(f"{prog}: cannot access: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file that cannot be read or written, with its name
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        print(f"{prog}: cannot access{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
