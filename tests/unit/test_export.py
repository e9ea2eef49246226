"""``covnet export RUN --format csv`` (issue 27, Stone Soup interop): the CSV holds the run's
arrays bit for bit (covariance control with one target and with ``targets:``, mobile), and
every input it cannot export is refused with one line naming it, exit 2, no traceback."""

from __future__ import annotations

import csv
import io
import json
import shutil
import stat
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.cli.app import main
from covnet.runs import export as ex
from covnet.runs.rundir import load_arrays, write_npz

ROOT = Path(__file__).resolve().parents[2]


def _config(tmp_path_factory, name: str, **changes) -> Path:
    data = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
    data.update(changes)
    for t in data.get("targets", []) if name == "multitarget" else []:
        for m in t.get("manoeuvres", []):  # the turn and the priority change inside the run
            m.update(from_scan=2, to_scan=4)
        for d in t["desired"][1:]:
            d["from_scan"] = 3
    p = tmp_path_factory.mktemp("cfg") / f"{name}.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _run(tmp_path_factory, cfg: Path, name: str) -> Path:
    out = tmp_path_factory.mktemp("runs") / name
    assert main(["run", str(cfg), "--out", str(out), "--no-figures"]) == 0
    return out


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> Path:
    return _run(tmp_path_factory, _config(tmp_path_factory, "paper", scans=7), "paper")


@pytest.fixture(scope="module")
def mt_run(tmp_path_factory) -> Path:
    return _run(tmp_path_factory, _config(tmp_path_factory, "multitarget", scans=5), "mt")


@pytest.fixture(scope="module")
def mobile_run(tmp_path_factory) -> Path:
    cfg = _config(tmp_path_factory, "mobile", scans=4, compare_exact=False)
    return _run(tmp_path_factory, cfg, "mobile")


def _rows(text: str) -> list[dict[str, str]]:
    reader = csv.DictReader(io.StringIO(text))
    assert tuple(reader.fieldnames or ()) == ex.CSV_COLUMNS
    return list(reader)


def _export_csv(run: Path, *extra: str) -> list[dict[str, str]]:
    out = run / "export.csv"
    assert main(["export", str(run), *extra]) == 0
    return _rows(out.read_text())


def _state(r: dict[str, str]) -> np.ndarray:
    return np.array([float(r[c]) for c in ex.STATE])


def _cov(r: dict[str, str]) -> np.ndarray:
    return np.array([float(r[f"P{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4)


def _check(rows, episode, tid, truth, est, cov, t, scans) -> None:
    """The rows of ``tid`` in ``episode`` are exactly these arrays (bitwise)."""
    tr = [r for r in rows if r["episode"] == episode and r["id"] == tid and r["kind"] == "truth"]
    tk = [r for r in rows if r["episode"] == episode and r["id"] == tid and r["kind"] == "track"]
    assert [int(r["scan"]) for r in tr] == list(scans)
    assert [int(r["scan"]) for r in tk] == list(scans)
    assert np.array_equal([float(r["t"]) for r in tr], t)
    assert np.array_equal([float(r["t"]) for r in tk], t)
    assert np.array_equal(np.stack([_state(r) for r in tr]), truth)
    assert np.array_equal(np.stack([_state(r) for r in tk]), est)
    assert np.array_equal(np.stack([_cov(r) for r in tk]), cov)
    assert all(r[f"P{i}{j}"] == "" for r in tr for i in range(4) for j in range(4))


def test_csv_of_a_single_target_run_is_its_arrays(paper_run):
    rows = _export_csv(paper_run)
    a = load_arrays(paper_run / "arrays.npz")
    metrics = [str(m) for m in a["metrics"]]
    assert len(metrics) == 3
    assert len(rows) == len(metrics) * 2 * 7
    assert [r["episode"] for r in rows[::14]] == metrics  # episode by episode, run's order
    for m in metrics:
        _check(rows, m, "T1", a["truth"], a[f"x_est.{m}"], a[f"P_post.{m}"], a["t"], range(1, 8))


def test_csv_of_a_many_target_run_is_its_arrays(mt_run):
    rows = _export_csv(mt_run)
    a = load_arrays(mt_run / "arrays.npz")
    tids = [str(x) for x in a["target_ids"]]
    assert tids == ["T1", "T2", "T3"]
    for m in (str(x) for x in a["metrics"]):
        for i, tid in enumerate(tids):
            _check(
                rows,
                m,
                tid,
                a["truth"][i],
                a[f"x_est.{m}"][i],
                a[f"P_post.{m}"][i],
                a["t"],
                range(1, 6),
            )
    # truths first, then tracks, target by target, scan by scan
    first = [(r["kind"], r["id"], r["scan"]) for r in rows[:16]]
    assert first[:6] == [("truth", "T1", str(k)) for k in range(1, 6)] + [("truth", "T2", "1")]
    assert first[15] == ("track", "T1", "1")


@pytest.fixture(scope="module")
def surveillance_run(tmp_path_factory) -> Path:
    """configs/surveillance.yaml for 30 scans: A1 from scan 1, A5 from 5 and A2 from 10 (the
    later ones dropped), tracks started from detections in clutter."""
    data = yaml.safe_load((ROOT / "configs" / "surveillance.yaml").read_text())
    data["scans"] = 30
    data["targets"] = [t for t in data["targets"] if t.get("appears_at_scan", 1) <= 10]
    p = tmp_path_factory.mktemp("cfg") / "surveillance.yaml"
    p.write_text(yaml.safe_dump(data))
    return _run(tmp_path_factory, p, "surveillance")


def test_csv_of_a_surveillance_run_is_its_targets_and_confirmed_tracks(surveillance_run):
    """A target's rows are the scans it exists, a track's the scans it is confirmed, with its
    own id (``track-N``); every value bit for bit from ``arrays.npz``."""
    rows = _export_csv(surveillance_run)
    a = load_arrays(surveillance_run / "arrays.npz")
    (m,) = (str(x) for x in a["metrics"])
    for i, tid in enumerate(str(x) for x in a["truth_ids"]):
        tr = [r for r in rows if r["kind"] == "truth" and r["id"] == tid]
        k = np.flatnonzero(a["exists"][i])
        assert [int(r["scan"]) for r in tr] == (k + 1).tolist()
        assert np.array_equal(np.stack([_state(r) for r in tr]), a["truth"][i, k])
        assert np.array_equal([float(r["t"]) for r in tr], a["t"][k])
    conf = a[f"track_rows.{m}"]
    conf = conf[conf[:, 2] == 1]
    tk = [r for r in rows if r["kind"] == "track"]
    assert len(tk) == len(conf) > 0
    assert {r["id"] for r in tk} == {f"track-{int(n)}" for n in conf[:, 1]}
    for n in {int(x) for x in conf[:, 1]}:
        mine = conf[conf[:, 1] == n]
        got = [r for r in tk if r["id"] == f"track-{n}"]
        assert [int(r["scan"]) for r in got] == mine[:, 0].astype(int).tolist()
        assert np.array_equal(np.stack([_state(r) for r in got]), mine[:, 3:7])
        assert np.array_equal(np.stack([_cov(r) for r in got]), mine[:, 7:].reshape(-1, 4, 4))
    # tentative and deleted tracks are not in it
    assert len({r["id"] for r in tk}) < len({int(x) for x in a[f"track_rows.{m}"][:, 1]})


def test_csv_of_a_mobile_run_starts_at_row_zero(mobile_run):
    rows = _export_csv(mobile_run)
    a = load_arrays(mobile_run / "arrays.npz")
    assert {r["episode"] for r in rows} == {"lp"}  # the run's solver
    t = np.arange(5) * 1.0  # scan_period_s
    for i, tid in enumerate(str(x) for x in a["target_ids"]):
        _check(rows, "lp", tid, a["truth"][:, i], a["x_est"][:, i], a["P_post"][:, i], t, range(5))


def test_one_episode_to_a_named_file_or_stdout(paper_run, tmp_path, capsys):
    out = tmp_path / "svd.csv"
    assert main(["export", str(paper_run), "--episode", "svd", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    rows = _rows(out.read_text())
    assert {r["episode"] for r in rows} == {"svd"} and len(rows) == 14
    assert main(["export", str(paper_run), "--episode", "svd", "--out", "-"]) == 0
    assert capsys.readouterr().out == out.read_text()


@pytest.mark.parametrize("kind", ["fifo", "link"])
def test_an_out_that_is_not_a_regular_file_is_never_replaced(paper_run, tmp_path, kind, capsys):
    """--out P --force replaced a FIFO, a device or a symlink with a regular file (as root,
    --out /dev/stdout --force would replace the machine's node): refused, even with --force."""
    import os

    target = tmp_path / "elsewhere.csv"
    target.write_text("kept\n")
    out = tmp_path / "out"
    if kind == "fifo":
        os.mkfifo(out)
    else:
        out.symlink_to(target)
    for extra in ([], ["--force"]):
        assert main(["export", str(paper_run), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert "not a regular file" in err and "--out - for stdout" in err, err
    assert out.is_symlink() if kind == "link" else stat.S_ISFIFO(out.lstat().st_mode)
    assert target.read_text() == "kept\n"


def _rewrite(run: Path, arrays: dict[str, np.ndarray]) -> None:
    """``run``'s arrays replaced by ``arrays``, as a run writing them would (its ``run.json``
    keeps the new file's digest)."""
    info = json.loads((run / "run.json").read_text())
    info["file_sha256"] = {"arrays.npz": write_npz(run / "arrays.npz", arrays)}
    (run / "run.json").write_text(json.dumps(info))


def test_a_stopped_run_exports_the_scans_its_episode_did(paper_run, tmp_path):
    """A network run stopped early writes shorter x_est / P_post than truth: the export
    (truth included) covers the scans the episode completed."""
    run = tmp_path / "stopped"
    shutil.copytree(paper_run, run)
    a = load_arrays(run / "arrays.npz")
    a["x_est.spectral"] = a["x_est.spectral"][:3]
    a["P_post.spectral"] = a["P_post.spectral"][:3]
    _rewrite(run, a)
    (e,) = [e for e in ex.read_run(run) if e.name == "spectral"]
    assert list(e.truths[0].scan) == [1, 2, 3] == list(e.tracks[0].scan)
    assert np.array_equal(e.truths[0].x, a["truth"][:3])


def _refused(capsys, argv: list[str], *words: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.count("\n") == 1, err
    for w in words:
        assert w in err, (w, err)


def test_refusals_name_what_is_wrong(paper_run, tmp_path, capsys):
    _refused(capsys, ["export", str(tmp_path / "nowhere")], "nowhere", "not a directory")
    _refused(capsys, ["export", str(tmp_path)], str(tmp_path), "config.json")
    _refused(capsys, ["export", str(paper_run), "--episode", "nope"], "nope", "spectral, ")
    missing = tmp_path / "no-folder" / "x.csv"
    _refused(capsys, ["export", str(paper_run), "--out", str(missing)], "--out", "no-folder")
    with pytest.raises(SystemExit) as exit_:  # argparse's choices
        main(["export", str(paper_run), "--format", "xml"])
    assert exit_.value.code == 2 and "csv" in capsys.readouterr().err

    no_arrays = tmp_path / "no-arrays"
    shutil.copytree(paper_run, no_arrays)
    (no_arrays / "arrays.npz").unlink()
    _refused(capsys, ["export", str(no_arrays)], "arrays.npz", "missing")

    no_key = tmp_path / "no-key"
    shutil.copytree(paper_run, no_key)
    a = load_arrays(no_key / "arrays.npz")
    del a["P_post.svd"]
    _rewrite(no_key, a)
    _refused(capsys, ["export", str(no_key)], "arrays.npz", "'P_post.svd'")

    broken = tmp_path / "broken"
    shutil.copytree(paper_run, broken)
    (broken / "arrays.npz").write_bytes(b"not a zip")
    _refused(capsys, ["export", str(broken)], "arrays.npz", "not a readable")

    edited = tmp_path / "edited"
    shutil.copytree(paper_run, edited)
    cfg = json.loads((edited / "config.json").read_text())
    cfg["seed"] += 1
    (edited / "config.json").write_text(json.dumps(cfg))
    _refused(capsys, ["export", str(edited)], "config.json", "edited after the run")


def test_a_passive_run_has_nothing_to_export(tmp_path, capsys):
    run = tmp_path / "passive"
    assert main(["run", str(ROOT / "configs" / "passive.yaml"), "--out", str(run)]) == 0
    capsys.readouterr()
    _refused(capsys, ["export", str(run)], str(run), "passive", "nothing to export")
    _refused(capsys, ["export", str(run), "--format", "stonesoup"], "passive")


def test_without_stone_soup_the_format_says_how_to_install_it(paper_run, monkeypatch, capsys):
    for name in [m for m in sys.modules if m.split(".")[0] == "stonesoup"] + ["stonesoup"]:
        monkeypatch.setitem(sys.modules, name, None)  # import stonesoup... fails
    _refused(
        capsys,
        ["export", str(paper_run), "--format", "stonesoup"],
        "Stone Soup",
        "pip install 'covnet[stonesoup]'",
    )
    assert not (paper_run / "export.stonesoup.yaml").exists()
    with pytest.raises(ImportError, match="covnet\\[stonesoup\\]"):
        ex.to_stonesoup(paper_run)


def test_a_peer_runs_metrics_block_and_export_are_the_first_nodes_and_say_so(
    tmp_path_factory, capsys
):
    """A peer run printed the node mean RMSE while ``summary.json``'s ``metrics`` block,
    ``x_est.<metric>`` and the export held node S1's alone, and nothing said so; the numbers
    stay (a golden hash holds them), the export's help and the README say whose they are."""
    cfg = _config(tmp_path_factory, "paper", scans=6, fusion={"mode": "peer"})
    out = tmp_path_factory.mktemp("runs") / "peer"
    assert main(["run", str(cfg), "--out", str(out), "--no-figures", "--metric", "spectral"]) == 0
    s = json.loads((out / "summary.json").read_text())
    s1 = s["peer"]["spectral"]["nodes"]["S1"]
    assert s["metrics"]["spectral"]["rmse_position"] == s1["rmse_position"]
    a = load_arrays(out / "arrays.npz")
    assert np.array_equal(a["x_est.spectral"], a["x_est.spectral.S1"])
    rows = _export_csv(out)
    _check(rows, "spectral", "T1", a["truth"], a["x_est.spectral.S1"], a["P_post.spectral.S1"],
           a["t"], range(1, 7))  # fmt: skip
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "A peer run's track is one node's estimate" in text, text
    assert "the first sensor's, S1 in the shipped configs" in text, text
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "not the node mean the run prints" in readme
