"""A scan collected from its topics as received (CDR bytes), until it is written as a scan bag.

The recon_service subscribes to the scan's topics with raw (serialized) callbacks and keeps the
messages here: the latched ones by topic, the per-frame ones by header stamp. A /ct/scan_info
different from the one held starts a new scan. :meth:`ScanCollector.write_bag` writes the
frames paired with a geometry, in stamp order, as a scan bag (docs/bag-format.md).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag.writer import ScanBagWriter

__all__ = ["ScanCollector", "PER_FRAME"]

PER_FRAME = (fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY, fmt.TOPIC_GEOMETRY_TRUE)
"""The per-frame topics a scan is collected from (paired by header stamp)."""


class ScanCollector:
    """The messages of one scan as received. Not thread-safe: feed it from one executor."""

    def __init__(self):
        self.latched: dict[str, tuple[str, bytes]] = {}
        self.per_frame: dict[str, dict[int, bytes]] = {t: {} for t in PER_FRAME}
        self.scan_id = ""
        self.new_pairs: list[int] = []  # stamps paired since the last take_new_pairs, in pairing order
        self.duplicates: dict[str, int] = {t: 0 for t in PER_FRAME}  # messages dropped for a stamp already held

    def add_latched(self, topic: str, data: bytes) -> bool:
        """Keep a latched message (scan_info, flat field, dead pixels); True when it is a
        /ct/scan_info different from the one held (the collection was reset: a new scan)."""
        data = bytes(data)
        old = self.latched.get(topic)
        new_scan = topic == fmt.TOPIC_SCAN_INFO and old is not None and old[1] != data
        if new_scan:
            self.reset()
        self.latched[topic] = (fmt.TOPIC_TYPES[topic], data)
        if topic == fmt.TOPIC_SCAN_INFO:
            try:
                self.scan_id = fmt.scan_id_of(json.loads(fmt.deserialize(data, fmt.STRING).data))
            except (ValueError, AttributeError):
                self.scan_id = ""
        return new_scan

    def add_frame_message(self, topic: str, data: bytes) -> bool:
        """Keep a per-frame message by its header stamp (the first one of a stamp wins); False
        when it cannot be decoded (it is then dropped)."""
        data = bytes(data)
        try:
            stamp = fmt.stamp_to_ns(fmt.deserialize(data, fmt.TOPIC_TYPES[topic]).header.stamp)
        except Exception:  # noqa: BLE001 - a damaged message is not collected
            return False
        if stamp in self.per_frame[topic]:
            self.duplicates[topic] += 1  # the bag written holds the first one: say so (warnings)
            return True
        self.per_frame[topic][stamp] = data
        other = {fmt.TOPIC_PROJECTION: fmt.TOPIC_GEOMETRY, fmt.TOPIC_GEOMETRY: fmt.TOPIC_PROJECTION}.get(topic)
        if other is not None and stamp in self.per_frame[other]:
            self.new_pairs.append(stamp)
        return True

    def take_new_pairs(self) -> list:
        """(stamp, projection bytes, geometry bytes) of the frames paired since the last call."""
        stamps, self.new_pairs = self.new_pairs, []
        frames, geoms = self.per_frame[fmt.TOPIC_PROJECTION], self.per_frame[fmt.TOPIC_GEOMETRY]
        return [(s, frames[s], geoms[s]) for s in stamps]

    def reset(self) -> None:
        """Forget the frames (a new scan starts); latched messages are replaced as they come."""
        for d in self.per_frame.values():
            d.clear()
        self.new_pairs = []
        self.duplicates = {t: 0 for t in PER_FRAME}

    @property
    def warnings(self) -> list[str]:
        """What the collection dropped, as the bag reader words it for a bag (the bag written cannot show it)."""
        return [f"{n} {topic} messages with a stamp already seen were dropped (the first one is used; header.stamp "
                "is the pairing key and must differ from frame to frame)" for topic, n in self.duplicates.items() if n]

    @property
    def n_frames(self) -> int:
        return len(self.per_frame[fmt.TOPIC_PROJECTION])

    @property
    def n_paired(self) -> int:
        """Frames that have a geometry with the same stamp."""
        return len(set(self.per_frame[fmt.TOPIC_PROJECTION]) & set(self.per_frame[fmt.TOPIC_GEOMETRY]))

    def write_bag(self, path) -> tuple[Path, int]:
        """Write the paired frames (and the latched messages) as a new scan bag at ``path``,
        replacing one there; returns the path and the number of frames.

        Raises
        ------
        ValueError
            No /ct/scan_info yet, or no frame paired with a geometry.
        """
        path = Path(path)
        if fmt.TOPIC_SCAN_INFO not in self.latched:
            raise ValueError("no /ct/scan_info received yet")
        frames, geoms = self.per_frame[fmt.TOPIC_PROJECTION], self.per_frame[fmt.TOPIC_GEOMETRY]
        true = self.per_frame[fmt.TOPIC_GEOMETRY_TRUE]
        stamps = sorted(set(frames) & set(geoms))
        if not stamps:
            raise ValueError(f"no frame paired with a geometry yet ({len(frames)} frames, {len(geoms)} geometries)")
        if path.exists():
            shutil.rmtree(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        t0 = stamps[0] - 1_000_000
        with ScanBagWriter(path, None, flush_every_frame=False) as w:
            for topic in fmt.LATCHED_TOPICS:  # scan_info first
                if topic in self.latched:
                    w.write_raw(topic, *self.latched[topic], t0)
            for s in stamps:
                w.flush()  # each frame in its own chunk (with its CRC): one damaged chunk costs one view
                w.write_raw(fmt.TOPIC_PROJECTION, fmt.IMAGE, frames[s], s)
                w.write_raw(fmt.TOPIC_GEOMETRY, fmt.POSE_ARRAY, geoms[s], s)
                if s in true:
                    w.write_raw(fmt.TOPIC_GEOMETRY_TRUE, fmt.POSE_ARRAY, true[s], s)
        return path, len(stamps)
