"""The visual channels: what Foxglove draws of a run, built from the run's messages.

``recording.mcap`` holds the run's messages as msgpack, which Foxglove cannot decode.  This
module turns them, scan by scan, into messages in Foxglove's own schemas, written beside the raw
channels of the same file by the recorder (and served live over the Foxglove WebSocket protocol
with ``covnet up --foxglove``; ``covnet run --mcap`` feeds it the in-process results):

==================  =========================  ===============================================
topic               schema (encoding)          one message per scan (per episode) holding
==================  =========================  ===============================================
``/covnet/scene``   ``foxglove.SceneUpdate``   true targets, estimates with their 1σ and 2σ
                    (protobuf)                 ellipses, the desired-covariance ellipse, every
                                               sensor (on / off / failed), its coverage, a line
                                               from each active sensor to its target, and what a
                                               kind adds (lines of sight, associated triples)
``/covnet/scan``    ``covnet.ScanMetrics``     plot-ready numbers: ``n_active`` (N_k), ``f``,
                    (json, JSON Schema)        ``trace_P``, ``trace_Pd``, RMSE so far, NEES,
                                               messages, bytes and latencies; per target in
                                               ``targets[]``
``/covnet/log``     ``foxglove.Log``           the scan's status line (warning level while a
                    (protobuf)                 sensor is failed)
==================  =========================  ===============================================

How the bytes are made (the design decision): the Foxglove SDK (``foxglove-sdk``) builds each
message and encodes it (``SceneUpdate(...).encode()``) and gives its schema
(``SceneUpdate.get_schema()``: name, encoding ``protobuf``, a serialized
``FileDescriptorSet``).  covnet writes those bytes and that schema into ``recording.mcap`` with
its own MCAP writer (:meth:`covnet.runs.recording.RecordingWriter.write_visual`), so the visual
channels sit beside the raw ones in the one file the replay reads (the SDK's own
``open_mcap`` would write a second file, which the issue did not want), and the live server
(:mod:`covnet.runs.live`) sends the very same bytes with the same schema.

What is kind-specific is one module per kind (``covnet/<kind>/visual.py``, reached through
the registry: ``Kind.visual(cfg)``) that maps one scan's decoded messages
(:class:`ScanMessages`) to a :class:`View`, the kind-neutral picture drawn here; it also
rebuilds the scans of an in-process run directory as messages (``covnet run --mcap``).
Nothing here knows a kind.

The scan's frame is made when the manager's :class:`~covnet.wire.messages.Status` of the scan
arrives (the manager publishes it last), from what arrived for that scan: its command, the
truth, the measurements and the tracks; its log time is the Status's receive time.  The
recorder draws the recording's visual channels after the run, from what it recorded (drawing
costs CPU, which on a small machine the scan loop would pay), and the live view's while the run
goes, at a bounded rate (``recorder/node.py``).
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import foxglove
import numpy as np
from foxglove import messages as fm
from numpy.typing import NDArray

from covnet.processes.node_kit import same_clock
from covnet.runs.recording import RecordingWriter, run_metadata
from covnet.wire import messages as msg

__all__ = [
    "COLOURS",
    "LOG_TOPIC",
    "METRICS_SCHEMA",
    "METRICS_TOPIC",
    "SCENE_TOPIC",
    "TOPICS",
    "XY",
    "Coverage",
    "Estimate",
    "KindVisual",
    "ScanMessages",
    "SensorView",
    "Segment",
    "View",
    "VisualMessage",
    "Visualiser",
    "ellipse_axes",
    "write_run_mcap",
    "ellipse_points",
    "scene_update",
]

SCENE_TOPIC = "/covnet/scene"
METRICS_TOPIC = "/covnet/scan"
LOG_TOPIC = "/covnet/log"
XY = [0, 2]
"""The position components of a target state ``[x, vx, y, vy]`` (every kind's)."""
TOPICS = (SCENE_TOPIC, METRICS_TOPIC, LOG_TOPIC)
"""The visual topics.  They start with ``/``, which a zenoh key (a raw channel) never does."""

ELLIPSE_POINTS = 24
"""Points of a drawn ellipse (a closed line loop)."""
ARC_POINTS = 32

Rgba = tuple[float, float, float, float]
COLOURS: dict[str, Rgba] = {
    "on": (0.15, 0.80, 0.25, 1.0),  # a sensor measuring this scan
    "off": (0.55, 0.55, 0.55, 1.0),  # alive, not allocated
    "failed": (0.90, 0.10, 0.10, 1.0),  # seen failed by the manager
    "truth": (1.00, 0.85, 0.00, 1.0),
    "estimate": (0.20, 0.60, 1.00, 1.0),
    "sigma1": (0.20, 0.60, 1.00, 1.0),
    "sigma2": (0.20, 0.60, 1.00, 0.45),
    "desired": (1.00, 0.45, 0.00, 1.0),
    "link": (0.15, 0.80, 0.25, 0.8),
    "coverage": (0.55, 0.55, 0.55, 0.35),
    "los": (0.70, 0.70, 0.90, 0.35),
    "triple": (0.85, 0.30, 0.95, 0.9),
    "tentative": (0.55, 0.75, 1.00, 0.6),  # a surveillance track not yet confirmed
    "deleted": (0.90, 0.10, 0.10, 0.8),  # a track deleted at this scan (its last estimate)
    "cell": (1.00, 0.55, 0.10, 1.0),  # a search cell; its alpha is set by its mass u_c
}
"""Colours (RGBA 0..1) of the scene: sensors by state, truth, estimate, ellipses, lines."""

METRICS_SCHEMA: dict[str, Any] = {
    "title": "covnet.ScanMetrics",
    "description": "One scan of a covnet run: plot-ready numbers (a number not known is left out)",
    "type": "object",
    "properties": {
        "episode": {"type": "integer", "description": "episode number (one per metric)"},
        "episode_name": {"type": "string"},
        "scan": {"type": "integer"},
        "t": {"type": "number", "description": "scenario time [s]"},
        "n_active": {"type": "integer", "description": "N_k: sensors enabled this scan"},
        "n_failed": {"type": "integer"},
        "f": {"type": "number", "description": "f(P, P_d) (the manager's value)"},
        "trace_P": {"type": "number"},
        "trace_Pd": {"type": "number"},
        "rmse": {"type": "number", "description": "position RMSE so far, episode"},
        "nees": {"type": "number", "description": "mean NEES of the scan's targets"},
        "messages": {"type": "integer", "description": "messages received since last scan"},
        "bytes": {"type": "integer"},
        "scan_latency_ms": {"type": "number", "description": "command -> status"},
        "measurement_latency_ms": {"type": "number", "description": "mean one-way"},
        "measurement_latency_max_ms": {"type": "number"},
        "targets": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "id": {"type": "string"},
                    "f": {"type": "number"},
                    "trace_P": {"type": "number"},
                    "trace_Pd": {"type": "number"},
                    "error": {"type": "number", "description": "position error"},
                    "rmse": {"type": "number"},
                    "nees": {"type": "number"},
                },
                "required": ["id"],
            },
        },
    },
    "required": ["episode", "scan", "t", "n_active", "targets"],
}
"""JSON Schema of ``/covnet/scan`` (schema name ``covnet.ScanMetrics``).  Every field has ONE
type and no field is ``null``: Foxglove's JSON-schema parser rejects the whole channel for a
field typed ``["number", "null"]`` (nothing plots), so a number that is not known is left out
of the message (:func:`_known`)."""


# --------------------------------------------------------------------------------------------
# the kind-neutral picture of one scan
# --------------------------------------------------------------------------------------------

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Coverage:
    """Where a sensor sees: a disc of ``max_range`` (frame units) around it, or the sector
    ``centre_deg ± half_width_deg`` (counter-clockwise from +x) of it."""

    max_range: float
    centre_deg: float | None = None
    half_width_deg: float | None = None


@dataclass(frozen=True)
class SensorView:
    """A sensor in the scene: ``state`` ``on`` / ``off`` / ``failed``; ``placed`` False for a
    sensor without a position (drawn where the kind puts it, labelled so)."""

    id: str
    position: Vec3
    state: str
    coverage: Coverage | None = None
    targets: tuple[str, ...] = ()
    placed: bool = True


@dataclass(frozen=True)
class Estimate:
    """An estimate: position, the x-y block of its covariance, the desired one (if any), and
    its numbers (``error``: distance to its true target, ``nees`` against it)."""

    id: str
    position: Vec3
    cov_xy: NDArray[np.float64] | None = None
    desired_xy: NDArray[np.float64] | None = None
    f: float | None = None
    trace_P: float | None = None
    trace_Pd: float | None = None
    error: float | None = None
    nees: float | None = None
    state: str | None = None  # surveillance: tentative, confirmed or deleted


@dataclass(frozen=True)
class Area:
    """A search cell ``[x0, x1] x [y0, y1]`` with its undetected mass ``u`` and ``level``
    (``u`` over the largest of the scan, 0..1: how strongly it is shaded)."""

    id: str
    x0: float
    x1: float
    y0: float
    y1: float
    u: float
    level: float


@dataclass(frozen=True)
class Segment:
    """A line between two points, of a colour of :data:`COLOURS` (lines of sight, triples)."""

    id: str
    a: Vec3
    b: Vec3
    colour: str


@dataclass
class View:
    """One scan as a kind sees it (:class:`KindVisual`), in ``frame`` (``world_m`` or
    ``world_km``); ``marker`` is the size of a drawn point in frame units."""

    frame: str
    marker: float
    truths: list[tuple[str, Vec3]] = field(default_factory=list)
    estimates: list[Estimate] = field(default_factory=list)
    sensors: list[SensorView] = field(default_factory=list)
    segments: list[Segment] = field(default_factory=list)
    areas: list[Area] = field(default_factory=list)
    n_active: int = 0
    f: float | None = None
    trace_P: float | None = None
    trace_Pd: float | None = None


@dataclass
class ScanMessages:
    """What arrived for one scan of one episode, decoded (the input of a kind's view)."""

    episode: int
    scan: int
    status: msg.Status
    command: msg.Command | None = None
    truth: msg.Truth | None = None
    measurements: dict[str, msg.Measurement] = field(default_factory=dict)
    tracks: list[msg.Track] = field(default_factory=list)


class KindVisual(Protocol):
    """A kind's visual module (``covnet/<kind>/visual.py``), made by ``Kind.visual(cfg)``.
    It may say ``measurements = True`` to get the scan's measurements decoded (the passive
    kind draws its lines of sight); the others are not decoded, only timed."""

    def view(self, scan: ScanMessages) -> View:
        """The picture of one scan."""
        ...


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------


def ellipse_axes(C: NDArray[np.float64], n_sigma: float = 1.0) -> tuple[NDArray[np.float64], ...]:
    """The n-σ ellipse ``{c + d : dᵀ C⁻¹ d = n²}`` of a 2x2 covariance: its semi-axes
    ``n √λᵢ`` and their unit directions (the eigen-decomposition ``C = V Λ Vᵀ``), ascending."""
    C = 0.5 * (np.asarray(C, dtype=np.float64) + np.asarray(C, dtype=np.float64).T)
    lam, V = np.linalg.eigh(C)
    return n_sigma * np.sqrt(np.clip(lam, 0.0, None)), V


def ellipse_points(
    centre: Sequence[float], C: NDArray[np.float64], n_sigma: float, n: int = ELLIPSE_POINTS
) -> NDArray[np.float64]:
    """``n`` points ``c + V diag(n_sigma √λ) [cos θ, sin θ]ᵀ`` on the n-σ ellipse, ``(n, 2)``."""
    axes, V = ellipse_axes(C, n_sigma)
    theta = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    unit = np.stack([np.cos(theta), np.sin(theta)])  # (2, n)
    return np.asarray(centre[:2], dtype=np.float64) + ((V * axes) @ unit).T


def _arc(centre: Vec3, cov: Coverage) -> NDArray[np.float64]:
    if cov.centre_deg is None or cov.half_width_deg is None or cov.half_width_deg >= 180.0:
        a = np.linspace(0.0, 2.0 * np.pi, ARC_POINTS, endpoint=False)
        closed = True
    else:
        c, h = math.radians(cov.centre_deg), math.radians(cov.half_width_deg)
        a = np.linspace(c - h, c + h, ARC_POINTS)
        closed = False
    pts = np.stack([centre[0] + cov.max_range * np.cos(a), centre[1] + cov.max_range * np.sin(a)])
    pts = pts.T
    if not closed:  # a sector: from the sensor, along the arc, back
        pts = np.vstack([[centre[0], centre[1]], pts, [centre[0], centre[1]]])
    return pts


# --------------------------------------------------------------------------------------------
# Foxglove messages
# --------------------------------------------------------------------------------------------

_IDENTITY = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def _colour(name: str) -> fm.Color:
    r, g, b, a = COLOURS[name]
    return fm.Color(r=r, g=g, b=b, a=a)


def _pose(p: Sequence[float]) -> fm.Pose:
    return fm.Pose(
        position=fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]) if len(p) > 2 else 0.0),
        orientation=_IDENTITY,
    )


def _points(xy: NDArray[np.float64], z: float = 0.0) -> list[fm.Point3]:
    return [fm.Point3(x=float(a), y=float(b), z=z) for a, b in xy]


def _line(kind: fm.LinePrimitiveLineType, pts: list[fm.Point3], colour: str, px: float) -> Any:
    return fm.LinePrimitive(
        type=kind,
        pose=_pose((0.0, 0.0, 0.0)),
        thickness=px,
        scale_invariant=True,
        points=pts,
        color=_colour(colour),
    )


def _text(p: Sequence[float], text: str, colour: str) -> Any:
    return fm.TextPrimitive(
        pose=_pose(p), billboard=True, font_size=12.0, scale_invariant=True,
        color=_colour(colour), text=text,
    )  # fmt: skip


_COVERAGE: dict[tuple[Vec3, Coverage], Any] = {}


def _coverage_line(position: Vec3, cov: Coverage) -> Any:
    """A sensor's coverage outline (cached: most sensors stay where they are)."""
    key = (position, cov)
    line = _COVERAGE.get(key)
    if line is None:
        if len(_COVERAGE) > 4096:
            _COVERAGE.clear()
        pts = _points(_arc(position, cov), position[2])
        line = _COVERAGE[key] = _line(fm.LinePrimitiveLineType.LineStrip, pts, "coverage", 1.0)
    return line


def _p3(p: Sequence[float]) -> fm.Point3:
    return fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]) if len(p) > 2 else 0.0)


def _timestamp(t_ns: int) -> Any:
    return fm.Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


def scene_update(view: View, t_ns: int) -> Any:
    """The ``foxglove.SceneUpdate`` of one scan: first a deletion of every entity (so what
    left the scene goes), then one entity per truth, search cell, estimate, sensor and segment
    (module docstring; ids ``truth/<id>``, ``cell/<id>``, ``estimate/<id>``, ``sensor/<id>``,
    ``segment/<id>``; an estimate with a ``state`` carries it as metadata)."""
    ts = _timestamp(t_ns)
    size = fm.Vector3(x=view.marker, y=view.marker, z=view.marker)
    LOOP, LIST = fm.LinePrimitiveLineType.LineLoop, fm.LinePrimitiveLineType.LineList
    entities = []

    def entity(eid: str, **prims: Any) -> None:
        entities.append(fm.SceneEntity(timestamp=ts, frame_id=view.frame, id=eid, **prims))

    truth_at = dict(view.truths)
    for tid, p in view.truths:
        entity(
            f"truth/{tid}",
            spheres=[fm.SpherePrimitive(pose=_pose(p), size=size, color=_colour("truth"))],
            texts=[_text((p[0], p[1], p[2] + view.marker), tid, "truth")],
        )
    for c in view.areas:  # search cells: flat boxes shaded by their undetected mass
        r, g, b, _ = COLOURS["cell"]
        centre = ((c.x0 + c.x1) / 2, (c.y0 + c.y1) / 2, 0.0)
        box = fm.CubePrimitive(
            pose=_pose(centre),
            size=fm.Vector3(x=c.x1 - c.x0, y=c.y1 - c.y0, z=view.marker / 10),
            color=fm.Color(r=r, g=g, b=b, a=0.04 + 0.4 * min(max(c.level, 0.0), 1.0)),
        )
        entity(f"cell/{c.id}", cubes=[box], texts=[_text(centre, f"u {c.u:.2f}", "cell")],
               metadata=[fm.KeyValuePair(key="u", value=f"{c.u:.6g}")])  # fmt: skip
    est_at = {}
    for e in view.estimates:
        est_at[e.id] = e.position
        z = e.position[2]
        lines = []
        if e.state == "deleted":  # its last estimate, marked; no ellipses
            sphere = fm.SpherePrimitive(pose=_pose(e.position), size=size, color=_colour("deleted"))
            entity(f"estimate/{e.id}", spheres=[sphere],
                   texts=[_text(e.position, f"{e.id} deleted", "deleted")],
                   metadata=[fm.KeyValuePair(key="state", value="deleted")])  # fmt: skip
            continue
        style = "tentative" if e.state == "tentative" else "estimate"
        if e.cov_xy is not None and style == "tentative":
            pts = _points(ellipse_points(e.position, e.cov_xy, 1.0), z)
            lines.append(_line(LOOP, pts, "tentative", 1.0))
        elif e.cov_xy is not None:
            for n, colour in ((1.0, "sigma1"), (2.0, "sigma2")):
                pts = _points(ellipse_points(e.position, e.cov_xy, n), z)
                lines.append(_line(LOOP, pts, colour, 2.0))
        if e.desired_xy is not None:
            pts = _points(ellipse_points(e.position, e.desired_xy, 1.0), z)
            lines.append(_line(LOOP, pts, "desired", 1.5))
        sphere = fm.SpherePrimitive(pose=_pose(e.position), size=size, color=_colour(style))
        meta = [] if e.state is None else [fm.KeyValuePair(key="state", value=e.state)]
        entity(f"estimate/{e.id}", spheres=[sphere], lines=lines, metadata=meta)
    for s in view.sensors:
        lines = []
        if s.coverage is not None:
            lines.append(_coverage_line(s.position, s.coverage))
        if s.state == "on":
            for tid in s.targets:
                end = truth_at.get(tid, est_at.get(tid))
                if end is not None:
                    lines.append(_line(LIST, [_p3(s.position), _p3(end)], "link", 1.5))
        label = s.id if s.placed else f"{s.id} (no position)"
        above = (s.position[0], s.position[1], s.position[2] + view.marker)
        entity(
            f"sensor/{s.id}",
            cubes=[fm.CubePrimitive(pose=_pose(s.position), size=size, color=_colour(s.state))],
            lines=lines,
            texts=[_text(above, label, s.state)],
            metadata=[fm.KeyValuePair(key="state", value=s.state)],
        )
    for seg in view.segments:
        entity(f"segment/{seg.id}", lines=[_line(LIST, [_p3(seg.a), _p3(seg.b)], seg.colour, 1.0)])
    return fm.SceneUpdate(
        deletions=[fm.SceneEntityDeletion(timestamp=ts, type=fm.SceneEntityDeletionType.All)],
        entities=entities,
    )


@dataclass(frozen=True)
class VisualMessage:
    """One encoded visual message: its topic, schema (name, encoding, data), message encoding,
    bytes and log time (ns)."""

    topic: str
    schema: foxglove.Schema
    encoding: str
    data: bytes
    log_time_ns: int


SCENE_SCHEMA = fm.SceneUpdate.get_schema()
LOG_SCHEMA = fm.Log.get_schema()
JSON_METRICS_SCHEMA = foxglove.Schema(
    name="covnet.ScanMetrics",
    encoding="jsonschema",
    data=json.dumps(METRICS_SCHEMA, sort_keys=True).encode(),
)
ENCODINGS = {SCENE_TOPIC: "protobuf", METRICS_TOPIC: "json", LOG_TOPIC: "protobuf"}
SCHEMAS = {SCENE_TOPIC: SCENE_SCHEMA, METRICS_TOPIC: JSON_METRICS_SCHEMA, LOG_TOPIC: LOG_SCHEMA}


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def _known(doc: dict[str, Any]) -> dict[str, Any]:
    """``doc`` without its unknown (None) values: Foxglove takes no ``null`` (see
    :data:`METRICS_SCHEMA`)."""
    return {k: v for k, v in doc.items() if v is not None}


# --------------------------------------------------------------------------------------------
# the stream of messages -> frames
# --------------------------------------------------------------------------------------------


@dataclass
class _Pending:
    command: msg.Command | None = None
    measurements: dict[str, msg.Measurement] = field(default_factory=dict)
    tracks: list[msg.Track] = field(default_factory=list)


_NEEDED = frozenset({"cmd", "truth", "meas", "track", "status"})
_MAX_TRUTHS = 20_000
_MAX_PENDING = 256


class Visualiser:
    """Feed it a run's messages in arrival order (:meth:`feed`); it returns the visual messages
    of every scan whose Status arrived (three per scan: scene, numbers, log line).

    ``episodes``: the run's episode names (``Kind.episodes``); ``kind_visual``: the kind's
    module.  Keeps per episode the sums for the RMSE so far, and per scan only what arrived for
    it until its Status (bounded: :data:`_MAX_PENDING` scans)."""

    def __init__(
        self, kind_visual: KindVisual, episodes: Sequence[str], *, timed: bool = True
    ) -> None:
        self.kind_visual = kind_visual
        self._wants_measurements = bool(getattr(kind_visual, "measurements", False))
        self.timed = timed
        self.episodes = list(episodes)
        self._truth: dict[int, msg.Truth] = {}
        self._pending: dict[tuple[int, int], _Pending] = {}
        self._sq: dict[tuple[int, str], tuple[float, int]] = {}  # (episode, id) -> (Σe², n)
        self._sq_all: dict[int, tuple[float, int]] = {}
        self._counts = 0
        self._bytes = 0
        self._latency_ms: list[float] = []
        #: the nodes whose heartbeats name another clock than this process's
        #: (:func:`~covnet.processes.node_kit.same_clock`): their latencies are not taken
        self._other_clock: set[str] = set()
        self.frames = 0
        self.undecodable = 0
        self.last_episode = -1

    def feed(
        self, kind: str, key: str, payload: bytes, t_recv_ns: int, t_sent_ns: int | None = None
    ) -> list[VisualMessage]:
        """One received message (``kind``, ``t_sent_ns``: :func:`covnet.runs.recording.peek`'s).
        A measurement is decoded only for a kind that draws them (``KindVisual.measurements``);
        for the others its latency comes from ``t_sent_ns``."""
        self._counts += 1
        self._bytes += len(payload)
        if kind == msg.Heartbeat.KIND:
            with contextlib.suppress(msg.WireError):
                hb = msg.decode_as(payload, msg.Heartbeat)
                if same_clock(hb.host):
                    self._other_clock.discard(hb.node_id)
                else:
                    self._other_clock.add(hb.node_id)
            return []
        if kind not in _NEEDED:
            return []
        if kind == "meas" and t_sent_ns is not None and not self._wants_measurements:
            with contextlib.suppress(ValueError):
                if msg.parse_measurement_key(key) not in self._other_clock:
                    self._latency_ms.append((t_recv_ns - t_sent_ns) / 1e6)
            return []
        try:
            m = msg.decode(payload)
        except msg.WireError:
            self.undecodable += 1
            return []
        return self.feed_message(m, t_recv_ns)

    def feed_message(self, m: msg.Message, t_recv_ns: int) -> list[VisualMessage]:
        """One decoded message (the in-process path feeds these directly)."""
        if isinstance(m, msg.Truth):
            if len(self._truth) >= _MAX_TRUTHS:
                self._truth.pop(next(iter(self._truth)))
            self._truth[m.scan] = m
        elif isinstance(m, msg.Measurement):
            self._at(m.episode, m.scan).measurements[m.sensor_id] = m
            if m.sensor_id not in self._other_clock:
                self._latency_ms.append((t_recv_ns - m.t_sent_ns) / 1e6)
        elif isinstance(m, msg.Command):
            self._at(m.episode, m.scan).command = m
        elif isinstance(m, msg.Track):
            if m.node_id is None:
                self._at(m.episode, m.scan).tracks.append(m)
        elif isinstance(m, msg.Status) and m.node_id is None:
            return self._frame(m, t_recv_ns)
        return []

    def _at(self, e: int, k: int) -> _Pending:
        p = self._pending.get((e, k))
        if p is None:
            if len(self._pending) >= _MAX_PENDING:
                self._pending.pop(next(iter(self._pending)))
            p = self._pending[(e, k)] = _Pending()
        return p

    def _frame(self, status: msg.Status, t_ns: int) -> list[VisualMessage]:
        e, k = status.episode, status.scan
        p = self._pending.pop((e, k), _Pending())
        for old in [key for key in self._pending if key <= (e, k)]:
            del self._pending[old]  # scans whose Status never came
        scan = ScanMessages(e, k, status, p.command, self._truth.get(k), p.measurements, p.tracks)
        view = self.kind_visual.view(scan)
        scene = scene_update(view, t_ns).encode()
        out = [
            VisualMessage(SCENE_TOPIC, SCENE_SCHEMA, "protobuf", scene, t_ns),
            VisualMessage(
                METRICS_TOPIC, JSON_METRICS_SCHEMA, "json", self._metrics(scan, view), t_ns
            ),
            VisualMessage(LOG_TOPIC, LOG_SCHEMA, "protobuf", self._log(scan, view, t_ns), t_ns),
        ]
        self.frames += 1
        self.last_episode = e
        return out

    def episode_name(self, e: int) -> str:
        return self.episodes[e] if 0 <= e < len(self.episodes) else str(e)

    def _metrics(self, scan: ScanMessages, view: View) -> bytes:
        e = scan.episode
        targets = []
        nees = []
        for est in view.estimates:
            rmse = None
            if est.error is not None and math.isfinite(est.error):
                s, n = self._sq.get((e, est.id), (0.0, 0))
                self._sq[(e, est.id)] = (s + est.error**2, n + 1)
                rmse = math.sqrt((s + est.error**2) / (n + 1))
                s, n = self._sq_all.get(e, (0.0, 0))
                self._sq_all[e] = (s + est.error**2, n + 1)
            if est.nees is not None and math.isfinite(est.nees):
                nees.append(est.nees)
            targets.append(
                _known(
                    {
                        "id": est.id,
                        "f": _num(est.f),
                        "trace_P": _num(est.trace_P),
                        "trace_Pd": _num(est.trace_Pd),
                        "error": _num(est.error),
                        "rmse": _num(rmse),
                        "nees": _num(est.nees),
                    }
                )
            )
        s, n = self._sq_all.get(e, (0.0, 0))
        cmd = scan.command
        lat = self._latency_ms
        doc = _known(
            {
                "episode": e,
                "episode_name": self.episode_name(e),
                "scan": scan.scan,
                "t": float(scan.status.t),
                "n_active": view.n_active,
                "n_failed": len(scan.status.failed),
                "f": _num(view.f),
                "trace_P": _num(view.trace_P),
                "trace_Pd": _num(view.trace_Pd),
                "rmse": _num(math.sqrt(s / n)) if n else None,
                "nees": _num(float(np.mean(nees))) if nees else None,
                # counts of a network's messages: none in covnet run --mcap (a 0 there drew a
                # line of zeros in Foxglove's plots)
                "messages": self._counts if self.timed else None,
                "bytes": self._bytes if self.timed else None,
                "scan_latency_ms": (
                    _num((scan.status.t_sent_ns - cmd.t_sent_ns) / 1e6)
                    if cmd is not None and self.timed
                    else None
                ),
                "measurement_latency_ms": float(np.mean(lat)) if lat and self.timed else None,
                "measurement_latency_max_ms": float(max(lat)) if lat and self.timed else None,
                "targets": targets,
            }
        )
        self._counts = self._bytes = 0
        self._latency_ms = []
        return json.dumps(doc, separators=(",", ":")).encode()

    def _log(self, scan: ScanMessages, view: View, t_ns: int) -> bytes:
        st = scan.status
        parts = [f"{self.episode_name(scan.episode)} scan {scan.scan}"]
        parts.append(f"enabled {','.join(st.enabled) or '-'}")
        if view.trace_P is not None:
            parts.append(f"tr P {view.trace_P:.4g}")
        if view.trace_Pd:
            parts.append(f"tr Pd {view.trace_Pd:.4g}")
        if view.f is not None:
            parts.append(f"f {view.f:.4g}")
        if st.failed:
            parts.append(f"failed {','.join(st.failed)}")
        level = fm.LogLevel.Warning if st.failed else fm.LogLevel.Info
        return fm.Log(
            timestamp=_timestamp(t_ns), level=level, message="  ".join(parts), name="manager"
        ).encode()


def sensor_states(status: msg.Status, ids: Iterable[str]) -> dict[str, str]:
    """Each sensor's state in a scan: ``failed`` (the manager saw it failed), ``on`` (enabled)
    or ``off``."""
    enabled, failed = set(status.enabled), set(status.failed)
    return {sid: "failed" if sid in failed else "on" if sid in enabled else "off" for sid in ids}


RUN_MCAP = "run.mcap"
"""``covnet run --mcap``'s file in the run directory."""


def write_run_mcap(kind: Any, cfg: Any, run_dir: Path, path: Path | None = None) -> Path:
    """``covnet run --mcap``: the visual channels of an in-process run directory, written to
    ``path`` (default ``run_dir/run.mcap``) with the run's metadata.  The kind rebuilds its
    scans as messages (``Kind.run_messages``), which go through the same :class:`Visualiser`
    as a recorder's; their times are scenario time (the episodes one after another, a second
    apart), and there are no message counts or latencies (nothing went over a network)."""
    path = Path(path) if path is not None else Path(run_dir) / RUN_MCAP
    vis = Visualiser(kind.visual(cfg), kind.episodes(cfg), timed=False)
    meta = run_metadata("in-process", cfg)
    meta["covnet.run"]["mode"] = "in-process (covnet run --mcap): visual channels only"
    # its times are the scenario's, not this host's clock (the recorder's metadata says so)
    meta["covnet.run"]["time_base"] = (
        "scenario time in ns from 0 (episodes one after another, a second apart)"
    )
    for key in ("start_monotonic_ns", "start_utc_ns"):
        meta["covnet.run"].pop(key, None)
    base_ns, last_ns, episode = 0, 0, 0
    with RecordingWriter(path, run_id="in-process", metadata=meta) as w:
        for m in kind.run_messages(cfg, Path(run_dir)):
            # a message without an episode (the Truth) belongs to the current one: taken for
            # episode 0, it moved the base twice a scan from the second episode on (its scan
            # 15 at 301 s instead of 31 s)
            e = getattr(m, "episode", None)
            if e is not None and int(e) != episode:
                episode, base_ns = int(e), last_ns + 1_000_000_000
            last_ns = max(last_ns, base_ns + round(float(getattr(m, "t", 0.0)) * 1e9))
            for vm in vis.feed_message(m, last_ns):
                w.write_visual(vm)
    return path
