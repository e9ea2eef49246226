"""The run's recording: every message of a run, as received, in an MCAP file.

MCAP (https://mcap.dev) is the log format of the robotics tools (Foxglove, Lichtblick, the
``mcap`` CLI, rosbag2's storage plugin); any MCAP reader opens ``recording.mcap``.

Layout of ``recording.mcap``
----------------------------
- Header: profile ``""`` (no ROS profile), library ``covnet <version>``.
- Metadata records, written first (before any message):

  ``covnet.run``     ``run_id``, ``config_hash``, ``scenario``, ``seed``, ``covnet_version``,
                     ``schema_version`` (:data:`covnet.wire.messages.SCHEMA_VERSION`),
                     ``time_base`` (``CLOCK_MONOTONIC`` ns: see "Times" below),
                     ``start_monotonic_ns`` and ``start_utc_ns`` (one instant on both clocks,
                     to put a log time on a calendar), ``array_ext`` (how arrays are packed)
  ``covnet.config``  ``config.json``: the normalised config (JSON) the recorder ran with

- Schemas: one per message kind of :mod:`covnet.wire.messages`, named ``covnet.<Class>``
  (``covnet.Truth``, ``covnet.Command``, ``covnet.Measurement``, ``covnet.Track``,
  ``covnet.Status``, ``covnet.Heartbeat``), with schema encoding ``""`` and empty data: msgpack
  is self-describing (the MCAP registry's rule for ``""``); the field list is the docstring of
  the class in :mod:`covnet.wire.messages`.
- Channels: one per concrete key, ``topic`` = the key (``covnet/<run>/sensor/S3/meas``, ...),
  ``message_encoding`` ``"msgpack"``, the schema of the kind that key carries (from the key
  builders of :mod:`covnet.wire.messages`; a sensor's key whose first payload is a LocalTrack,
  as the info, ci and peer rules send, is ``ltrack``; ``schema_id`` 0 for a key no builder
  makes), metadata
  ``{"kind": <Message.KIND or "">}``. A channel is registered when its first message arrives;
  keys of no covnet layout, or of covnet's layout naming a node the run does not have (a
  command key ``cmd/~S9999~``, when the recorder knows the run's sensors), get at most
  :data:`MAX_FOREIGN_CHANNELS` channels and all keys at most :data:`MAX_KEY_CHANNELS` (the ids
  are 16-bit): a message on a new key beyond them is not recorded, the recorder counts it
  ``no_channel``, and the recording ends with a metadata record ``covnet.unrecorded``
  (``{"no_channel": n, "first_key": ...}``) that the replay reports.
- Messages: ``data`` = the payload exactly as received (also when it does not decode: the
  recording is of the wire, the replay decodes strictly); ``log_time`` = receive time
  (:attr:`covnet.wire.bus.Sample.t_recv_ns`); ``publish_time`` = the message's own ``t_sent_ns``
  when it has one (read by :func:`peek`, without the strict decode) and it is a stamp of the
  recorder's clock (:data:`recorder.node.OWN_CLOCK_S`: not after the receipt, at most a minute
  before it; another host's stamps count from its own boot), else the receive time;
  ``sequence`` = 1, 2, ... per channel.
- Visual channels (:mod:`covnet.runs.visual`): topics ``/covnet/scene`` (``foxglove.SceneUpdate``),
  ``/covnet/scan`` (``covnet.ScanMetrics``, JSON) and ``/covnet/log`` (``foxglove.Log``), one
  message each per scan, with the schemas the Foxglove SDK gives (protobuf
  ``FileDescriptorSet`` / JSON Schema), written by the recorder from the messages it received
  (:meth:`RecordingWriter.write_visual`); ``log_time`` = the receive time of the scan's Status.
  Their topics start with ``/`` (a key never does) and their encoding is not ``msgpack``:
  :class:`RecordingReader` skips them, so the replay never sees them.
- Chunks: zstd-compressed, at most :data:`CHUNK_SIZE` bytes (uncompressed) each, and a chunk is
  also closed and flushed to the OS every :data:`FLUSH_INTERVAL_S` seconds, so a recorder killed
  with SIGKILL leaves a file whose every complete chunk :func:`read_recording` still reads (the
  summary section and footer are missing then; an indexed reader refuses such a file, a stream
  reader does not).

Times
-----
``log_time`` / ``publish_time`` are ``time.monotonic_ns()`` stamps (CLOCK_MONOTONIC, shared by
every process of one Linux host), not Unix time: ``log_time - publish_time`` of a message is a
one-way latency (0 where the sender's stamp was another host's).
``utc = start_utc_ns + (t - start_monotonic_ns)`` converts to calendar time.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgpack
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Chunk, Footer, Message, MessageIndex, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from covnet import __version__, kinds
from covnet.code_identity import code_identity
from covnet.config import hash_of
from covnet.runs.rundir import name_file
from covnet.wire import messages as msg
from covnet.wire.bus import keyexpr_matches

__all__ = [
    "CHUNK_SIZE",
    "FLUSH_INTERVAL_S",
    "MESSAGE_ENCODING",
    "RecordedSample",
    "RecordingReader",
    "RecordingWriter",
    "key_kind",
    "mcap_start_problem",
    "peek",
    "read_metadata",
    "read_recording",
    "run_metadata",
]

MESSAGE_ENCODING = "msgpack"
CHUNK_SIZE = 1024 * 1024
"""Largest uncompressed chunk: what a SIGKILLed recorder may lose at most, besides the last
:data:`FLUSH_INTERVAL_S`.  Chunks are closed mostly by time: the writer keeps one chunk index
(~2-3 KB with a channel per key) per chunk for the file's summary, so fewer, larger chunks keep
a long run's recorder flat (the soak: 32 KiB chunks grew it 7.9 % over 20 000 scans)."""
FLUSH_INTERVAL_S = 1.0
#: MCAP channel ids are 16-bit: the received keys get at most this many channels, the rest of
#: the id range is the visual channels' (a new key beyond it is not recorded, and counted)
MAX_KEY_CHANNELS = 65_000
#: keys of no covnet message layout (nothing covnet publishes) get at most this many channels:
#: a rogue client's puts on 70 000 distinct keys of the run had used up the id range, and the
#: recorder died (``struct.error``); their payloads are recorded while there is room
MAX_FOREIGN_CHANNELS = 1024
"""Longest time a received message stays only in the recorder's memory (what a recorder killed
with SIGKILL loses at most)."""
META_RUN = "covnet.run"
META_CONFIG = "covnet.config"
META_UNRECORDED = "covnet.unrecorded"
"""The metadata record a recording ends with when messages went unrecorded (no channel left:
``no_channel``, how many; ``first_key``, the first such key)."""
ARRAY_EXT_DOC = (
    "msgpack ext type 1 = msgpack [dtype '<f8', shape [d0, d1, ...], raw little-endian bytes]"
)


def mcap_start_problem(path: Path) -> str | None:
    """Why ``path`` is no MCAP file from its first byte (None: it starts as one): empty, or
    other bytes.  Not a recording cut short, whose start reads, but no recording at all (the
    replay read it as a truncated one, "no footer: killed?")."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP0_MAGIC))
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    if not head:
        return f"{path}: empty (no recording was written)"
    if head != MCAP0_MAGIC:
        return f"{path}: not an MCAP file (it does not start with the MCAP magic)"
    return None


_OTHER_NODES = frozenset(
    (role, role) for role in (msg.MANAGER_ID, msg.WORLD_ID, msg.RECORDER_ID)
)
"""``(role, node id)`` of the run's nodes besides its sensors (their heartbeat keys)."""


def _names_members(run_id: str, key: str, sensors: Collection[str]) -> bool:
    """Every node ``key`` names (a key of covnet's layout) is one of the run's: sensors
    ``sensors``, and the manager, world and recorder."""
    if keyexpr_matches(msg.command_keyexpr(run_id), key):
        return all(s in sensors for s in msg.parse_command_key(key))
    if keyexpr_matches(msg.measurement_keyexpr(run_id), key):
        return msg.parse_measurement_key(key) in sensors
    if keyexpr_matches(msg.heartbeat_keyexpr(run_id), key):
        role, node = key.rsplit("/", 2)[1:]
        return (role == "sensor" and node in sensors) or (role, node) in _OTHER_NODES
    if keyexpr_matches(msg.peer_keyexpr(run_id, "*"), key):
        return msg.parse_peer_key(key)[0] in sensors
    return True


def key_kind(run_id: str, key: str, sensors: Collection[str] | None = None) -> str | None:
    """The message kind (``Message.KIND``) the key builders of :mod:`covnet.wire.messages` put on
    ``key`` for run ``run_id``, or None for a key they never make; with ``sensors`` (the run's
    sensor ids) also None for a key of their layout that names a node the run does not have
    (a rogue's ``cmd/~Z17~``: a foreign key)."""
    if sensors is not None:
        try:
            if not _names_members(run_id, key, sensors):
                return None
        except ValueError:  # not a valid key at all
            return None
    fixed = {
        msg.truth_key(run_id): msg.Truth.KIND,
        msg.track_key(run_id): msg.Track.KIND,
        msg.status_key(run_id): msg.Status.KIND,
    }
    if key in fixed:
        return fixed[key]
    try:
        if keyexpr_matches(msg.command_keyexpr(run_id), key):
            return msg.Command.KIND
        if keyexpr_matches(msg.measurement_keyexpr(run_id), key):
            return msg.Measurement.KIND
        if keyexpr_matches(msg.heartbeat_keyexpr(run_id), key):
            return msg.Heartbeat.KIND
        if keyexpr_matches(msg.peer_keyexpr(run_id, "*"), key):
            # a peer node's Track and Status (they were foreign keys: no schema, and more
            # than MAX_FOREIGN_CHANNELS of them, a network of 512 peers, went unrecorded)
            what = msg.parse_peer_key(key)[1]
            return msg.Track.KIND if what == "track" else msg.Status.KIND
    except ValueError:  # not a valid key at all
        return None
    return None


_KINDS = frozenset(cls.KIND for cls in msg.MESSAGE_TYPES)
_STAMP_MAX = 2**63 - 1


def peek(payload: bytes) -> tuple[str, int | None, int | None]:
    """What a recorder needs of a payload, read with one plain msgpack unpack (no strict
    decode: the recording is of the wire, and the replay decodes strictly): ``(kind,
    t_sent_ns, scan)``.  ``kind`` is the payload's ``"k"`` when it is a msgpack map of a known
    kind and :data:`~covnet.wire.messages.SCHEMA_VERSION`, else ``"undecodable:<reason>"``
    (``not_msgpack``, ``not_a_map``, ``bad_version`` or ``unknown_kind``); ``t_sent_ns`` and
    ``scan`` are its fields when they are ints in ``[0, 2**63)``, else None."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # msgpack's ValueError, ExtraData, FormatError, StackError, ...
        return "undecodable:not_msgpack", None, None
    if type(obj) is not dict:
        return "undecodable:not_a_map", None, None
    version, kind = obj.get("v"), obj.get("k")
    if type(version) is not int or version != msg.SCHEMA_VERSION:
        return "undecodable:bad_version", None, None
    if type(kind) is not str or kind not in _KINDS:
        return "undecodable:unknown_kind", None, None
    t_sent, scan = obj.get("t_sent_ns"), obj.get("scan")
    return (
        kind,
        t_sent if type(t_sent) is int and 0 <= t_sent <= _STAMP_MAX else None,
        scan if type(scan) is int and 0 <= scan <= _STAMP_MAX else None,
    )


_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
"""An MCAP Message record's head: opcode 0x05, record length (22 + data), channel id (u16),
sequence (u32), log time, publish time (u64, little-endian), then the data."""
_OP_MESSAGE = 0x05


def _fast_parts(writer: Writer) -> tuple[Any, Any, int] | None:
    """The ``mcap`` writer's statistics, chunk builder and chunk size, for
    :meth:`RecordingWriter._add`'s direct path; None (the library's ``add_message`` then) when
    this version of the library keeps them elsewhere."""
    try:
        parts = (
            writer._Writer__statistics,  # type: ignore[attr-defined]
            writer._Writer__chunk_builder,  # type: ignore[attr-defined]
            int(writer._Writer__chunk_size),  # type: ignore[attr-defined]
        )
        checks = (
            parts[1].record_writer._buffer.tell,
            parts[1].message_indices.get,
            parts[0].channel_message_counts,
        )
    except AttributeError:
        return None
    return parts if parts[1] is not None and all(c is not None for c in checks) else None


def _schema_name(cls: type[msg.Message]) -> str:
    return f"covnet.{cls.__name__}"


@dataclass(frozen=True, slots=True)
class RecordedSample:
    """One recorded message: its key (the MCAP topic), its payload as received, the receive
    stamp (``log_time``) and the sender's stamp (``publish_time``: the message's
    ``t_sent_ns`` when :func:`peek` found one at record time, else equal to ``t_recv_ns``)."""

    key: str
    payload: bytes
    t_recv_ns: int
    t_sent_ns: int


class RecordingWriter:
    """Append received messages to an MCAP file (layout: module docstring).

    A context manager; :meth:`close` writes the summary and footer and closes the file.  Not
    thread-safe: one recorder loop writes.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        run_id: str,
        metadata: dict[str, dict[str, str]] | None = None,
        chunk_size: int = CHUNK_SIZE,
        flush_interval_s: float = FLUSH_INTERVAL_S,
        sensors: Collection[str] | None = None,
    ) -> None:
        """Create (truncate) ``path`` and write the header, the schemas and ``metadata``
        (name -> str map; see :func:`run_metadata`); ``sensors``: the run's sensor ids, so that
        a key naming another node counts as foreign (:func:`key_kind`)."""
        self.path = Path(path)
        self.run_id = run_id
        self.sensors = frozenset(sensors) if sensors is not None else None
        self.unrecorded = 0  # messages on a new key with no channel left
        self._first_unrecorded = ""
        self._flush_interval_ns = int(flush_interval_s * 1e9)
        self._file: IO[bytes] | None = open(self.path, "wb")  # closed in close()
        try:
            self._writer = Writer(
                self._file,
                chunk_size=chunk_size,
                compression=CompressionType.ZSTD,
            )
            self._writer.start(profile="", library=f"covnet {__version__}")
            for name, data in (metadata or {}).items():
                self._writer.add_metadata(name, dict(data))
            self._schemas = {
                cls.KIND: self._writer.register_schema(_schema_name(cls), "", b"")
                for cls in msg.MESSAGE_TYPES
            }
            self._writer.flush()
        except BaseException:
            self._file.close()
            self._file = None
            raise
        self._fast = _fast_parts(self._writer)
        self._channels: dict[str, int] = {}
        self._key_channels = self._foreign_channels = 0
        self._visual_schemas: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._last_flush_ns = time.monotonic_ns()
        self.messages = 0
        self.visual_messages = 0

    @property
    def closed(self) -> bool:
        return self._file is None

    def write(self, key: str, payload: bytes, t_recv_ns: int, t_sent_ns: int | None) -> bool:
        """Record one message received at ``t_recv_ns`` (``t_sent_ns``: the sender's stamp
        when the payload decoded, else None); False when its key is new and no channel is
        left for it (:data:`MAX_KEY_CHANNELS`, :data:`MAX_FOREIGN_CHANNELS`): not recorded."""
        if self._file is None:
            raise ValueError(f"recording {self.path} is closed")
        channel = self._channels.get(key)
        if channel is None:
            kind = key_kind(self.run_id, key, self.sensors)
            if kind == msg.Measurement.KIND and peek(payload)[0] == msg.LocalTrack.KIND:
                # a sensor's key carries its local track where the fusion rule fuses tracks
                # (info, ci, peer): named by the first payload, not "meas" for every run
                kind = msg.LocalTrack.KIND
            if self._key_channels >= MAX_KEY_CHANNELS or (
                kind is None and self._foreign_channels >= MAX_FOREIGN_CHANNELS
            ):
                self.unrecorded += 1
                self._first_unrecorded = self._first_unrecorded or key
                return False
            self._key_channels += 1
            self._foreign_channels += kind is None
            channel = self._writer.register_channel(
                topic=key,
                message_encoding=MESSAGE_ENCODING,
                schema_id=self._schemas[kind] if kind is not None else 0,
                metadata={"kind": kind or ""},
            )
            self._channels[key] = channel
        self._add(channel, t_recv_ns, bytes(payload), t_recv_ns if t_sent_ns is None else t_sent_ns)
        self.messages += 1
        return True

    def write_visual(self, vm: Any) -> None:
        """Record one visual message (a :class:`covnet.runs.visual.VisualMessage`: topic, schema,
        message encoding, bytes, log time) on its own channel, registered with the schema the
        Foxglove SDK gave (``foxglove.SceneUpdate`` / ``foxglove.Log``: protobuf, a serialized
        ``FileDescriptorSet``; ``covnet.ScanMetrics``: JSON Schema)."""
        if self._file is None:
            raise ValueError(f"recording {self.path} is closed")
        channel = self._channels.get(vm.topic)
        if channel is None:
            schema = self._visual_schemas.get(vm.schema.name)
            if schema is None:
                schema = self._writer.register_schema(
                    vm.schema.name, vm.schema.encoding, bytes(vm.schema.data)
                )
                self._visual_schemas[vm.schema.name] = schema
            channel = self._writer.register_channel(
                topic=vm.topic, message_encoding=vm.encoding, schema_id=schema, metadata={}
            )
            self._channels[vm.topic] = channel
        self._add(channel, vm.log_time_ns, vm.data, vm.log_time_ns)
        self.visual_messages += 1

    def _add(self, channel: int, log_time: int, data: bytes, publish_time: int) -> None:
        """One message on ``channel``, numbered 1, 2, ... per channel; flushed when due.

        The message record goes straight into the current chunk (one ``struct`` pack, the
        statistics, chunk times and message index kept as the library's ``add_message`` keeps
        them: the same file, byte for byte, a test compares them) instead of through the
        library's record objects: the recorder writes every message of the run, and that path
        cost ~20 us a message on the loaded 2-core host (of the recorder's 50-75 us)."""
        seq = self._sequence.get(channel, 0) + 1
        self._sequence[channel] = seq
        fast = self._fast
        if fast is None:
            self._writer.add_message(
                channel_id=channel,
                log_time=log_time,
                data=data,
                publish_time=publish_time,
                sequence=seq & 0xFFFFFFFF,
            )
        else:
            stats, chunk, size = fast
            if stats.message_count == 0 or log_time < stats.message_start_time:
                stats.message_start_time = log_time
            if log_time > stats.message_end_time:
                stats.message_end_time = log_time
            stats.channel_message_counts[channel] += 1
            stats.message_count += 1
            if chunk.num_messages == 0 or log_time < chunk.message_start_time:
                chunk.message_start_time = log_time
            if log_time > chunk.message_end_time:
                chunk.message_end_time = log_time
            index = chunk.message_indices.get(channel)
            if index is None:
                index = MessageIndex(channel_id=channel, records=[])
                chunk.message_indices[channel] = index
            buf = chunk.record_writer._buffer
            at = buf.tell()
            index.records.append((log_time, at))
            chunk.num_messages += 1
            buf.write(
                _MESSAGE_HEAD.pack(
                    _OP_MESSAGE, 22 + len(data), channel, seq & 0xFFFFFFFF, log_time, publish_time
                )
            )
            buf.write(data)
            if at + 31 + len(data) > size:
                self._writer._Writer__maybe_finalize_chunk()  # type: ignore[attr-defined]
        self.maybe_flush()

    def maybe_flush(self) -> None:
        """:meth:`flush` when the last one is older than the flush interval (call it from an
        idle loop too, so a quiet period does not keep messages in memory)."""
        if self._file is not None and (
            time.monotonic_ns() - self._last_flush_ns >= self._flush_interval_ns
        ):
            self.flush()

    def flush(self) -> None:
        """Close the current chunk (if it has messages) and hand everything to the OS: from
        here on a SIGKILL loses none of it."""
        if self._file is None:
            return
        self._writer.flush()
        self._last_flush_ns = time.monotonic_ns()

    def close(self) -> None:
        """Write the last chunk, the summary (statistics, indexes) and the footer; close."""
        f, self._file = self._file, None
        if f is None:
            return
        try:
            if self.unrecorded:
                self._writer.add_metadata(
                    META_UNRECORDED,
                    {"no_channel": str(self.unrecorded), "first_key": self._first_unrecorded},
                )
            self._writer.finish()
        finally:
            f.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, kind: object, exc: BaseException | None, tb: object) -> None:
        """Close (:meth:`close`).  An ``OSError`` of the block or of the closing that names no
        file (a full disk's failed ``write()``) is raised naming this recording."""
        try:
            self.close()
        except OSError as err:
            name_file(err, self.path)
            raise
        if isinstance(exc, OSError):
            name_file(exc, self.path)


def run_metadata(run_id: str, config: Any | None) -> dict[str, dict[str, str]]:
    """The metadata records of a recording: ``covnet.run`` (and ``covnet.config`` when the
    run's config, of any kind, is given: its normalised form and its hash)."""
    run: dict[str, str] = {
        "run_id": run_id,
        "covnet_version": __version__,
        "code": code_identity(),  # covnet.code_identity: a replay by other code says so
        "schema_version": str(msg.SCHEMA_VERSION),
        "time_base": "CLOCK_MONOTONIC ns (time.monotonic_ns) of the recording host",
        "start_monotonic_ns": str(time.monotonic_ns()),
        "start_utc_ns": str(time.time_ns()),
        "array_ext": ARRAY_EXT_DOC,
    }
    out = {META_RUN: run}
    if config is not None:
        data = kinds.of(config).normalised(config)
        run.update(
            {"config_hash": hash_of(data), "scenario": config.name, "seed": str(config.seed)}
        )
        out[META_CONFIG] = {"config.json": json.dumps(data, sort_keys=True)}
    return out


class _Exact:
    """A read-only stream whose ``read(n)`` returns exactly ``n`` bytes or raises
    :class:`~mcap.exceptions.EndOfFile`: a record cut by a truncation is never half-parsed."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f
        self.offset = 0  # bytes consumed (complete reads only)
        self.end = -1  # file size, once the end was hit

    def read(self, n: int) -> bytes:
        data = self._f.read(n)
        if len(data) < n:
            self.end = self.offset + len(data)
            raise EndOfFile()
        self.offset += n
        return data


def segment_paths(path: Path | str) -> list[Path]:
    """The files of one recording, in order: ``path`` (``recording.mcap``), then the segments a
    restarted recorder wrote (``recording.2.mcap``, ``recording.3.mcap``, ...)."""
    path = Path(path)
    out = [path] if path.exists() else []
    n = 2
    while (seg := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists():
        out.append(seg)
        n += 1
    return out


def next_segment(path: Path | str) -> Path:
    """Where a recorder writes: ``path``, or when it exists (the recorder was restarted: never
    overwrite what was recorded) the next free segment name (:func:`segment_paths`)."""
    path = Path(path)
    if not path.exists():
        return path
    n = 2
    while (seg := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists():
        n += 1
    return seg


@dataclass
class RecordingReader:
    """Read a recording front to back with MCAP's stream reader (no index needed), so a file
    whose writer was killed (no summary, no footer, a half-written last chunk) reads up to its
    last complete record.

    Iterate :meth:`samples` (the raw ``msgpack`` channels only: a message of another channel, a
    visual one, is counted in ``visual`` and skipped); afterwards ``metadata`` (name -> map),
    ``complete`` (the footer and the closing magic were read), ``truncated`` (the file ends
    inside a record: its writer died while writing it; a file that ends between records, as a
    killed writer leaves it too, has ``complete`` False and ``truncated`` False),
    ``corrupt_chunks`` (offsets of chunks skipped because they failed their CRC or did not
    decompress), ``orphans`` (messages of a channel whose record was lost in such a chunk) and
    ``error`` (why reading stopped early on a damaged file, else None) describe what was read.

    A recording a restarted recorder continued in further segments (:func:`segment_paths`) is
    read segment after segment: ``segments`` counts them, ``complete`` and ``truncated`` are
    the last one's, ``corrupt_chunks`` the offsets within their segment, and
    ``incomplete_segments`` the earlier ones that end without a footer (their recorder was
    killed: what came in until its restart is missing)."""

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False
    truncated: bool = False
    corrupt_chunks: list[int] = field(default_factory=list)
    orphans: int = 0
    visual: int = 0
    error: str | None = None
    segments: int = 0
    incomplete_segments: list[str] = field(default_factory=list)

    def samples(self) -> Iterator[RecordedSample]:
        paths = segment_paths(self.path) or [self.path]  # a missing file raises, as before
        for i, path in enumerate(paths):
            self.segments = i + 1
            self.complete = self.truncated = False
            yield from self._segment(path)
            if self.error is not None:
                return
            if i < len(paths) - 1 and not self.complete:
                self.incomplete_segments.append(path.name)

    def _segment(self, path: Path) -> Iterator[RecordedSample]:
        channels: dict[int, str] = {}
        visual: set[int] = set()  # channels of another encoding: the visual ones, skipped
        if path.exists() and not path.is_file():  # a FIFO was read forever, a directory failed
            self.error = f"{path.name} is not a regular file"
            return
        with open(path, "rb") as f:
            stream = _Exact(f)
            reader = StreamReader(stream, emit_chunks=True, validate_crcs=False)  # type: ignore[arg-type]
            records = reader.records
            footer = False
            while True:
                start = stream.offset
                try:
                    record = next(records)
                except StopIteration:  # after the footer, the closing magic was read too
                    self.complete = footer
                    return
                except EndOfFile:
                    self.truncated = stream.end > start  # a record was cut, not just missing
                    return
                except (McapError, ValueError, UnicodeDecodeError, OverflowError) as exc:
                    self.error = f"unreadable record at byte {start}: {exc}"
                    return
                if isinstance(record, Chunk):
                    try:
                        inner = breakup_chunk(record, validate_crc=True)
                    except Exception:  # CRC mismatch, zstd/lz4 errors, bad inner framing
                        self.corrupt_chunks.append(start)
                        continue
                else:
                    inner = [record]
                for r in inner:
                    if isinstance(r, Message):
                        key = channels.get(r.channel_id)
                        if key is None:
                            if r.channel_id in visual:
                                self.visual += 1
                            else:
                                self.orphans += 1
                        else:
                            yield RecordedSample(key, r.data, r.log_time, r.publish_time)
                    elif isinstance(r, Channel):
                        if r.message_encoding == MESSAGE_ENCODING:
                            channels.setdefault(r.id, r.topic)
                        else:
                            visual.add(r.id)
                    elif isinstance(r, Metadata):
                        self.metadata[r.name] = dict(r.metadata)
                    elif isinstance(r, Footer):
                        footer = True
                    elif isinstance(r, Schema):
                        pass


def read_metadata(path: Path | str) -> dict[str, dict[str, str]]:
    """The metadata records of a recording (name -> map), read from its start: the writer puts
    them before any message (a summary-less, killed recording has them too)."""
    out: dict[str, dict[str, str]] = {}
    with open(path, "rb") as f:
        reader = StreamReader(_Exact(f), emit_chunks=True)  # type: ignore[arg-type]
        try:
            for record in reader.records:
                if isinstance(record, Metadata):
                    out[record.name] = dict(record.metadata)
                elif isinstance(record, Chunk | Message | Footer):
                    break
        except (McapError, ValueError, UnicodeDecodeError, OverflowError):
            pass
    return out


def read_recording(path: Path | str) -> Iterator[RecordedSample]:
    """Every message of a recording in the order it was received (see
    :class:`RecordingReader`, which also reports metadata and damage)."""
    return RecordingReader(Path(path)).samples()
