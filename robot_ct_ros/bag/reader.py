"""Reading scan bags, including damaged ones, into core arrays (mm) and geometry.

Two layers:

* :func:`read_raw_messages`: every (topic, type, log time, CDR bytes) of a bag. A healthy
  bag (metadata.yaml + indexed MCAP) is read with rosbags. When rosbags cannot read it (no
  metadata.yaml after a crash, MCAP without summary, a cut or overwritten tail, garbage in
  the middle) the ``.mcap`` file is scanned record by record with the ``mcap`` library's
  record parsers: every complete chunk and message is kept (of a chunk cut by the file's end,
  the complete messages before the cut when the chunk has no CRC, and of a compressed one only
  those in its whole compressed blocks: a small zstd chunk cut short gives none), a damaged region is skipped
  by re-synchronising on the next well-formed chunk, and what was lost is reported.
* :func:`read_scan`: the scan (frames, per-view geometry, flat field, pixel masks) with
  frames and geometries paired by equal header stamps; anything unpaired, undecodable or
  of the wrong size is counted in ``ScanData.warnings`` and never used. A stamp that appears
  on /ct/projection_rejected (a frame the acquisition rejected, e.g. beam interrupted) is never
  a view, even when the same frame is also on /ct/projection.
"""

from __future__ import annotations

import io
import math
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid, central_points_mm, views_center_mm

from . import format as fmt
from .format import ScanBagError, TooFewViewsError

MCAP_MAGIC = b"\x89MCAP0\r\n"

MIN_VIEWS = 4
"""The fewest paired views (frames and geometries with equal, distinct stamps) a scan may have; a bag
with fewer is refused with the reasons its frames and geometries were not used (e.g. every stamp
equal, every frame of the wrong size or NaN)."""


class ChunkCrcError(ValueError):
    """An MCAP chunk whose records do not match its CRC."""


@dataclass(frozen=True)
class RawMessage:
    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes


@dataclass(frozen=True)
class RawBag:
    """Messages of a bag in log-time order; ``recovered`` when the MCAP had to be scanned. ``qos``: topic -> the
    QoS profiles its publishers offered (rosbags ``Qos``, one per publisher), as metadata.yaml records them
    (``offered_qos_profiles``); a topic without a recorded profile, or a bag read without metadata.yaml, has none."""

    path: Path
    messages: list
    warnings: list
    recovered: bool
    reader: str  # "rosbags" or "mcap-scan" (record by record, see the module docstring)
    qos: dict = field(default_factory=dict)

    def topics(self) -> dict:
        out: dict[str, list] = {}
        for m in self.messages:
            out.setdefault(m.topic, [m.msgtype, 0])[1] += 1
        return {k: tuple(v) for k, v in out.items()}


# ------------------------------------------------------------------------------ raw layer
def _mcap_files(path: Path) -> list:
    if path.is_file() and path.suffix == ".db3":  # rosbag2's sqlite3 storage: only rosbags reads it
        raise ScanBagError(f"{path}: an sqlite3 bag file is read through its bag folder's metadata.yaml; give the "
                           "folder")
    if path.is_file():
        if _is_zstd_file(path):
            raise ScanBagError(f"{path}: a zstd-compressed file (a rosbag2 bag with file compression), not an MCAP "
                               "file; give the bag folder, with its metadata.yaml")
        return [path]
    if path.is_dir():
        return sorted(path.glob("*.mcap"))
    raise ScanBagError(f"{path}: no such bag (neither a bag directory nor an .mcap file)")


ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
"""The first four bytes of a zstd frame (RFC 8878): a file rosbag2 compressed whole (``compression_mode: file``)."""


def _is_zstd_file(path: Path) -> bool:
    """Whether the file at ``path`` starts with :data:`ZSTD_MAGIC` (an MCAP file starts with its own magic)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(ZSTD_MAGIC)) == ZSTD_MAGIC
    except OSError:
        return False


def _read_with_rosbags(path: Path) -> tuple[list, int, dict]:
    """The messages rosbags reads through metadata.yaml, how many metadata.yaml announces, and each topic's
    offered QoS profiles (:attr:`RawBag.qos`)."""
    from rosbags.rosbag2 import Reader

    out = []
    qos: dict[str, list] = {}
    with Reader(path) as reader:
        for conn in reader.connections:
            profiles = list(getattr(conn.ext, "offered_qos_profiles", None) or [])
            if profiles:
                qos.setdefault(conn.topic, []).extend(profiles)
        for conn, t, data in reader.messages():
            out.append(RawMessage(conn.topic, conn.msgtype, int(t), bytes(data)))
        announced = int(reader.message_count)
    return out, announced, qos


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        try:
            import zstandard
            return zstandard.decompress(data, size)
        except ImportError:
            try:
                from compression import zstd  # Python >= 3.14
            except ImportError:
                from backports import zstd
            return zstd.decompress(data)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    raise ValueError(f"unsupported chunk compression {compression!r}")


_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression string length


def _chunk_header_ok(buf, pos: int, n: int) -> bool:
    """Is there a self-consistent MCAP Chunk record header at ``pos``?"""
    if pos + 9 + _CHUNK_FIXED > n or buf[pos] != 0x06:
        return False
    (length,) = struct.unpack_from("<Q", buf, pos + 1)
    if length < _CHUNK_FIXED + 8 or pos + 9 + length > n:
        return False
    start, end, usize, _crc, clen = struct.unpack_from("<QQQII", buf, pos + 9)
    if clen not in (0, 3, 4) or start > end:
        return False
    comp = bytes(buf[pos + 9 + _CHUNK_FIXED: pos + 9 + _CHUNK_FIXED + clen])
    if comp not in (b"", b"lz4", b"zstd"):
        return False
    (rlen,) = struct.unpack_from("<Q", buf, pos + 9 + _CHUNK_FIXED + clen)
    if _CHUNK_FIXED + clen + 8 + rlen != length:
        return False
    return comp != b"" or rlen == usize


def _resync(buf, pos: int, n: int) -> int | None:
    """The next position >= pos holding a well-formed chunk record (None: none left)."""
    while True:
        pos = buf.find(b"\x06", pos)
        if pos < 0:
            return None
        if _chunk_header_ok(buf, pos, n):
            return pos
        pos += 1


def _partial_chunk(buf, pos: int, n: int, handle) -> None:
    """The complete records at the start of a chunk record cut by the end of the file (``buf[pos:n]``), each
    given to ``handle(opcode, content)``, up to the first incomplete one.

    Only a chunk without a CRC is read so (rosbags' own writer stores none, and packs a scan into chunks of
    1 MiB, so a cut file would otherwise lose up to a megabyte of frames); a chunk with a CRC is taken whole or
    not at all, as everywhere in the reader. A compressed chunk gives what its decompressor yields from the
    bytes present: whole compressed blocks only (zstd at most 128 KiB of records each, lz4's default frame 64 KiB), so a
    chunk of one block gives nothing."""
    head = pos + 9 + _CHUNK_FIXED
    if head > n:
        return
    _start, _end, _usize, crc, clen = struct.unpack_from("<QQQII", buf, pos + 9)
    if crc or clen not in (0, 3, 4) or head + clen + 8 > n:
        return
    comp = bytes(buf[head:head + clen])
    data = bytes(buf[head + clen + 8:n])
    try:
        if comp == b"zstd":
            import zstandard
            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif comp == b"lz4":
            import lz4.frame
            data = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif comp != b"":
            return
    except Exception:  # noqa: BLE001 - nothing decodable in what is left
        return
    for op, content in _chunk_records(data, partial=True):
        try:
            handle(op, content)
        except Exception:  # noqa: BLE001 - a malformed record ends what is taken
            break


def _chunk_records(data: bytes, partial: bool = False):
    """(opcode, content) of each record in a chunk's uncompressed records, in order. A record cut short, or of a
    kind a chunk does not hold, raises ValueError after the records before it; with ``partial`` (a chunk cut by the
    end of the file) it ends the records instead."""
    q, cn = 0, len(data)
    while q < cn:
        op, ln = (data[q], struct.unpack_from("<Q", data, q + 1)[0]) if q + 9 <= cn else (None, 0)
        if op is None or q + 9 + ln > cn or op not in (0x03, 0x04, 0x05):
            if partial:
                return
            raise ValueError("chunk ends inside a record header" if op is None
                             else f"bad record (opcode {op:#x}, length {ln}) inside a chunk")
        yield op, data[q + 9:q + 9 + ln]
        q += 9 + ln


def _recover_mcap(path: Path) -> tuple[list, list]:
    """Scan an MCAP file record by record; returns (messages, warnings). See the module docstring."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Chunk, Message, Schema

    buf = path.read_bytes()
    n = len(buf)
    warnings: list[str] = []
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    orphans: list = []  # messages whose channel record was lost (kept until the end)
    foreign: dict[str, str] = {}  # topic -> a message encoding other than CDR
    out: list[RawMessage] = []
    damaged = 0
    bad_chunks = 0
    lost_bytes = 0

    def stream(content: bytes) -> ReadDataStream:
        return ReadDataStream(io.BytesIO(content))

    def handle(opcode: int, content: bytes):
        if opcode == 0x03:
            s = Schema.read(stream(content))
            schemas[s.id] = s.name
        elif opcode == 0x04:
            c = Channel.read(stream(content))
            channels[c.id] = (c.topic, schemas.get(c.schema_id, ""))
            if c.message_encoding not in ("cdr", "") and c.topic not in foreign:  # the contract: CDR
                foreign[c.topic] = c.message_encoding
                warnings.append(f"{path.name}: {c.topic} is encoded as {c.message_encoding!r}; the scan bag "
                                "contract reads CDR only")
        elif opcode == 0x05:
            m = Message.read(stream(content), len(content))
            ch = channels.get(m.channel_id)
            if ch is None:
                orphans.append(m)
            else:
                out.append(RawMessage(ch[0], ch[1], int(m.log_time), bytes(m.data)))

    if buf[:8] == MCAP_MAGIC:
        pos = 8
    else:
        warnings.append(f"{path.name}: no MCAP magic at the start; scanning for chunks")
        pos = _resync(buf, 0, n)
        damaged += 1
    while pos is not None and pos < n:
        if pos + 9 > n:
            lost_bytes += n - pos
            warnings.append(f"{path.name}: file ends inside a record header at byte {pos} (truncated)")
            break
        opcode = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        end = pos + 9 + length
        if opcode == 0x02 and end <= n:  # footer: the end
            break
        ok = 0x01 <= opcode <= 0x0F and end <= n
        if ok and opcode == 0x06:
            ok = _chunk_header_ok(buf, pos, n)
        elif ok and end < n:  # the record after this one must look like a record too
            ok = end + 9 <= n and 0x01 <= buf[end] <= 0x0F
        if ok:
            content = buf[pos + 9:end]
            try:
                if opcode == 0x06:
                    chunk = Chunk.read(stream(content))
                    data = _decompress(chunk.compression, chunk.data, chunk.uncompressed_size)
                    if chunk.uncompressed_crc and zlib.crc32(data) & 0xFFFFFFFF != chunk.uncompressed_crc:
                        raise ChunkCrcError(
                            f"CRC mismatch: the chunk at bytes {pos} to {end} (log times {chunk.message_start_time} "
                            f"to {chunk.message_end_time} ns) is damaged; its messages are not used")
                    for op, record in _chunk_records(data):
                        handle(op, record)
                elif opcode in (0x03, 0x04, 0x05):
                    handle(opcode, content)
            except ChunkCrcError as exc:  # nothing of a chunk that fails its checksum is trusted
                damaged += 1
                bad_chunks += 1
                warnings.append(f"{path.name}: {exc}")
            except Exception as exc:  # noqa: BLE001 - a damaged record: keep what came before it
                damaged += 1
                warnings.append(f"{path.name}: damaged record at byte {pos} ({type(exc).__name__}: {exc}); "
                                "the messages before it in that record are kept")
            pos = end
            continue
        if end > n and 0x01 <= opcode <= 0x0F and _resync(buf, pos + 1, n) is None:
            lost_bytes += n - pos
            before = len(out)
            if opcode == 0x06:
                _partial_chunk(buf, pos, n, handle)
            warnings.append(f"{path.name}: the file is truncated: the last record (byte {pos}, "
                            f"{length} bytes announced, {n - pos - 9} present) is incomplete"
                            + (f"; {len(out) - before} complete messages recovered from its start (a chunk "
                               "without a CRC)" if len(out) > before else ""))
            break
        nxt = _resync(buf, pos + 1, n)
        damaged += 1
        lost_bytes += (n if nxt is None else nxt) - pos
        warnings.append(f"{path.name}: unreadable bytes from {pos} to {n if nxt is None else nxt}; "
                        + ("skipped to the next chunk" if nxt is not None else "nothing readable after them"))
        pos = nxt
    if orphans:
        kept = 0
        for m in orphans:
            ch = channels.get(m.channel_id)
            if ch is not None:
                out.append(RawMessage(ch[0], ch[1], int(m.log_time), bytes(m.data)))
                kept += 1
        if len(orphans) - kept:
            warnings.append(f"{path.name}: {len(orphans) - kept} messages lost: their channel record was damaged")
    if damaged or lost_bytes:
        warnings.append(f"{path.name}: recovered {len(out)} messages ({damaged} damaged regions"
                        + (f", {bad_chunks} of them chunks failing their CRC" if bad_chunks else "")
                        + f", {lost_bytes} bytes unreadable)")
    return out, warnings


def _scan_mcaps(files: list, warnings: list) -> list:
    """Every message :func:`_recover_mcap` finds in ``files``; its warnings appended to ``warnings``."""
    msgs: list[RawMessage] = []
    for f in files:
        try:
            got, warn = _recover_mcap(f)
        except OSError as exc:
            raise ScanBagError(f"{f}: cannot read: {exc}") from None
        msgs.extend(got)
        warnings.extend(warn)
    return msgs


def read_raw_messages(path) -> RawBag:
    """Every message of the bag at ``path`` (bag directory or ``.mcap`` file), in log-time order.

    Raises :class:`ScanBagError` only when nothing can be read; otherwise damage is reported
    in ``warnings``.
    """
    path = Path(path)
    warnings: list[str] = []
    if path.is_dir() and (path / "metadata.yaml").is_file():
        try:
            msgs, announced, qos = _read_with_rosbags(path)
            msgs.sort(key=lambda m: m.log_time_ns)
            files = _mcap_files(path) if len(msgs) < announced else []
            if not files:
                return RawBag(path, msgs, warnings, False, "rosbags", qos)
            # rosbags matches metadata.yaml's topics to the MCAP's channels, QoS included: a mismatch drops a
            # topic without an error. The MCAP itself holds the messages (readers ignore QoS: the contract)
            scanned = _scan_mcaps(files, [])
            if len(scanned) <= len(msgs):
                return RawBag(path, msgs, warnings, False, "rosbags", qos)
            warnings.append(f"rosbags read {len(msgs)} of the {announced} messages metadata.yaml announces (its "
                            "topics, QoS or types do not match the MCAP's channels); read from the MCAP file instead")
            scanned.sort(key=lambda m: m.log_time_ns)
            return RawBag(path, scanned, warnings, False, "mcap-scan", qos)
        except ScanBagError:
            raise
        except Exception as exc:  # noqa: BLE001 - any failure: fall back to scanning the MCAP
            warnings.append(f"rosbags could not read {path.name} ({type(exc).__name__}: {exc}); "
                            "recovering from the MCAP file")
    elif path.is_dir():
        warnings.append(f"{path.name} has no metadata.yaml (recording interrupted?); recovering from the MCAP file")
    files = _mcap_files(path)
    if not files:
        raise ScanBagError(f"{path}: no .mcap file found (the bag directory holds "
                           f"{sorted(p.name for p in path.iterdir()) if path.is_dir() else []})")
    msgs = _scan_mcaps(files, warnings)
    if not msgs:
        raise ScanBagError(f"{path}: no readable message in {', '.join(f.name for f in files)}"
                           + (f" ({'; '.join(warnings)})" if warnings else ""))
    msgs.sort(key=lambda m: m.log_time_ns)
    # recovered: something was wrong (a plain intact .mcap file read directly is not "recovered")
    return RawBag(path, msgs, warnings, bool(warnings), "mcap-scan")


# ------------------------------------------------------------------------------ scan layer
@dataclass(frozen=True, eq=False)
class ScanData:
    """A scan read from a bag (core units: mm, float32 images; arrays per geometry.py).

    ``counts`` (n, rows, cols) float32: the paired frames in stamp order, as stored (photon
    counts, or line integrals when ``info["projection_units"] == "line_integral"``);
    non-finite values are replaced by 0 and marked invalid. ``stamps_ns`` (n,) int64 the
    frames' header stamps. ``geom`` the per-view geometry (/ct/geometry, mm).
    ``flat`` (rows, cols) float32 mean counts per frame without object (None for line
    integrals without flat). ``pixel_mask`` (rows, cols) bool: not dead and flat > 0.
    ``valid_mask`` (n, rows, cols) bool: ``pixel_mask`` and a finite, non-negative value in
    that frame. ``geom_corrected`` / ``geom_true`` when the bag holds them for every frame.
    ``frame_id``: the world frame the geometries name (that of most /ct/geometry messages).
    ``warnings``: everything that was dropped or repaired, one line each. ``raw``: every message
    of the bag as read (``read_scan(keep_raw=True)``), so that a corrected copy needs no second read; its topics
    are the bag's own. ``namespace``: the namespace the scan's contract topics were recorded under (``""``: the
    contract's names; ``/scanner_a``: ``/scanner_a/ct/projection`` and so on, see :func:`scan_namespace`).
    """

    path: Path
    counts: np.ndarray
    stamps_ns: np.ndarray
    geom: ConeGeometry
    flat: np.ndarray | None
    pixel_mask: np.ndarray
    valid_mask: np.ndarray
    info: dict
    warnings: list = field(default_factory=list)
    geom_corrected: ConeGeometry | None = None
    geom_true: ConeGeometry | None = None
    recovered: bool = False
    raw: RawBag | None = None
    frame_id: str = fmt.FRAME_WORLD
    namespace: str = ""

    @property
    def n_views(self) -> int:
        return int(self.counts.shape[0])

    @property
    def units(self) -> str:
        return self.info["projection_units"]

    def to_line_integrals(self, min_counts: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
        """(line_integrals float32 (n, rows, cols), mask bool (n, rows, cols)).

        Counts go through :func:`robot_ct_ros.ct.simulation.counts_to_line_integrals`
        (log(flat / counts), invalid pixels 0); line-integral bags are returned as stored.
        """
        if self.units == "line_integral":
            return np.where(self.valid_mask, self.counts, 0.0).astype(np.float32), self.valid_mask.copy()
        from robot_ct_ros.ct.simulation import counts_to_line_integrals

        return counts_to_line_integrals(self.counts, self.flat, self.valid_mask, min_counts)

    def scan_center_mm(self) -> np.ndarray:
        """ROI centre: scan_info's ``roi_center_m``, else :func:`views_center_mm` (the point nearest to all
        central rays: the principal rays where the detector sees them)."""
        c = fmt.info_mm(self.info, "roi_center_m")
        if c is not None:
            return c
        return views_center_mm(self.geom)

    def grid_direction(self) -> np.ndarray:
        """The reconstruction grid's direction: scan_info's ``roi_direction`` (9 values, row-major,
        columns = the grid's x, y, z axes in the world) where given, else the frame whose z axis is
        the scan axis (:func:`robot_ct_ros.ct.geometry.axis_frame`; the identity for a scan about z)."""
        d = self.info.get("roi_direction")
        if d is not None:
            return np.asarray(d, dtype=np.float64).reshape(3, 3)
        from robot_ct_ros.ct.geometry import axis_frame
        from robot_ct_ros.ct.reconstruction import estimate_scan_axis

        return axis_frame(estimate_scan_axis(self.geom))

    def default_grid(self, voxel_size_mm=None, shape_zyx=None) -> VolumeGrid:
        """The reconstruction grid: scan_info's ROI (``roi_center_m``, ``roi_size_m`` along the
        grid's own axes, ``voxel_size_m``, ``roi_direction``) where given, else the field of view of
        the scan centred on :meth:`scan_center_mm` with voxels of pitch / magnification; its z axis
        follows the scan axis (:meth:`grid_direction`)."""
        g = self.geom
        c = self.scan_center_mm()
        D = self.grid_direction()
        mag = float(np.median(g.magnification(c)))
        if voxel_size_mm is None:
            voxel_size_mm = fmt.info_mm(self.info, "voxel_size_m")
        vs = (np.full(3, min(g.row_pitch_mm, g.col_pitch_mm) / mag) if voxel_size_mm is None
              else np.broadcast_to(np.asarray(voxel_size_mm, float), (3,)).copy())
        if shape_zyx is not None:
            return VolumeGrid.centered(tuple(int(s) for s in shape_zyx), vs, c, D)
        size = fmt.info_mm(self.info, "roi_size_m")
        if size is None:
            # transaxial: up to the detector edge farther from the central ray (central_points_mm: the
            # principal ray where the detector sees it) across the grid's z axis (the scan axis), as the angle
            # seen from the source in the plane of the detector normal w and the detector's direction t across
            # the axis; axial: the detector's extent along the axis; in the detector plane, whichever way the
            # detector is turned in it (rows along or across the axis). A detector with its principal point on
            # it gives reach / sdd = the farther edge's distance from that point / SDD, as it always did
            t = np.cross(D[:, 2], g.w)
            nt = np.linalg.norm(t, axis=1, keepdims=True)
            t = np.where(nt > 1e-9, t / np.maximum(nt, 1e-300), g.u)  # axis along the normal: rows
            a = np.cross(g.w, t)

            def half(e):  # half the detector's extent along the in-plane unit vectors e (n_views, 3)
                return 0.5 * (g.n_cols * g.col_pitch_mm * np.abs(np.einsum("ij,ij->i", e, g.u))
                              + g.n_rows * g.row_pitch_mm * np.abs(np.einsum("ij,ij->i", e, g.v)))

            def in_plane(p):  # (along t, along w away from the source) of the vectors p (n_views, 3)
                return np.einsum("ij,ij->i", p, t), np.einsum("ij,ij->i", p, g.w) * side

            side = np.where(np.einsum("ij,ij->i", g.detector_mm - g.source_mm, g.w) < 0, -1.0, 1.0)
            ct, cw = in_plane(central_points_mm(g) - g.source_mm)
            centre_angle = np.arctan2(ct, cw)
            dt, dw = in_plane(g.detector_mm - g.source_mm)
            far = np.maximum(np.abs(np.arctan2(dt + half(t), dw) - centre_angle),
                             np.abs(np.arctan2(dt - half(t), dw) - centre_angle))
            ot, ow = in_plane(c[None] - g.source_mm)
            sdd_i = np.hypot(ct, cw)  # to the detector plane along the central ray: SDD for the principal ray
            reach = float(np.median(sdd_i * np.tan(np.minimum(far, 0.5 * math.pi - 1e-9))))
            sod = float(np.median(np.abs(ot * np.sin(centre_angle) + ow * np.cos(centre_angle))))
            sdd = float(np.median(sdd_i))
            radius = sod * reach / math.hypot(sdd, reach)
            axial = 2.0 * float(np.median(half(a))) / mag
            size = np.array([2 * radius, 2 * radius, axial])  # across, across, along the scan axis
        n = np.maximum(1, np.round(np.asarray(size) / vs).astype(int))
        return VolumeGrid.centered(tuple(n[::-1]), vs, c, D)


def _decode(raw: RawBag, topic: str, msgtype: str, warnings: list) -> list:
    """(log_time, message) of ``topic``; undecodable messages and unexpected types are reported."""
    out, bad, wrong = [], 0, set()
    for m in raw.messages:
        if m.topic != topic:
            continue
        if m.msgtype != msgtype:
            wrong.add(m.msgtype)
            continue
        try:
            out.append((m.log_time_ns, fmt.deserialize(m.data, msgtype)))
        except Exception:  # noqa: BLE001 - damaged CDR
            bad += 1
    if wrong:
        raise ScanBagError(f"{topic} has type {', '.join(sorted(wrong))}; the scan bag contract says {msgtype}")
    if bad:
        warnings.append(f"{bad} message(s) on {topic} could not be decoded (damaged) and were dropped")
    return out


def _by_stamp(items, what: str, warnings: list) -> dict:
    out, dup, repeated = {}, 0, {}
    for stamp, value in items:
        if stamp in out:
            dup += 1
            repeated[stamp] = repeated.get(stamp, 1) + 1
            continue
        out[stamp] = value
    if dup:
        stamp, times = max(repeated.items(), key=lambda kv: kv[1])
        warnings.append(f"{dup} {what} with a stamp already seen were dropped (the first one is used; "
                        f"{len(items)} messages carry {len(out)} distinct stamps, {times} of them stamp {stamp} ns: "
                        "header.stamp is the pairing key and must differ from frame to frame)")
    return out


def _main_frame(frames: dict) -> str:
    """The frame most geometries name (``frames``: frame_id -> count), :data:`fmt.FRAME_WORLD` for none."""
    return min(frames, key=lambda name: (-frames[name], name)) if frames else fmt.FRAME_WORLD


def geometry_frame(raw: RawBag, namespace: str = "") -> str:
    """The world frame of a bag's messages: the frame_id most /ct/geometry messages (under ``namespace``) name (the
    writer's, docs/bag-format.md), :data:`fmt.FRAME_WORLD` when none can be read."""
    frames: dict = {}
    for _, msg in _decode(raw, namespace + fmt.TOPIC_GEOMETRY, fmt.POSE_ARRAY, []):
        frames[msg.header.frame_id] = frames.get(msg.header.frame_id, 0) + 1
    return _main_frame(frames)


def _geometries(raw: RawBag, topic: str, warnings: list, frames_of: dict | None = None) -> dict:
    """The usable geometries on ``topic`` by stamp; ``frames_of[topic]`` gets the frames they name (name -> count)."""
    items, bad, frames = [], 0, {}
    for _, msg in _decode(raw, topic, fmt.POSE_ARRAY, warnings):
        try:
            items.append((fmt.stamp_to_ns(msg.header.stamp), fmt.view_from_pose_array(msg)))
            frames[msg.header.frame_id] = frames.get(msg.header.frame_id, 0) + 1
        except ValueError as exc:
            bad += 1
            last = str(exc)
    if bad:
        warnings.append(f"{bad} geometries on {topic} are unusable and were dropped (e.g. {last})")
    if len(frames) > 1:  # the contract: one frame for every geometry of a bag; the views may not fit together
        warnings.append(f"the geometries on {topic} name {len(frames)} frames ("
                        + ", ".join(f"{name or '(empty)'!r}: {n}" for name, n in sorted(frames.items()))
                        + "); a bag's geometries must share one frame, and they are used as if they did")
    if frames_of is not None and frames:
        frames_of[topic] = frames
    return _by_stamp(items, f"geometries on {topic}", warnings)


def _single_image(raw: RawBag, topic: str, shape, encodings, warnings: list):
    msgs = _decode(raw, topic, fmt.IMAGE, warnings)
    if not msgs:
        return None
    if len(msgs) > 1:
        warnings.append(f"{len(msgs)} messages on {topic}; the last one is used")
    try:
        arr = fmt.array_from_image(msgs[-1][1], encodings)
    except ValueError as exc:
        raise ScanBagError(f"{topic}: {exc}") from None
    if arr.shape != tuple(shape):
        raise ScanBagError(f"{topic} is {arr.shape[0]}x{arr.shape[1]}, scan_info says {shape[0]}x{shape[1]}")
    return arr


STARVED_FLAT_COUNTS = 100.0
"""A usable pixel reading 0 counts where its flat field holds at least this many is reported
(:func:`zero_counts_warning`)."""


def zero_counts_warning(counts, flat, valid) -> str | None:
    """A warning when usable pixels read exactly 0 counts under a bright flat field: either photon starvation
    behind dense matter, or pixels that dropped out in those frames (a dead column reads as an attenuation of
    ln(flat / 0.5), some 60 times a tissue scan's, and streaks the whole volume). The data are kept as they are:
    the reader cannot tell the two apart, the user can (a dead pixel belongs in /ct/dead_pixels)."""
    if flat is None:
        return None
    zero = valid & (counts == 0) & (np.asarray(flat)[None] >= STARVED_FLAT_COUNTS)
    if not zero.any():
        return None
    frames = np.flatnonzero(zero.any(axis=(1, 2)))

    def whole(kind: str, at_zero) -> str:  # at_zero (frames, lines): a line of a frame entirely at 0
        lines = np.flatnonzero(at_zero.any(axis=0))
        if not lines.size:
            return ""
        listed = f"{lines[:10].tolist()}{' ...' if lines.size > 10 else ''}"
        return f"{lines.size} whole detector {kind} {listed} (at 0 in {int(at_zero.any(axis=1).sum())} frames)"

    whole = " and ".join(w for w in (whole("columns", zero.all(axis=1)), whole("rows", zero.all(axis=2))) if w)
    return (f"{int(zero.sum())} usable pixels in {len(frames)} frames (first {frames[:5].tolist()}) read 0 counts "
            f"under a flat field of at least {STARVED_FLAT_COUNTS:g} counts" + (f", among them {whole}" if whole else "")
            + ": photon starvation behind dense matter, or pixels that dropped out; they are used as the attenuation "
            "of 0.5 counts. If they are dead, list them in /ct/dead_pixels or write them as NaN")


LINE_INTEGRAL_COUNTS_FRACTION = 1e-3
"""Counts whose median over the usable pixels is below this fraction of the flat field (a median line integral
above ln(1000) = 6.9) are warned as probably line integrals declared as counts (:func:`counts_fraction_warning`).
The project's strongly attenuating simulated scans stay far above it: ``robot-ct simulate --phantom carotid``
(13 cm of water) has a median of 0.17, the battery 0.24, bags/sim_mouse_80 0.73; line integrals of 0.05 to 0.5
under a flat of 1e4 read 5e-6 to 5e-5."""


def counts_fraction_warning(counts, flat, valid) -> str | None:
    """A warning when usable counts are a tiny fraction of their flat field almost everywhere: the median of
    counts / flat over the usable pixels (flat > 0) below :data:`LINE_INTEGRAL_COUNTS_FRACTION`. Line integrals
    (0 to a few) written under ``projection_units: counts`` with a flat of thousands read so, and FDK then gives
    a garbage volume without a word. The data are kept: only the user knows what was written."""
    if flat is None:
        return None
    counts = np.asarray(counts)
    step = max(1, counts.shape[0] // 32)  # 32 views tell the median as well, at any scan size
    flat = np.asarray(flat, np.float64)
    use = np.broadcast_to(valid, counts.shape)[::step] & (flat > 0)[None]
    if not use.any():
        return None
    ratio = counts[::step][use] / np.broadcast_to(flat, counts.shape)[::step][use]
    median = float(np.median(ratio))
    if not median < LINE_INTEGRAL_COUNTS_FRACTION:
        return None
    below = float(np.mean(ratio < LINE_INTEGRAL_COUNTS_FRACTION))
    return (f"the counts are about {median:.2g} of the flat field everywhere (median of counts / flat over the usable "
            f"pixels; {100 * below:.0f} % of them below {LINE_INTEGRAL_COUNTS_FRACTION:g}, a line integral above "
            f"{-math.log(LINE_INTEGRAL_COUNTS_FRACTION):.1f}): are these line integrals? (projection_units is "
            "'counts'; write 'line_integral' for -ln(I/I0), or check the flat field's scale)")


COUNTS_MEDIAN_LINE_INTEGRAL = 20.0
"""A median usable line integral above this is no measurement but raw counts stored as line integrals: a
transmission of e^-20 (2e-9) needs some 5e8 photons per pixel for one to arrive, where a detector holds at most
about 1e6 (line integrals up to some 14) (:func:`line_integral_warning`)."""
NEGATIVE_LINE_INTEGRAL = -0.5
"""A line integral below this is clearly negative: 1.65 times the flat field's light, 5 standard deviations above
a flat of 100 counts (noise 0.1), where air reads 0 within the noise."""
NEGATIVE_SHARE = 0.05
"""More than this share of usable line integrals below :data:`NEGATIVE_LINE_INTEGRAL` is warned: an object's edges,
a moved flat or a few hot pixels stay far below it."""
NEGATIVE_MEDIAN_LINE_INTEGRAL = -0.1
"""A median usable line integral below this is warned: half the pixels see more light than the flat field
(a flat within 10 % of the exposure leaves air above -0.1); it catches a sign-flipped scan of a faint object."""

NEGATIVE_TAIL_LINE_INTEGRAL = -0.05
"""The 1st percentile of usable line integrals below this, and its magnitude more than
:data:`NEGATIVE_TAIL_RATIO` times the 99th percentile, is a sign-flipped scan of a weak object (values 0 to
-0.44, median 0, slip past the median and share tests). Measured 1st / 99th percentiles that stay unwarned:
bags/htc2022_01a (real data) 0.0074 / 2.23, bags/sim_mouse_80 0.25 / 0.44, ``robot-ct simulate`` mouse -0.0077 /
0.43, battery -0.0085 / 2.03 (the noise of air stays within a few hundredths)."""
NEGATIVE_TAIL_RATIO = 2.0
"""See :data:`NEGATIVE_TAIL_LINE_INTEGRAL`: a margin over symmetric noise, whose 1st and 99th percentiles of a
scan of air are equal and opposite."""


def line_integral_warning(li, valid) -> str | None:
    """A warning when stored line integrals ``li`` (usable where ``valid``) look like no line integrals: a median
    above :data:`COUNTS_MEDIAN_LINE_INTEGRAL` (raw counts without their flat field), or clearly negative values
    (the median below :data:`NEGATIVE_MEDIAN_LINE_INTEGRAL`, or more than :data:`NEGATIVE_SHARE` below
    :data:`NEGATIVE_LINE_INTEGRAL`: the sign flipped, log(I/I0) for -log(I/I0)), or a negative tail that dominates
    (the 1st percentile below :data:`NEGATIVE_TAIL_LINE_INTEGRAL` and more than :data:`NEGATIVE_TAIL_RATIO` times
    the 99th in size: a weak object sign-flipped). The data are kept: only the user knows what was written."""
    li = np.asarray(li)
    step = max(1, li.shape[0] // 32)  # 32 views tell the median and the share as well, at any scan size
    values = li[::step][np.broadcast_to(valid, li.shape)[::step]]
    if not values.size:
        return None
    median = float(np.median(values))
    if median > COUNTS_MEDIAN_LINE_INTEGRAL:
        return (f"the usable line integrals have a median of {median:.4g}, an attenuation of e^-{median:.0f} that no "
                "detector measures: these look like raw counts (robot-ct import: give --counts with --flat), or a "
                "simulator's sums over path lengths in voxels rather than -ln(I/I0) (the volume then comes out in "
                "1/voxel, not 1/mm)")
    negative = float(np.mean(values < NEGATIVE_LINE_INTEGRAL))
    if median < NEGATIVE_MEDIAN_LINE_INTEGRAL or negative > NEGATIVE_SHARE:
        return (f"{100 * negative:.0f} % of the usable line integrals lie below {NEGATIVE_LINE_INTEGRAL:g} (their "
                f"median is {median:.3g}{': most rays see air' if median >= NEGATIVE_MEDIAN_LINE_INTEGRAL else ''}): "
                "more light than the flat field; sign-flipped (log(I/I0) written for "
                "-log(I/I0)), or a flat field dimmer than the exposures (the source drifted)?")
    p1, p99 = (float(x) for x in np.percentile(values, [1, 99]))
    if p1 < NEGATIVE_TAIL_LINE_INTEGRAL and -p1 > NEGATIVE_TAIL_RATIO * max(p99, 0.0):
        return (f"the usable line integrals reach further below 0 than above it (1st percentile {p1:.3g}, 99th "
                f"{p99 + 0.0:.3g}): an object attenuates, so its line integrals are positive and air reads 0 within "
                "the noise; sign-flipped (log(I/I0) written for -log(I/I0))? The volume would come out negated")
    return None


def zero_frames_warning(li, valid, stamps_ns=None) -> str | None:
    """A warning naming the line-integral frames ``li`` (n, rows, cols) that hold exactly 0 in every usable pixel
    (``valid``) among frames that do not: a frame that was never filled (a dropped exposure written as zeros)
    reads as a view of air and is used as one. ``stamps_ns``: the frames' header stamps, named with their indices
    (0-based, in stamp order). None when no frame, or every frame, is all zero (a scan of nothing). The data are
    kept: only the user knows whether the view saw nothing."""
    li = np.asarray(li)
    valid = np.broadcast_to(valid, li.shape)
    zero = ~np.any(valid & (li != 0), axis=(1, 2)) & np.any(valid, axis=(1, 2))
    if not zero.any() or zero.sum() == np.any(valid, axis=(1, 2)).sum():
        return None
    idx = np.flatnonzero(zero)
    listed = f"{idx[:10].tolist()}{' ...' if idx.size > 10 else ''}"
    stamps = (f", stamps {np.asarray(stamps_ns)[idx[:10]].tolist()}{' ...' if idx.size > 10 else ''} ns"
              if stamps_ns is not None else "")
    return (f"{idx.size} line-integral frame(s) of {li.shape[0]} hold exactly 0 in every usable pixel (frame "
            f"{listed}{stamps}) where the others do not: each is used as a view of air; an exposure that was "
            "dropped or never written? Drop it, or write it as NaN")


MAX_SDD_M = 10.0
"""The largest source-to-detector distance (m) a scan bag may hold: no cone-beam scanner is larger, and a
bag whose positions were written in mm on a wire in metres (docs/bag-format.md) is 1000 times too big."""
MIN_SDD_MM = 1e-3
"""A view whose detector plane passes within this distance (mm) of its source (the detector centre written as
the source position, say) has no cone: every ray lies in the detector plane (:func:`check_distances`)."""


def check_distances(geom: ConeGeometry, topic: str) -> None:
    """Refuse (ValueError, naming ``topic``, the views affected and the values) a geometry that no transmission
    scan has: a median source-to-detector distance above :data:`MAX_SDD_M` (positions in mm on a wire in metres);
    a view whose detector plane passes through its source (distance below :data:`MIN_SDD_MM`: no cone); or a view
    whose magnification of the centre of the views (:func:`views_center_mm`; not scan_info's ``roi_center_m``,
    which only places the grid) is not above 1: SDD / SOD along the detector normal w, signed, so a detector
    between the source and that centre (SDD < SOD) and a centre behind the source are both refused. Transmission
    CT needs the object between the source and the detector. The last check needs that centre: it is skipped for a
    single view or views whose central rays are all parallel (a scan streamed as it arrives starts with one)."""
    n = geom.n_views
    sdd_all = geom.sdd_mm
    flat = sdd_all < MIN_SDD_MM
    if flat.any():
        raise ValueError(f"{topic}: source-to-detector distance {float(np.min(sdd_all)):.3g} mm in {int(flat.sum())} "
                         f"of {n} views (e.g. view {int(np.flatnonzero(flat)[0])}): the detector plane passes "
                         "through the source (the detector centre written as the source position?), so no ray "
                         "crosses it; a scan needs the detector facing the source across the object")
    sdd_m = float(np.median(sdd_all)) / fmt.MM_PER_M
    if not sdd_m <= MAX_SDD_M:
        raise ValueError(f"{topic}: source-to-detector distance {sdd_m:g} m (median over {geom.n_views} views) is "
                         f"above {MAX_SDD_M:g} m: the positions look like mm written on a wire in metres (ROS and "
                         f"this format take metres: {sdd_m:g} mm would be {sdd_m / fmt.MM_PER_M:g} m); write them "
                         "in metres")
    c = views_center_mm(geom, determined_only=True)
    if c is None:
        return  # one view, or rays all parallel: no centre of the views to judge the magnification by
    w = geom.w
    sdd_signed = np.einsum("ij,ij->i", geom.detector_mm - geom.source_mm, w)
    sod_signed = np.einsum("ij,ij->i", c[None] - geom.source_mm, w)
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = sdd_signed / sod_signed
    bad = ~(mag > 1.0)
    if not bad.any():
        return
    k = int(bad.sum())
    sdd, sod, m = (float(np.median(x[bad])) for x in (np.abs(sdd_signed), np.abs(sod_signed), mag))
    where = f"in {k} of {n} views (e.g. view {int(np.flatnonzero(bad)[0])}"
    centre = f"centre of the views {np.round(c, 1).tolist()} mm"
    if np.all(mag[bad] >= 0) and np.all(np.isfinite(mag[bad])):
        what = (f"the detector lies between the source and the centre of the views {where}; SDD {sdd:.4g} mm "
                f"{'<' if sdd < sod else '<='} SOD {sod:.4g} mm, magnification {m:.2f}; {centre})")
    else:
        what = (f"the centre of the views lies behind the source or in its detector-parallel plane {where}; "
                f"SDD {sdd:.4g} mm, SOD {sod:.4g} mm, magnification {m:.2f}; {centre})")
    raise ValueError(f"{topic}: {what}: transmission CT needs the object between the source and the detector "
                     "(magnification above 1); is the detector position (or its normal) written on the wrong side?")


def scan_namespace(raw: RawBag, namespace: str | None = None) -> str:
    """The namespace under which ``raw`` holds its scan: ``""`` when it has /ct/scan_info; else the one prefix P
    with P/ct/scan_info (a bag recorded with ``ros2 bag record -a`` from a scanner run under a namespace, e.g.
    ``namespace:=/scanner_a``; the nodes' topic names are relative, the bag keeps the absolute ones). ``""`` also
    when no prefix has one (the caller then says that scan_info is missing). ``namespace``: the one to read,
    given (``/scanner_a``, ``scanner_a`` or ``/`` for the contract's own names); refused when it holds no
    scan_info. Raises :class:`ScanBagError` naming them when several namespaces hold a scan."""
    topics = raw.topics()
    if namespace is not None:
        ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
        if ns + fmt.TOPIC_SCAN_INFO not in topics:
            raise ScanBagError(f"{raw.path}: no {ns + fmt.TOPIC_SCAN_INFO} message (namespace {ns or '/'} asked for; "
                               f"the bag's scans: {', '.join(_scan_namespaces(topics)) or 'none'})")
        return ns
    if fmt.TOPIC_SCAN_INFO in topics:
        return ""
    found = _scan_namespaces(topics)
    if len(found) > 1:
        raise ScanBagError(f"{raw.path}: no {fmt.TOPIC_SCAN_INFO} message, but scans recorded under "
                           f"{len(found)} namespaces: {', '.join(found)}; read one of them (ros2 bag convert with a "
                           f"topics filter, or record one scanner's topics per bag)")
    return found[0] if found else ""


def _scan_namespaces(topics) -> list:
    """The namespaces P (sorted) with a P/ct/scan_info topic; ``/`` for /ct/scan_info itself."""
    return sorted((t[:-len(fmt.TOPIC_SCAN_INFO)] or "/") for t in topics if t.endswith(fmt.TOPIC_SCAN_INFO))


def _under_namespace(raw: RawBag, ns: str) -> RawBag:
    """``raw`` with the contract topics under ``ns`` named as the contract names them (``/scanner_a/ct/projection``
    read as /ct/projection; /diagnostics stays global); contract topics of other namespaces or of none are left
    out, so two scanners' messages never mix. Every other topic is kept as it is."""
    if not ns:
        return raw
    contract = set(fmt.TOPIC_TYPES) - set(fmt.GLOBAL_TOPICS)
    def renamed(topic: str) -> str | None:  # the name it is read under; None: left out
        if topic.startswith(ns + "/") and topic[len(ns):] in contract:
            return topic[len(ns):]
        return None if topic in contract or any(topic.endswith(t) for t in contract) else topic

    msgs = [m if name == m.topic else RawMessage(name, m.msgtype, m.log_time_ns, m.data)
            for m in raw.messages if (name := renamed(m.topic)) is not None]
    qos = {name: profiles for topic, profiles in raw.qos.items() if (name := renamed(topic)) is not None}
    return RawBag(raw.path, msgs, list(raw.warnings) + [f"read the scan recorded under namespace {ns}"],
                  raw.recovered, raw.reader, qos)


def read_scan(path, *, keep_raw: bool = False, namespace: str | None = None) -> ScanData:
    """Read the scan bag at ``path`` (see the module docstring and docs/bag-format.md); a scan recorded under a
    namespace is read there (:func:`scan_namespace`; ``namespace`` picks one).

    Raises :class:`ScanBagError` with the reason when the bag cannot give a scan: nothing
    readable, no /ct/scan_info, no frame paired with a geometry, no flat field for counts.
    """
    return scan_from_raw(read_raw_messages(path), path, keep_raw=keep_raw, namespace=namespace)


def scan_from_raw(raw: RawBag, path, *, keep_raw: bool = False, min_views: int | None = None,
                  namespace: str | None = None) -> ScanData:
    """The scan held by messages already read (:func:`read_scan`'s body; ``min_views``: the fewest
    paired frames accepted, default :data:`MIN_VIEWS`, e.g. 1 for a few frames of a scan streamed as
    they arrive). A scan recorded under a namespace is read there (:func:`scan_namespace`, ``namespace``)."""
    min_views = MIN_VIEWS if min_views is None else int(min_views)
    bag_raw, ns = raw, scan_namespace(raw, namespace)
    raw = _under_namespace(raw, ns)
    warnings = list(raw.warnings)
    infos = _decode(raw, fmt.TOPIC_SCAN_INFO, fmt.STRING, warnings)
    if not infos:
        topics = ", ".join(f"{t} ({n})" for t, (_, n) in sorted(raw.topics().items()))
        undecodable = ([w for w in raw.warnings if fmt.TOPIC_SCAN_INFO in w and "CDR only" in w]
                       + [w for w in warnings[len(raw.warnings):] if fmt.TOPIC_SCAN_INFO in w])
        found = f"found: {topics}" if topics else "the bag holds no message at all"
        hint = undecodable[0] if undecodable else ""
        if hint and "CDR only" not in hint:  # a message that is there but does not decode
            hint += ": not CDR? compressed per message without its metadata.yaml, or another encoding"
        raise ScanBagError(f"{path}: no {'decodable ' if hint else ''}/ct/scan_info message; a scan bag starts with "
                           f"one ({found}{'; ' + hint if hint else ''})")
    info = fmt.scan_info_from_msg(infos[0][1])
    if len(infos) > 1:
        others = [m.data for _, m in infos[1:]]
        if any(o != infos[0][1].data for o in others):
            warnings.append(f"{len(infos)} differing /ct/scan_info messages; the first one is used")
    shape = (info["n_rows"], info["n_cols"])
    row_pitch_mm, col_pitch_mm = info["row_pitch_m"] * fmt.MM_PER_M, info["col_pitch_m"] * fmt.MM_PER_M

    causes: list[str] = []  # why frames or geometries were not used: named when too few views are left
    frames, bad_enc, bad_size, empty = [], 0, 0, 0
    dropped_stamps = set()  # frames dropped above: their geometries are not "without a frame"
    for _, msg in _decode(raw, fmt.TOPIC_PROJECTION, fmt.IMAGE, warnings):
        try:
            arr = fmt.array_from_image(msg, fmt.READ_ENCODINGS)
        except ValueError as exc:
            dropped_stamps.add(fmt.stamp_to_ns(msg.header.stamp))
            bad_enc += 1
            enc_reason = str(exc)
            continue
        if arr.shape != shape:
            dropped_stamps.add(fmt.stamp_to_ns(msg.header.stamp))
            bad_size += 1
            size_seen = arr.shape
            continue
        with np.errstate(invalid="ignore"):
            usable = np.isfinite(arr) & (arr > 0 if info["projection_units"] == "counts" else True)
        if not usable.any():  # a frame with nothing in it is no view: kept, it would weigh as one
            dropped_stamps.add(fmt.stamp_to_ns(msg.header.stamp))
            empty += 1
            continue
        frames.append((fmt.stamp_to_ns(msg.header.stamp), arr))
    if bad_enc:
        causes.append(f"{bad_enc} frames dropped: {enc_reason}")
    if bad_size:
        causes.append(f"{bad_size} frames dropped: size {size_seen[0]}x{size_seen[1]} differs from scan_info's "
                      f"{shape[0]}x{shape[1]}")
    if empty:
        what = "a finite, positive count" if info["projection_units"] == "counts" else "a finite value"
        causes.append(f"{empty} frames dropped: not one pixel holds {what} (NaN, infinite or empty frames)")
    warnings.extend(causes)
    n_frame_msgs = len(frames)
    frames = _by_stamp(frames, "frames", warnings)
    if len(frames) < n_frame_msgs:
        causes.append(warnings[-1])
    # frames the acquisition rejected (e.g. the beam dropped during the exposure) are never projections,
    # even when a writer also put them on /ct/projection
    rejected = {fmt.stamp_to_ns(m.header.stamp) for _, m in _decode(raw, fmt.TOPIC_PROJECTION_REJECTED, fmt.IMAGE,
                                                                      warnings)}
    if rejected:
        dropped = sorted(set(frames) & rejected)
        for s in dropped:
            del frames[s]
        also = f"; {len(dropped)} of them also on {fmt.TOPIC_PROJECTION}, dropped there" if dropped else ""
        warnings.append(f"{len(rejected)} frame(s) on {fmt.TOPIC_PROJECTION_REJECTED} were rejected during the "
                        f"acquisition (e.g. beam interrupted) and are not used{also}")
        if dropped:
            causes.append(warnings[-1])
    n_warn = len(warnings)
    frames_of: dict = {}  # geometry topic -> the frames its messages name (name -> count)
    geoms = _geometries(raw, fmt.TOPIC_GEOMETRY, warnings, frames_of)
    causes.extend(warnings[n_warn:])

    paired = sorted(set(frames) & set(geoms))
    lone_frames = len(frames) - len(paired)
    lone_geoms = len(set(geoms) - set(frames) - dropped_stamps - rejected)  # not those whose frame was dropped
    if lone_frames:
        warnings.append(f"{lone_frames} frames have no geometry with the same stamp and are not used")
    if lone_geoms:
        warnings.append(f"{lone_geoms} geometries have no frame with the same stamp and are not used")
    if len(paired) < min_views:
        found = f"{len(paired)} paired view{'s' if len(paired) != 1 else ''}"
        if frames and geoms and not paired:
            f0, f1, g0, g1 = min(frames), max(frames), min(geoms), max(geoms)
            causes.append(f"no stamp is shared: frames are stamped {f0} to {f1} ns, geometries {g0} to {g1} ns "
                          "(a pair needs equal header stamps)")
        elif not frames and not geoms:
            causes.append("neither a usable frame nor a usable geometry")
        elif not frames:
            causes.append("no usable frame on /ct/projection")
        elif not geoms:
            causes.append("no usable geometry on /ct/geometry")
        raise TooFewViewsError(f"{path}: not a usable scan: {found}, a scan needs at least {min_views} "
                               f"({len(frames)} usable frames, {len(geoms)} usable geometries)"
                               + (f"; {'; '.join(causes)}" if causes else ""), causes)
    n_views = info.get("n_views")
    if isinstance(n_views, int) and n_views != len(paired):
        warnings.append(f"scan_info announces {n_views} views, the bag holds {len(paired)} paired frames")

    try:
        geom = fmt.geometry_from_views([geoms[s] for s in paired], *shape, row_pitch_mm, col_pitch_mm)
    except ValueError as exc:
        raise ScanBagError(f"{path}: /ct/geometry: {exc}") from None
    try:
        check_distances(geom, fmt.TOPIC_GEOMETRY)
    except ValueError as exc:
        raise ScanBagError(f"{path}: {exc}") from None
    counts = np.stack([frames[s] for s in paired]).astype(np.float32, copy=False)

    flat = _single_image(raw, fmt.TOPIC_FLAT_FIELD, shape, fmt.READ_ENCODINGS, warnings)
    if flat is None and info["projection_units"] == "counts":
        raise ScanBagError(f"{path}: projection_units is 'counts' but the bag has no /ct/flat_field "
                           "(needed to turn counts into line integrals)")
    pixel_mask = np.ones(shape, bool)
    if flat is not None:
        if not np.all(np.isfinite(flat)):
            warnings.append(f"{int((~np.isfinite(flat)).sum())} flat-field pixels are not finite and are masked")
            flat = np.where(np.isfinite(flat), flat, 0.0).astype(np.float32)
        pixel_mask &= flat > 0
    try:
        dead = _single_image(raw, fmt.TOPIC_DEAD_PIXELS, shape, ("mono8", "8UC1"), warnings)
    except ScanBagError as exc:
        warnings.append(f"dead-pixel map ignored: {exc}")
        dead = None
    if dead is not None:
        pixel_mask &= dead == 0

    finite = np.isfinite(counts)
    n_nonfinite = int((~finite).sum())
    if n_nonfinite:
        bad_frames = int((~finite).any(axis=(1, 2)).sum())
        warnings.append(f"{n_nonfinite} non-finite pixel values in {bad_frames} frames are marked invalid")
        counts = np.where(finite, counts, 0.0).astype(np.float32)
    valid = pixel_mask[None] & finite
    if info["projection_units"] == "counts":
        neg = counts < 0
        if neg.any():
            warnings.append(f"{int(neg.sum())} negative counts are marked invalid")
            valid &= ~neg
        for check in (counts_fraction_warning, zero_counts_warning):
            said = check(counts, flat, valid)
            if said:
                warnings.append(said)
    else:
        for said in (line_integral_warning(counts, valid), zero_frames_warning(counts, valid, paired)):
            if said:
                warnings.append(said)

    def extra(topic):
        gs = _geometries(raw, topic, warnings, frames_of)
        if not gs:
            return None
        have = [s in gs for s in paired]
        if not all(have):
            warnings.append(f"{topic} covers {sum(have)} of {len(paired)} frames; ignored")
            return None
        try:
            g = fmt.geometry_from_views([gs[s] for s in paired], *shape, row_pitch_mm, col_pitch_mm)
            check_distances(g, topic)
            return g
        except ValueError as exc:
            warnings.append(f"{topic} ignored: {exc}")
            return None

    geom_corrected, geom_true = extra(fmt.TOPIC_GEOMETRY_CORRECTED), extra(fmt.TOPIC_GEOMETRY_TRUE)
    if len({frozenset(f) for f in frames_of.values()}) > 1:  # the topics disagree (one topic's mix is warned above)
        warnings.append("the geometry topics name different frames ("
                        + "; ".join(f"{topic}: " + ", ".join(repr(name) for name in sorted(f))
                                    for topic, f in frames_of.items())
                        + "); a bag's geometries must share one frame, and they are used as if they did")
    return ScanData(path=Path(path), counts=counts, stamps_ns=np.asarray(paired, np.int64), geom=geom, flat=flat,
                    pixel_mask=pixel_mask, valid_mask=valid, info=info, warnings=warnings,
                    geom_corrected=geom_corrected, geom_true=geom_true, recovered=raw.recovered,
                    raw=bag_raw if keep_raw else None, frame_id=_main_frame(frames_of.get(fmt.TOPIC_GEOMETRY, {})),
                    namespace=ns)


def summarize(path) -> dict:
    """A short description of a bag (topics, counts, scan info, pairing, warnings) for ``robot-ct info``;
    a one-row scan over a full circle also gets ``opposed_rays`` (:func:`_opposed_rays`)."""
    raw = read_raw_messages(path)
    out = {"path": str(path), "reader": raw.reader, "recovered": raw.recovered,
           "topics": {t: {"type": ty, "messages": n} for t, (ty, n) in sorted(raw.topics().items())}}
    if raw.messages:
        out["duration_s"] = (raw.messages[-1].log_time_ns - raw.messages[0].log_time_ns) * 1e-9
    try:
        scan = scan_from_raw(raw, path)  # the messages already read: the bag is read once
    except ScanBagError as exc:
        out["scan_error"] = str(exc)
        out["warnings"] = raw.warnings
        return out
    from robot_ct_ros.ct.reconstruction import scan_arc

    g = scan.geom
    c = scan.scan_center_mm()
    out.update({
        "scan_info": scan.info, "paired_views": scan.n_views,
        "detector": f"{g.n_rows} x {g.n_cols} pixels of {g.row_pitch_mm * 1000:.1f} x {g.col_pitch_mm * 1000:.1f} um",
        "source_to_detector_mm": float(np.median(g.sdd_mm)),
        "magnification": float(np.median(g.magnification(c))),
        "arc_deg": float(np.degrees(scan_arc(g, c)[0])),
        "scan_center_mm": [float(x) for x in c],
        "valid_pixel_fraction": float(scan.valid_mask.mean()),
        "has_geometry_corrected": scan.geom_corrected is not None,
        "has_geometry_true": scan.geom_true is not None,
        "warnings": scan.warnings,
    })
    if g.n_rows == 1:
        out["opposed_rays"] = _opposed_rays(scan)
    return out


# the rays compared for the centre of rotation by ray distance: fractions of the outermost ray's distance
OPPOSED_RAY_MAX_STEP_DEG = 2.0
"""The widest angle between views (a full circle over their number) at which ``info`` checks a one-row scan's
centre of rotation by its opposed rays. Measured on generated one-row full-circle scans (SOD 200 mm, SDD 400 mm, 64
columns of 0.8 mm; two phantoms, the stated centre exact or 1 px off): the found shift was off by up to 1.41 px at
60 views (6 degrees apart), 0.10 px at 90 and 0.17 px at 120, and within 0.001 px at 180, 240 and 360."""

OPPOSED_RAY_FRACTIONS = (0.4, 0.8, 0.95)


def _opposed_rays(scan: ScanData) -> dict:
    """The detector shift at which a one-row scan's opposed rays agree best (robot_ct_ros.ct.opposed_rays:
    the stated centre of rotation's error as the data see it), or {"not_checked": why}; and the same
    comparing only the rays within each of :data:`OPPOSED_RAY_FRACTIONS` of the outermost ray's distance
    from the centre (``by_ray_distance``: fraction -> px, a fraction left out where its search fails).
    On a scan that one geometry explains these agree; on the measured HTC2022 scans the rays through the
    object's rim want up to 0.12 px more than the inner ones (docs/results/realdata_consistency.md)."""
    from robot_ct_ros.ct.opposed_rays import opposed_ray_offset

    g = scan.geom
    step_deg = 360.0 / g.n_views  # a full circle (the caller checks that)
    if step_deg > OPPOSED_RAY_MAX_STEP_DEG:
        return {"not_checked": f"its views lie {step_deg:.3g} degrees apart, more than "
                               f"{OPPOSED_RAY_MAX_STEP_DEG:g}: the opposed ray is interpolated between views, which "
                               "biases this check by a tenth of a pixel and more there"}
    li, mask = scan.to_line_integrals()
    if mask is not None and not np.all(mask):
        return {"not_checked": "it has dead or masked pixels"}
    try:
        coarse = opposed_ray_offset(li, g, reach_px=3.0, steps=31)
    except ValueError as e:
        return {"not_checked": str(e)}
    # then in 0.1 px steps within half a pixel of it, over the default rays and each fraction
    moved = g.replace(detector_mm=g.detector_mm + coarse.best_shift_mm * g.u)
    best_px, by_distance = coarse.best_shift_px, {}
    for fraction in sorted(set(OPPOSED_RAY_FRACTIONS) | {0.8}):
        try:
            near = opposed_ray_offset(li, moved, reach_px=0.5, steps=11, central_fraction=fraction)
        except ValueError:
            continue
        if fraction == 0.8:  # opposed_ray_offset's default rays
            best_px = coarse.best_shift_px + near.best_shift_px
        if fraction in OPPOSED_RAY_FRACTIONS:
            by_distance[f"{fraction:g}"] = coarse.best_shift_px + near.best_shift_px
    return {"best_shift_px": best_px, "best_shift_mm": best_px * g.col_pitch_mm, "by_ray_distance": by_distance}
