"""Run directories: where a command writes, and how, for every scenario kind.

- :func:`prepare_out`: the ``--out`` rule every command follows (a new folder under ``runs/``
  when none is given; an existing non-empty directory only with ``--force``), and the claim
  on the directory (:func:`claim`) that refuses a second command writing into it at once;
- :func:`write_json`, :func:`write_npz`: written to a temporary name of their own and
  renamed, so a reader never sees half a file and two writers never share one;
- :func:`read_json`, :func:`load_arrays`: the matching readers.

The file names every kind shares are constants here: ``config.json`` (the normalised config the
run used), ``run.json`` (wall-clock facts: creation time, version, timings, process layout:
what a replay cannot and need not reproduce), ``summary.json`` and ``arrays.npz`` (what the
config and seed determine).  ``run.json`` also keeps the SHA-256 of the ``arrays.npz`` the run
wrote (:data:`FILE_DIGESTS`), and :func:`load_arrays` refuses another file in its place: the
config's hash in ``summary.json`` ties the summary to ``config.json``, the digest ties the
arrays to the run.

How a run or batch ended is in ``run.json`` (:func:`record_end`), for every command and kind:
``status`` (:data:`STATUSES`: ``completed``, ``interrupted`` by Ctrl-C or SIGTERM, ``failed``),
``ended`` (why, in words) and the command's counts (``scans_completed`` per episode for a run,
``runs_completed`` / ``runs_total`` for a batch).  A command stopped by an ``OSError`` (a full
disk) is recorded ``failed`` by :func:`claims` (:func:`record_failure`); the writers here name
the file that could not be written.  A directory without a ``status`` is still
being written (or was written by an older covnet).
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import hashlib
import json
import math
import os
import shutil
import sys
import threading
import time
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from covnet import __version__, blas_kernel
from covnet.code_identity import code_identity
from covnet.errors import UsageError
from covnet.processes import interrupts

__all__ = [
    "ARRAYS",
    "CONFIG",
    "FILE_DIGESTS",
    "LIVE",
    "RUN_INFO",
    "run_info",
    "STATUSES",
    "SUMMARY",
    "after_the_results",
    "atomic_write",
    "check_writable",
    "claim",
    "claims",
    "config_mismatch",
    "file_sha256",
    "load_arrays",
    "name_file",
    "new_run_dir",
    "os_error_text",
    "prepare_out",
    "read_json",
    "reading",
    "record_end",
    "record_failure",
    "save_figure",
    "try_record_end",
    "utc_now",
    "write_json",
    "write_npz",
    "writing",
]

SUMMARY = "summary.json"
ARRAYS = "arrays.npz"
CONFIG = "config.json"
RUN_INFO = "run.json"
LIVE = "live.json"
"""A network run's live snapshot (the manager's last STATUS), while it runs; the results
(``summary.json``, ``arrays.npz``, ...) are written once, when the run ends."""
STATUSES = ("completed", "interrupted", "failed")


def new_run_dir(name: str, base: Path = Path("runs")) -> Path:
    """``runs/<name>-<YYYYmmdd-HHMMSS>`` (``-2``, ``-3``, ... when taken)."""
    first = base / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"
    out, i = first, 1
    while out.exists():
        i += 1
        out = first.with_name(f"{first.name}-{i}")
    return out


OUTPUT_MARKERS = (
    CONFIG,
    RUN_INFO,
    LIVE,
    SUMMARY,
    "processes.json",
    "recording.mcap",
    "association.json",
    "montecarlo.json",
    "results.json",
    "compare.json",
    "sweep.json",
    "replay.json",
    "batch.json",  # a batch (sweep, compare, mc) begun: its trials, even if it never finished
)
"""Files one of covnet's commands writes: a directory holding one is covnet's output, which
``--force`` may clear."""


def prepare_out(
    out: str | Path | None,
    name: str,
    force: bool,
    option: str = "--out",
    *,
    reads: Path | None = None,
) -> Path:
    """The directory a command writes to: ``out``, or :func:`new_run_dir` of ``name`` when
    ``None``, made and claimed (:func:`claim`) for this command: another covnet command
    writing there now is a :class:`~covnet.errors.UsageError`, with or without ``force``.  An
    existing file, or a non-empty directory without ``force``, is a
    :class:`~covnet.errors.UsageError` naming ``--out``.  With ``force`` a non-empty directory
    is emptied first (so nothing of an earlier run stays beside the new one), but only when it
    is an earlier output of covnet (:data:`OUTPUT_MARKERS`) and neither the working directory
    nor one of its parents: ``--force`` never deletes anything else.  ``reads``: the
    directory the command reads; ``out`` may not be it or hold it (``covnet replay RUN --out
    RUN --force`` emptied the run it was asked to read, recording and all)."""
    if out is not None and not str(out).strip():
        raise UsageError(f"{option}: empty; give a directory (or leave {option} out)")
    if out is None:
        return _new_claimed_dir(name, option)
    p = Path(out)
    if reads is not None:
        src, target = reads.resolve(), p.resolve()
        if target == src or target in src.parents:
            raise UsageError(
                f"{option} {out}: it is (or holds) {reads}, the directory this command reads: "
                "choose another"
            )
    if p.exists() and not p.is_dir():
        raise UsageError(f"{option} {out}: exists and is not a directory")
    # claimed before it is looked into: the check that it is empty (or the emptying) holds
    # until this command ends
    new = claim(p, f"{option} {out}")
    try:
        if any(p.iterdir()):
            if not force:
                raise UsageError(
                    f"{option} {out}: directory is not empty; choose another or pass --force "
                    "to replace its contents"
                )
            clear_output(p, option)
        check_writable(p, f"{option} {out}")
    except BaseException:
        if new:
            _release(p.resolve())
        raise
    return p


def _new_claimed_dir(name: str, option: str) -> Path:
    """A new :func:`new_run_dir` of ``name``, made (by this process alone: two commands
    started in the same second take ``-2`` and the first) and claimed."""
    for _ in range(1000):
        made = new_run_dir(name)
        what = f"{made} (the default output directory; give {option})"
        try:
            made.mkdir(parents=True)
        except FileExistsError:
            continue
        except OSError as exc:
            raise UsageError(f"{what}: cannot write there ({exc.strerror or exc})") from None
        claim(made, what, made=True)
        try:
            check_writable(made, what)
        except BaseException:
            _release(made.resolve())
            raise
        return made
    raise UsageError(f"{option}: no free name for {name} under runs/; give {option}")


@dataclass
class _Claim:
    path: Path
    fd: int  # open on the directory, flock'ed: the lock lives as long as this descriptor
    made: bool  # made by this claim: removed again at the release when still empty
    pid: int
    owner: object  # the command that holds it (:func:`_owner`)


_CLAIMS: dict[Path, _Claim] = {}
"""The directories this process holds (:func:`claim`), by resolved path."""
_CLAIMS_LOCK = threading.RLock()
_SCOPE: ContextVar[list[Path] | None] = ContextVar("covnet_claims", default=None)
#: the outermost :func:`claims` block running in this context: the command a claim is for
_OWNER: ContextVar[object | None] = ContextVar("covnet_claims_owner", default=None)


def _owner() -> object:
    """Who claims now: the outermost :func:`claims` block of this context (a command; the
    blocks within it are the same command), else this thread."""
    owner = _OWNER.get()
    return owner if owner is not None else threading.current_thread()


def _held_by_another(have: _Claim) -> bool:
    """Whether ``have`` (a claim of this process) is another command's, still running: another
    :func:`claims` block (a block's claims go when it ends), or another thread that is alive."""
    if have.owner is _owner() or have.owner is threading.current_thread():
        return False  # (this thread's claim outside any block: held for it until the exit)
    return not isinstance(have.owner, threading.Thread) or have.owner.is_alive()


_BUSY = (
    "{what}: another covnet command is writing there now (it holds the directory until it "
    "ends; --force does not take it over); wait for it to end, or choose another directory"
)


def claim(p: Path, what: str, *, made: bool = False) -> bool:
    """Claim the directory ``p`` (made when missing) for this command: an exclusive
    ``flock`` on the directory itself (no file of its own appears in it), held until the
    :func:`claims` block that took it ends (every CLI command is one), else until this process
    exits.  Another command holding it (a covnet command writing there now: another process,
    or another :func:`claims` block or thread of this one, such as two ``api.run`` calls in
    threads) is a :class:`~covnet.errors.UsageError` naming ``what`` (``--out DIR``);
    ``--force`` does not change that.  The same command claiming it again is no error (a
    command may prepare its directory twice).  A forked child keeps no claim
    (:func:`_forget_claims`).  On a file system without ``flock`` (some network mounts) the
    directory is used unclaimed.
    True: claimed now, False: held already or not lockable."""
    made = made or not p.exists()
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{what}: cannot write there ({exc.strerror or exc})") from None
    key = p.resolve()
    with _CLAIMS_LOCK:
        have = _CLAIMS.get(key)
        if have is not None:
            if have.pid == os.getpid() and _same_dir(have.fd, p):
                if _held_by_another(have):
                    raise UsageError(_BUSY.format(what=what))
                return False
            _release(key)  # the directory it held was removed (and made again)
        for _ in range(10):
            try:
                fd = os.open(p, os.O_RDONLY | os.O_DIRECTORY)
            except FileNotFoundError:  # removed by an empty command's release: make it again
                p.mkdir(parents=True, exist_ok=True)
                made = True
                continue
            except OSError as exc:
                raise UsageError(f"{what}: cannot open it ({exc.strerror or exc})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                    raise UsageError(_BUSY.format(what=what)) from None
                return False  # no flock here: unclaimed, as before
            if not _same_dir(fd, p):  # removed (and made again) before the lock: once more
                os.close(fd)
                continue
            _CLAIMS[key] = _Claim(p, fd, made, os.getpid(), _owner())
            scope = _SCOPE.get()
            if scope is not None:
                scope.append(key)
            return True
    raise UsageError(f"{what}: the directory keeps disappearing (removed by another process?)")


def _same_dir(fd: int, p: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(p)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _release(key: Path) -> None:
    """Give up the claim on ``key`` (removing the directory when the claim made it and it is
    still empty: a command refused, or failed before it wrote, leaves no empty directory)."""
    with _CLAIMS_LOCK:
        c = _CLAIMS.pop(key, None)
        if c is None:
            return
        if c.pid == os.getpid() and c.made and _same_dir(c.fd, c.path):
            with contextlib.suppress(OSError):
                c.path.rmdir()  # only when empty
        with contextlib.suppress(OSError):
            os.close(c.fd)


@contextmanager
def claims() -> Iterator[None]:
    """Within this block, the directories :func:`claim` (:func:`prepare_out`) takes are this
    block's: released when it ends (the CLI wraps every command in one, the API its
    functions).  Claimed outside any block, a directory is held until the process exits.

    The block ending in an ``OSError`` (a full disk: a file that could not be written) marks
    each of its directories that holds something ``status: failed`` in ``run.json``
    (:func:`record_failure`) before it is released."""
    mine: list[Path] = []
    token = _SCOPE.set(mine)
    owned = _OWNER.set(_OWNER.get() or object())  # (a block within one: the same command)
    try:
        yield
    except OSError as exc:
        if not isinstance(exc, BrokenPipeError):  # a reader gone: the command's own ending
            for key in mine:
                record_failure(_CLAIMS[key].path if key in _CLAIMS else key, exc)
        raise
    finally:
        _SCOPE.reset(token)
        _OWNER.reset(owned)
        for key in reversed(mine):
            _release(key)


def os_error_text(exc: OSError) -> str:
    """``FILE: why`` of an ``OSError`` (``why`` alone when it names no file)."""
    where = f"{exc.filename}: " if exc.filename else ""
    return f"{where}{exc.strerror or exc}"


def record_failure(out: Path, exc: OSError) -> None:
    """Best effort: ``out/run.json`` says ``status: failed`` because of ``exc`` (what could
    not be written, and why), when ``out`` holds anything (a command that failed before it
    wrote leaves its directory empty).  When ``run.json`` cannot be written either (the disk
    is still full), a note on ``exc`` says so (the CLI prints it after the error).  A
    ``failed`` already recorded (by ``covnet up``'s launcher) keeps its reason, this one
    after it."""
    why = f"stopped by an error: {os_error_text(exc)}"
    info: Any = None
    try:
        if not out.is_dir() or not any(out.iterdir()):
            return
        info = json.loads((out / RUN_INFO).read_text())
    except (OSError, ValueError):
        pass
    failed = isinstance(info, dict) and info.get("status") == "failed"
    if failed and info.get("ended"):
        why = f"{info['ended']}; then {why}"
    unwritten = try_record_end(out, "failed", why)
    if unwritten:
        said = "says failed, but not this error" if failed else "does not say the command failed"
        exc.add_note(f"{out / RUN_INFO} {said} (not written: {unwritten})")


def try_record_end(out: Path, status: str, ended: str, **facts: Any) -> str:
    """:func:`record_end`, best effort: ``""``, or why ``run.json`` could not be written (a
    full disk), for the caller's message about a run that is ending badly anyway."""
    try:
        record_end(out, status, ended, **facts)
    except OSError as exc:
        return str(exc.strerror or exc)
    return ""


def _release_all() -> None:
    for key in list(_CLAIMS):
        _release(key)


def _forget_claims() -> None:
    """In a forked child: the parent's claims are the parent's (the lock stays with it while
    it lives); the child closes its copies, so none outlives the command that made it."""
    global _CLAIMS_LOCK
    _CLAIMS_LOCK = threading.RLock()
    for c in _CLAIMS.values():
        with contextlib.suppress(OSError):
            os.close(c.fd)
    _CLAIMS.clear()


atexit.register(_release_all)
os.register_at_fork(after_in_child=_forget_claims)


def check_writable(p: Path, what: str) -> None:
    """Write (then remove) a file in ``p``, made for the check and removed again when it did
    not exist (a command refused later leaves no empty directory): a read-only file system,
    ``/proc`` or a directory without write permission is a :class:`~covnet.errors.UsageError`
    naming ``what`` now, not an ``OSError`` on a temporary file once the whole run is done.
    (A real write, not ``os.access``: root passes every permission check, not a read-only
    mount.)"""
    made = not p.exists()
    try:
        p.mkdir(parents=True, exist_ok=True)
        probe = p / f".covnet-write-check-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        if made:
            p.rmdir()
    except OSError as exc:
        raise UsageError(f"{what}: cannot write there ({exc.strerror or exc})") from None


_READS: ContextVar[tuple[Path, ...]] = ContextVar("covnet_reads", default=())
"""The files the running command reads (:func:`reading`): :func:`clear_output` never deletes
them."""


@contextmanager
def reading(*paths: str | Path) -> Iterator[None]:
    """Within this block, ``paths`` are files the command reads (its config): ``--force`` never
    empties a directory holding one (``covnet run OUT/my.yaml --out OUT --force`` deleted the
    user's ``my.yaml``).  Set by the CLI around every command."""
    token = _READS.set(_READS.get() + tuple(Path(p).resolve() for p in paths))
    try:
        yield
    finally:
        _READS.reset(token)


def clear_output(p: Path, option: str = "--out") -> None:
    """Delete everything in ``p``, an earlier covnet output directory (see :func:`prepare_out`),
    unless it holds a file the command reads (:func:`reading`)."""
    here = Path.cwd().resolve()
    target = p.resolve()
    if target == here or target in here.parents or target == Path.home().resolve():
        raise UsageError(
            f"{option} {p} --force: refusing to empty {target}: it holds the working "
            "directory (or is the home directory)"
        )
    for src in _READS.get():
        if target == src or target in src.parents:
            raise UsageError(
                f"{option} {p} --force: refusing to empty {p}: it holds {src}, which this "
                "command reads; choose another directory, or move the file out of it first"
            )
    if not any((p / m).exists() for m in OUTPUT_MARKERS):
        raise UsageError(
            f"{option} {p} --force: refusing to empty {p}: it is not an output of covnet "
            f"(none of {', '.join(OUTPUT_MARKERS[:4])}, ... in it); choose an empty or new "
            "directory"
        )
    for child in p.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()


def _new_file_beside(path: Path) -> tuple[int, Path]:
    """A new file of its own beside ``path`` (``NAME.<random>.tmp``), open for writing, with a
    new file's mode: created with ``0o666``, which the kernel narrows by the process's umask as
    it is at that moment (as any ``open()`` of a new file; a default ACL of the directory
    too).  ``tempfile.mkstemp`` makes ``0o600`` files, which were then given a mode computed
    from the umask cached once per process: a notebook that tightened its umask after a first
    run still wrote ``0o644`` results.  No umask is read or set here (setting it to read it
    would change it for the other threads a moment)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC
    for _ in range(100):
        tmp = path.parent / f"{path.name}.{os.urandom(6).hex()}.tmp"
        try:
            return os.open(tmp, flags, 0o666), tmp
        except FileExistsError:
            continue  # another writer's name (2**48 of them): draw again
    raise FileExistsError(errno.EEXIST, "no free temporary file name beside it", str(path))


@contextmanager
def writing(path: str | Path) -> Iterator[None]:
    """Within this block ``path`` is being written: an ``OSError`` that names no file (a
    failed ``write()``: a full disk, a quota, an I/O error) is raised again naming ``path``,
    so the message says which file (``covnet: error: No space left on device`` named none).
    A ``ConnectionError`` (a network's, a pipe's) is left as it is."""
    try:
        yield
    except OSError as exc:
        name_file(exc, path)
        raise


def name_file(exc: OSError, path: str | Path) -> None:
    """``exc`` names ``path`` when it names no file (a failed ``write()``); a
    ``ConnectionError`` (a network's, a pipe's) is left as it is."""
    if exc.filename is None and not isinstance(exc, ConnectionError):
        exc.filename = str(path)


def save_figure(fig: Any, path: Path, **kwargs: Any) -> None:
    """``fig.savefig(path, **kwargs)`` (matplotlib; the image library removes a file it could
    not finish), an ``OSError`` naming ``path`` (:func:`writing`)."""
    with writing(path):
        fig.savefig(path, **kwargs)


@contextmanager
def _temporary_beside(path: Path) -> Iterator[tuple[Any, Path]]:
    """A new file of its own (``NAME.<random>.tmp``) in ``path``'s directory, open for
    writing, with a new file's mode; moved onto ``path`` when the block ends, removed when it
    fails: two writers of one file never share a temporary one (a fixed ``NAME.tmp`` mixed
    two runs' arrays into one corrupt file).  An ``OSError`` (a full disk, a read-only file
    system) names ``path``, the file that could not be written, not the temporary one."""
    tmp: Path | None = None
    try:
        fd, tmp = _new_file_beside(path)
        with os.fdopen(fd, "wb") as fh:
            yield fh, tmp
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, ConnectionError):
            exc.filename, exc.filename2 = str(path), None
        raise


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file of its own in the same directory
    (:func:`_temporary_beside`)."""
    with _temporary_beside(path) as (fh, _):
        fh.write(data)


def _nulls(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _nulls(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_nulls(v) for v in obj]
    return obj


def json_line(obj: Any) -> str:
    """``obj`` as one line of strict JSON: a non-finite float (a NaN where no value exists, an
    infinite cap) as ``null`` (``json.dumps`` wrote ``NaN``/``Infinity``, which JavaScript's,
    Go's and Rust's parsers reject)."""
    return json.dumps(_nulls(obj), allow_nan=False)


def write_json(path: Path, obj: Any) -> None:
    """``obj`` as indented JSON (plus a newline), atomically."""
    atomic_write(path, (json.dumps(obj, indent=2) + "\n").encode())


def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> str:
    """A compressed ``.npz`` of ``arrays``, atomically; returns the SHA-256 of the file written
    (``run.json`` keeps it under :data:`FILE_DIGESTS`, so :func:`load_arrays` knows the run's own
    file from another run's)."""
    with _temporary_beside(path) as (fh, tmp):
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
        fh.flush()
        digest = file_sha256(tmp)
    return digest


def file_sha256(path: Path) -> str:
    """The SHA-256 of ``path``'s bytes, in hex."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


#: ``run.json``'s map of a run's arrays file name to the SHA-256 of the file the run wrote
#: (``{"arrays.npz": "..."}``): an ``arrays.npz`` copied from another run, or edited, differs
FILE_DIGESTS = "file_sha256"


def _digest_mismatch(path: Path) -> str | None:
    """Why ``path`` is not the file its run directory's ``run.json`` says the run wrote (None:
    it is, or ``run.json`` keeps no digest of it: runs before the digests, batch files).  A
    ``run.json`` that is there but cannot be read (cut short, not JSON) is named: its digest
    cannot be checked, and the check was skipped silently."""
    info_path = path.parent / RUN_INFO
    try:
        info = read_json(info_path)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        return (
            f"{info_path} cannot be read ({exc}), so {path.name} cannot be checked against the "
            "digest it keeps: put back the run's own run.json, or run it again"
        )
    want = info.get(FILE_DIGESTS, {}) if isinstance(info, dict) else {}
    want = want.get(path.name) if isinstance(want, dict) else None
    if not isinstance(want, str):
        return None
    got = file_sha256(path)
    if got == want:
        return None
    return (
        f"{path}: not the file this run wrote (SHA-256 {got[:12]}..., {RUN_INFO}'s "
        f"{FILE_DIGESTS} says {want[:12]}...): copied from another run or edited? Put back the "
        "run's own file, or run it again"
    )


def read_json(path: Path) -> Any:
    """The JSON in ``path``; a ``ValueError`` when it is not a regular file (a FIFO or a device
    was read until the machine's memory ran out, or forever) or not JSON."""
    p = Path(path)
    if p.exists() and not p.is_file():
        raise ValueError(f"{p} is not a regular file")
    return json.loads(p.read_text())


#: the result files that carry the hash of the config they were computed from (a run's
#: summary, a passive run's association, a Monte Carlo batch's table), the first one present
#: is what :func:`config_mismatch` compares with
HASHED_RESULTS = (SUMMARY, "association.json", "montecarlo.json", "results.json")


def config_mismatch(run_dir: Path, config_hashes: Sequence[str]) -> str | None:
    """Why ``run_dir``'s ``config.json`` (whose hashes are ``config_hashes``:
    :func:`covnet.kinds.config_hashes`, today's first) is not the config its results were
    computed from (None: it is, or no result file says): ``config.json`` edited after the run,
    as ``covnet replay`` finds against the recording."""
    if isinstance(config_hashes, str):  # one hash, not its characters
        config_hashes = (config_hashes,)
    config_hash = config_hashes[0]
    for name in HASHED_RESULTS:
        path = run_dir / name
        if not path.is_file():
            continue
        try:
            stored = read_json(path).get("config_hash")
        except (ValueError, AttributeError):
            return f"{path}: not a readable result file (not a JSON object)"
        if stored is not None and stored not in config_hashes:
            return (
                f"{run_dir / CONFIG}: not the config of this run's results (config hash "
                f"{config_hash}, {name}: {stored}); was it edited after the run? Put back the "
                "config the run used"
            )
        return None
    return None


def load_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, read into memory (the file is closed on return).  A
    file that is not a whole ``.npz`` (cut short, emptied, overwritten) is a
    :class:`~covnet.errors.UsageError` naming it: the user named its run directory.  So is a
    whole ``.npz`` other than the one its run wrote (the digest in the run's ``run.json``,
    :data:`FILE_DIGESTS`): another run's arrays would draw and export that run's numbers under
    this one's config and summary."""
    try:  # opened here: numpy leaves its own handle open when the archive is damaged
        with open(path, "rb") as fh, np.load(fh) as data:
            arrays = {k: data[k] for k in data.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, KeyError) as exc:
        # numpy takes a file that is no archive for a pickle, and advises loading it unsafely
        why = "not an .npz archive" if "pickle" in str(exc) else str(exc) or type(exc).__name__
        raise UsageError(f"{path}: not a readable arrays file ({why})") from None
    why_not = _digest_mismatch(Path(path))
    if why_not:
        raise UsageError(why_not)
    return arrays


def record_end(out: Path, status: str, ended: str, **facts: Any) -> None:
    """Merge how the run ended into ``out/run.json`` (created if missing): ``status`` (one of
    :data:`STATUSES`), ``ended`` (why) and ``facts``; atomically, and whole: a Ctrl-C or
    SIGTERM during the write is answered once it is done (:func:`covnet.processes.interrupts.
    held`)."""
    if status not in STATUSES:
        raise ValueError(f"status: one of {STATUSES}, got {status!r}")
    with interrupts.held():  # once begun, the status is written (then the Ctrl-C is answered)
        _record_end(Path(out), status, ended, facts)


def _record_end(out: Path, status: str, ended: str, facts: dict[str, Any]) -> None:
    path = out / RUN_INFO
    info: dict[str, Any] = {}
    if path.is_file():
        try:
            info = json.loads(path.read_text())
        except ValueError:
            info = {}
    if not info:
        info = {"created_utc": utc_now(), "covnet_version": __version__}
    # the OpenBLAS kernels of the process that ends the run (covnet.blas_kernel: the same
    # config and seed give the same bits where this is the same), and the code that ran it
    info.setdefault("blas_kernel", blas_kernel.kernel())
    info.setdefault("code", code_identity())
    info.update({"status": status, "ended": ended, **facts})
    out.mkdir(parents=True, exist_ok=True)
    write_json(path, info)


def run_info(out: Path) -> dict[str, Any]:
    """``out/run.json`` as a dict, ``{}`` when it is missing, unreadable or not an object."""
    try:
        info = json.loads((out / RUN_INFO).read_text())
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


@contextmanager
def after_the_results(out: Path, step: str) -> Iterator[None]:
    """Around what a command does once its results are written and ``out/run.json`` says how
    it ended: ``step``, ``"figures"`` (drawing them, then the printout) or ``"printing"``.  An
    interruption there (Ctrl-C, SIGTERM, or an extension's error in its place) keeps
    ``run.json``'s ``status``, adds ``(<step> interrupted)`` to its ``ended``, says on stderr
    that ``out`` holds the results and ``covnet plot`` draws the figures, and goes on (exit
    130).  It ended with "interrupted" only, the figures missing and ``run.json`` saying it all
    went well (``covnet up``, the batch commands)."""
    try:
        yield
    except BaseException as exc:
        if not interrupts.caused(exc):
            raise
        info = run_info(Path(out))
        status = info.get("status")
        if status in STATUSES:
            ended = info.get("ended") or status
            record_end(out, status, f"{ended} ({step} interrupted)")
            what = "the complete results" if status == "completed" else f"the results ({status})"
            doing = "drawing the figures" if step == "figures" else "printing the results"
            print(f"covnet: interrupted while {doing}: {out} holds {what} (covnet plot {out} "
                  "draws the figures)", file=sys.stderr)  # fmt: skip
        raise


def utc_now() -> str:
    """The current UTC time as ``YYYY-mm-ddTHH:MM:SSZ`` (``run.json``'s ``created_utc``)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
