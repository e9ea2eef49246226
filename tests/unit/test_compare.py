"""``covnet compare``: the table's numbers follow from the runs (info == central, message
counts from the enabled sets), the NEES verdicts, the files, the CLI."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from covnet.cli.app import main
from covnet.covariance_control.compare import Trial, compare, modes, scenario_for, summarise
from covnet.covariance_control.config import from_dict, load, normalised


@pytest.fixture(scope="module")
def short(paper_path):
    data = normalised(load(paper_path))
    data["scans"] = 50
    return from_dict(data)


@pytest.fixture(scope="module")
def rows(short):
    return {r["mode"]: r for r in compare(short, modes(), "abs_trace", 2, graph="ring", workers=1)}


def test_info_row_equals_central(rows):
    a, b = rows["central"], rows["info"]
    for key in ("allocation_rate", "sensors_per_scan", "messages_per_scan"):
        assert a[key] == b[key], key
    assert b["rmse_position"] == pytest.approx(a["rmse_position"], rel=1e-9)
    assert b["mean_nees"] == pytest.approx(a["mean_nees"], rel=1e-9)
    assert b["bytes_per_scan"] > a["bytes_per_scan"]  # a local track carries two estimates


def test_message_counts_follow_from_the_enabled_sets(rows):
    # central: command + one measurement per enabled sensor + track + status
    c = rows["central"]
    assert c["messages_per_scan"] == pytest.approx(3 + c["sensors_per_scan"])
    # peer: one local track per enabled node + a track and a status from each of the 8 nodes
    p = rows["peer-info"]
    assert p["messages_per_scan"] == pytest.approx(16 + p["sensors_per_scan"])
    # ring: each local track reaches its 2 neighbours; each status 8 receivers
    assert p["deliveries_per_scan"] == pytest.approx(2 * p["sensors_per_scan"] + 8 + 64)


def test_ci_is_conservative_and_bands_are_ordered(rows):
    for r in rows.values():
        lo, hi = r["nees_band_95"]
        glo, ghi = r["nees_mean_ci_95"]
        assert lo < 4.0 < hi and glo < r["mean_nees"] < ghi
        assert 0.0 <= r["nees_inside_fraction"] <= 1.0
    assert rows["ci"]["mean_nees"] < rows["central"]["mean_nees"]
    assert rows["central"]["nees_verdict"] != "optimistic"


@pytest.mark.parametrize(
    ("level", "verdict"), [(2.0, "conservative"), (4.0, "consistent"), (7.0, "optimistic")]
)
def test_nees_verdict_from_the_run_averages(short, level, verdict):
    rng = np.random.default_rng(0)
    trials = [
        Trial("central", r, level * rng.chisquare(4, 50) / 4, np.ones(50), np.ones((50, 8), bool))
        for r in range(30)
    ]
    row = summarise(short, "central", trials, None)
    assert row["nees_verdict"] == verdict
    assert row["mean_nees"] == pytest.approx(level, rel=0.1)


@pytest.mark.parametrize("burn_in", [0, 4, 10, 30])
def test_nees_columns_start_after_the_burn_in(short, burn_in):
    """``mean_nees``, its verdict and band share started at scan 11 whatever
    ``evaluation.burn_in_scans`` was, beside ``nees_steady_*`` from the burn-in: two "mean NEES
    after the burn-in" in one row (4.54 against 4.28 with a burn-in of 0)."""
    rng = np.random.default_rng(1)
    trials = [
        Trial("central", r, rng.chisquare(4, 50) * np.linspace(3, 1, 50) / 4, np.ones(50),
              np.ones((50, 8), bool))
        for r in range(5)
    ]  # fmt: skip
    row = summarise(short, "central", trials, None, burn_in=burn_in)
    nees = np.stack([t.nees for t in trials])
    b = min(burn_in, 25)
    assert row["burn_in_scans"] == b
    assert row["mean_nees"] == pytest.approx(nees[:, b:].mean(), rel=1e-12)
    assert row["mean_nees"] == pytest.approx(row["nees_steady_mean"], rel=1e-12)


def test_scenario_for_each_mode(short):
    assert scenario_for(short, "ci-fast").fusion.ci_objective == "fast"
    sc = scenario_for(short, "peer-ci", graph="star", seed=7)
    assert (sc.fusion.mode, sc.fusion.rule, sc.fusion.peer.graph, sc.seed) == (
        "peer",
        "ci",
        "star",
        7,
    )
    with pytest.raises(ValueError, match="unknown fusion mode"):
        scenario_for(short, "gossip")


def test_cli_compare_writes_table_and_figure(paper_path, tmp_path, capsys):
    out = tmp_path / "cmp"
    args = ["compare", str(paper_path), "--modes", "central,ci", "--runs", "2", "--workers", "1"]
    assert main([*args, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "verdict" in text and "central" in text
    doc = json.loads((out / "compare.json").read_text())
    assert [r["mode"] for r in doc["rows"]] == ["central", "ci"] and doc["runs"] == 2
    with (out / "compare.csv").open() as f:
        assert [r["mode"] for r in csv.DictReader(f)] == ["central", "ci"]
    assert (out / "compare.png").stat().st_size > 10_000
    (out / "compare.png").unlink()
    assert main(["plot", str(out)]) == 0  # redrawn from compare.json alone
    assert (out / "compare.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--modes", "central,gossip"], "--modes: unknown mode 'gossip'"),
        (["--runs", "1"], "--runs: at least 2"),
        (["--metric", "nope"], "nope"),
    ],
)
def test_cli_compare_bad_options(paper_path, tmp_path, capsys, extra, needle):
    rc = main(["compare", str(paper_path), "--out", str(tmp_path / "x"), *extra])
    assert rc == 2
    assert needle in capsys.readouterr().err


def test_modes_of_different_seed_counts_each_get_their_own_band_and_the_title_the_range(
    short, tmp_path, saved_figures
):
    """With --ci-width the modes run different counts: the table gave the first mode's chi-
    square band ("of 9 runs") for every mode, and compare.png's title the first round's seed
    count ("3 seeds" where the modes ran 9, 6 and 9)."""
    from scipy.stats import chi2

    from covnet.covariance_control import compare as cmp

    (three,) = compare(short, ["central"], "abs_trace", 3, workers=1)
    (two,) = compare(short, ["ci"], "abs_trace", 2, workers=1)
    rows = [three, two]
    for r in rows:
        R = r["runs"]
        assert r["nees_band_95"] == pytest.approx(chi2.ppf([0.025, 0.975], 4 * R) / R)
    text = cmp.format_table(rows)
    for r in rows:
        lo, hi = r["nees_band_95"]
        assert f"[{lo:.2f}, {hi:.2f}] of {r['runs']} runs" in text, text
    figs = saved_figures(cmp)
    cmp.make_figure(tmp_path, rows, cmp.figure_title({"scenario": "paper", "runs": 3}))
    (fig,) = figs
    assert fig._suptitle.get_text().endswith(", 2-3 seeds a mode"), fig._suptitle.get_text()
    nees_ax = fig.axes[2]
    bands = sorted(
        (round(p.get_y(), 9), round(p.get_y() + p.get_height(), 9))
        for p in nees_ax.patches
        if p.get_alpha() == 0.35
    )
    assert bands == sorted(
        (round(r["nees_band_95"][0], 9), round(r["nees_band_95"][1], 9)) for r in rows
    )


def test_the_grand_mean_nees_interval_stops_at_zero():
    """compare.json's nees_mean_ci_95 (and compare.png's bar) reached -0.39 where the row's
    other NEES interval, printed in the table, was cut at 0."""
    from covnet.covariance_control.compare import nees_consistency

    nees = np.array([[1.0] * 20, [9.0] * 20])  # two runs far apart: a wide t interval
    r = nees_consistency(nees, 0)
    assert r["nees_mean_ci_95"][0] == 0.0 and r["nees_mean_ci_95"][1] > 9.0
    assert r["mean_nees"] == 5.0 and r["nees_verdict"] == "consistent"
