"""Every kind's recording is the whole run: ``covnet replay`` of a real ``covnet up`` run of each
kind (covariance control, mobile, passive; lockstep, real processes over zenoh) says
``identical`` and reproduces the run's result file byte for byte, and ``Kind.rebuild`` of a
recording cut anywhere (a killed recorder or manager) writes a valid run directory of exactly
the scans fully recorded, equal to the run's own first scans."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from multiproc import REPO, CovnetProcess, assert_nothing_left

import covnet.cli.app
from covnet import kinds
from covnet.runs.recording import RecordingReader, RecordingWriter, read_metadata
from covnet.runs.replay_kit import RECORDING, REPLAY_DIR, REPORT
from covnet.runs.rundir import load_arrays, read_json
from covnet.wire import messages as msg

CONFIGS = REPO / "configs"
CASES = {
    "covariance_control": (
        CONFIGS / "paper.yaml",
        {"scans": 12, "allocation": {"metrics": ["spectral"]}},
        "summary.json",
    ),
    "mobile": (CONFIGS / "mobile.yaml", {"scans": 10}, "summary.json"),
    "passive": (CONFIGS / "passive.yaml", {}, "association.json"),
}
"""kind -> (shipped config, changes to it that keep the run short, the result file compared)."""
CUTS = (0.02, 0.3, 0.55, 0.8, 0.999)
"""Where the recording is cut, as fractions of its length (the last one: inside the footer)."""


def _short_config(path, changes, out):
    data = yaml.safe_load(path.read_text())
    for key, value in changes.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    out.write_text(yaml.safe_dump(data))
    return out


@pytest.fixture(scope="module")
def up_runs(tmp_path_factory):
    """One lockstep ``covnet up`` of each kind (started together, bounded in time; each gets
    a free port and a fresh run id from the launcher), seed 3."""
    base = tmp_path_factory.mktemp("up")
    procs = {}
    try:
        for name, (src, changes, _) in CASES.items():
            cfg_path = _short_config(src, changes, base / f"{name}.yaml")
            argv = ["up", str(cfg_path), "--out", str(base / name), "--seed", "3", "--no-figures"]
            procs[name] = CovnetProcess(argv)
        for name, p in procs.items():
            assert p.wait(timeout=120) == 0, p.output()
            assert_nothing_left(base / name)
    finally:
        for p in procs.values():
            p.stop()
    return {name: base / name for name in CASES}


@pytest.mark.integration
@pytest.mark.timeout(180)
@pytest.mark.parametrize("kind", sorted(CASES))
def test_replay_of_an_up_run_is_identical(up_runs, kind, capsys):
    run = up_runs[kind]
    result = CASES[kind][2]
    reader = RecordingReader(run / RECORDING)
    assert sum(1 for _ in reader.samples()) > 0 and reader.complete
    assert covnet.cli.app.main(["replay", str(run)]) == 0
    out = capsys.readouterr().out
    assert "identical" in out and result in out, out
    assert (run / REPLAY_DIR / result).read_bytes() == (run / result).read_bytes()
    report = read_json(run / REPLAY_DIR / REPORT)
    assert report["identical"] and report["differences"] == [] and report["notes"] == []
    assert _progress(kind, run / REPLAY_DIR, kinds.get(kind).episodes(_config(run))) == (
        True,
        _config(run).scans,
    )


def _config(run):
    return kinds.from_dict(read_json(run / "config.json"), "config.json")[1]


def _rechunked(src, dst, run_id):
    """``src`` rewritten with small chunks (as a recorder flushing often leaves it), so that a
    cut keeps some scans and loses the rest."""
    with RecordingWriter(dst, run_id=run_id, metadata=read_metadata(src), chunk_size=1024) as w:
        for s in RecordingReader(src).samples():
            w.write(s.key, s.payload, s.t_recv_ns, s.t_sent_ns)


def _statuses(path, run_id):
    """The scans of episode 0 with a Status in a (possibly cut) recording, 1, 2, ... n."""
    scans = set()
    for s in RecordingReader(path).samples():
        if s.key == msg.status_key(run_id):
            st = msg.decode_as(s.payload, msg.Status)
            scans.add((st.episode, st.scan))
    n = 0
    while (0, n + 1) in scans:
        n += 1
    return n


def _progress(kind, out, episodes):
    """``(completed, scans)`` of a run directory, from its own files."""
    if kind == "covariance_control":  # in the summary, the scans per metric
        summary = read_json(out / "summary.json")
        return summary["completed"], summary["scans_completed"].get(episodes[0], 0)
    info = read_json(out / "run.json")
    return info["completed"], info["scans_completed"]


def _same_first_scans(kind, run, out, n):
    """The rebuilt directory's n scans are the run's first n."""
    if kind == "passive":
        assert (
            read_json(out / "association.json")["scans"]
            == read_json(run / "association.json")["scans"][:n]
        )
        return
    a, b = load_arrays(run / "arrays.npz"), load_arrays(out / "arrays.npz")
    for name in ("x_est", "P_post", "x_est.spectral", "P_post.spectral", "assign", "modes"):
        if name in a:
            rows = n + 1 if kind == "mobile" and name in ("x_est", "P_post") else n
            np.testing.assert_array_equal(b[name], a[name][:rows], err_msg=name)


@pytest.mark.integration
@pytest.mark.timeout(180)
@pytest.mark.parametrize("kind", sorted(CASES))
def test_rebuild_of_a_cut_recording_keeps_the_scans_fully_recorded(up_runs, kind, tmp_path):
    run = up_runs[kind]
    kd, cfg = kinds.from_dict(read_json(run / "config.json"), "config.json")
    info = read_json(run / "run.json")
    run_id, episodes = info["run_id"], kd.episodes(cfg)
    full = tmp_path / "full.mcap"
    _rechunked(run / RECORDING, full, run_id)
    data = full.read_bytes()
    total = cfg.scans
    kept = []
    for frac in CUTS:
        cut = tmp_path / f"cut-{frac}" / RECORDING
        cut.parent.mkdir()
        cut.write_bytes(data[: int(len(data) * frac)])
        n = _statuses(cut, run_id)
        out = tmp_path / f"rebuilt-{frac}"
        report = kd.rebuild(cfg, run_id, episodes, cut, out, {"status": "failed"})
        assert report.differences == [], (frac, report.differences)
        assert any("no footer" in note for note in report.notes)
        rebuilt = read_json(out / "run.json")
        assert rebuilt["status"] == "failed" and rebuilt["run_id"] == run_id
        assert rebuilt["episodes"] == episodes
        assert _progress(kind, out, episodes) == (n == total, n)
        assert n <= total
        if n:
            _same_first_scans(kind, run, out, n)
        kept.append(n)
    assert kept == sorted(kept) and kept[0] < total and kept[-1] == total, kept
    assert any(0 < n < total for n in kept), kept  # some cut fell mid-run
    # the whole recording, rebuilt into the run's own layout, is the run
    out = tmp_path / "rebuilt-full"
    report = kd.rebuild(cfg, run_id, episodes, full, out)
    assert report.differences == [] and report.notes == []
    result = CASES[kind][2]
    assert (out / result).read_bytes() == (run / result).read_bytes()
    assert _progress(kind, out, episodes) == (True, total)
