"""Writing scan bags: incremental and crash-tolerant (rosbags' rosbag2 MCAP writer, version 9).

``ScanBagWriter`` writes one frame and its geometry per call. rosbags keeps messages in an
in-memory MCAP chunk (up to 1 MiB) and writes the summary section and metadata.yaml only
on close; to keep a crash from losing frames, the writer closes the chunk and flushes the
file after every frame (``flush_every_frame``), so a process killed mid-scan (SIGKILL, power
cut with ``fsync=True``) leaves an MCAP file holding every completed frame, without the
summary and metadata.yaml; :func:`robot_ct_ros.bag.reader.read_scan` recovers it. An
exception or SIGINT (KeyboardInterrupt) inside the ``with`` block still closes the bag
cleanly (rosbags' own context manager would abort it without an index).

Integrity: rosbags writes every MCAP chunk with a CRC of 0 ("none"); this writer fills in each
chunk's CRC-32 of its uncompressed records (MCAP specification), which rosbags, the ``mcap``
library and :func:`robot_ct_ros.bag.reader.read_raw_messages` verify when reading, so a flipped
byte is a reported damaged chunk instead of silently different pixels.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry

from . import format as fmt

BAG_CUSTOM_DATA_KEY = "robot_ct_ros.format"


class ScanBagWriter:
    """Write a scan bag at ``path`` (a new directory, rosbag2 layout).

    ``info`` is the /ct/scan_info object (:func:`robot_ct_ros.bag.format.make_scan_info`),
    written first with log time ``start_ns`` (default: the first stamp written, or now).

    Use as a context manager; ``write_frame(counts, view_geometry, stamp_ns)`` per view.
    ``frame_id``: the world frame every geometry written names (docs/bag-format.md: one frame per bag).
    """

    def __init__(self, path, info: dict | None, *, flush_every_frame: bool = True, fsync: bool = False,
                 start_ns: int | None = None, frame_id: str = fmt.FRAME_WORLD):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        self.info = None if info is None else fmt.validate_scan_info(dict(info))
        self.flush_every_frame = flush_every_frame
        self.fsync = fsync
        self.frame_id = frame_id
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.set_custom_data(BAG_CUSTOM_DATA_KEY, fmt.FORMAT)
        self._connections: dict[tuple[str, str], object] = {}
        self._start_ns = start_ns
        self._open = False
        self._closed = False
        self.n_frames = 0
        self.counts: dict[str, int] = {}

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "ScanBagWriter":
        if self._open:
            return self
        self._writer.open()
        _checksum_chunks(getattr(self._writer, "storage", None))
        self._open = True
        # the contract's topics are listed from the start (a bag cut short still names them); a scan of line
        # integrals has no flat field, and an empty /ct/flat_field would only puzzle ros2 bag info and Foxglove
        topics = [fmt.TOPIC_SCAN_INFO, fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY]
        if self.info is None or self.info.get("projection_units") == "counts":
            topics.append(fmt.TOPIC_FLAT_FIELD)
        for topic in topics:
            self._connection(topic, fmt.TOPIC_TYPES[topic])
        if self.info is not None:
            self.write_info(self.info, self._start_ns)
        return self

    def __enter__(self) -> "ScanBagWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()  # also on errors and KeyboardInterrupt: what was written stays readable
        return False

    def close(self) -> None:
        """Write the MCAP summary and metadata.yaml. Idempotent."""
        if self._open and not self._closed:
            self._closed = True
            self._writer.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def flush(self) -> None:
        """Push everything written so far into the file (complete MCAP chunk + message index)."""
        storage = getattr(self._writer, "storage", None)
        if storage is None:
            return
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and getattr(chunk, "msgs", None) and hasattr(storage, "close_chunk"):
            storage.close_chunk()
        bio = getattr(storage, "bio", None)
        if bio is not None:
            bio.flush()
            if self.fsync:
                os.fsync(bio.fileno())

    # ------------------------------------------------------------------ low level
    def _connection(self, topic: str, msgtype: str):
        key = (topic, msgtype)
        conn = self._connections.get(key)
        if conn is None:
            if not self._open:
                self.open()
            conn = self._writer.add_connection(topic, msgtype, typestore=fmt.typestore(),
                                               offered_qos_profiles=[fmt.offered_qos(topic)])
            self._connections[key] = conn
        return conn

    def _require_open(self):
        if self._closed:
            raise RuntimeError(f"scan bag {self.path} is closed")
        if not self._open:
            self.open()

    def write_raw(self, topic: str, msgtype: str, data: bytes, log_time_ns: int) -> None:
        """Write already serialised CDR bytes (as rclpy gives them with ``raw=True``)."""
        self._require_open()
        if self._start_ns is None:
            self._start_ns = int(log_time_ns)
        self._writer.write(self._connection(topic, msgtype), int(log_time_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_msg(self, topic: str, msg, log_time_ns: int, msgtype: str | None = None) -> None:
        """Write a rosbags message object."""
        msgtype = msgtype or msg.__msgtype__
        self.write_raw(topic, msgtype, fmt.serialize(msg, msgtype), log_time_ns)

    # ------------------------------------------------------------------ contract
    def write_info(self, info: dict, log_time_ns: int | None = None) -> None:
        self.info = fmt.validate_scan_info(dict(info))
        t = self._start_ns if log_time_ns is None else log_time_ns
        if t is None:
            import time
            t = time.time_ns()
        self.write_msg(fmt.TOPIC_SCAN_INFO, fmt.scan_info_to_msg(self.info), t, fmt.STRING)
        self.flush()

    def _check_shape(self, arr: np.ndarray, what: str):
        if self.info is not None and arr.shape != (self.info["n_rows"], self.info["n_cols"]):
            raise ValueError(f"{what} has shape {arr.shape}, scan_info says "
                             f"({self.info['n_rows']}, {self.info['n_cols']})")

    def write_flat(self, flat, stamp_ns: int) -> None:
        """/ct/flat_field: mean counts per frame without object (rows, cols)."""
        arr = np.asarray(flat, np.float32)
        self._check_shape(arr, "flat field")
        self.write_msg(fmt.TOPIC_FLAT_FIELD, fmt.image_from_array(arr, stamp_ns), stamp_ns, fmt.IMAGE)
        self.flush()

    def write_dead_pixels(self, bad, stamp_ns: int) -> None:
        """/ct/dead_pixels: True (written 1) = unusable pixel."""
        arr = np.asarray(bad, bool)
        self._check_shape(arr, "dead-pixel map")
        self.write_msg(fmt.TOPIC_DEAD_PIXELS, fmt.mask_image(arr, stamp_ns), stamp_ns, fmt.IMAGE)
        self.flush()

    def write_geometry(self, geom_view: ConeGeometry, stamp_ns: int, topic: str = fmt.TOPIC_GEOMETRY,
                       view: int = 0) -> None:
        """One view of ``geom_view`` (mm) as a PoseArray (m) on ``topic``, stamped ``stamp_ns``, in ``frame_id``."""
        msg = fmt.view_pose_array(geom_view.source_mm[view], geom_view.detector_mm[view], geom_view.u[view],
                                  geom_view.v[view], stamp_ns, self.frame_id)
        self.write_msg(topic, msg, stamp_ns, fmt.POSE_ARRAY)

    def write_frame(self, frame, geom_view: ConeGeometry | None, stamp_ns: int, view: int = 0, *,
                    corrected: ConeGeometry | None = None, true: ConeGeometry | None = None) -> None:
        """One projection (rows, cols; counts or line integrals per scan_info) and its geometry.

        ``geom_view``'s view ``view`` (and of ``corrected``/``true`` when given) is written with
        the same stamp (the pairing key). Flushes to disk unless ``flush_every_frame`` is off.
        """
        arr = np.asarray(frame, np.float32)
        self._check_shape(arr, "frame")
        if geom_view is not None and self.info is not None and geom_view.det_shape != arr.shape:
            raise ValueError(f"geometry detector {geom_view.det_shape} differs from the frame {arr.shape}")
        self.write_msg(fmt.TOPIC_PROJECTION, fmt.image_from_array(arr, stamp_ns), stamp_ns, fmt.IMAGE)
        if geom_view is not None:
            self.write_geometry(geom_view, stamp_ns, fmt.TOPIC_GEOMETRY, view)
        if corrected is not None:
            self.write_geometry(corrected, stamp_ns, fmt.TOPIC_GEOMETRY_CORRECTED, view)
        if true is not None:
            self.write_geometry(true, stamp_ns, fmt.TOPIC_GEOMETRY_TRUE, view)
        self.n_frames += 1
        if self.flush_every_frame:
            self.flush()


_CHUNK_CRC_OFFSET = 1 + 8 + 8 + 8 + 8  # opcode, record length, message start and end time, uncompressed size


def _checksum_chunks(storage) -> None:
    """Make rosbags' MCAP storage write each chunk's CRC-32 (it writes 0): the CRC of the chunk's
    uncompressed records is computed before the chunk is written and patched into its header after."""
    close_chunk = getattr(storage, "close_chunk", None)
    if close_chunk is None or not hasattr(storage, "chunk") or not hasattr(storage, "bio"):
        return  # another storage plugin, or a rosbags version without these internals: CRC stays 0

    def close_chunk_with_crc() -> None:
        crc = zlib.crc32(storage.chunk.bio.getbuffer()) & 0xFFFFFFFF
        start = storage.bio.tell()
        close_chunk()
        end = storage.bio.tell()
        storage.bio.seek(start + _CHUNK_CRC_OFFSET)
        storage.bio.write(struct.pack("<I", crc))
        storage.bio.seek(end)

    storage.close_chunk = close_chunk_with_crc


def default_stamps(n_views: int, start_ns: int = 1_767_225_600_000_000_000, period_s: float = 0.1,
                   exposure_s: float = 0.1) -> np.ndarray:
    """Mid-exposure stamps (int64 ns) of ``n_views`` frames taken every ``period_s``."""
    offsets = np.round((np.arange(n_views) * period_s + 0.5 * exposure_s) * 1e9).astype(np.int64)
    return np.int64(start_ns) + offsets


def write_scan(path, frames, geom: ConeGeometry, *, info: dict | None = None, stamps_ns=None, flat=None,
               dead_pixels=None, geom_corrected: ConeGeometry | None = None, geom_true: ConeGeometry | None = None,
               progress=None, frame_id: str = fmt.FRAME_WORLD, **info_kw) -> Path:
    """Write a whole scan (frames (n, rows, cols) with per-view ``geom``) as a scan bag; returns the path.

    ``info`` defaults to ``scan_info_for(geom, **info_kw)``. ``progress`` wraps the view range
    (e.g. ``tqdm``). ``frame_id``: the world frame the geometries name.
    """
    frames = np.asarray(frames)
    if frames.shape != (geom.n_views,) + geom.det_shape:
        raise ValueError(f"frames {frames.shape} do not match the geometry ({geom.n_views},) + {geom.det_shape}")
    info = fmt.scan_info_for(geom, **info_kw) if info is None else info
    stamps = default_stamps(geom.n_views) if stamps_ns is None else np.asarray(stamps_ns, np.int64)
    t0 = int(stamps.min()) - 1_000_000  # scan_info, flat and dead pixels precede the first frame
    views = range(geom.n_views) if progress is None else progress(range(geom.n_views))
    with ScanBagWriter(path, info, start_ns=t0, frame_id=frame_id) as w:
        if flat is not None:
            w.write_flat(flat, t0)
        if dead_pixels is not None:
            w.write_dead_pixels(dead_pixels, t0)
        for i in views:
            w.write_frame(frames[i], geom, int(stamps[i]), i, corrected=geom_corrected, true=geom_true)
    return Path(path)


def write_corrected_bag(src, dst, geom_corrected: ConeGeometry, stamps_ns, *, notes: str | None = None,
                        frame_id: str | None = None, namespace: str = "") -> Path:
    """Copy every message of the bag ``src`` to a new bag ``dst`` with /ct/geometry_corrected added.

    ``src`` is a bag path or the :class:`~robot_ct_ros.bag.reader.RawBag` already read from it.
    ``stamps_ns`` are the stamps of the views of ``geom_corrected`` (the paired frames' stamps);
    corrected geometries already in ``src`` are replaced. They name ``frame_id``, by default the frame
    of ``src``'s /ct/geometry (:func:`~robot_ct_ros.bag.reader.geometry_frame`): one frame per bag.
    Works on damaged bags (copies what :func:`robot_ct_ros.bag.reader.read_raw_messages` recovers).

    As the recorder's bags, every frame opens its own MCAP chunk (with its CRC), so one damaged chunk
    costs one view; each corrected geometry goes in at its stamp's place in log time, beside its frame.
    ``namespace``: that of a scan recorded under one (``/scanner_a``, ScanData.namespace): the corrected
    geometries go on ``/scanner_a/ct/geometry_corrected``, beside the scan's other topics, where the reader finds
    them again.
    """
    from .reader import RawBag, geometry_frame, read_raw_messages

    raw = src if isinstance(src, RawBag) else read_raw_messages(src)
    stamps = np.asarray(stamps_ns, np.int64)
    pending = sorted((int(s), i) for i, s in enumerate(stamps))[::-1]  # popped from the end, earliest first
    frame_id = geometry_frame(raw, namespace) if frame_id is None else frame_id
    corrected, projection = namespace + fmt.TOPIC_GEOMETRY_CORRECTED, namespace + fmt.TOPIC_PROJECTION
    w = ScanBagWriter(dst, None, flush_every_frame=False, frame_id=frame_id)
    with w:
        for m in raw.messages:
            if m.topic == corrected:
                continue
            if m.topic == projection:
                w.flush()
            while pending and pending[-1][0] <= m.log_time_ns:
                s, i = pending.pop()
                w.write_geometry(geom_corrected, s, corrected, i)
            w.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns)
        while pending:
            s, i = pending.pop()
            w.write_geometry(geom_corrected, s, corrected, i)
        if notes:
            w._writer.set_custom_data("robot_ct_ros.notes", notes)
    return Path(dst)
