"""Counters a process keeps about the bus: messages and bytes per key, rejections by reason,
per-scan latency.  Written to ``network.json`` by the manager.

``rejected`` / ``rejected_by_key`` are the manager's own rejections (measurements, heartbeats);
``rejected_by_node`` are the other nodes' (world, sensors: commands, truth), as last reported in
their heartbeats.  Reasons are :data:`covnet.wire.messages.REASONS` plus the manager's semantic
ones:
``key_mismatch``, ``late``, ``wrong_scan``, ``duplicate``, ``not_enabled``, ``bad_measurement``,
``bad_key``, ``bad_seq``.

What became of each sensor's messages (``sensors`` in ``network.json``, and the totals), the
same words as ``covnet run``'s latency counts (:mod:`covnet.covariance_control.latency_sim`):

- ``sent``: how many the sensor sent (the highest ``seq`` received, or the count in its last
  heartbeat when that is higher: :class:`SeqCount`);
- ``on_time``: arrived by their scan's deadline and taken for it;
- ``late``: arrived after their scan's deadline (``late_refiltered``: re-filtered into their
  scan; ``late_dropped``: dropped; ``late`` alone: the kind has no use for late ones);
- ``rejected``: arrived but refused (another scan, a duplicate, unusable, ...: by reason in
  ``rejected``);
- ``lost``: sent and not received before the run ended (a gap in ``seq``, or beyond the last
  one received), so ``sent = on_time + late + rejected + lost`` per sensor;
- ``missing_at_deadline`` (totals only): awaited at a deadline and not there then: those that
  came later are ``late``, the rest ``lost`` or never sent (a command that did not arrive, a
  sensor that failed).
"""

from __future__ import annotations

from array import array
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

SEQ_AHEAD = 100_000
"""A ``seq`` more than this beyond the highest one received is refused (``bad_seq``): a forged
number must not make the counter's memory grow."""


@dataclass
class SeqCount:
    """Which of one sensor's numbered messages arrived: ``seq`` 1, 2, ... per process; a
    restarted sensor process counts from 1 again (:meth:`restart` folds the old counts)."""

    high: int = 0
    reported: int = 0  # the sensor's own count (its heartbeats' ``sent``)
    arrived: int = 0
    sent_before: int = 0
    arrived_before: int = 0
    seen: bytearray = field(default_factory=bytearray)  # bit i: seq i + 1 arrived
    first_at: tuple[int, int] | None = None  # (episode, scan) of this stretch's seq 1

    def add(self, seq: int, at: tuple[int, int] | None = None) -> str | None:
        """Note ``seq``'s arrival (of a message of ``(episode, scan)`` ``at``); None, or why it
        is refused (``duplicate``, ``bad_seq``).  A second ``seq`` 1 of a later scan than the
        first one's is a restarted process counting again (:meth:`restart`); of the same scan
        or an earlier one, or without a scan, it is a copy (``duplicate``: one replayed
        ``seq`` 1 was taken for a restart and made up hundreds of lost messages)."""
        if seq == 1 and self.seen and self.seen[0] & 1:
            if at is None or self.first_at is None or at <= self.first_at:
                return "duplicate"
            self.restart()
        if seq == 1:
            self.first_at = at
        i = seq - 1
        if i < 0 or seq > self.high + SEQ_AHEAD:
            return "bad_seq"
        byte, bit = divmod(i, 8)
        if byte >= len(self.seen):
            self.seen.extend(bytes(byte + 1 - len(self.seen)))
        if self.seen[byte] >> bit & 1:
            return "duplicate"
        self.seen[byte] |= 1 << bit
        self.arrived += 1
        self.high = max(self.high, seq)
        return None

    def restart(self) -> None:
        """The sensor's process restarted: its next ``seq`` starts a new stretch."""
        self.sent_before += max(self.high, self.reported)
        self.arrived_before += self.arrived
        self.high = self.reported = self.arrived = 0
        self.seen = bytearray()

    def report(self, sent: int) -> None:
        """The sensor says it has sent ``sent`` so far (a heartbeat): the last ones count
        as sent even when none of them arrives."""
        if sent <= SEQ_AHEAD + self.high:
            self.reported = max(self.reported, sent)

    @property
    def sent(self) -> int:
        return self.sent_before + max(self.high, self.reported)

    @property
    def lost(self) -> int:
        return self.sent - self.arrived_before - self.arrived


@dataclass
class NetStats:
    sent_msgs: Counter[str] = field(default_factory=Counter)
    sent_bytes: Counter[str] = field(default_factory=Counter)
    recv_msgs: Counter[str] = field(default_factory=Counter)
    recv_bytes: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)  # reason -> count
    rejected_by_key: defaultdict[str, Counter[str]] = field(
        default_factory=lambda: defaultdict(Counter)
    )
    # int64 arrays, not lists: 8 bytes a value over a long run (covnet bench soak)
    scan_latency_ns: array[int] = field(default_factory=lambda: array("q"))  # cmd -> fused
    meas_latency_ns: array[int] = field(default_factory=lambda: array("q"))  # sensor -> manager
    #: measurements whose sender stamps with another clock (another host: its monotonic clock
    #: counts from its own boot), left out of ``meas_latency_ns``
    meas_latency_other_clock: int = 0
    core_ns: array[int] = field(default_factory=lambda: array("q"))  # predict+allocate+fuse
    loop_wall_ns: int = 0  # READY -> last scan fused, all episodes
    scans_done: int = 0
    late: int = 0
    late_refiltered: int = 0  # late, re-filtered from their scan (network.latency.late: oosm)
    late_dropped: int = 0  # late and dropped (policy drop, older than the buffer, CI)
    unsolicited: int = 0  # fused from a sensor that measured on a stale command
    missing_at_deadline: int = 0  # awaited and not there at the deadline (late or lost later)
    seq: dict[str, SeqCount] = field(default_factory=dict)  # per sensor: what arrived
    outcome: defaultdict[str, Counter[str]] = field(
        default_factory=lambda: defaultdict(Counter)
    )  # per sensor: on_time, late, late_refiltered, late_dropped, rejected
    membership: defaultdict[str, Counter[str]] = field(
        default_factory=lambda: defaultdict(Counter)
    )  # per node: failed, rejoined (events seen by the manager)
    node_rejected: dict[str, dict[str, int]] = field(default_factory=dict)  # from heartbeats
    #: the world or recorder down as the last scan was done, and since when: ``{node:
    #: {"after_scan": k, "episode": name}}`` (:meth:`manager.loop.Loop.note_vital`)
    gone_at_end: dict[str, dict[str, Any]] = field(default_factory=dict)
    # over the bus only: what the manager's bus dropped before decoding ({key: {reason: n}},
    # reason "oversize": covnet.wire.bus); None in process (no bus, and not in network.json)
    dropped: dict[str, dict[str, int]] | None = None

    def sent(self, key: str, n_bytes: int) -> None:
        self.sent_msgs[key] += 1
        self.sent_bytes[key] += n_bytes

    def received(self, key: str, n_bytes: int) -> None:
        self.recv_msgs[key] += 1
        self.recv_bytes[key] += n_bytes

    def reject(self, key: str, reason: str) -> None:
        self.rejected[reason] += 1
        self.rejected_by_key[key][reason] += 1

    def arrived(
        self, sensor: str, seq: int | None, at: tuple[int, int] | None = None
    ) -> str | None:
        """A well-formed message of ``sensor`` numbered ``seq`` (of ``(episode, scan)`` ``at``)
        arrived; None, or why its number is refused (then it is rejected, uncounted):
        ``missing_seq`` for a message without one (every sensor numbers its messages: such a
        message is not a sensor's, and counted as its ``late`` it broke ``sent = on_time +
        late + rejected + lost``)."""
        if seq is None:
            return "missing_seq"
        counts = self.seq.get(sensor)
        if counts is None:  # (not setdefault: it would build a SeqCount per message)
            counts = self.seq[sensor] = SeqCount()
        return counts.add(seq, at)

    def reported(self, sensor: str, sent: int) -> None:
        """``sensor``'s heartbeat says it has sent ``sent`` messages (:meth:`SeqCount.report`)."""
        self.seq.setdefault(sensor, SeqCount()).report(sent)

    def membership_counts(self) -> dict[str, dict[str, int]]:
        """Per node that failed at least once: how often it ``failed`` and ``rejoined``."""
        return {
            n: {"failed": c["failed"], "rejoined": c["rejoined"]}
            for n, c in sorted(self.membership.items())
        }

    @property
    def lost(self) -> int:
        """Messages sent and never arrived (so far), over every sensor."""
        return sum(c.lost for c in self.seq.values())

    def sensors(self) -> dict[str, dict[str, int]]:
        """Per sensor: ``sent``, ``on_time``, ``late`` (and how), ``rejected``, ``lost``."""
        out = {}
        for sid in sorted(set(self.seq) | set(self.outcome)):
            c, o = self.seq.get(sid), self.outcome.get(sid, Counter())
            out[sid] = {
                "sent": c.sent if c else 0,
                "on_time": o["on_time"],
                "late": o["late"],
                "late_refiltered": o["late_refiltered"],
                "late_dropped": o["late_dropped"],
                "rejected": o["rejected"],
                "lost": c.lost if c else 0,
            }
        return out

    def as_dict(self) -> dict[str, Any]:
        def pct(xs: array[int]) -> dict[str, float | None]:
            if not xs:
                return {"p50_ms": None, "p99_ms": None, "max_ms": None, "n": 0}
            a = np.asarray(xs, dtype=np.float64) / 1e6
            return {
                "p50_ms": float(np.percentile(a, 50)),
                "p99_ms": float(np.percentile(a, 99)),
                "max_ms": float(a.max()),
                "n": int(a.size),
            }

        return {
            "sent": {
                k: {"messages": v, "bytes": self.sent_bytes[k]} for k, v in self.sent_msgs.items()
            },
            "received": {
                k: {"messages": v, "bytes": self.recv_bytes[k]} for k, v in self.recv_msgs.items()
            },
            "rejected": dict(self.rejected),
            "rejected_by_key": {k: dict(v) for k, v in self.rejected_by_key.items()},
            "rejected_by_node": self.node_rejected,
            "scan_latency": pct(self.scan_latency_ns),
            "measurement_latency": pct(self.meas_latency_ns),
            "core": pct(self.core_ns),
            "scans": self.scans_done,
            "loop_wall_s": self.loop_wall_ns / 1e9,
            "core_share": sum(self.core_ns) / self.loop_wall_ns if self.loop_wall_ns else None,
            "scans_per_s": self.scans_done / (self.loop_wall_ns / 1e9)
            if self.loop_wall_ns
            else None,
            "late": self.late,
            "lost": self.lost,
            "late_refiltered": self.late_refiltered,
            "late_dropped": self.late_dropped,
            "unsolicited": self.unsolicited,
            "missing_at_deadline": self.missing_at_deadline,
            "sensors": self.sensors(),
            "membership": self.membership_counts(),
            **({} if self.dropped is None else {"dropped": self.dropped}),
            **(
                {"measurement_latency_other_clocks": self.meas_latency_other_clock}
                if self.meas_latency_other_clock
                else {}
            ),
        }
