"""A run directory's truths and tracks, exported: plain CSV, or Stone Soup objects.

``covnet export RUN --format csv|stonesoup [--out PATH] [--episode NAME]``.

**Records.**  :func:`read_run` reads a run directory into :class:`Episode` s, one per episode
of the run (a covariance-control run: one per allocation metric, ``spectral``, ...; a mobile
run: one, named after its solver).  An episode holds the truth of every target and covnet's
track of it, each a :class:`StateSeries`: per scan its number, its time ``t`` (seconds), the
state ``[x, vx, y, vy]`` (m, m/s) and, for a track, the posterior covariance ``P`` (4 x 4) after
that scan's update.  Every target has exactly one track, with the target's id (covnet's
trackers are cued: no initiation, no deletion); a single-target (paper) run's target is
``T1``.  A surveillance run (targets that appear and leave, tracks started from detections) is
the exception: each target over the scans it exists and each *confirmed* track over the scans
it is confirmed, with the track's own id (``track-17``;
:func:`covnet.covariance_control.surveillance_results.surveillance_tracks`).  The truth of an
episode covers the scans its tracks cover (a network run stopped early: the scans it
completed).

Which scans: a covariance-control run's scans ``1..K`` at ``t = k T`` (``arrays.npz``'s ``t``);
a mobile run's rows ``0..K`` at ``t = k T`` (row 0 the start: the true initial state and the
initial estimate).  Each kind reads its own files (:meth:`covnet.kinds.Kind.tracks`); a passive
run (one association scene, no tracks over time) has nothing to export and is refused.

**CSV** (:func:`write_csv`): one header line, then one row per target, scan and series::

    kind,episode,id,scan,t,x,vx,y,vy,P00,P01,P02,P03,P10,...,P33

``kind`` is ``truth`` or ``track``; ``Pij`` is ``P[i, j]`` in the state order ``x, vx, y, vy``
(row-major, all 16, empty on a truth row).  Rows come episode by episode (the run's order),
truths then tracks, target by target, scan by scan.  Floats are written in Python's shortest
round-trip form, so reading them back gives the run's arrays bit for bit.

**Stone Soup** (optional extra: ``pip install 'covnet[stonesoup]'``; imported only by the
functions that need it): :func:`to_stonesoup` gives one episode as
``(set[GroundTruthPath], set[Track])``: a ``GroundTruthPath`` of ``GroundTruthState`` s per
target and a ``Track`` of ``GaussianState`` s (mean and covariance) per track, each with the
target's id as its ``id``, timestamps ``start + t`` (``start`` defaults to :data:`EPOCH`,
naive ``1970-01-01 00:00:00``; a scan time is kept to the microsecond, datetime's resolution).
The states are ``GaussianState`` s, not ``GaussianStateUpdate`` s: the export has no
measurements or hypotheses to attach.  Stone Soup's metric generators take them as they are:
position is ``Euclidean(mapping=(0, 2))`` of the state.

:func:`write_stonesoup` writes Stone Soup's own YAML serialisation
(``stonesoup.serialise.YAML``), which Stone Soup reads back into the same objects
(``YAML().load(text)``; means, covariances and timestamps round-trip exactly): a mapping
``episode name -> {"groundtruth_paths": set, "tracks": set}`` (the keys a Stone Soup
``MetricManager`` uses by default), every episode of the run or the one asked for.

**Agreement with covnet's own OSPA / GOSPA.**  Stone Soup's ``OSPAMetric`` and ``GOSPAMetric``
with covnet's ``c`` and ``p`` (the config's ``ospa``) and ``measure=Euclidean(mapping=(0, 2))``
give, on an export, covnet's per-scan ``ospa`` and ``gospa`` (``arrays.npz``, ``summary.json``)
to rounding (tests/integration/test_export_stonesoup.py).  One caveat: Stone Soup 1.9.1's OSPA
chooses its assignment by the cut distances, not their ``p``-th powers, so with ``p != 1``
and targets closer together than their errors its value can exceed OSPA's definition
(covnet's); GOSPA agrees always.
"""

from __future__ import annotations

import csv
import io
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from covnet import kinds
from covnet.config import read_yaml
from covnet.errors import UsageError
from covnet.runs.rundir import (
    ARRAYS,
    CONFIG,
    atomic_write,
    check_writable,
    config_mismatch,
    load_arrays,
)

if TYPE_CHECKING:  # the optional extra (no type information: Any to mypy)
    from stonesoup.types.groundtruth import GroundTruthPath
    from stonesoup.types.track import Track

__all__ = [
    "CSV_COLUMNS",
    "EPOCH",
    "FORMATS",
    "STATE",
    "Episode",
    "StateSeries",
    "StoneSoupMissing",
    "episode_of",
    "export",
    "read_arrays",
    "read_run",
    "require_arrays",
    "to_stonesoup",
    "write_csv",
    "write_stonesoup",
]

STATE = ("x", "vx", "y", "vy")
"""The state's components, in covnet's order (position is components 0 and 2)."""
CSV_COLUMNS = (
    "kind",
    "episode",
    "id",
    "scan",
    "t",
    *STATE,
    *(f"P{i}{j}" for i in range(4) for j in range(4)),
)
EPOCH = datetime(1970, 1, 1)
"""The datetime of ``t = 0`` in the Stone Soup export (naive, read as UTC)."""
FORMATS = ("csv", "stonesoup")
DEFAULT_NAMES = {"csv": "export.csv", "stonesoup": "export.stonesoup.yaml"}
"""The file :func:`export` writes in the run directory when no ``out`` is given."""
INSTALL = "pip install 'covnet[stonesoup]'"


class StoneSoupMissing(UsageError, ImportError):
    """Stone Soup is not installed (the optional extra): a user's fixable mistake (the CLI's
    exit 2) and an :class:`ImportError` to library callers."""


@dataclass(frozen=True, eq=False)
class StateSeries:
    """One target's truth or one track over the scans of an episode: ``scan`` ``(n,)``, ``t``
    ``(n,)`` seconds, ``x`` ``(n, 4)`` states ``[x, vx, y, vy]``, ``P`` ``(n, 4, 4)`` (a
    track's covariances; ``None`` for a truth)."""

    id: str
    scan: NDArray[np.int64]
    t: NDArray[np.float64]
    x: NDArray[np.float64]
    P: NDArray[np.float64] | None = None


@dataclass(frozen=True, eq=False)
class Episode:
    """One episode of a run: its truths and its tracks (one per target, same ids)."""

    name: str
    truths: tuple[StateSeries, ...]
    tracks: tuple[StateSeries, ...]


def read_arrays(run_dir: Path, *names: str) -> dict[str, np.ndarray]:
    """``run_dir``'s ``arrays.npz``; a missing or unreadable file, or a missing array among
    ``names``, is a :class:`UsageError` naming it (for the kinds' readers)."""
    path = Path(run_dir) / ARRAYS
    if not path.is_file():
        raise UsageError(
            f"{path}: missing (not the directory of one run of covnet run or covnet up; or a "
            "run still going, or one that ended before writing its results)"
        )
    try:
        arrays = load_arrays(path)
    except (OSError, ValueError) as exc:
        raise UsageError(f"{path}: not a readable .npz file ({exc})") from None
    require_arrays(arrays, run_dir, *names)
    return arrays


def require_arrays(arrays: Mapping[str, np.ndarray], run_dir: Path, *names: str) -> None:
    """A :class:`UsageError` naming the arrays among ``names`` that ``arrays`` (read from
    ``run_dir``'s ``arrays.npz``) lacks."""
    missing = [n for n in names if n not in arrays]
    if missing:
        raise UsageError(
            f"{Path(run_dir) / ARRAYS}: no array {', '.join(map(repr, missing))} in it"
        )


def read_run(run_dir: str | Path) -> list[Episode]:
    """Every episode of the run directory ``run_dir`` (module docstring), in the run's order.
    Not a run directory, a missing or stale file, a kind without tracks: :class:`UsageError`
    naming it."""
    d = Path(run_dir)
    if not d.is_dir():
        raise UsageError(f"{d}: not a directory (expected a run directory)")
    if not (d / CONFIG).is_file():
        raise UsageError(f"{d}: not a run directory (no {CONFIG}, which names its kind)")
    # a corrupt or invalid config.json is a ConfigError (exit 2), as for covnet plot
    kind, cfg = kinds.from_dict(read_yaml(d / CONFIG), str(d / CONFIG))
    stale = config_mismatch(d, kinds.config_hashes(cfg))
    if stale is not None:
        raise UsageError(stale)
    episodes: list[Episode] = kind.tracks(cfg, d)
    if not episodes:
        raise UsageError(f"{d}: the run has no episode with a scan done")
    return episodes


def episode_of(episodes: Sequence[Episode], name: str | None, where: object) -> Episode:
    """The episode called ``name`` (``None``: the run's first); an unknown name is a
    :class:`UsageError` listing the run's episodes."""
    if name is None:
        return episodes[0]
    for e in episodes:
        if e.name == name:
            return e
    raise UsageError(
        f"--episode {name}: not an episode of {where}; its episodes: "
        + ", ".join(e.name for e in episodes)
    )


def _select(episodes: list[Episode], name: str | None, where: object) -> list[Episode]:
    return episodes if name is None else [episode_of(episodes, name, where)]


def _rows(episodes: Iterable[Episode]) -> Iterable[list[str]]:
    blank = [""] * 16
    for e in episodes:
        for label, series in (("truth", e.truths), ("track", e.tracks)):
            for s in series:
                for i in range(s.scan.size):
                    cov = blank if s.P is None else [repr(float(v)) for v in s.P[i].ravel()]
                    yield [
                        label,
                        e.name,
                        s.id,
                        str(int(s.scan[i])),
                        repr(float(s.t[i])),
                        *(repr(float(v)) for v in s.x[i]),
                        *cov,
                    ]


def _an_export(path: Path) -> bool:
    """``path`` holds an earlier export (its first line is the CSV header, or a Stone Soup
    document's ``groundtruth_paths``): ``--force`` may replace it under its own name in the run
    directory (only the default names could be replaced there)."""
    try:
        with open(path, encoding="utf-8") as f:
            head = [f.readline().rstrip("\n") for _ in range(2)]
    except (OSError, UnicodeDecodeError):
        return False
    return head[0] == ",".join(CSV_COLUMNS) or head[1].strip() == "groundtruth_paths: !!set"


def write_csv(episodes: Iterable[Episode]) -> str:
    """The CSV text of ``episodes`` (module docstring)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    w.writerows(_rows(episodes))
    return buf.getvalue()


def _stonesoup_types() -> Any:
    """Stone Soup's state, track and serialisation modules (start-up: the optional extra,
    imported only here; without it a :class:`StoneSoupMissing` that says how to install it)."""
    try:
        from stonesoup import serialise
        from stonesoup.types import groundtruth, state, track
    except ImportError as exc:
        raise StoneSoupMissing(
            f"--format stonesoup: Stone Soup is not installed ({exc}); install the optional "
            f"extra: {INSTALL}"
        ) from None
    return groundtruth, state, track, serialise


def _stonesoup_episode(e: Episode, start: datetime) -> tuple[set[GroundTruthPath], set[Track]]:
    groundtruth, state, track, _ = _stonesoup_types()

    def stamp(t: float) -> datetime:
        return start + timedelta(seconds=float(t))

    truths = {
        groundtruth.GroundTruthPath(
            [
                groundtruth.GroundTruthState(s.x[i].reshape(4, 1), timestamp=stamp(s.t[i]))
                for i in range(s.scan.size)
            ],
            id=s.id,
        )
        for s in e.truths
    }
    tracks = set()
    for s in e.tracks:
        assert s.P is not None  # a track always has its covariances
        tracks.add(
            track.Track(
                [
                    state.GaussianState(s.x[i].reshape(4, 1), s.P[i], timestamp=stamp(s.t[i]))
                    for i in range(s.scan.size)
                ],
                id=s.id,
            )
        )
    return truths, tracks


def to_stonesoup(
    run_dir: str | Path, episode: str | None = None, *, start: datetime = EPOCH
) -> tuple[set[GroundTruthPath], set[Track]]:
    """One episode of ``run_dir`` (``None``: the run's first, e.g. its first metric) as Stone
    Soup's ``(set[GroundTruthPath], set[Track])`` (module docstring).  Needs the optional
    extra (:class:`StoneSoupMissing` otherwise)."""
    return _stonesoup_episode(episode_of(read_run(run_dir), episode, run_dir), start)


class _WrittenSorted(set[Any]):
    """A set whose items iterate, and so are written, in a fixed order: by ``id``, then first
    timestamp (:func:`_set_order`).  Stone Soup's objects hash by identity (their memory
    address), so a plain set's order, and with it the file, changed from one export of a run
    to the next."""

    def __iter__(self) -> Iterator[Any]:
        return iter(sorted(super().__iter__(), key=_set_order))


def _set_order(item: Any) -> tuple[str, datetime]:
    states = getattr(item, "states", None)
    return str(item.id), (states[0].timestamp if states else EPOCH)


def write_stonesoup(episodes: Iterable[Episode], start: datetime = EPOCH) -> str:
    """Stone Soup's YAML of ``episodes`` (module docstring); the same text for the same
    episodes, each set's items by id (:class:`_WrittenSorted`)."""
    serialise = _stonesoup_types()[3]
    doc = {}
    for e in episodes:
        truths, tracks = _stonesoup_episode(e, start)
        doc[e.name] = {
            "groundtruth_paths": _WrittenSorted(truths),
            "tracks": _WrittenSorted(tracks),
        }
    yaml = serialise.YAML()
    # written as the plain set it is (a !!set, read back as one), in its own order
    yaml.representer.add_representer(_WrittenSorted, type(yaml.representer).yaml_representers[set])
    text: str = yaml.dumps(doc)
    return text


def export(
    run_dir: str | Path,
    fmt: str,
    out: str | Path | None = None,
    episode: str | None = None,
    force: bool = False,
) -> Path | None:
    """``covnet export``: ``run_dir``'s episodes (or the one called ``episode``) in format
    ``fmt`` (:data:`FORMATS`) written to ``out`` (default: :data:`DEFAULT_NAMES` in the run
    directory, replaced; ``"-"``: standard output).  Returns the file written (``None`` for
    stdout).  An existing ``out`` is replaced only with ``force``, and never when it is one of
    the run's own files (``--out RUN/summary.json`` wrote CSV over the run's summary).  A
    folder it cannot write in (a read-only file system) is a :class:`UsageError` naming
    ``--out`` (or the run directory, the default's folder) before the export is made."""
    if fmt not in FORMATS:
        raise UsageError(f"--format {fmt}: choose from {', '.join(FORMATS)}")
    chosen = _select(read_run(run_dir), episode, run_dir)  # what is wrong with the run first
    to_stdout = out is not None and str(out) == "-"
    path = None if to_stdout else _out_path(run_dir, fmt, out, force)
    text = write_csv(chosen) if fmt == "csv" else write_stonesoup(chosen)
    if path is None:
        sys.stdout.write(text)
        return None
    atomic_write(path, text.encode())
    return path


def _out_path(run_dir: str | Path, fmt: str, out: str | Path | None, force: bool) -> Path:
    """The file :func:`export` writes, checked: a folder that exists and can be written in
    (:func:`~covnet.runs.rundir.check_writable`), not a directory, not one of the run's own
    files, and an existing file only with ``force``."""
    path = Path(run_dir) / DEFAULT_NAMES[fmt] if out is None else Path(out)
    if path.is_dir():
        raise UsageError(f"--out {out}: is a directory (expected a file name)")
    if not path.parent.is_dir():
        raise UsageError(f"--out {out}: its folder {path.parent} does not exist")
    if path.is_symlink() or (path.exists() and not path.is_file()):
        # a device, a FIFO or a link was replaced by a regular file with --force (as root,
        # --out /dev/stdout --force would have replaced the machine's /dev/stdout)
        raise UsageError(
            f"--out {out if out is not None else path}: not a regular file (a link, a device or "
            "a pipe), which an export never replaces; give a file name, or --out - for stdout"
        )
    if out is not None and path.exists():
        own = path.resolve().parent == Path(run_dir).resolve()
        if own and path.name not in DEFAULT_NAMES.values() and not _an_export(path):
            raise UsageError(f"--out {out}: is one of the run's own files; choose another name")
        if not force:
            raise UsageError(f"--out {out}: exists; choose another name or pass --force")
    what = (
        f"--out {out}" if out is not None
        else f"{run_dir} (the export's default folder: give --out, or --out - for stdout)"
    )  # fmt: skip
    check_writable(path.parent, what)
    return path
