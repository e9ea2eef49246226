"""``covnet mc`` and ``covnet sweep`` (over the search weight λ) of a surveillance config, end to
end through the CLI: intervals over the seeds, the same rows whatever the workers, and the
sweep's reductions (λ = 0 never searches)."""

from __future__ import annotations

import json

import yaml
from test_surveillance_run import base

from covnet.cli.app import main


def small(tmp_path, **over):
    d = base(scans=8)
    d.update(over)
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def test_mc_gives_intervals_over_the_seeds(tmp_path, capsys):
    cfg = small(tmp_path)
    out = tmp_path / "mc"
    args = ["mc", str(cfg), "--trials", "3", "--out", str(out), "--no-figures"]
    assert main(args) == 0
    doc = json.loads((out / "montecarlo.json").read_text())
    assert doc["surveillance"] is True and doc["seeds"] == [7, 8, 9]
    blk = doc["aggregate"]["spectral"]
    g = blk["gospa_mean"]
    assert g["n"] == 3 and g["ci95"][0] <= g["mean"] <= g["ci95"][1]
    assert len(blk["gospa_per_scan"]["mean"]) == 8
    assert "95 % confidence" in capsys.readouterr().out
    # the first seed's row is covnet run's
    run = tmp_path / "run"
    assert main(["run", str(cfg), "--out", str(run), "--no-figures"]) == 0
    s = json.loads((run / "summary.json").read_text())["metrics"]["spectral"]
    assert doc["per_seed"][0]["metrics"]["spectral"]["gospa_mean"] == s["gospa_mean"]


def test_the_mc_figure_starts_its_axes_at_zero(tmp_path, monkeypatch):
    """GOSPA and a count of tracks are >= 0; a few seeds' Student intervals reach below 0
    (configs/surveillance.yaml, 3 seeds: to -600 m), and the figure drew its axes down there."""
    import matplotlib.figure

    from covnet.covariance_control import surveillance_plots

    band = {"mean": [200.0, 50.0, 400.0], "ci95_low": [-300.0, 20.0, -600.0],
            "ci95_high": [700.0, 80.0, 1400.0]}  # fmt: skip
    count = {"mean": [0.0, 1.0, 2.0], "ci95_low": [-1.0, 0.0, 0.5], "ci95_high": [1.0, 2.0, 3.5]}
    blk = {"gospa_per_scan": band, "n_confirmed_per_scan": count}
    doc = {"scenario": "s", "seeds": [1, 2, 3], "aggregate": {"spectral": blk}}
    seen = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: seen.append(fig))
    surveillance_plots.mc_figure(tmp_path, doc)
    (fig,) = seen
    assert [ax.get_ylim()[0] for ax in fig.axes] == [0.0, 0.0]
    assert fig.axes[0].get_ylim()[1] >= 1400.0  # the top of every band still shown


def test_sweep_over_the_search_weight(tmp_path, capsys):
    cfg = small(tmp_path, sweep={"search_weight": [0.0, 30.0], "seeds": 2})
    out = tmp_path / "sw"
    assert main(["sweep", str(cfg), "--out", str(out)]) == 0
    doc = json.loads((out / "sweep.json").read_text())
    rows = {r["search_weight"]: r for r in doc["rows"]}
    assert set(rows) == {0.0, 30.0}
    assert rows[0.0]["search_share"]["mean"] == 0.0  # λ = 0 never searches
    assert rows[0.0]["time_to_confirm_mean"]["n"] == 0  # nothing is ever found
    assert rows[30.0]["search_share"]["mean"] > 0.0
    assert (out / "sweep.png").exists() and (out / "sweep.csv").exists()
    assert "search.weight" in capsys.readouterr().out


def test_a_sweep_without_the_weight_grid_says_what_to_give(tmp_path, capsys):
    cfg = small(tmp_path)
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "x")]) == 2
    assert "search_weight" in capsys.readouterr().err


def test_compare_modes_says_surveillance_is_central_only(tmp_path, capsys):
    """It advised ``covnet mc --fusion info``, which a surveillance config refuses."""
    cfg = small(tmp_path)
    assert main(["compare", str(cfg), "--modes", "central,info", "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "centrally only" in err and "--fusion info" not in err and "--policies" in err


def test_policies_side_by_side_with_search(tmp_path, capsys):
    """covnet compare --policies on a surveillance config: every policy on the same seeds; a
    baseline's spare sensors search (so every policy finds targets)."""
    cfg = small(tmp_path)
    out = tmp_path / "cmp"
    args = ["compare", str(cfg), "--policies", "covariance_control,greedy_information,random",
            "--budget", "2", "--runs", "2", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    doc = json.loads((out / "compare.json").read_text())
    rows = {r["point"]: r for r in doc["rows"]}
    assert set(rows) == {"policy=covariance_control", "policy=greedy_information,budget=2",
                         "policy=random,budget=2"}  # fmt: skip
    for r in rows.values():
        assert r["seeds"] == 2 and r["search_share"]["mean"] > 0.0
        assert r["gospa_mean"]["n"] == 2
    assert "greedy_information" in capsys.readouterr().out


def test_sweep_json_prints_rows_only(tmp_path, capsys):
    cfg = small(tmp_path, sweep={"search_weight": [10.0], "seeds": 2})
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "j"), "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["search_weight"] == 10.0


def test_metric_option_is_honoured_and_checked(tmp_path, capsys):
    """``--metric`` on a surveillance sweep or policy comparison: it ran the config's metrics
    whatever was asked (``--metric nonsense`` exited 0); ``--workers 0`` and ``--max-seeds``
    without ``--ci-width`` were taken by the surveillance sweep alone."""
    cfg = small(
        tmp_path,
        allocation={"metrics": ["spectral", "kl"]},
        sweep={"search_weight": [10.0], "seeds": 1},
    )
    out = tmp_path / "sw"
    assert main(["sweep", str(cfg), "--out", str(out), "--metric", "kl", "--no-figures"]) == 0
    doc = json.loads((out / "sweep.json").read_text())
    assert [r["metric"] for r in doc["rows"]] == ["kl"]
    cmp = tmp_path / "cmp"
    args = ["compare", str(cfg), "--policies", "covariance_control,random", "--budget", "2",
            "--runs", "2", "--metric", "kl", "--out", str(cmp), "--no-figures"]  # fmt: skip
    assert main(args) == 0
    doc = json.loads((cmp / "compare.json").read_text())
    assert {r["metric"] for r in doc["rows"]} == {"kl"}
    capsys.readouterr()
    for bad, word in ((["--metric", "nonsense"], "--metric"), (["--workers", "0"], "--workers"),
                      (["--max-seeds", "3"], "--max-seeds")):  # fmt: skip
        x = tmp_path / "x"
        assert main(["sweep", str(cfg), "--out", str(x), *bad]) == 2, bad
        assert word in capsys.readouterr().err
        assert not x.exists()


def test_a_changed_config_of_the_same_name_is_another_batch(tmp_path, capsys):
    """The batch was keyed by the scenario's name: the same command on a changed config ran
    into the earlier batch's directory and replaced its results, without ``--force``."""
    grid = {"search_weight": [10.0], "seeds": 1}
    cfg = small(tmp_path, sweep=grid)
    out = tmp_path / "sw"
    assert main(["sweep", str(cfg), "--out", str(out), "--no-figures"]) == 0
    before = (out / "sweep.json").read_bytes()
    assert main(["sweep", str(cfg), "--out", str(out), "--no-figures"]) == 0  # resumes
    assert "already done" in capsys.readouterr().err
    changed = small(tmp_path, sweep=grid, scans=6)
    assert main(["sweep", str(changed), "--out", str(out), "--no-figures"]) == 2
    assert "holds the trials of another batch" in capsys.readouterr().err
    assert (out / "sweep.json").read_bytes() == before


def test_plot_redraws_surveillance_sweeps_and_comparisons(tmp_path, capsys):
    """``covnet plot`` of a surveillance sweep or policy comparison directory: exit 2 ("was it
    edited?", KeyError) on untouched directories; the comparison drew no figure at all."""
    cfg = small(tmp_path, sweep={"search_weight": [0.0, 10.0], "seeds": 1})
    sw, cmp = tmp_path / "sw", tmp_path / "cmp"
    assert main(["sweep", str(cfg), "--out", str(sw), "--no-figures"]) == 0
    args = ["compare", str(cfg), "--policies", "covariance_control,random", "--budget", "2",
            "--runs", "2", "--out", str(cmp)]  # fmt: skip
    assert main(args) == 0
    assert (cmp / "compare.png").is_file()
    (cmp / "compare.png").unlink()
    for d, fig in ((sw, "sweep.png"), (cmp, "compare.png")):
        capsys.readouterr()
        assert main(["plot", str(d)]) == 0, capsys.readouterr().err
        assert (d / fig).is_file()
        assert main(["plot", str(d), "--point", "x"]) == 2
        assert "no per-point curves" in capsys.readouterr().err


def test_run_mcap_of_a_surveillance_config_is_refused_before_the_run(tmp_path, capsys):
    """``covnet run --mcap`` of a surveillance config was refused once the whole run was done,
    leaving its results, a ``run.mcap`` of no message and a ``run.json`` without a status."""
    cfg = small(tmp_path)
    out = tmp_path / "run"
    assert main(["run", str(cfg), "--out", str(out), "--mcap", "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert "--mcap: a surveillance run's scene is recorded by covnet up" in err, err
    assert not out.exists()


def test_a_missing_budget_advises_only_what_is_taken(tmp_path, capsys):
    """A surveillance comparison of ``random`` without a budget advised ``--budget match``,
    which it then refuses."""
    cfg = small(tmp_path)
    out = str(tmp_path / "c")
    argv = ["compare", str(cfg), "--policies", "random", "--runs", "2", "--out", out]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "give --budget K" in err and "match" not in err, err


def test_intervals_of_nonnegative_scalars_stop_at_zero():
    """Every scalar of a surveillance batch is >= 0; with 2 seeds the tracked RMSE's interval
    read 14.6 [-6.6, 35.7] m."""
    from covnet.covariance_control.surveillance_batch import SCALARS, aggregate

    def row(v):
        return {"metrics": {"m": {**dict.fromkeys(SCALARS, v), "gospa": [v], "n_confirmed": [v]}}}

    blk = aggregate([row(1.0), row(30.0)])["m"]
    for k in SCALARS:
        lo, hi = blk[k]["ci95"]
        # a share within [0, 1] (its values here are not: the ends show the cut)
        assert lo == 0.0 and (hi == 1.0 if k == "search_share" else hi > 30.0), (k, blk[k])
    assert blk["rmse_tracked"]["mean"] == 15.5  # the mean itself untouched
    for k in ("gospa_per_scan", "n_confirmed_per_scan"):  # the per-scan bands too
        assert blk[k]["ci95_low"][0] == 0.0 and blk[k]["ci95_high"][0] > 0.0, (k, blk[k])


def test_many_target_mc_intervals_stop_at_zero():
    """The many-target Monte Carlo's scalars and per-scan curves (OSPA, traces, rates, NEES,
    sensors) are >= 0: a heavy-tailed trace (one seed's lost track) gave a band from -300 to
    700 in its figure."""
    from covnet.covariance_control.montecarlo import _SCALARS, _TARGET_SCALARS, aggregate

    def row(v):
        t = {**dict.fromkeys(_TARGET_SCALARS, v), "nees_n": 1, "nees_sum": v}
        t |= {"trace_P": [v, 1.0], "sensors_per_scan": [v, 1.0]}
        return {"metrics": {"m": {**dict.fromkeys(_SCALARS, v), "ospa": [v], "targets": {"T": t}}}}

    blk = aggregate([row(1.0), row(30.0)])["m"]
    tb = blk["targets"]["T"]
    for k, b in [*((k, blk[k]) for k in _SCALARS), *((k, tb[k]) for k in _TARGET_SCALARS)]:
        hi = b["ci95"][1]  # a rate within [0, 1] (its values here are not: the end shows the cut)
        assert b["ci95"][0] == 0.0 and b["mean"] == 15.5, b
        assert hi == 1.0 if k == "allocation_rate" else hi > 30.0, (k, b)
    for b in (blk["ospa_per_scan"], tb["trace_P_per_scan"], tb["sensors_per_scan"]):
        assert b["ci95_low"][0] == 0.0 and b["ci95_high"][0] > 30.0, b
    assert tb["trace_P_per_scan"]["ci95_low"][1] == 1.0  # no spread: the value itself


def test_policies_are_paired_against_covariance_control(tmp_path, capsys):
    """``compare --policies`` of a surveillance config gave each policy's intervals only (two
    overlapping intervals decide nothing): each other policy's row now holds its paired
    differences from covariance control, seed by seed, here against ``covnet run`` of each
    policy and seed."""
    import math

    from covnet.batches.stats import t_half_width

    cfg = small(tmp_path)
    out = tmp_path / "cmp"
    args = ["compare", str(cfg), "--policies", "covariance_control,random", "--budget", "2",
            "--runs", "3", "--out", str(out), "--no-figures"]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    doc = json.loads((out / "compare.json").read_text())
    rows = {r["point"]: r for r in doc["rows"]}
    assert rows["policy=covariance_control"].get("vs_reference") is None
    row = rows["policy=random,budget=2"]
    assert row["vs_reference"] == "covariance_control"
    summaries = {}
    for policy in ("covariance_control", "random"):
        for seed in (7, 8, 9):
            d = yaml.safe_load(cfg.read_text())
            d["seed"] = seed
            d["allocation"] = {**d.get("allocation", {}), "policy": policy,
                               "budget": None if policy == "covariance_control" else 2}  # fmt: skip
            if policy != "covariance_control":  # a baseline takes no search keys
                for k in ("search", "gap", "time_limit_s", "node_limit"):
                    d["allocation"].pop(k, None)
            p = tmp_path / f"{policy}-{seed}.yaml"
            p.write_text(yaml.safe_dump(d))
            run = tmp_path / f"run-{policy}-{seed}"
            assert main(["run", str(p), "--out", str(run), "--no-figures"]) == 0
            summaries[policy, seed] = json.loads((run / "summary.json").read_text())["metrics"][
                "spectral"
            ]
    for key in ("gospa_mean", "false_tracks", "missed_targets"):
        d = [summaries["random", s][key] - summaries["covariance_control", s][key]
             for s in (7, 8, 9)]  # fmt: skip
        got = row[f"{key}_vs_reference"]
        assert got["n"] == 3 and math.isclose(got["mean"], sum(d) / 3, rel_tol=1e-12, abs_tol=1e-12)
        mean = sum(d) / 3
        sd = math.sqrt(sum((x - mean) ** 2 for x in d) / 2)
        half = float(t_half_width(sd, 3))
        assert got["ci95"] == [mean - half, mean + half] or math.isclose(
            got["ci95"][1] - got["ci95"][0], 2 * half, rel_tol=1e-9, abs_tol=1e-12
        )
    csv = (out / "compare.csv").read_text().splitlines()
    assert "gospa_mean_vs_reference_mean" in csv[0].split(",")
    assert "paired against covariance_control" in printed
