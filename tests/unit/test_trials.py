"""The batch layer (issue 18, :mod:`covnet.batches.trials`): trials stored as they finish and
skipped
on a re-run, the directory rules, seeds added until the intervals are narrow, failures that do
not stop the others, the progress line, and the statistics (:mod:`covnet.batches.stats`)."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sps

from covnet.batches.pool import BatchInterrupted
from covnet.batches.stats import add_stats, error_stats, per_scan_bands, seed_stats
from covnet.batches.trials import (
    Batch,
    BatchProgress,
    TrialStore,
    batch_options,
    point_key,
    prepare_batch_out,
    run_trials,
    write_batch_info,
)
from covnet.errors import UsageError


def noisy(task):
    """A task: per seed a value with a spread that depends on the point."""
    point, seeds = task
    scale = {"narrow": 0.1, "wide": 3.0}[point]
    return [{"seed": s, "x": float(np.random.default_rng(s).normal(0.0, scale))} for s in seeds]


def fails_on_seed_2(task):
    point, seeds = task
    if 2 in seeds:
        raise ValueError("seed 2 is bad")
    return [{"seed": s} for s in seeds]


def interrupts_on_seed_3(task):
    point, seeds = task
    if 3 in seeds:
        raise KeyboardInterrupt
    return [{"seed": s} for s in seeds]


def _batch(fn=noisy, points=("narrow", "wide"), group=1):
    return Batch(
        "test",
        fn,
        lambda p, seeds: (p, seeds),
        list(points),
        first_seed=0,
        group=group,
        headline=lambda p, rs: 0.5 * ((s := seed_stats(r["x"] for r in rs))["ci_hi"] - s["ci_lo"]),
        headline_name="x",
    )


def test_trials_are_stored_and_skipped_on_a_rerun(tmp_path):
    notes = []
    first = run_trials(_batch(), 3, out=tmp_path, key="k", workers=1, note=notes.append)
    assert (first.ran, first.skipped) == (6, 0)
    files = sorted(p.relative_to(tmp_path) for p in (tmp_path / "trials").rglob("*.json"))
    assert [str(f) for f in files] == [
        f"trials/k/{p}/{s}.json" for p in ("narrow", "wide") for s in range(3)
    ]
    again = run_trials(_batch(), 4, out=tmp_path, key="k", workers=1, note=notes.append)
    assert (again.ran, again.skipped) == (2, 6)
    assert notes == [f"resuming {tmp_path}: 6 of 8 trials already done, skipped"]
    assert again.results["wide"][:3] == first.results["wide"]
    # the store reads back what was written, exactly
    assert TrialStore(tmp_path, "k").load()[("wide", 3)] == again.results["wide"][3]


def test_a_damaged_trial_file_is_named_and_run_again(tmp_path):
    first = run_trials(_batch(), 2, out=tmp_path, key="d", workers=1)
    damaged = tmp_path / "trials" / "d" / "wide" / "1.json"
    damaged.write_bytes(damaged.read_bytes()[:20])  # cut short, as by a full disk
    with pytest.raises(ValueError) as why:
        json.loads(damaged.read_text())
    notes = []
    again = run_trials(_batch(), 2, out=tmp_path, key="d", workers=1, note=notes.append)
    assert (again.ran, again.skipped) == (1, 3)
    assert again.results == first.results  # the trial is deterministic
    assert notes[0] == (
        f"1 trial file(s) of {tmp_path} could not be read and run again: {damaged} ({why.value})"
    )
    # the file is whole again
    assert TrialStore(tmp_path, "d").load()[("wide", 1)] == first.results["wide"][1]


def test_a_trial_file_that_is_a_directory_is_named_not_a_traceback(tmp_path):
    run_trials(_batch(), 1, out=tmp_path, key="e", workers=1)
    (tmp_path / "trials" / "e" / "wide" / "0.json").unlink()
    (tmp_path / "trials" / "e" / "wide" / "0.json").mkdir()
    store = TrialStore(tmp_path, "e")
    assert sorted(store.load()) == [("narrow", 0)]
    assert [p.name for p, _ in store.unreadable] == ["0.json"]


def test_grouped_tasks_are_one_file_each(tmp_path):
    out = run_trials(_batch(group=5), 7, out=tmp_path, key="g", workers=1)
    names = sorted(p.name for p in (tmp_path / "trials" / "g" / "wide").iterdir())
    assert names == ["0-4.json", "5-6.json"]
    assert [r["seed"] for r in out.results["wide"]] == list(range(7))


def test_seeds_are_added_until_every_interval_is_narrow(tmp_path):
    notes = []
    out = run_trials(
        _batch(), 3, workers=1, ci_width=0.5, max_seeds=40, ci_batch=4, note=notes.append
    )
    assert out.seeds["narrow"] == 3  # narrow from the start
    assert (
        3 < out.seeds["wide"] <= 40
        and (out.seeds["wide"] - 3) % 4 == 0
        or (out.seeds["wide"] == 40)
    )
    s = seed_stats(r["x"] for r in out.results["wide"])
    assert s["ci_hi"] - s["ci_lo"] < 0.5 or out.seeds["wide"] == 40
    assert out.rounds > 1 and any("more seed(s) each" in n for n in notes)
    # the same rounds when resumed from a store that holds part of them
    part = run_trials(_batch(), 3, out=tmp_path, key="c", workers=1, note=notes.append)
    assert part.ran == 6
    again = run_trials(
        _batch(), 3, out=tmp_path, key="c", workers=1, ci_width=0.5, max_seeds=40, ci_batch=4,
        note=notes.append,
    )  # fmt: skip
    assert again.seeds == out.seeds and again.results == out.results


def test_a_failed_task_does_not_stop_the_others(tmp_path):
    with pytest.raises(ValueError, match="seed 2 is bad") as info:
        run_trials(_batch(fails_on_seed_2, ("a", "b")), 4, out=tmp_path, key="f", workers=2)
    assert any("2 of 8 task(s) failed" in n for n in info.value.__notes__)
    assert any("(without --force, which starts over)" in n for n in info.value.__notes__)
    stored = TrialStore(tmp_path, "f").load()
    assert sorted(stored) == [(p, s) for p in ("a", "b") for s in (0, 1, 3)]


def test_an_interruption_carries_every_trial_done(tmp_path):
    with pytest.raises(BatchInterrupted) as info:
        run_trials(_batch(interrupts_on_seed_3, ("a",)), 5, out=tmp_path, key="i", workers=1)
    assert sorted(info.value.done) == [("a", 0), ("a", 1), ("a", 2)]
    assert sorted(TrialStore(tmp_path, "i").load()) == sorted(info.value.done)


def test_the_directory_rules(tmp_path):
    out, resuming = prepare_batch_out(tmp_path / "new", "x", False, "sweep", "h1")
    assert not resuming
    write_batch_info(out, "sweep", "h1", {})
    (out / "sweep.json").write_text("{}")
    assert prepare_batch_out(out, "x", False, "sweep", "h1") == (out, True)
    with pytest.raises(UsageError, match="holds the trials of another batch"):
        prepare_batch_out(out, "x", False, "sweep", "h2")
    with pytest.raises(UsageError, match="another batch"):
        prepare_batch_out(out, "x", False, "compare", "h1")
    assert prepare_batch_out(out, "x", True, "sweep", "h2") == (out, False)
    assert not any(out.iterdir())  # --force emptied it
    other = tmp_path / "notes"
    other.mkdir()
    (other / "a.txt").write_text("mine")
    with pytest.raises(UsageError, match="not empty"):
        prepare_batch_out(other, "x", False, "sweep", "h1")


def test_force_replaces_a_batch_that_never_finished(tmp_path):
    """A batch stopped by a failure or Ctrl-C leaves only ``batch.json`` and its trials: the
    same command resumes it, and with ``--force`` it is replaced (it is covnet's output)."""
    out, _ = prepare_batch_out(tmp_path / "b", "x", False, "compare", "h1")
    write_batch_info(out, "compare", "h1", {})
    TrialStore(out, "h1").save("p", [1], [{"v": 1.0}])
    assert sorted(p.name for p in out.iterdir()) == ["batch.json", "trials"]
    assert prepare_batch_out(out, "x", False, "compare", "h1") == (out, True)
    assert prepare_batch_out(out, "x", True, "compare", "h1") == (out, False)
    assert not any(out.iterdir())


def test_batch_options_are_checked():
    class A:
        cluster = None
        ci_width = None
        max_seeds = None
        workers = None

    a = A()
    assert batch_options(a, 4).max_seeds is None
    a.ci_width = 1.0
    assert batch_options(a, 4).max_seeds == 100
    for attr, value, msg in (
        ("ci_width", -1.0, "--ci-width"),
        ("max_seeds", 2, "--max-seeds"),
        ("cluster", "no address", "--cluster"),
    ):
        b = A()
        b.ci_width = 1.0
        setattr(b, attr, value)
        with pytest.raises(UsageError, match=msg):
            batch_options(b, 4)
    c = A()
    c.cluster, c.workers = "tcp://127.0.0.1:8786", 2
    with pytest.raises(UsageError, match="--workers"):
        batch_options(c, 4)


def test_the_progress_line():
    buf = io.StringIO()
    p = BatchProgress("sweep", stream=buf, every_s_log=0.0, where=" on tcp://h:1")
    p.add(10, 4)
    p.update(force=True)
    p.update(ran=3)
    p.update(failed=1)
    p.close()
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("[sweep] 4/10 trials (4 skipped), ")
    assert "7/10 trials (4 skipped)" in lines[1] and "ETA" in lines[1]
    assert lines[-1].endswith("1 failed on tcp://h:1")
    assert all("/s, ETA " in line for line in lines)


def test_point_keys_are_file_names():
    key = point_key({"delay_ms": 350.0, "loss": 0.1, "mode": "ci", "aware": False, "x": "a/b"})
    assert key == "delay_ms=350,loss=0.1,mode=ci,aware=false,x=a_b"


def test_seed_stats_is_the_student_t_interval():
    v = [5.5, 6.9, 21.5, 6.0]  # the four seeds
    s = seed_stats(v)
    lo, hi = sps.t.interval(0.95, 3, loc=np.mean(v), scale=sps.sem(v))
    assert (s["n"], s["mean"]) == (4, pytest.approx(np.mean(v)))
    assert s["std"] == pytest.approx(np.std(v, ddof=1))
    assert (s["ci_lo"], s["ci_hi"]) == (pytest.approx(lo), pytest.approx(hi))
    one = seed_stats([3.0])
    assert one["mean"] == 3.0 and one["std"] is None and one["ci_lo"] is None
    row = {}
    add_stats(row, "x", [1.0, math.nan, 3.0])
    assert row["x_mean"] == 2.0  # NaN left out


def test_error_stats_burn_in_and_transient():
    R, N = 4, 100
    e2 = np.full((R, N), 36.0)
    e2[2, 0] = 205.0**2  # one transient scan of one seed, as in the issue
    nees = np.full((R, N), 4.0)
    row = error_stats({}, e2, nees, burn_in=10)
    assert row["burn_in_scans"] == 10
    assert row["rmse_steady"] == pytest.approx(6.0) and row["rmse_steady_std"] == 0.0
    assert row["rmse_transient_max"] > 60 and row["rmse_transient"] > row["rmse_steady"]
    assert row["nees_steady_mean"] == 4.0
    short = error_stats({}, e2[:, :8], nees[:, :8], burn_in=10)
    assert short["burn_in_scans"] == 4  # a short run keeps its second half
    none = error_stats({}, e2, nees, burn_in=0)
    assert none["rmse_transient"] is None and none["rmse_steady"] == pytest.approx(
        np.sqrt(e2.mean(axis=1).mean())
    )


def test_per_scan_bands():
    rng = np.random.default_rng(1)
    e2 = rng.chisquare(2, (30, 50)) * 10.0
    nees = rng.chisquare(4, (30, 50))
    b = per_scan_bands(e2, nees)
    assert b["rmse"].shape == (50,)
    assert np.all(b["rmse_lo"] <= b["rmse"]) and np.all(b["rmse"] <= b["rmse_hi"])
    assert np.all(b["nees_lo"] < b["nees"]) and np.all(b["nees"] < b["nees_hi"])
    assert b["nees_band"][0] < 4.0 < b["nees_band"][1]


def test_passive_trials_in_chunks_equal_the_whole_cell(tmp_path):
    from test_passive_cli import _tiny

    from covnet.passive.config import load
    from covnet.passive.montecarlo import cell_rows, grid, run_cell, run_cell_trials

    cfg = load(_tiny(tmp_path))
    cell = grid(cfg)[0]
    methods = tuple(cfg.montecarlo.methods)
    whole = run_cell(cfg, cell, 5, methods)
    parts = run_cell_trials(cfg, cell, [0, 1], methods) + run_cell_trials(
        cfg, cell, [2, 3, 4], methods
    )
    parts = json.loads(json.dumps(parts))  # as read back from the store
    wall = "median_time_s"
    strip = lambda rows: [{k: v for k, v in r.items() if k != wall} for r in rows]  # noqa: E731
    assert strip(cell_rows(cell, parts, methods)) == strip(whole)


def test_cli_ci_width_adds_seeds_until_narrow_and_says_so(tmp_path, capsys):
    import yaml

    from covnet.cli.app import main

    repo = Path(__file__).resolve().parents[2]
    data = yaml.safe_load((repo / "configs" / "latency.yaml").read_text())
    data["scans"] = 12
    data["sweep"] = {"delay_ms": [0, 350], "loss": [0.0], "modes": ["central"],
                     "account_for_loss": [False], "seeds": 2}  # fmt: skip
    cfg = tmp_path / "s.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "o"
    argv = ["sweep", str(cfg), "--out", str(out), "--workers", "1", "--no-figures", "--json"]
    assert main([*argv, "--ci-width", "0.001", "--max-seeds", "4"]) == 0
    captured = capsys.readouterr()
    rows = [json.loads(line) for line in captured.out.splitlines()]
    assert [r["seeds"] for r in rows] == [4, 4]  # never narrow enough: the cap
    assert "2 more seed(s) each" in captured.err
    doc = json.loads((out / "sweep.json").read_text())
    assert (doc["ci_width"], doc["max_seeds"], doc["rounds"]) == (0.001, 4, 2)
    for r in rows:  # the table's interval is the one the rule looked at
        assert r["rmse_steady_ci_hi"] - r["rmse_steady_ci_lo"] >= 0.001
    # a wide enough width stops at the first round; the trials are there already
    out2 = tmp_path / "o2"
    argv2 = ["sweep", str(cfg), "--out", str(out2), "--workers", "1", "--no-figures"]
    assert main([*argv2, "--ci-width", "1e9"]) == 0
    assert json.loads((out2 / "sweep.json").read_text())["rounds"] == 1
    assert main(["plot", str(out), "--point", "delay_ms=350"]) == 0
    assert (out / "curves.png").stat().st_size > 10_000
    drawn = {f: (out / f).stat().st_mtime_ns for f in ("sweep.png", "curves.png")}
    assert main(["plot", str(out), "--point", "nope"]) == 2
    # refused before anything was drawn (it redrew sweep.png, then exited 2)
    assert {f: (out / f).stat().st_mtime_ns for f in drawn} == drawn
    # a cap that leaves room for fewer seeds than the step: the note says how many (it said
    # "2 more seed(s) each" where 1 was added)
    out3 = tmp_path / "o3"
    capsys.readouterr()
    assert main([*argv[:3], str(out3), *argv[4:], "--ci-width", "0.001", "--max-seeds", "3"]) == 0
    err = capsys.readouterr().err
    assert "1 more seed(s) each (cap 3)" in err and "2 more" not in err, err


@pytest.mark.parametrize("damage", [b"", b"[]", b"null", b"{\"command\": ", b"{}"])
def test_a_damaged_batch_json_resumes_from_its_trials_or_says_what_is_wrong(tmp_path, damage):
    """A damaged ``batch.json`` was taken for another batch's ("holds the trials of another
    batch (covnet None, ...) ... or pass --force to replace it", advice that deletes every
    trial), or ended in an AttributeError (a list, null).  Its ``trials/<hash>`` folder says
    which batch the directory holds: the batch resumes and writes it again; without that
    folder the message names the file."""
    out = tmp_path / "b"
    o, resuming = prepare_batch_out(out, "x", False, "sweep", "h1")
    write_batch_info(o, "sweep", "h1", {})
    run_trials(_batch(), 2, out=o, key="h1", workers=1)
    (o / "batch.json").write_bytes(damage)
    again, resuming = prepare_batch_out(out, "x", False, "sweep", "h1")
    assert again == out and resuming
    write_batch_info(again, "sweep", "h1", {})
    assert json.loads((o / "batch.json").read_text())["trial_hash"] == "h1"
    (o / "batch.json").write_bytes(damage)
    with pytest.raises(UsageError, match="batch.json cannot be read") as info:
        prepare_batch_out(out, "x", False, "sweep", "h2")
    assert "another batch" not in str(info.value)
    assert (o / "trials" / "h1").is_dir()


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d["results"][0].update(x=None),  # a result's field set to null
        lambda d: d["results"][0].pop("x"),  # removed
        lambda d: d.update(point="narrow"),  # another point's trial in its place
        lambda d: d.update(seeds=[9999]),  # another seed's
    ],
)
def test_a_trial_file_edited_into_another_valid_one_is_run_again_with_a_note(tmp_path, edit):
    """A trial file edited or damaged into valid JSON of another content was taken as it was
    (a null RMSE left out of the mean silently; a missing field a KeyError traceback in the
    table; a changed point or seed another trial's result): its digest now tells it."""
    first = run_trials(_batch(), 2, out=tmp_path, key="s", workers=1)
    path = tmp_path / "trials" / "s" / "wide" / "1.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    notes = []
    again = run_trials(_batch(), 2, out=tmp_path, key="s", workers=1, note=notes.append)
    assert again.results == first.results and again.ran == 1
    assert "could not be read and run again" in notes[0] and "sha256" in notes[0]


def test_a_trial_file_without_a_digest_is_read_as_before(tmp_path):
    first = run_trials(_batch(), 2, out=tmp_path, key="o", workers=1)
    for path in (tmp_path / "trials" / "o").rglob("*.json"):
        doc = json.loads(path.read_text())
        del doc["sha256"]
        path.write_text(json.dumps(doc))
    again = run_trials(_batch(), 2, out=tmp_path, key="o", workers=1)
    assert again.ran == 0 and again.results == first.results


def test_a_trial_of_other_code_is_run_again_with_a_note(tmp_path):
    """A batch begun by one covnet and resumed by another averaged both codes' trials into one
    table, exit 0, nothing said (a compare's bytes per scan 4157 where either code alone gave
    2560 or 5805: hunt 14).  Each trial file names its code; one of other code, or of none
    (an older covnet), runs again, with a note naming it, and the batch is this code's."""
    from covnet.code_identity import code_identity

    first = run_trials(_batch(), 2, out=tmp_path, key="c", workers=1)
    files = sorted((tmp_path / "trials" / "c").rglob("*.json"))
    assert {json.loads(f.read_text())["code"] for f in files} == {code_identity()}
    other, older = files[0], files[1]
    doc = json.loads(other.read_text())
    doc["code"] = "0123456789abcdef"  # the digest covers point, seeds and results only
    other.write_text(json.dumps(doc))
    doc = json.loads(older.read_text())
    del doc["code"]
    older.write_text(json.dumps(doc))
    notes = []
    again = run_trials(_batch(), 2, out=tmp_path, key="c", workers=1, note=notes.append)
    assert (again.ran, again.skipped) == (2, 2) and again.results == first.results
    note, resumed = notes
    assert note.startswith("2 trial file(s) of ") and "run again with this code" in note, note
    assert "another covnet's (0123456789abcdef; this one is " in note or "older covnet" in note
    assert "2 of 4 trials already done" in resumed, resumed
    assert {json.loads(f.read_text())["code"] for f in files} == {code_identity()}
    notes.clear()
    assert run_trials(_batch(), 2, out=tmp_path, key="c", workers=1, note=notes.append).ran == 0
    assert len(notes) == 1 and "4 of 4 trials already done" in notes[0], notes


def test_a_batch_without_its_batch_json_resumes_from_its_trials(tmp_path, capsys):
    """``batch.json`` lost, this batch's trials there: refused as "not empty", pointing to
    ``--force``, which deletes every finished trial (hunt 14).  It resumes, as a damaged
    ``batch.json`` does; another batch's trials alone are still refused."""
    out = tmp_path / "b"
    p, resuming = prepare_batch_out(out, "x", False, "sweep", "h1")
    write_batch_info(p, "sweep", "h1", {})
    run_trials(_batch(), 2, out=p, key="h1", workers=1)
    (p / "batch.json").unlink()
    with pytest.raises(UsageError, match="not empty"):
        prepare_batch_out(out, "x", False, "sweep", "h2")
    capsys.readouterr()
    p, resuming = prepare_batch_out(out, "x", False, "sweep", "h1")
    assert resuming and "has no batch.json" in capsys.readouterr().err
    write_batch_info(p, "sweep", "h1", {})
    again = run_trials(_batch(), 2, out=p, key="h1", workers=1)
    assert (again.ran, again.skipped) == (0, 4)


@pytest.mark.parametrize("damage", ["none", "batch.json cut", "batch.json gone"])
def test_a_resume_into_an_unwritable_out_is_refused_before_any_trial(
    tmp_path, monkeypatch, damage
):
    """Resuming a batch on a read-only file system ran its trials, then ended with exit 1 on
    the first trial file (a new ``--out`` is refused before anything runs: hunt 14)."""
    import errno
    import os

    out = tmp_path / "b"
    p, _ = prepare_batch_out(out, "x", False, "mc", "h1")
    write_batch_info(p, "mc", "h1", {})
    run_trials(_batch(), 1, out=p, key="h1", workers=1)
    if damage == "batch.json cut":
        (p / "batch.json").write_text('{"comm')
    elif damage == "batch.json gone":
        (p / "batch.json").unlink()
    real = Path.write_bytes

    def write_bytes(self, data):  # root writes into a chmod 0555 directory all the same
        if self.name.startswith(".covnet-write-check"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", write_bytes)
    with pytest.raises(UsageError, match="cannot write there"):
        prepare_batch_out(out, "x", False, "mc", "h1")
