"""``covnet up`` with real processes and real zenoh sessions on 127.0.0.1 (a free port per run,
multicast scouting off, a per-run key prefix)."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left
from traffic_check import assert_compare_counts_what_was_sent

from covnet.cli.app import main as covnet_main
from covnet.runs.recording import META_RUN, RecordingReader, read_metadata
from covnet.runs.replay_kit import load_recording
from covnet.runs.rundir import load_arrays

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory, paper_path):
    out = tmp_path_factory.mktemp("ref") / "run"
    assert covnet_main(["run", str(paper_path), "--out", str(out), "--no-figures"]) == 0
    return out


@pytest.fixture(scope="module")
def lockstep_up(tmp_path_factory, paper_path):
    out = tmp_path_factory.mktemp("up") / "run"
    p = CovnetProcess(["up", str(paper_path), "--out", str(out), "--verbose"])
    try:
        rc = p.wait(timeout=150)
    finally:
        p.stop()
    assert rc == 0, p.output()
    return out, p.output()


def test_up_equals_run(reference, lockstep_up):
    out, _ = lockstep_up
    ref = json.loads((reference / "summary.json").read_text())
    got = json.loads((out / "summary.json").read_text())
    assert got["completed"] is True
    assert json.loads((out / "run.json").read_text())["mode"] == "network"
    assert set(got["metrics"]) == set(ref["metrics"])
    a_ref, a_got = load_arrays(reference / "arrays.npz"), load_arrays(out / "arrays.npz")
    for m in ref["metrics"]:
        assert got["metrics"][m]["subsets"] == ref["metrics"][m]["subsets"]
        np.testing.assert_allclose(a_got[f"x_est.{m}"], a_ref[f"x_est.{m}"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(a_got[f"P_post.{m}"], a_ref[f"P_post.{m}"], rtol=0, atol=1e-12)


def test_compare_counts_the_messages_and_bytes_the_network_sent(lockstep_up):
    """``covnet compare``'s messages and bytes per scan for the run's decisions are the
    recording's, every metric's episode (they were 7 % short: placeholder fields)."""
    out, _ = lockstep_up
    assert_compare_counts_what_was_sent(out, "central")


def test_sensors_obey_commands(lockstep_up):
    """Per sensor: measurements == commands it received == scans it was enabled (zenoh
    delivers a command, by its key, to the sensors it enables only)."""
    out, output = lockstep_up
    summary = json.loads((out / "summary.json").read_text())
    net = json.loads((out / "network.json").read_text())
    for sid in summary["sensor_ids"]:
        enabled = sum(blk["usage"][sid] for blk in summary["metrics"].values())
        keys = [k for k in net["received"] if k.endswith(f"/sensor/{sid}/meas")]
        received = sum(net["received"][k]["messages"] for k in keys)
        assert received == enabled, sid
        said = re.search(rf"\[{sid}\] stopped: (\d+) commands received, (\d+) scans enabled, "
                         rf"(\d+) measurements sent", output)  # fmt: skip
        assert said is not None, output
        assert [int(n) for n in said.groups()] == [enabled] * 3, sid
    assert net["rejected"] == {} and net["lost"] == 0


def test_run_directory_complete(lockstep_up):
    out, output = lockstep_up
    names = set(json.loads((out / "processes.json").read_text()))
    assert names == {"manager", "world", "recorder", *(f"S{i}" for i in range(1, 9))}
    for f in (
        "summary.json",
        "arrays.npz",
        "config.json",
        "network.json",
        "run.json",
        "recording.mcap",
    ):
        assert (out / f).is_file(), f
    net = json.loads((out / "network.json").read_text())
    assert net["scan_latency"]["n"] == 300 and net["scan_latency"]["p50_ms"] > 0
    assert "READY" in output
    assert_nothing_left(out)


def test_ctrl_c_stops_everything_and_keeps_what_was_recorded(covnet_proc, tmp_path, paper_path):
    out = tmp_path / "run"
    p = covnet_proc(
        [
            "up",
            str(paper_path),
            "--out",
            str(out),
            "--realtime",
            "--speed",
            "25",
            "--metric",
            "spectral",
        ]
    )
    assert p.wait_for("[manager] READY", timeout=60), p.output()
    assert p.wait_for(lambda s: s.startswith("[status]") and "scan 1/" not in s, timeout=30)
    os.killpg(p.proc.pid, signal.SIGINT)
    assert p.wait(timeout=5) == 130, p.output()  # Ctrl-C: everything stops within 5 s
    assert_nothing_left(out)
    # the summary of the scans done, not the figures (they took seconds more, 10 s under load)
    assert not list(out.glob("fig*.png")), sorted(f.name for f in out.iterdir())
    assert f"the figures were not drawn (interrupted): covnet plot {out}" in p.output()
    summary = json.loads((out / "summary.json").read_text())
    done = summary["scans_completed"].get("spectral")
    assert done is not None, f"no complete scan rebuilt: {summary}\n{p.output()}"
    assert 0 < done < 100 and summary["completed"] is False
    assert len(summary["metrics"]["spectral"]["subsets"]) == done


def recorded_complete_scans(recording: Path) -> int:
    """How many scans of the first episode the recording holds complete as it is on disk now
    (read while its recorder writes it: up to its last complete record): scans 1, 2, ... each
    with its Status and a measurement of every sensor that Status fused."""
    if not recording.is_file():
        return 0
    run_id = read_metadata(recording).get(META_RUN, {}).get("run_id")
    if run_id is None:
        return 0
    rec = load_recording(RecordingReader(recording).samples(), run_id)
    k = 0
    while (st := rec.status.get((0, k + 1))) is not None and all(
        (0, k + 1, sid) in rec.meas for sid in st.fused
    ):
        k += 1
    return k


def test_crashed_manager_ends_the_run_with_a_message(covnet_proc, tmp_path, paper_path):
    out = tmp_path / "run"
    p = covnet_proc(
        [
            "up",
            str(paper_path),
            "--out",
            str(out),
            "--realtime",
            "--speed",
            "20",
            "--metric",
            "spectral",
            "--no-figures",
        ]
    )
    assert p.wait_for("[manager] READY", timeout=60), p.output()
    # Not on a STATUS line: the manager prints scan k's as it hands its Status to zenoh, and a
    # SIGKILL right then can keep that Status from ever leaving the process, so the recording
    # legitimately holds no complete scan ("(no scan)"; a status line also says "1/100", not
    # "scan 1/100", when every sensor is on).  Wait until the recording on disk (the recorder
    # flushes at least every second) holds a complete scan: whatever the kill loses after that,
    # the rebuild has that scan.  The manager's live snapshot exists by then; results are not
    # written while the run goes on, only live.json.
    recording = out / "recording.mcap"
    deadline = time.monotonic() + 30
    while not (recorded_complete_scans(recording) >= 1 and (out / "live.json").is_file()):
        assert p.proc.poll() is None and time.monotonic() < deadline, p.output()
        time.sleep(0.05)
    assert not (out / "summary.json").exists()
    pids = json.loads((out / "processes.json").read_text())
    os.kill(pids["manager"], signal.SIGKILL)
    assert p.wait(timeout=30) == 1, p.output()
    assert "the manager failed (exit status -9)" in p.output()
    assert "from the recording up to the last complete scan" in p.output()
    assert_nothing_left(out)
    # the launcher rebuilt the directory from the recording (covnet replay's code), marked failed
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "failed" and info["rebuilt_from_recording"] is True
    assert "exited with status -9" in info["ended"]
    assert info["membership"] == {}  # counted from the rebuilt failures: none (it had none)
    summary = json.loads((out / "summary.json").read_text())
    done = summary["scans_completed"].get("spectral")
    assert done is not None, f"no complete scan rebuilt: {summary}\n{p.output()}"
    assert summary["completed"] is False and 0 < done < 100
    assert info["scans_completed"] == {"spectral": done}
    assert not (out / "live.json").exists()
    rp = covnet_proc(["replay", str(out)])
    assert rp.wait(timeout=120) == 0, rp.output()
    assert "identical" in rp.output()


def test_a_node_that_dies_before_ready_is_a_failed_run_not_an_interrupted_one(
    covnet_proc, tmp_path, paper_path
):
    """A sensor process gone before READY: the launcher stops the network and exits 1, but
    run.json said ``interrupted`` ("Ctrl-C in the launcher"): the manager, stopped by the
    launcher, took it for a Ctrl-C. (S8 is never started, so READY cannot come first.)"""
    out = tmp_path / "run"
    here = ",".join(["manager", "world", "recorder", *(f"S{i}" for i in range(1, 8))])
    p = covnet_proc(["up", str(paper_path), "--nodes", here, "--out", str(out), "--no-figures"])
    deadline = time.monotonic() + 60
    while "S7" not in (pids := _pids(out)):
        assert p.proc.poll() is None and time.monotonic() < deadline, p.output()
        time.sleep(0.05)
    os.kill(pids["S7"], signal.SIGKILL)
    assert p.wait(timeout=60) == 1, p.output()
    assert "S7 exited with status -9 before the network was READY" in p.output()
    assert_nothing_left(out)
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "failed", info
    assert "S7 exited" in info["ended"], info


def _pids(out: Path) -> dict[str, int]:
    try:
        return dict(json.loads((out / "processes.json").read_text()))
    except (OSError, ValueError):
        return {}


def test_force_replaces_an_earlier_run_directory(covnet_proc, tmp_path, paper_path):
    """``covnet up --out DIR --force`` on a directory an earlier covnet run wrote: the new run's
    files only, nothing of the old one left (an old figure, an old replay/)."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text("{}")
    (out / "fig9_from_an_earlier_run.png").write_text("old")
    (out / "replay").mkdir()
    (out / "replay" / "summary.json").write_text("{}")
    argv = ["up", str(paper_path), "--out", str(out), "--metric", "spectral", "--no-figures"]
    refused = covnet_proc(argv)
    assert refused.wait(timeout=30) == 2, refused.output()
    assert "directory is not empty" in refused.output()
    assert (out / "fig9_from_an_earlier_run.png").exists()
    p = covnet_proc([*argv, "--force"])
    assert p.wait(timeout=150) == 0, p.output()
    assert_nothing_left(out)
    assert not (out / "fig9_from_an_earlier_run.png").exists() and not (out / "replay").exists()
    assert json.loads((out / "config.json").read_text())["allocation"]["metrics"] == ["spectral"]
    assert json.loads((out / "run.json").read_text())["status"] == "completed"


def test_the_nodes_are_forks_of_the_launcher_unless_told_otherwise(tmp_path, paper_path):
    """``covnet up`` starts its local nodes as forks of the launcher (process name
    ``covnet-<name>``, the launcher's command line); ``COVNET_FORK=0``: new interpreters
    (``python -m <role>``).  Either way a Ctrl-C stops them all."""
    for fork in ("1", "0"):
        out = tmp_path / f"fork-{fork}"
        p = CovnetProcess(
            [
                "up",
                str(paper_path),
                "--out",
                str(out),
                "--no-figures",
                "--realtime",
                "--speed",
                "5",
            ],
            prefix=["env", f"COVNET_FORK={fork}"],
        )
        try:
            assert p.wait_for("[manager] READY", timeout=60), p.output()
            pids = json.loads((out / "processes.json").read_text())
            names = {}
            for name, pid in pids.items():
                if isinstance(pid, int):
                    proc = Path(f"/proc/{pid}")
                    names[name] = (
                        (proc / "comm").read_text().strip(),
                        (proc / "cmdline").read_bytes().split(b"\0"),
                    )
            p.proc.send_signal(signal.SIGINT)
            assert p.wait(timeout=60) == 130, p.output()
        finally:
            p.stop()
        assert_nothing_left(out)
        assert set(names) == {"manager", "world", "recorder", *(f"S{i}" for i in range(1, 9))}
        for name, (comm, cmdline) in names.items():
            role = {"manager": b"manager", "world": b"world", "recorder": b"recorder"}
            if fork == "1":
                assert comm == f"covnet-{name}"[:15], (name, comm)
                assert b"up" in cmdline, (name, cmdline)
            else:
                assert cmdline[1:3] == [b"-m", role.get(name, b"sensors")], (name, cmdline)


@pytest.mark.parametrize("fork", ["1", "0"])
def test_an_ascii_stdout_does_not_lose_the_nodes_lines(tmp_path, paper_path, fork):
    """``PYTHONIOENCODING=ascii`` and a run directory named ``é``: the launcher's reader
    thread died of a ``UnicodeEncodeError`` on the manager's ``DONE ... out=`` line (hunt 14).
    The launcher escapes what it cannot encode; the nodes write UTF-8, which it reads."""
    out = tmp_path / "up é"
    p = CovnetProcess(
        ["up", str(paper_path), "--out", str(out), "--no-figures", "--metric", "spectral"],
        prefix=["env", "PYTHONIOENCODING=ascii", f"COVNET_FORK={fork}"],
    )
    try:
        rc = p.wait(timeout=150)
    finally:
        p.stop()
    said = p.output()
    assert rc == 0 and "Traceback" not in said, said
    assert "[manager] DONE completed=True out=" in said and "up \\xe9" in said, said
    assert json.loads((out / "run.json").read_text())["status"] == "completed"


def test_up_called_from_a_thread_runs(tmp_path, paper_path):
    """``covnet.cli.main(["up", ...])`` called from a thread other than the main one (a
    notebook's worker, a host program's job thread) runs the network as from the main thread: it
    ended in a ``ValueError`` traceback ("signal only works in main thread") when it installed
    its SIGTERM handler; the main thread's handlers stay as they were."""
    import threading

    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 5
    cfg = tmp_path / "paper5.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "run"
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    got: dict[str, object] = {}

    def call() -> None:
        try:
            got["rc"] = covnet_main(["up", str(cfg), "--out", str(out), "--no-figures"])
        except BaseException as exc:  # noqa: BLE001 - the test reports it
            got["raised"] = exc

    th = threading.Thread(target=call)
    th.start()
    th.join(150)
    assert not th.is_alive()
    assert got == {"rc": 0}
    assert_nothing_left(out)
    assert json.loads((out / "run.json").read_text())["status"] == "completed"
    assert {s: signal.getsignal(s) for s in handlers} == handlers
