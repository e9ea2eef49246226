"""Counters a process keeps about the bus: messages and bytes per key, rejections by reason,
per-scan latency.  Written to ``network.json`` by the manager.

``rejected`` / ``rejected_by_key`` are the manager's own rejections (measurements, heartbeats);
``rejected_by_node`` are the other nodes' (world, sensors: commands, truth), as last reported in
their heartbeats.  Reasons are :data:`covnet.messages.REASONS` plus the manager's semantic ones:
``key_mismatch``, ``late``, ``wrong_scan``, ``duplicate``, ``not_enabled``, ``bad_measurement``,
``bad_key``.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np


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
    scan_latency_ns: list[int] = field(default_factory=list)  # command sent -> scan fused
    meas_latency_ns: list[int] = field(default_factory=list)  # one-way sensor -> manager
    core_ns: list[int] = field(default_factory=list)  # per scan: predict+allocate+fuse
    loop_wall_ns: int = 0  # READY -> last scan fused, all episodes
    scans_done: int = 0
    late: int = 0
    lost: int = 0
    late_refiltered: int = 0  # late, re-filtered from their scan (network.latency.late: oosm)
    late_dropped: int = 0  # late and dropped (policy drop, older than the buffer, CI)
    unsolicited: int = 0  # fused from a sensor that measured on a stale command
    node_rejected: dict[str, dict[str, int]] = field(default_factory=dict)  # from heartbeats

    def sent(self, key: str, n_bytes: int) -> None:
        self.sent_msgs[key] += 1
        self.sent_bytes[key] += n_bytes

    def received(self, key: str, n_bytes: int) -> None:
        self.recv_msgs[key] += 1
        self.recv_bytes[key] += n_bytes

    def reject(self, key: str, reason: str) -> None:
        self.rejected[reason] += 1
        self.rejected_by_key[key][reason] += 1

    def as_dict(self) -> dict[str, Any]:
        def pct(xs: list[int]) -> dict[str, float | None]:
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
        }
