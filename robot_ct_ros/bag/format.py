"""The scan bag contract (``robot_ct_ros.scan/1``): topics, message layouts, units, conversions.

A scan bag is a rosbag2 bag (MCAP storage, CDR, ``ros2msg`` schemas) whose topics carry
standard ROS 2 Jazzy messages; docs/bag-format.md is the normative
text. This module is the only place where ROS units (metres, REP 103) meet the core's
millimetres (robot_ct_ros.ct.geometry): every conversion happens here.

Messages are rosbags typestore objects (``rosbags.typesys.Stores.ROS2_JAZZY``); their CDR
bytes are exactly what rclpy publishes, so the nodes pass bytes through unchanged.
"""

from __future__ import annotations

import json
import math
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.geometry import ConeGeometry

FORMAT = "robot_ct_ros.scan/1"
FORMAT_PREFIX = "robot_ct_ros.scan/"
FORMAT_MAJOR = 1

# ------------------------------------------------------------------------------ topics
TOPIC_SCAN_INFO = "/ct/scan_info"
TOPIC_PROJECTION = "/ct/projection"
TOPIC_PROJECTION_REJECTED = "/ct/projection_rejected"  # frames the acquisition rejected: never projections
TOPIC_GEOMETRY = "/ct/geometry"
TOPIC_FLAT_FIELD = "/ct/flat_field"
TOPIC_DEAD_PIXELS = "/ct/dead_pixels"
TOPIC_GEOMETRY_CORRECTED = "/ct/geometry_corrected"
TOPIC_GEOMETRY_LIVE = "/ct/geometry_live"  # recon_service stream=true: each view's live estimate (not in bags)
TOPIC_GEOMETRY_TRUE = "/ct/geometry_true"  # simulation only: the geometry the data was simulated with
TOPIC_SOURCE_POSE = "/source_arm/tool_pose"
TOPIC_DETECTOR_POSE = "/detector_arm/tool_pose"
TOPIC_DIAGNOSTICS = "/diagnostics"
TOPIC_BEAM_ON = "/source/beam_on"

STRING = "std_msgs/msg/String"
BOOL = "std_msgs/msg/Bool"
IMAGE = "sensor_msgs/msg/Image"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

TOPIC_TYPES = {
    TOPIC_SCAN_INFO: STRING,
    TOPIC_PROJECTION: IMAGE,
    TOPIC_PROJECTION_REJECTED: IMAGE,
    TOPIC_GEOMETRY: POSE_ARRAY,
    TOPIC_FLAT_FIELD: IMAGE,
    TOPIC_DEAD_PIXELS: IMAGE,
    TOPIC_GEOMETRY_CORRECTED: POSE_ARRAY,
    TOPIC_GEOMETRY_TRUE: POSE_ARRAY,
    TOPIC_SOURCE_POSE: POSE_STAMPED,
    TOPIC_DETECTOR_POSE: POSE_STAMPED,
    TOPIC_DIAGNOSTICS: DIAGNOSTIC_ARRAY,
    TOPIC_BEAM_ON: BOOL,
}
"""Every topic the contract names, with its message type."""

GLOBAL_TOPICS = (TOPIC_DIAGNOSTICS,)
"""Contract topics the nodes keep absolute: /diagnostics, as ROS tools (aggregator, rqt) expect; every
status is named after its node's fully qualified name, so two scanners' statuses stay apart."""


def node_topic(topic: str) -> str:
    """The name under which the nodes publish and subscribe a contract topic: relative (``ct/projection``),
    so the node's namespace applies and ``-r __ns:=/scanner_a`` moves a whole scanner; bags keep the
    contract's absolute names (``/ct/projection``) whatever the namespace. /diagnostics stays absolute."""
    return topic if topic in GLOBAL_TOPICS else topic.lstrip("/")


LATCHED_TOPICS = (TOPIC_SCAN_INFO, TOPIC_FLAT_FIELD, TOPIC_DEAD_PIXELS)
"""Published once per scan, transient-local (late subscribers such as the recorder get them)."""

STATE_TOPICS = (TOPIC_BEAM_ON,)
"""Published on every change, transient-local with depth 1 (the last state for a late subscriber), as live: their
bag metadata says so, so that a replay (``replay``, ``ros2 bag play``) republishes them to the transient-local
subscribers of the nodes (the recorder, the orchestrator), which a volatile publisher never matches."""

FRAME_DETECTOR = "pcd_detector"
FRAME_WORLD = "world"

ENCODING_FRAME = "32FC1"
ENCODING_MASK = "mono8"
READ_ENCODINGS = ("32FC1", "16UC1", "mono16", "32SC1")
"""Encodings accepted on /ct/projection and /ct/flat_field when reading."""

PROJECTION_UNITS = ("counts", "line_integral")

M_PER_MM = 1e-3
MM_PER_M = 1e3


class ScanBagError(Exception):
    """A scan bag that cannot be used (the message says why and what was found)."""


class TooFewViewsError(ScanBagError):
    """Too few frames paired with a geometry are usable (``causes``: why frames or geometries were not used).
    Raised for the scan's messages themselves, not for a missing scan_info or flat field: the live path
    (robot_ct_ros.jobs.streaming), which decodes a few frames at a time, counts such frames as dropped."""

    def __init__(self, message: str, causes=()):
        super().__init__(message)
        self.causes = list(causes)


# ------------------------------------------------------------------------------ QoS
def _qos(depth: int, latched: bool):
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(9223372036, 854775807)  # rmw's "infinite" duration, as rosbag2 Jazzy writes it
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               infinite, infinite, QosLiveliness.AUTOMATIC, infinite, False)


def offered_qos(topic: str):
    """The QoS profile a contract topic is published with (rosbags ``Qos``), for the bag metadata.

    Latched and state topics: reliable, transient-local, keep-last 1. Frame/geometry streams: reliable,
    volatile, keep-last 100. Anything else: reliable, volatile, keep-last 10.
    """
    if topic in LATCHED_TOPICS or topic in STATE_TOPICS:
        return _qos(1, True)
    if topic in (TOPIC_PROJECTION, TOPIC_PROJECTION_REJECTED, TOPIC_GEOMETRY, TOPIC_GEOMETRY_CORRECTED,
                 TOPIC_GEOMETRY_TRUE):
        return _qos(100, False)
    return _qos(10, False)


@lru_cache(maxsize=1)
def typestore():
    """The rosbags typestore of ROS 2 Jazzy (message classes, CDR (de)serialisation)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def serialize(msg, msgtype: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(data, msgtype: str):
    return typestore().deserialize_cdr(bytes(data) if isinstance(data, memoryview) else data, msgtype)


# ------------------------------------------------------------------------------ time
def ns_to_stamp(ns: int):
    """builtin_interfaces/Time from integer nanoseconds since the epoch."""
    Time = typestore().types["builtin_interfaces/msg/Time"]
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header(stamp_ns: int, frame_id: str):
    Header = typestore().types["std_msgs/msg/Header"]
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


# ------------------------------------------------------------------------------ scan info
def make_scan_info(n_rows: int, n_cols: int, row_pitch_mm: float, col_pitch_mm: float, *, binning: int = 1,
                   projection_units: str = "counts", roi_center_mm=None, roi_size_mm=None, voxel_size_mm=None,
                   n_views: int | None = None, phantom: str | None = None, notes=None, **extra) -> dict:
    """The /ct/scan_info JSON object (SI units) from core (mm) values; validated."""
    info = {"format": FORMAT, "n_rows": int(n_rows), "n_cols": int(n_cols),
            "row_pitch_m": float(row_pitch_mm) * M_PER_MM, "col_pitch_m": float(col_pitch_mm) * M_PER_MM,
            "binning": int(binning), "projection_units": projection_units}
    if roi_center_mm is not None:
        info["roi_center_m"] = [float(x) * M_PER_MM for x in np.broadcast_to(roi_center_mm, (3,))]
    if roi_size_mm is not None:
        info["roi_size_m"] = [float(x) * M_PER_MM for x in np.broadcast_to(roi_size_mm, (3,))]
    if voxel_size_mm is not None:
        info["voxel_size_m"] = [float(x) * M_PER_MM for x in np.broadcast_to(voxel_size_mm, (3,))]
    if n_views is not None:
        info["n_views"] = int(n_views)
    if phantom is not None:
        info["phantom"] = str(phantom)
    if notes is not None:
        info["notes"] = notes
    info.update(extra)
    return validate_scan_info(info)


def scan_info_for(geom: ConeGeometry, **kw) -> dict:
    """:func:`make_scan_info` with the detector of ``geom`` and ``n_views``."""
    kw.setdefault("n_views", geom.n_views)
    return make_scan_info(geom.n_rows, geom.n_cols, geom.row_pitch_mm, geom.col_pitch_mm, **kw)


def _vec3(info: dict, key: str):
    val = info.get(key)
    if val is None:
        return None
    arr = np.asarray(val, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.repeat(arr, 3)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ScanBagError(f"/ct/scan_info: {key} must be a number or 3 finite numbers, got {val!r}")
    return arr


def validate_scan_info(info) -> dict:
    """Check a parsed /ct/scan_info object; returns it (a dict) or raises ScanBagError."""
    if not isinstance(info, dict):
        raise ScanBagError(f"/ct/scan_info must hold a JSON object, got {type(info).__name__}")
    fmt = info.get("format")
    if not isinstance(fmt, str) or not fmt.startswith(FORMAT_PREFIX):
        raise ScanBagError(f"/ct/scan_info: format must be {FORMAT!r}, got {fmt!r}")
    try:
        major = int(fmt[len(FORMAT_PREFIX):].split(".")[0])
    except ValueError:
        raise ScanBagError(f"/ct/scan_info: cannot parse the format version of {fmt!r}") from None
    if major != FORMAT_MAJOR:
        raise ScanBagError(f"/ct/scan_info: format {fmt!r} is not supported (this reader reads {FORMAT!r})")
    missing = [k for k in ("n_rows", "n_cols", "row_pitch_m", "col_pitch_m") if k not in info]
    if missing:
        raise ScanBagError(f"/ct/scan_info lacks {', '.join(missing)}")
    for k in ("n_rows", "n_cols"):
        if not isinstance(info[k], int) or isinstance(info[k], bool) or info[k] < 1:
            raise ScanBagError(f"/ct/scan_info: {k} must be a positive integer, got {info[k]!r}")
    for k in ("row_pitch_m", "col_pitch_m"):
        v = info[k]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v <= 0:
            raise ScanBagError(f"/ct/scan_info: {k} must be a positive number of metres, got {v!r}")
        if v > 0.01:
            raise ScanBagError(f"/ct/scan_info: {k} = {v} m is larger than 1 cm: pitches are in metres, not mm")
    units = info.setdefault("projection_units", "counts")
    if units not in PROJECTION_UNITS:
        raise ScanBagError(f"/ct/scan_info: projection_units must be one of {PROJECTION_UNITS}, got {units!r}")
    b = info.setdefault("binning", 1)
    if not isinstance(b, int) or isinstance(b, bool) or b < 1:
        raise ScanBagError(f"/ct/scan_info: binning must be a positive integer, got {b!r}")
    for k in ("roi_center_m", "roi_size_m", "voxel_size_m"):
        _vec3(info, k)
    for k in ("roi_size_m", "voxel_size_m"):
        if info.get(k) is not None and np.any(_vec3(info, k) <= 0):
            raise ScanBagError(f"/ct/scan_info: {k} must be positive")
    d = info.get("roi_direction")
    if d is not None:
        try:
            D = np.asarray(d, dtype=np.float64).reshape(3, 3)
        except (TypeError, ValueError):
            D = None
        if D is None or not np.all(np.isfinite(D)) or np.abs(D.T @ D - np.eye(3)).max() > 1e-6 \
                or np.linalg.det(D) < 0:
            raise ScanBagError("/ct/scan_info: roi_direction must be 9 numbers, a rotation matrix row by row "
                               "(its columns are the ROI grid's x, y, z axes in the world)")
    return info


def scan_info_to_msg(info: dict):
    String = typestore().types[STRING]
    return String(data=json.dumps(validate_scan_info(dict(info))))


def scan_info_from_msg(msg) -> dict:
    try:
        info = json.loads(msg.data)
    except json.JSONDecodeError as exc:
        raise ScanBagError(f"/ct/scan_info is not valid JSON: {exc}") from None
    return validate_scan_info(info)


def scan_id_of(info) -> str:
    """The scan's id a parsed /ct/scan_info names (``notes.scan_id``, the scan_sequencer's), "" when it names none."""
    notes = info.get("notes") if isinstance(info, dict) else None
    return str(notes.get("scan_id", "")) if isinstance(notes, dict) else ""


def info_mm(info: dict, key: str):
    """An optional 3-vector of the scan info converted to mm (None when absent)."""
    v = _vec3(info, key)
    return None if v is None else v * MM_PER_M


# ------------------------------------------------------------------------------ images
_DTYPES = {"32FC1": np.float32, "16UC1": np.uint16, "mono16": np.uint16, "32SC1": np.int32,
           "mono8": np.uint8, "8UC1": np.uint8}


def image_from_array(arr, stamp_ns: int, frame_id: str = FRAME_DETECTOR, encoding: str = ENCODING_FRAME):
    """sensor_msgs/Image (little endian, row-major, step = width * bytes) from a 2D array."""
    a = np.asarray(arr)
    if a.ndim != 2:
        raise ValueError(f"an image must be 2D (rows, cols), got shape {a.shape}")
    if encoding not in _DTYPES:
        raise ValueError(f"unsupported encoding {encoding!r}")
    a = np.ascontiguousarray(a, dtype=np.dtype(_DTYPES[encoding]).newbyteorder("<"))
    Image = typestore().types[IMAGE]
    return Image(header=header(stamp_ns, frame_id), height=a.shape[0], width=a.shape[1], encoding=encoding,
                 is_bigendian=0, step=a.shape[1] * a.itemsize, data=a.view(np.uint8).reshape(-1).copy())


def mask_image(bad, stamp_ns: int, frame_id: str = FRAME_DETECTOR):
    """/ct/dead_pixels image: mono8, 1 = unusable pixel, 0 = good."""
    return image_from_array(np.asarray(bad, bool).astype(np.uint8), stamp_ns, frame_id, ENCODING_MASK)


def array_from_image(msg, encodings=None) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as a (height, width) array (float32 for non-mono8).

    Honours ``step`` (row padding) and ``is_bigendian``. Raises ValueError (with the reason)
    for an unsupported encoding or a data size that does not fit height, width and step.
    """
    enc = msg.encoding
    allowed = tuple(_DTYPES) if encodings is None else tuple(encodings)
    if enc not in allowed or enc not in _DTYPES:
        raise ValueError(f"unsupported image encoding {enc!r} (accepted: {', '.join(allowed)})")
    dt = np.dtype(_DTYPES[enc]).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if h < 1 or w < 1:
        raise ValueError(f"empty image {h}x{w}")
    if step < w * dt.itemsize:
        raise ValueError(f"step {step} is smaller than width {w} x {dt.itemsize} bytes")
    if raw.size < step * (h - 1) + w * dt.itemsize:
        raise ValueError(f"image data holds {raw.size} bytes, {h}x{w} {enc} with step {step} needs {step * h}")
    if raw.size < step * h:  # tolerate a missing padding after the last row
        raw = np.concatenate([raw, np.zeros(step * h - raw.size, np.uint8)])
    rows = raw[: step * h].reshape(h, step)[:, : w * dt.itemsize]
    out = np.ascontiguousarray(rows).view(dt).reshape(h, w)
    return out.astype(np.uint8) if enc in ("mono8", "8UC1") else out.astype(np.float32)


# ------------------------------------------------------------------------------ geometry
def _point(xyz):
    Point = typestore().types["geometry_msgs/msg/Point"]
    return Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def _quat(xyzw):
    Quaternion = typestore().types["geometry_msgs/msg/Quaternion"]
    return Quaternion(x=float(xyzw[0]), y=float(xyzw[1]), z=float(xyzw[2]), w=float(xyzw[3]))


def view_pose_array(source_mm, detector_mm, u, v, stamp_ns: int, frame_id: str = FRAME_WORLD):
    """geometry_msgs/PoseArray of one view (metres): poses[0] source, poses[1] detector centre + (u, v, w)."""
    types = typestore().types
    R = np.stack([np.asarray(u, float), np.asarray(v, float), np.cross(u, v)], axis=1)
    q = Rotation.from_matrix(R).as_quat()  # (x, y, z, w)
    if q[3] < 0:
        q = -q
    Pose = types["geometry_msgs/msg/Pose"]
    poses = [Pose(position=_point(np.asarray(source_mm, float) * M_PER_MM), orientation=_quat((0, 0, 0, 1))),
             Pose(position=_point(np.asarray(detector_mm, float) * M_PER_MM), orientation=_quat(q))]
    return types[POSE_ARRAY](header=header(stamp_ns, frame_id), poses=poses)


def geometry_pose_arrays(geom: ConeGeometry, stamps_ns, frame_id: str = FRAME_WORLD) -> list:
    """One PoseArray per view of ``geom`` with the given stamps (the frames' stamps)."""
    stamps = list(stamps_ns)
    if len(stamps) != geom.n_views:
        raise ValueError(f"{len(stamps)} stamps for {geom.n_views} views")
    return [view_pose_array(geom.source_mm[i], geom.detector_mm[i], geom.u[i], geom.v[i], stamps[i], frame_id)
            for i in range(geom.n_views)]


def view_from_pose_array(msg):
    """(source_mm, detector_mm, u, v) of a /ct/geometry PoseArray; ValueError when it is unusable."""
    if len(msg.poses) < 2:
        raise ValueError(f"a geometry PoseArray needs 2 poses (source, detector), got {len(msg.poses)}")
    p0, p1 = msg.poses[0].position, msg.poses[1].position
    o = msg.poses[1].orientation
    with np.errstate(all="ignore"):  # damaged messages may hold any bit pattern
        s = np.array([p0.x, p0.y, p0.z], float) * MM_PER_M
        d = np.array([p1.x, p1.y, p1.z], float) * MM_PER_M
        q = np.array([o.x, o.y, o.z, o.w], float)
        if not (np.all(np.isfinite(s)) and np.all(np.isfinite(d)) and np.all(np.isfinite(q))):
            raise ValueError("geometry holds NaN or infinite values")
        n = float(np.sqrt(np.sum(q * q)))
    if n < 1e-6:
        raise ValueError("detector orientation quaternion is zero")
    if abs(n - 1.0) > 1e-3:
        raise ValueError(f"detector orientation quaternion is not normalised (norm {n:.6f})")
    R = Rotation.from_quat(q / n).as_matrix()
    return s, d, R[:, 0], R[:, 1]


def geometry_from_views(views, n_rows: int, n_cols: int, row_pitch_mm: float, col_pitch_mm: float) -> ConeGeometry:
    """ConeGeometry (mm) from a list of (source_mm, detector_mm, u, v)."""
    s, d, u, v = (np.array([view[k] for view in views], float) for k in range(4))
    return ConeGeometry(source_mm=s, detector_mm=d, u=u, v=v, n_rows=n_rows, n_cols=n_cols,
                        row_pitch_mm=row_pitch_mm, col_pitch_mm=col_pitch_mm)


def as_transmitted(geom: ConeGeometry) -> ConeGeometry:
    """``geom`` as a reader gets it back from /ct/geometry_* messages (metres and quaternions
    round-tripped): what a published or recorded correction is, to the last bit."""
    views = [view_from_pose_array(m) for m in geometry_pose_arrays(geom, range(geom.n_views))]
    return geometry_from_views(views, geom.n_rows, geom.n_cols, geom.row_pitch_mm, geom.col_pitch_mm)
