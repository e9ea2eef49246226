"""A peer-mode run's results (``fusion.mode: peer``): every node's reports by episode and scan
(:class:`NodeLog`, :class:`PeerResult`) and the run directory they make
(:func:`write_peer_run`), written alike by the network's observer (:mod:`manager.peer_monitor`,
from the nodes' Tracks and Statuses on the bus) and by ``covnet replay`` (from the kind's engine
stepped with the recording, :mod:`covnet.covariance_control.replay`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees, predict_covariance
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import Model, build_model, truth_trajectory
from covnet.covariance_control.results import write_json, write_run
from covnet.covariance_control.simulate import MetricRun, shared_trajectory
from covnet.processes.runtime_stats import NetStats
from covnet.runs.columns import Column
from covnet.wire import messages as msg

__all__ = ["NodeLog", "PeerResult", "StatusRow", "TrackRow", "write_peer_run"]


class TrackRow(NamedTuple):
    """What a peer run keeps of a node's Track of a scan."""

    x: np.ndarray
    P: np.ndarray


class StatusRow(NamedTuple):
    """What a peer run keeps of a node's Status of a scan."""

    enabled: tuple[str, ...]
    value: float
    failed: tuple[str, ...]


_ROW = np.dtype(
    [
        ("scan", np.int64),
        ("status", np.bool_),  # a Status's row (else a Track's)
        ("x", np.float64, (4,)),
        ("P", np.float64, (4, 4)),
        ("value", np.float64),
        ("enabled", np.int32),  # index of the node set in NodeLog's table of sets
        ("failed", np.int32),
    ]
)
_RECENT = 64
"""The Statuses a :class:`NodeLog` keeps whole, of its latest scans (the monitor reports and
asks of the scan in progress); older ones are looked up in the rows."""


class NodeLog:
    """One node's reports in one episode, by scan: every Track and Status as a row of one
    :class:`~covnet.runs.columns.Column` (a long run's rows go to its spill file as blocks
    fill: the monitor kept every decoded message, about 17 kB a scan for 8 nodes, and was the
    one process of a peer soak that grew), read back as ``tracks`` and ``statuses`` (scan ->
    :class:`TrackRow` / :class:`StatusRow`; a later report of a scan replaces an earlier
    one, as the dictionaries of messages did)."""

    def __init__(self) -> None:
        self._rows = Column((), _ROW)
        self._sets: dict[tuple[str, ...], int] = {}
        self._set_list: list[tuple[str, ...]] = []
        self._recent: dict[int, msg.Status] = {}
        self._views: tuple[dict[int, TrackRow], dict[int, StatusRow]] | None = None

    def _set(self, nodes: tuple[str, ...]) -> int:
        i = self._sets.get(nodes)
        if i is None:
            i = self._sets[nodes] = len(self._set_list)
            self._set_list.append(nodes)
        return i

    def add(self, m: msg.Track | msg.Status) -> None:
        """Keep a node's Track or Status (of this log's episode)."""
        row: tuple[Any, ...]
        if isinstance(m, msg.Track):
            row = (m.scan, False, m.x, m.P, 0.0, -1, -1)
        else:
            row = (m.scan, True, 0.0, 0.0, m.value, self._set(m.enabled), self._set(m.failed))
            self._recent[m.scan] = m
            if len(self._recent) > _RECENT:
                for k in sorted(self._recent)[: _RECENT // 2]:
                    del self._recent[k]
        self._rows.append(np.array(row, dtype=_ROW))
        self._views = None

    def recent_status(self, k: int) -> msg.Status | None:
        """The Status of scan ``k`` as it came, if it is among the latest :data:`_RECENT`."""
        return self._recent.get(k)

    def has_status(self, k: int) -> bool:
        """Whether a Status of scan ``k`` is here."""
        if k in self._recent:
            return True
        if not self._recent or k > min(self._recent):
            return False
        return k in self.statuses

    def _built(self) -> tuple[dict[int, TrackRow], dict[int, StatusRow]]:
        if self._views is None:
            rows = self._rows.array()
            tracks: dict[int, TrackRow] = {}
            statuses: dict[int, StatusRow] = {}
            sets = self._set_list
            for r in rows:
                k = int(r["scan"])
                if r["status"]:
                    statuses[k] = StatusRow(
                        sets[int(r["enabled"])], float(r["value"]), sets[int(r["failed"])]
                    )
                else:
                    tracks[k] = TrackRow(r["x"].copy(), r["P"].copy())
            self._views = (tracks, statuses)
        return self._views

    @property
    def tracks(self) -> dict[int, TrackRow]:
        return self._built()[0]

    @property
    def statuses(self) -> dict[int, StatusRow]:
        return self._built()[1]

    def scans(self) -> int:
        """Scans 1..n reported completely (track and status), without a gap."""
        n = 0
        while n + 1 in self.tracks and n + 1 in self.statuses:
            n += 1
        return n

    def as_run(
        self, metric: str, ids: tuple[str, ...], truth: np.ndarray, model: Model | None = None
    ) -> MetricRun:
        """The node's run; ``P_pred`` (which a node does not report) is rebuilt with
        ``model``'s motion from the node's own previous estimate, as its filter predicted it
        (the network wrote NaN where ``covnet run --fusion peer`` wrote the prediction);
        without ``model``, NaN."""
        n = self.scans()
        enabled = np.zeros((n, len(ids)), dtype=bool)
        for k in range(1, n + 1):
            enabled[k - 1, [ids.index(s) for s in self.statuses[k].enabled]] = True
        x = np.array([self.tracks[k].x for k in range(1, n + 1)]).reshape(n, 4)
        P = np.array([self.tracks[k].P for k in range(1, n + 1)]).reshape(n, 4, 4)
        eps = np.array([nees(Gaussian(x[i], P[i]), truth[i]) for i in range(n)])
        return MetricRun(
            metric=metric,
            enabled=enabled,
            value=np.array([self.statuses[k].value for k in range(1, n + 1)]),
            x_est=x,
            P_post=P,
            P_pred=_predictions(P, model) if model is not None else np.full((n, 4, 4), np.nan),
            nees=eps,
            decision_s=np.zeros(n),
            n_evaluated=np.full(n, -1, dtype=np.int64),  # not reported by a node
        )


def _predictions(P_post: np.ndarray, model: Model) -> np.ndarray:
    """``P⁻_k = F P_{k-1} Fᵀ + Q`` (``P_0``: the filter's initial covariance), with the
    filter's own arithmetic (:func:`~covnet.core.kalman.predict_covariance`)."""
    out = np.empty_like(P_post)
    prev = model.P0
    for k in range(P_post.shape[0]):
        out[k] = predict_covariance(prev, model.F, model.Q)
        prev = P_post[k]
    return out


@dataclass
class PeerResult:
    metrics: list[str]
    nodes: dict[int, dict[str, NodeLog]]  # episode -> node -> log
    stats: NetStats
    completed: bool = False
    error: str | None = None


def failed_by_majority(statuses: Mapping[str, Mapping[int, Any]]) -> dict[str, int]:
    """Per node, the first scan at which most of the other nodes that reported that scan
    name it failed (``statuses``: node -> scan -> its Status, whose ``failed`` are the nodes
    it left out).  Every node's own view counted alone, a node frozen for a few seconds, which
    then found none of its peers' statuses and left them all out, made every sensor "failed";
    by the majority only the frozen one is."""
    scans = sorted({k for by_scan in statuses.values() for k in by_scan})
    out: dict[str, int] = {}
    for k in scans:
        reports = {n: by_scan[k] for n, by_scan in statuses.items() if k in by_scan}
        named = {m for st in reports.values() for m in st.failed}
        for m in sorted(named - set(out)):
            voters = [n for n in reports if n != m]
            votes = sum(m in reports[n].failed for n in voters)
            if voters and 2 * votes > len(voters):
                out[m] = k
    return out


def disagreement(logs: Mapping[str, NodeLog]) -> list[int]:
    """The scans at which the nodes' reports disagree: over every scan any node reported, the
    nodes' Statuses name different enabled sets, or a node that reported a later scan has none
    of this one (it missed it and went on alone).  (The runs stop at a node's first gap, so
    comparing them said "agree" of a node frozen for 1.5 s whose peers left it out for the
    rest of the run: 258 of 300 scans differed.)"""
    last = {n: max(log.statuses, default=0) for n, log in logs.items()}
    out: list[int] = []
    for k in range(1, max(last.values(), default=0) + 1):
        sets = {frozenset(log.statuses[k].enabled) for log in logs.values() if k in log.statuses}
        gap = any(k not in log.statuses and k < last[n] for n, log in logs.items())
        if len(sets) > 1 or gap:
            out.append(k)
    return out


def write_peer_run(
    out: Path, sc: Scenario, result: PeerResult, run_info: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The run directory of a peer-mode network: as ``covnet run --fusion peer`` writes it (the
    first node's run under ``metrics``, every node's under ``peer``), for the scans reported,
    plus ``network.json`` and the failures the nodes reported (``failures``: per metric, the
    first scan at which the live nodes excluded each failed node); ``run.json`` gets
    ``run_info`` and ``scans_completed``."""
    model = build_model(sc)
    traj = shared_trajectory(model)
    truth = truth_trajectory(model)
    ids = model.sensor_ids
    node_runs: dict[str, dict[str, MetricRun]] = {}
    runs: dict[str, MetricRun] = {}
    failures: dict[str, list[dict[str, Any]]] = {}
    disagree: dict[str, list[int]] = {}
    for e, metric in enumerate(result.metrics):
        logs = result.nodes.get(e, {})
        nodes = {n: logs[n].as_run(metric, ids, truth, model) for n in ids if n in logs}
        nodes = {n: r for n, r in nodes.items() if len(r.value)}
        if not nodes:
            continue
        node_runs[metric] = nodes
        # the metrics block: the first node that completed the most scans
        first = max(nodes, key=lambda n: (len(nodes[n].value), -ids.index(n)))
        runs[metric] = nodes[first]
        disagree[metric] = disagreement({n: logs[n] for n in nodes})
        seen = failed_by_majority({n: log.statuses for n, log in logs.items()})
        failures[metric] = [
            {"sensor": n, "scan": k, "event": "failed"} for n, k in sorted(seen.items())
        ]
    extra: dict[str, Any] = {
        "completed": result.completed,
        "scans_completed": {m: len(r.value) for m, r in runs.items()},
        "failures": failures,
    }
    # run.json says how far the run got, as a central manager's does (the launcher prints it)
    info: dict[str, Any] = {"mode": "network", "scans_completed": extra["scans_completed"]}
    info.update(run_info or {})
    summary = write_run(
        out, sc, traj, runs, extra=extra, run_info=info, node_runs=node_runs, disagree=disagree
    )
    write_json(out / "network.json", result.stats.as_dict())
    return summary
