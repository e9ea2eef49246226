"""One ``--out`` for one command at a time: :func:`prepare_out` claims the directory (a second
command writing there now is refused, with or without ``--force``), and ``atomic_write`` /
``write_npz`` use temporary files of their own (a fixed ``NAME.tmp`` was shared by two writers:
a run exited 0 with the other run's results, or with a corrupt ``arrays.npz``)."""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from covnet.batches.trials import BATCH_INFO, prepare_batch_out
from covnet.errors import UsageError
from covnet.runs import rundir
from covnet.runs.rundir import (
    FILE_DIGESTS,
    atomic_write,
    claims,
    file_sha256,
    load_arrays,
    prepare_out,
    write_npz,
)

HELD = "another covnet command is writing there"


def _covnet_run(paper_path: Path, out: Path, seed: int, *extra: str) -> subprocess.Popen[str]:
    argv = [sys.executable, "-m", "covnet", "run", str(paper_path), "--seed", str(seed)]
    return subprocess.Popen(
        [*argv, "--out", str(out), "--no-figures", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str]:
    try:
        _, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise
    return proc.returncode, err


def _free(p: Path) -> bool:
    """No process holds a claim on ``p`` (an exclusive flock on it can be taken)."""
    fd = os.open(p, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    finally:
        os.close(fd)


def _assert_own_results(out: Path, seed: int) -> None:
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed"
    assert file_sha256(out / "arrays.npz") == info[FILE_DIGESTS]["arrays.npz"]
    assert load_arrays(out / "arrays.npz")["truth"].shape == (100, 4)
    assert json.loads((out / "summary.json").read_text())["seed"] == seed


def test_a_command_into_an_out_another_holds_is_refused_with_or_without_force(tmp_path, paper_path):
    out = tmp_path / "same"
    out.mkdir()
    with claims():
        assert prepare_out(out, "paper", False) == out  # this test is the command writing there
        (out / "config.json").write_text("{}")  # an earlier covnet output, as --force empties
        for extra in ((), ("--force",)):
            code, err = _finish(_covnet_run(paper_path, out, 1, *extra))
            assert code == 2, err
            assert f"--out {out}: {HELD}" in err and "Traceback" not in err
        assert sorted(p.name for p in out.iterdir()) == ["config.json"]  # --force cleared nothing
    assert _free(out)  # released with the block
    code, err = _finish(_covnet_run(paper_path, out, 2, "--force"))
    assert code == 0, err
    _assert_own_results(out, 2)
    assert _free(out)  # nothing left locked once the command has ended


def test_two_concurrent_runs_into_one_new_out_one_wins_the_other_is_refused(tmp_path, paper_path):
    out = tmp_path / "new"
    procs = {seed: _covnet_run(paper_path, out, seed) for seed in (1, 2)}
    ends = {seed: _finish(p) for seed, p in procs.items()}
    codes = sorted(code for code, _ in ends.values())
    assert codes == [0, 2], ends
    (won,) = [seed for seed, (code, _) in ends.items() if code == 0]
    (_, err) = next(e for seed, e in ends.items() if seed != won)
    # refused while the winner writes, or (had it finished first) for the directory it filled
    assert f"--out {out}: " in err and (HELD in err or "directory is not empty" in err), err
    _assert_own_results(out, won)
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]


def test_the_same_command_may_prepare_its_directory_again(tmp_path):
    out = tmp_path / "o"
    with claims():
        prepare_out(out, "x", False)
        (out / "run.json").write_text("{}")
        assert prepare_out(out, "x", True) == out  # its own claim: not "another command"
        assert not any(out.iterdir())
        assert not _free(out)
        (out / "run.json").write_text("{}")  # written: kept when the claim ends
    assert _free(out)


@pytest.mark.parametrize("force", [False, True])
def test_another_thread_of_this_process_is_another_command(tmp_path, force):
    """Two ``api.run(out=DIR)`` calls in threads of one process both wrote into DIR (one run's
    results, the other's figures; with ``force`` one emptied it as the other wrote): the
    claim was per process.  A directory another block or live thread of this process holds is
    refused as another process's is; blocks within one command share it, and a thread's claim
    outside any block is free once that thread has ended."""
    out = tmp_path / "o"
    held, done = threading.Event(), threading.Event()
    seen: list[BaseException] = []

    def first() -> None:
        with claims():
            prepare_out(out, "x", False)
            (out / "run.json").write_text("{}")
            held.set()
            done.wait(30)

    a = threading.Thread(target=first)
    a.start()
    try:
        assert held.wait(30)
        for attempt in (lambda: prepare_out(out, "x", force), lambda: rundir.claim(out, "o")):
            with claims(), pytest.raises(UsageError, match=HELD):
                attempt()

        def second() -> None:  # a thread of its own, no block
            try:
                prepare_out(out, "x", force)
            except BaseException as exc:
                seen.append(exc)

        b = threading.Thread(target=second)
        b.start()
        b.join(30)
        assert len(seen) == 1 and HELD in str(seen[0]), seen
        assert (out / "run.json").is_file()  # force emptied nothing
    finally:
        done.set()
        a.join(30)
    # the same command, in blocks within its own, prepares it again
    with claims():
        prepare_out(out, "x", True)
        with claims():
            assert prepare_out(out, "x", True) == out
    # a thread's claim outside any block, its thread gone: free for the next command
    lone = threading.Thread(target=lambda: rundir.claim(tmp_path / "lone", "lone"))
    lone.start()
    lone.join(30)
    with claims():
        assert prepare_out(tmp_path / "lone", "x", False) == tmp_path / "lone"
    rundir._release((tmp_path / "lone").resolve())


def test_a_claimed_directory_left_empty_is_removed_and_a_fork_keeps_no_claim(tmp_path):
    out = tmp_path / "made"
    with claims():
        prepare_out(out, "x", False)
        assert out.is_dir() and not _free(out)
        pid = os.fork()
        if pid == 0:  # the child holds none of the parent's claims
            os._exit(0 if not rundir._CLAIMS else 1)
        assert os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) == 0
        assert not _free(out)  # the child closing its copy left the parent's lock
    assert not out.exists()  # made by the claim, never written: gone again


def test_a_resumed_batch_is_refused_while_another_process_holds_it_then_resumes(tmp_path):
    out = tmp_path / "batch"
    out.mkdir()
    (out / BATCH_INFO).write_text(json.dumps({"command": "sweep", "trial_hash": "k"}))
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; from covnet.runs.rundir import claim; "
            "claim(Path(sys.argv[1]), 'held'); print('ready', flush=True); time.sleep(120)",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "ready"
        with claims(), pytest.raises(UsageError, match=f"--out {out}: {HELD}"):
            prepare_batch_out(out, "x", False, "sweep", "k")
    finally:
        holder.kill()
        holder.communicate(timeout=30)
    with claims():  # the first process is gone: the batch resumes
        assert prepare_batch_out(out, "x", False, "sweep", "k") == (out, True)


def _race(fn, n: int = 2) -> list[BaseException]:
    errors: list[BaseException] = []
    start = threading.Barrier(n)

    def body(i: int) -> None:
        start.wait()
        try:
            fn(i)
        except BaseException as exc:  # noqa: BLE001 (reported by the test)
            errors.append(exc)

    threads = [threading.Thread(target=body, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    return errors


def test_two_writers_of_one_file_never_share_a_temporary_file(tmp_path):
    path = tmp_path / "results.json"
    payloads = [bytes([65 + i]) * (1 << 18) for i in range(2)]  # 256 KiB each

    def writer(i: int) -> None:
        for _ in range(150):
            atomic_write(path, payloads[i])
            assert path.read_bytes() in payloads  # never half of one, or a mix of both

    assert _race(writer) == []
    assert path.read_bytes() in payloads
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]  # no temporary file left


def test_two_write_npz_into_one_path_leave_a_whole_file_with_its_digest(tmp_path):
    path = tmp_path / "arrays.npz"
    rng = np.random.default_rng(0)
    arrays = [{"a": rng.random((200, 200))}, {"a": rng.random((200, 200))}]
    digests: list[set[str]] = [set(), set()]

    def writer(i: int) -> None:
        for _ in range(20):
            digests[i].add(write_npz(path, arrays[i]))

    assert _race(writer) == []
    assert all(len(d) == 1 for d in digests)  # the same bytes every time
    got = file_sha256(path)
    i = [next(iter(d)) for d in digests].index(got)  # the whole file of one writer
    np.testing.assert_array_equal(load_arrays(path)["a"], arrays[i]["a"])
    assert [p.name for p in tmp_path.iterdir()] == ["arrays.npz"]


def test_written_files_get_a_new_files_mode_and_a_failed_write_leaves_nothing(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    atomic_write(tmp_path / "a.json", b"{}")
    write_npz(tmp_path / "b.npz", {"x": np.zeros(3)})
    for name in ("a.json", "b.npz"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask

    class Unpicklable:
        def __reduce__(self):
            raise TypeError("cannot be saved")

    bad = np.empty(1, dtype=object)
    bad[0] = Unpicklable()
    with pytest.raises(TypeError, match="cannot be saved"):
        write_npz(tmp_path / "c.npz", {"x": bad})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.npz"]


def test_a_new_files_mode_follows_the_umask_of_the_moment(tmp_path):
    """The umask was read once per process: after a first write under umask 022, a later
    ``umask 077`` still gave ``0o644`` files (and the reverse ``0o600``), the directory
    following the new umask.  Each file gets the mode the umask gives as it is written."""
    before = os.umask(0o022)
    try:
        for i, (umask, mode) in enumerate([(0o022, 0o644), (0o077, 0o600), (0o022, 0o644)]):
            os.umask(umask)
            atomic_write(tmp_path / f"{i}.json", b"{}")
            write_npz(tmp_path / f"{i}.npz", {"x": np.zeros(3)})
            for name in (f"{i}.json", f"{i}.npz"):
                assert (tmp_path / name).stat().st_mode & 0o777 == mode, (name, oct(umask))
    finally:
        os.umask(before)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"{i}.{ext}" for i in range(3) for ext in ("json", "npz")
    )


def test_flock_on_a_directory_works_here(tmp_path):
    """The claim's mechanism: an exclusive flock on a directory, refused to a second open."""
    a, b = os.open(tmp_path, os.O_RDONLY), os.open(tmp_path, os.O_RDONLY)
    try:
        fcntl.flock(a, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(BlockingIOError):
            fcntl.flock(b, fcntl.LOCK_EX | fcntl.LOCK_NB)
    finally:
        os.close(a)
        os.close(b)
