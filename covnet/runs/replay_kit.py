"""What every kind's replay shares: rebuild a network run's directory from its recording alone
(``covnet replay RUN_DIR``; the launcher, after a manager crash), and compare it with the run's.

A kind's replay module (``covnet/<kind>/replay.py``) subclasses :class:`KindReplay` with what
only it knows: which messages it reads from the recording (:meth:`KindReplay.load`, usually
:func:`load_recording` with the manager's acceptance test), how the manager's own code
recomputes every scan from them (:meth:`KindReplay.recompute`, reporting what it finds that is
not what the manager recorded to a :class:`Differences`) and the manager's own writer
(:meth:`KindReplay.write`).  A single-episode kind whose manager steps a :class:`ScanSteps`
(mobile, passive) is a :class:`StepsReplay` of its steps and writer: the recomputation
(:func:`recompute_scans`) is then shared too.  The rest is here, the same for every kind:

- :meth:`KindReplay.rebuild` ``(cfg, run_id, episodes, recording, out, run_info)``: read the
  recording front to back (:class:`covnet.runs.recording.RecordingReader`: a file whose recorder or
  manager was killed reads up to its last complete record), check its metadata against the
  run (run id, config hash), decode strictly (:func:`covnet.wire.messages.decode_as`; a payload that
  does not decode is counted by reason, ``skipped:<reason>``, never used), recompute every scan
  the manager recorded a Status of, up to the first one missing, write the run directory into
  ``out`` with ``run.json`` = the writer's own, ``episodes``, ``run_id`` and ``run_info``
  (which wins), and ``replay.json``: the :class:`ReplayReport`;
- :meth:`KindReplay.replay_run` ``(run_dir, out)``: ``config.json``, ``run.json`` (``run_id``;
  ``episodes``, by default the kind's episodes of the config) and ``recording.mcap`` of
  ``run_dir``, :meth:`~KindReplay.rebuild` into ``out`` (default ``run_dir/replay``), then each
  of the kind's result files (:attr:`KindReplay.compared`) byte for byte against the run's; a
  file that differs is listed by JSON path (``path: original != replayed``, the shallowest
  first), or as "same content but different bytes";
- :meth:`KindReplay.command`: ``covnet replay RUN_DIR [--out DIR] [--force]``.

``identical`` in the report: no difference at all, i.e. every compared file equal byte for byte
and every recomputed decision and estimate equal to the recorded one.  Differences are grouped
by kind (``allocation``, ``measurement``, ``summary``, ...), at most :data:`MAX_LISTED` listed
per kind and the rest counted.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from covnet import kinds
from covnet.code_identity import other_code
from covnet.errors import UsageError
from covnet.processes.network_run import ScanDecision, ScanImpossible
from covnet.runs.recording import (
    META_RUN,
    META_UNRECORDED,
    RecordedSample,
    RecordingReader,
    key_kind,
    mcap_start_problem,
    read_metadata,
)
from covnet.runs.rundir import CONFIG, RUN_INFO, SUMMARY, prepare_out, write_json
from covnet.wire import messages as msg

__all__ = [
    "MAX_LISTED",
    "RECORDING",
    "REPLAY_DIR",
    "REPORT",
    "Differences",
    "KindReplay",
    "Recorded",
    "ReplayError",
    "ReplayReport",
    "ScanSteps",
    "StepsReplay",
    "compare_file",
    "failure_events",
    "load_recording",
    "recompute_scans",
    "recording_notes",
]

RECORDING = "recording.mcap"
REPLAY_DIR = "replay"
REPORT = "replay.json"
MAX_LISTED = 10
"""Differences listed per kind (the rest are counted)."""
EXIT_OK, EXIT_FAIL = 0, 1


class ReplayError(RuntimeError):
    """The run directory cannot be replayed at all (a file missing or unreadable)."""


@dataclass
class ReplayReport:
    """``identical``: the replayed result files equal the original byte for byte and the
    recomputed decisions, values and tracks equal the recorded ones.  ``differences``: what
    did not (human-readable, the first few of each kind).  ``notes``: facts about the recording
    that are not differences (skipped payloads, damage).  ``counts``: what was read."""

    identical: bool
    differences: list[str]
    out_dir: Path
    notes: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "identical": self.identical,
            "differences": self.differences,
            "notes": self.notes,
            "counts": self.counts,
        }


class Differences:
    """Differences grouped by kind, at most :data:`MAX_LISTED` listed per kind."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._per_kind: dict[str, int] = {}

    def add(self, kind: str, text: str) -> None:
        n = self._per_kind.get(kind, 0) + 1
        self._per_kind[kind] = n
        if n <= MAX_LISTED:
            self.lines.append(text)

    def finish(self) -> list[str]:
        out = list(self.lines)
        for kind, n in self._per_kind.items():
            if n > MAX_LISTED:
                out.append(f"... and {n - MAX_LISTED} more differences of kind {kind!r}")
        return out


@dataclass
class Recorded:
    """What a replay uses from the recording, keyed by ``(episode, scan[, sensor])``: the
    manager's Status (the first one received), its Tracks (in the order received), the
    sensors' messages (the first acceptable one per sensor and scan) and, when asked for, the
    manager's Commands (the first one)."""

    status: dict[tuple[int, int], msg.Status] = field(default_factory=dict)
    tracks: dict[tuple[int, int], list[msg.Track]] = field(default_factory=dict)
    meas: dict[tuple[int, int, str], Any] = field(default_factory=dict)  # or LocalTrack
    # the later acceptable ones of the same sensor and scan, in the order received (a kind
    # whose manager tests a message against its scan, e.g. a validation gate, picks among them)
    others: dict[tuple[int, int, str], list[Any]] = field(default_factory=dict)
    commands: dict[tuple[int, int], msg.Command] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    def candidates(self, episode: int, scan: int, sensor: str) -> list[Any]:
        """Every acceptable recorded message of ``sensor`` for ``(episode, scan)``, in the
        order received."""
        first = self.meas.get((episode, scan, sensor))
        return [] if first is None else [first, *self.others.get((episode, scan, sensor), ())]

    def last_scan(self, episode: int) -> int:
        """The last scan of ``episode`` with a recorded Status (0: none)."""
        return max((k for (e, k) in self.status if e == episode), default=0)


def load_recording(
    samples: Iterator[RecordedSample],
    run_id: str,
    *,
    message: type[msg.Measurement] | type[msg.LocalTrack] = msg.Measurement,
    label: str = "measurement",
    acceptable: Callable[[Any], bool] = lambda m: True,
    commands: bool = False,
) -> Recorded:
    """Decode what a replay uses from ``samples`` (strictly; a :class:`~covnet.wire.messages.
    WireError` is counted ``skipped:<reason>``).  The sensors' keys carry ``message`` s (counted
    as ``label``); one is kept when its key names its ``sensor_id`` and ``acceptable(m)`` (the
    manager's test of its content), else counted ``skipped:invalid_<label>``; a second one of
    the same sensor and scan is counted ``<label>_duplicate``.  ``commands``: keep the
    Commands too (strictly, with their key: :func:`~covnet.wire.messages.decode_command`)."""
    rec = Recorded()
    # each key's kind worked out once: a recording has few keys (the recorder bounds its
    # channels) and up to millions of messages (a 256-sensor run's replay spent a quarter of
    # its time classifying the same 260 keys again)
    kind_of: dict[str, str | None] = {}
    for s in samples:
        rec.count("samples")
        if s.key not in kind_of:
            kind_of[s.key] = key_kind(run_id, s.key)
        kind = kind_of[s.key]
        try:
            if kind == msg.Status.KIND:
                st = msg.decode_as(s.payload, msg.Status)
                rec.count("status")
                if rec.status.setdefault((st.episode, st.scan), st) is not st:
                    rec.count("status_duplicate")
            elif kind == msg.Track.KIND:
                tr = msg.decode_as(s.payload, msg.Track)
                rec.tracks.setdefault((tr.episode, tr.scan), []).append(tr)
            elif kind == msg.Measurement.KIND:
                m = msg.decode_as(s.payload, message)
                rec.count(label)
                try:
                    key_sensor = msg.parse_measurement_key(s.key)
                except ValueError:  # an id no sensor can have: the manager's ``bad_key``
                    rec.count("skipped:bad_key")
                    continue
                if m.sensor_id != key_sensor or not acceptable(m):
                    rec.count(f"skipped:invalid_{label}")
                elif rec.meas.setdefault((m.episode, m.scan, m.sensor_id), m) is not m:
                    rec.count(f"{label}_duplicate")
                    rec.others.setdefault((m.episode, m.scan, m.sensor_id), []).append(m)
            elif kind == msg.Command.KIND and commands:
                cmd = msg.decode_command(s.key, s.payload)
                rec.count("command")
                if rec.commands.setdefault((cmd.episode, cmd.scan), cmd) is not cmd:
                    rec.count("command_duplicate")
        except msg.WireError as exc:
            rec.count(f"skipped:{exc.reason}")
    return rec


def recording_notes(reader: RecordingReader, counts: dict[str, int]) -> list[str]:
    """What a read recording says of itself (no footer: its recorder was killed; corrupt chunks;
    messages of a lost channel; why reading stopped) and the payloads skipped."""
    notes: list[str] = []
    if reader.segments > 1:
        notes.append(
            f"recording in {reader.segments} segments (the recorder was restarted "
            f"{reader.segments - 1} time(s)); "
            + (
                f"{', '.join(reader.incomplete_segments)} end without a footer: what arrived "
                "until its restart is missing"
                if reader.incomplete_segments
                else "every earlier segment is complete"
            )
        )
    if not reader.complete and reader.error is None:  # stopped early: the error says where
        notes.append(
            "recording has no footer (the recorder did not close it: killed?); read up to "
            + ("its last complete record (the last one is cut)" if reader.truncated else "its end")
        )
    if reader.corrupt_chunks:
        notes.append(
            f"recording: {len(reader.corrupt_chunks)} corrupt chunk(s) skipped at "
            f"bytes {reader.corrupt_chunks[:5]}"
        )
    if reader.orphans:
        notes.append(f"recording: {reader.orphans} message(s) of an unknown channel skipped")
    if reader.error:
        notes.append(f"recording: {reader.error}; the replay used what came before it")
    lost = reader.metadata.get(META_UNRECORDED)
    if lost:
        notes.append(
            f"recording: {lost.get('no_channel', '?')} message(s) on new keys were not recorded "
            f"(no channel left; the first on {lost.get('first_key', '?')!r}): another session "
            "filled the recorder's channels, so messages of the run may be missing"
        )
    skipped = {k: v for k, v in counts.items() if k.startswith("skipped:")}
    if skipped:
        notes.append(f"payloads skipped (not used by the replay): {skipped}")
    if counts.get("status_duplicate"):
        notes.append(
            f"{counts['status_duplicate']} scan(s) have more than one Status recorded: the "
            "manager sends one, so the others are another session's (a forger's, when the "
            "run has no access control); the replay takes the first of each, and where a "
            "forged one came first the differences below are the forger's"
        )
    return notes


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ReplayError(f"cannot read {path}: {exc}") from None


class KindReplay:
    """A kind's replay: subclass it with the four kind-specific parts (module docstring); the
    public entry points are :meth:`rebuild`, :meth:`replay_run` and :meth:`command`."""

    kind: str
    """The kind's registry name (:data:`covnet.kinds.REGISTRY`)."""
    compared: tuple[str, ...] = (SUMMARY,)
    """The run's files that config and recording determine: compared byte for byte."""

    def check(self, cfg: Any, run_dir: Path) -> None:
        """Raise :class:`ReplayError` when runs of ``cfg`` cannot be replayed at all."""

    def load(self, cfg: Any, samples: Iterator[RecordedSample], run_id: str) -> Recorded:
        """What the replay uses from the recording (:func:`load_recording`)."""
        raise NotImplementedError

    def recompute(self, cfg: Any, episodes: list[str], rec: Recorded, diffs: Differences) -> Any:
        """The manager's result, recomputed with the manager's own code from ``rec``; what
        differs from what the manager recorded goes to ``diffs``."""
        raise NotImplementedError

    def write(self, out: Path, cfg: Any, result: Any, run_info: dict[str, Any]) -> object:
        """The manager's own run-directory writer."""
        raise NotImplementedError

    # ---- what every kind shares ---------------------------------------------------------

    def rebuild(
        self,
        cfg: Any,
        run_id: str,
        episodes: list[str],
        recording: Path,
        out: Path,
        run_info: dict[str, Any] | None = None,
        *,
        compare_with: Path | None = None,
    ) -> ReplayReport:
        """Rebuild run ``run_id`` of ``cfg`` (its ``episodes``) from ``recording`` (possibly
        cut: up to its last complete record; every episode up to its last scan with a recorded
        Status) into ``out``: the kind's whole network-run directory, ``run_info`` merged into
        its ``run.json``, and ``replay.json``.  ``compare_with``: a run directory whose
        :attr:`compared` files the rebuilt ones must equal byte for byte.  Raises
        :class:`ReplayError` when the run cannot be replayed at all."""
        recording, out = Path(recording), Path(out)
        self.check(cfg, recording.parent)
        diffs = Differences()
        meta_run = read_metadata(recording).get(META_RUN, {})
        whose = other_code(meta_run.get("code"))
        # a recording and a config.json (or run.json) of two runs are the user's input, as
        # for plot and export (exit 2), not a difference the replay found (it said DIFFERS)
        by = "" if whose is None else f"; or the run was recorded by {whose}"
        if meta_run.get("run_id", run_id) != run_id:
            raise ReplayError(
                f"{recording} is a recording of run {meta_run['run_id']!r}, its run.json names "
                f"run {run_id!r}: files of two runs (one copied from another run?){by}"
            )
        h, *older = kinds.config_hashes(cfg)
        if meta_run.get("config_hash", h) not in (h, *older):
            raise ReplayError(
                f"{recording} was recorded with config {meta_run['config_hash']}, its "
                f"config.json is config {h}: not this run's config (copied from another run or "
                f"edited?); put back the run's own config.json{by}"
            )
        reader = RecordingReader(recording)
        rec = self.load(cfg, reader.samples(), run_id)
        notes = recording_notes(reader, rec.counts)
        if whose is not None:  # the same recording re-fused by other code may differ by it
            notes.insert(
                0,
                f"the run was recorded by {whose}: a difference below may be the code's, not "
                "the recording's (replay a run with the covnet that recorded it)",
            )
        result = self.recompute(cfg, list(episodes), rec, diffs)
        info = dict(run_info or {})
        info.setdefault("episodes", list(episodes))
        info.setdefault("run_id", run_id)
        self.write(out, cfg, result, info)
        if compare_with is not None:
            for name in self.compared:
                compare_file(Path(compare_with) / name, out / name, diffs)
        differences = diffs.finish()
        report = ReplayReport(
            identical=not differences,
            differences=differences,
            out_dir=out,
            notes=notes,
            counts=dict(sorted(rec.counts.items())),
        )
        write_json(out / REPORT, report.as_dict())
        return report

    def replay_run(
        self, run_dir: Path, out: Path | None = None, *, compare: bool = True
    ) -> ReplayReport:
        """Replay ``run_dir`` from its recording into ``out`` (default ``run_dir/replay``) and
        compare (module docstring; ``compare=False``: rebuild only, for a run that never wrote
        its results).  Raises :class:`ReplayError` when a needed file is missing or
        unreadable."""
        run_dir = Path(run_dir)
        out_dir = Path(out) if out is not None else run_dir / REPLAY_DIR
        compared = self.compared if compare else ()
        for name in (CONFIG, RUN_INFO, *compared, RECORDING):
            if not (run_dir / name).is_file():
                raise ReplayError(f"{run_dir} has no {name}: not a recorded network run")
        kind = kinds.get(self.kind)
        cfg = kind.from_dict(_read_json(run_dir / CONFIG), str(run_dir / CONFIG), None)
        info = _read_json(run_dir / RUN_INFO)
        if not isinstance(info, dict):
            raise ReplayError(f"{run_dir / RUN_INFO}: not a JSON object (not a network run?)")
        episodes = info.get("episodes", kind.episodes(cfg))
        if not isinstance(episodes, list) or not all(isinstance(m, str) for m in episodes):
            raise ReplayError(f"{run_dir / RUN_INFO} has no 'episodes' list (not a network run?)")
        # the files compared and the recording are readable before anything is compared: an
        # unreadable one was a "difference" (exit 1), where the README says exit 2
        for name in compared:
            _read_json(run_dir / name)
        problem = mcap_start_problem(run_dir / RECORDING)
        if problem is not None:
            raise ReplayError(problem)
        meta_run = read_metadata(run_dir / RECORDING).get(META_RUN, {})
        run_id = info.get("run_id") or meta_run.get("run_id")
        if not isinstance(run_id, str):
            raise ReplayError(f"no run id in {run_dir / RUN_INFO} nor in the recording's metadata")
        run_info = {
            "mode": "replay",
            "episodes": episodes,
            "run_id": run_id,
            "replayed_from": str(run_dir),
        }
        return self.rebuild(
            cfg, run_id, episodes, run_dir / RECORDING, out_dir, run_info,
            compare_with=run_dir if compare else None,
        )  # fmt: skip

    def command(self, args: argparse.Namespace, cfg: Any) -> int:
        """``covnet replay RUN_DIR [--out DIR] [--force]``: :meth:`replay_run`, then one line
        (``identical``) or the differences, and the recording's notes (:func:`recording_notes`)
        on stderr; exit 0 when identical, else 1.  A run whose results were never written (a
        full disk as it ended, and the launcher's rebuild on the same disk) but whose config,
        ``run.json`` and recording are there is rebuilt without a comparison, and says so
        (exit 0): it was refused, and no command gave its results back."""
        run_dir = Path(args.run_dir)
        needed = (CONFIG, RUN_INFO, RECORDING)
        missing = [f for f in needed if not (run_dir / f).is_file()]
        if missing:
            raise UsageError(
                f"{run_dir}: not a recorded network run directory (missing {', '.join(missing)})"
            )
        absent = [f for f in self.compared if not (run_dir / f).is_file()]
        # default: the run's own replay directory, replaced
        own = args.out is None
        out = prepare_out(
            run_dir / REPLAY_DIR if own else args.out, "replay", own or args.force,
            "the replay directory" if own else "--out", reads=run_dir,
        )  # fmt: skip
        try:
            report = self.replay_run(run_dir, out, compare=not absent)
        except ReplayError as exc:  # a file of the run missing or unreadable: the user's input
            raise UsageError(str(exc)) from None
        files = " and ".join(self.compared)
        if absent:
            print(
                f"rebuilt {run_dir} from its recording into {report.out_dir}: it has no "
                f"{' or '.join(absent)} to compare with (its results were never written)"
            )
        elif report.identical:
            print(f"replayed {run_dir}: identical: {files} reproduced exactly ({report.out_dir})")
        else:
            print(f"replayed {run_dir}: {files} DIFFERS ({report.out_dir}):", file=sys.stderr)
            for d in report.differences[:20]:
                print(f"  {d}", file=sys.stderr)
        # what the recording says of itself (damage, a restarted recorder, skipped payloads):
        # a damaged file is told apart from a wrong replay
        for note in report.notes:
            print(f"  note: {note}", file=sys.stderr)
        return EXIT_OK if report.identical else EXIT_FAIL


class ScanSteps(Protocol):
    """A single-episode kind's manager steps without a bus (``covnet.<kind>.network``): what
    the manager process and :func:`recompute_scans` both step."""

    @property
    def result(self) -> Any:
        """The kind's result record: ``failures`` (a list), ``completed``, ``scans_done``."""
        ...

    def decide(self, failed: frozenset[str]) -> ScanDecision: ...

    def ahead(self) -> None: ...

    def usable(self, m: Any) -> bool | str:
        """True, or False / the reason the manager refused ``m`` for (module docstring)."""
        ...

    def fuse(self, k: int, got: dict[str, Any]) -> Any: ...

    def report(
        self, k: int, fused: Any, failed: frozenset[str], now_ns: Callable[[], int]
    ) -> tuple[list[msg.Track], msg.Status]: ...


def failure_events(
    previous: frozenset[str], failed: frozenset[str], k: int
) -> list[dict[str, Any]]:
    """The failure and rejoin events at scan ``k``, from the failed sets of two successive
    Status messages, as the manager derived them from its membership view (without their
    wall-clock detection times)."""
    return [
        {"sensor": sid, "scan": k, "event": "failed" if sid in failed else "rejoined"}
        for sid in sorted(failed ^ previous)
    ]


def recompute_scans(
    steps: ScanSteps, scans: int, rec: Recorded, diffs: Differences, where: str
) -> None:
    """Step ``steps`` through episode 0 as the manager did, scan ``k = 1, 2, ...`` while a
    Status of ``k`` was recorded::

        failed  = Status(k).failed                (failure events: its changes between scans)
        D       = steps.decide(failed)            == the recorded Command(k) (enabled, modes,
                                                      targets)
        got     = {s: first usable recorded Measurement(k) of s, s in Status(k).fused}
        T, S    = steps.report(k, steps.fuse(k, got), failed)
                  S == Status(k) (enabled, value, tr P),  T == the recorded Track(k)s (by
                  target id: x and P bit for bit)

    Each mismatch is a difference; ``steps.result.completed`` says whether all ``scans``
    were recomputed."""
    result = steps.result
    last = rec.last_scan(0)
    previous: frozenset[str] = frozenset()
    for k in range(1, scans + 1):
        st = rec.status.get((0, k))
        if st is None:
            if k <= last:
                diffs.add(
                    "status",
                    f"{where}: no Status of scan {k} recorded (scans up to {last} are); the "
                    f"replay of this episode stops at scan {k - 1}",
                )
            break
        failed = frozenset(st.failed)
        result.failures.extend(failure_events(previous, failed, k))
        previous = failed
        try:
            decision = steps.decide(failed)
        except ScanImpossible as exc:
            diffs.add(
                "allocation", f"{where} scan {k}: cannot decide ({exc}) but a Status is recorded"
            )
            break
        _check_command(f"{where} scan {k}", rec.commands.get((0, k)), decision, diffs)
        steps.ahead()
        got: dict[str, Any] = {}
        for sid in st.fused:
            m = rec.meas.get((0, k, sid))
            if m is None or steps.usable(m) is not True:  # a str is a reason for no
                diffs.add(
                    "measurement",
                    f"{where} scan {k}: the manager fused {sid} but no valid measurement of it "
                    "is recorded",
                )
                continue
            got[sid] = m
        tracks, status = steps.report(k, steps.fuse(k, got), failed, lambda: 0)
        _check_status(f"{where} scan {k}", st, status, diffs)
        _check_tracks(f"{where} scan {k}", rec.tracks.get((0, k), []), tracks, diffs)
    result.completed = result.scans_done == scans


def _check_command(
    where: str, recorded: msg.Command | None, decision: ScanDecision, diffs: Differences
) -> None:
    if recorded is None:
        diffs.add("command", f"{where}: no Command recorded")
        return
    for name in ("enabled", "modes", "targets"):
        a, b = getattr(decision, name), getattr(recorded, name)
        if a != b:
            diffs.add("command", f"{where}: replayed command {name} {a!r} != recorded {b!r}")


def _check_status(
    where: str, recorded: msg.Status, replayed: msg.Status, diffs: Differences
) -> None:
    if replayed.enabled != recorded.enabled:
        diffs.add(
            "allocation",
            f"{where}: replayed allocation {list(replayed.enabled)} != recorded "
            f"{list(recorded.enabled)}",
        )
    if replayed.value != recorded.value:
        diffs.add(
            "value",
            f"{where}: replayed objective {replayed.value!r} != recorded {recorded.value!r}",
        )
    if replayed.trace_P != recorded.trace_P:
        diffs.add(
            "trace_P",
            f"{where}: replayed tr P {replayed.trace_P!r} != recorded {recorded.trace_P!r}",
        )


def _check_tracks(
    where: str, recorded: list[msg.Track], replayed: list[msg.Track], diffs: Differences
) -> None:
    ids = [t.target_id for t in replayed]
    if ids != [t.target_id for t in recorded]:
        diffs.add(
            "track",
            f"{where}: replayed tracks {ids} != recorded {[t.target_id for t in recorded]}",
        )
    by_id = {t.target_id: t for t in recorded}
    for t in replayed:
        r = by_id.get(t.target_id)
        if r is not None and not (np.array_equal(r.x, t.x) and np.array_equal(r.P, t.P)):
            dx = float(np.max(np.abs(r.x - t.x))) if r.x.shape == t.x.shape else float("nan")
            diffs.add(
                "track",
                f"{where}: replayed estimate of {t.target_id} differs from the recorded Track "
                f"(max |dx| = {dx:.6g})",
            )


class StepsReplay(KindReplay):
    """The replay of a single-episode kind whose manager steps a :class:`ScanSteps`
    (:func:`recompute_scans`): the kind's name, its steps' class, its network-run writer, the
    manager's content test of a sensor's message (``acceptable``, applied when reading) and
    the result files to compare."""

    def __init__(
        self,
        kind: str,
        steps: Callable[[Any], ScanSteps],
        write: Callable[[Path, Any, Any, dict[str, Any]], object],
        *,
        acceptable: Callable[[Any], bool] = lambda m: True,
        compared: tuple[str, ...] = (SUMMARY,),
    ) -> None:
        self.kind, self.compared = kind, compared
        self._steps, self._write, self._acceptable = steps, write, acceptable

    def load(self, cfg: Any, samples: Iterator[RecordedSample], run_id: str) -> Recorded:
        return load_recording(samples, run_id, acceptable=self._acceptable, commands=True)

    def recompute(self, cfg: Any, episodes: list[str], rec: Recorded, diffs: Differences) -> Any:
        steps = self._steps(cfg)
        label = episodes[0] if episodes else kinds.get(self.kind).episodes(cfg)[0]
        recompute_scans(steps, int(cfg.scans), rec, diffs, f"episode 0 ({label})")
        return steps.result

    def write(self, out: Path, cfg: Any, result: Any, run_info: dict[str, Any]) -> object:
        return self._write(out, cfg, result, run_info)


def compare_file(original: Path, replayed: Path, diffs: Differences) -> None:
    """``replayed`` against ``original``, a JSON result file, byte for byte; differences of
    kind ``<file stem>`` (``summary`` for ``summary.json``), each differing JSON path listed."""
    name, what = original.name, Path(original.name).stem
    if not replayed.is_file():
        diffs.add(what, f"{name}: the replay wrote none (no scan recorded?)")
        return
    a, b = original.read_bytes(), replayed.read_bytes()
    if a == b:
        return
    try:
        ja, jb = json.loads(a), json.loads(b)
    except ValueError:
        diffs.add(what, f"{original} is not valid JSON")
        return
    paths: list[str] = []
    _json_diff(ja, jb, "", paths, limit=500)
    paths.sort(key=_depth)  # stable: the shallowest (most telling) differences first
    if not paths:  # same data, different bytes (formatting, key order)
        diffs.add(what, f"{name}: same content but different bytes (format/order)")
    for p in paths:
        diffs.add(what, f"{name} {p}")


def _json_diff(a: Any, b: Any, path: str, out: list[str], limit: int = 50) -> None:
    """Append ``path: original != replayed`` for the first ``limit`` differing leaves."""
    if len(out) >= limit:
        return
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            out.append(f"{path or '.'}: keys {list(a)} != {list(b)}")
        for k in a:
            if k in b:
                _json_diff(a[k], b[k], f"{path}.{k}" if path else k, out, limit)
        return
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: length {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            _json_diff(x, y, f"{path}[{i}]", out, limit)
        return
    if a != b or type(a) is not type(b):
        out.append(f"{path}: {_short(a)} (original) != {_short(b)} (replayed)")


def _depth(line: str) -> int:
    path = line.split(":", 1)[0]
    return path.count(".") + path.count("[")


def _short(v: Any) -> str:
    text = json.dumps(v)
    return text if len(text) <= 80 else text[:77] + "..."
