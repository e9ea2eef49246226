"""``covnet compare --policies``: each row's numbers against direct in-process runs (the
oracle), the paired seeds, ``--budget match``, the refusals, the files and the CLI end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from covnet.batches.stats import seed_stats
from covnet.cli.app import main
from covnet.covariance_control import compare_policies as cp
from covnet.covariance_control.config import from_dict, load, normalised
from covnet.covariance_control.model import build_model
from covnet.covariance_control.simulate import run_metric, run_targets, shared_trajectory
from covnet.errors import UsageError

MULTI = Path(__file__).resolve().parents[2] / "configs" / "multitarget.yaml"
POLICIES = ["covariance_control", "all_on", "random"]


def _short(path, scans):
    data = normalised(load(path))
    data["scans"] = scans
    for tg in data.get("targets") or ():
        tg["manoeuvres"] = []  # the turn is beyond a short run
    return from_dict(data)


@pytest.fixture(scope="module")
def paper30(paper_path):
    return _short(paper_path, 30)


@pytest.fixture(scope="module")
def matched(paper30):
    """``--budget match`` over 3 seeds, in this process."""
    return cp.compare_outcome(paper30, POLICIES, "spectral", 3, budget="match", workers=1)


def _with(sc, policy, budget, seed):
    data = normalised(sc)
    data["allocation"] = {**data["allocation"], "policy": policy, "budget": budget}
    data["seed"] = seed
    return from_dict(data)


def test_rows_equal_direct_runs(paper30, matched):
    """The oracle: each row from the runs covnet run makes, seed by seed."""
    rows, outcome, plan = matched
    burn = paper30.evaluation.burn_in_scans  # 10 of 30 scans
    for row in rows:
        policy, budget = row["policy"], row["budget"]
        assert row["runs"] == 3 and row["seeds"] == [paper30.seed + i for i in range(3)]
        rmse, nees, f, share, sensors = [], [], [], [], []
        for seed in row["seeds"]:
            sc = _with(paper30, policy, budget, seed)
            model = build_model(sc)
            traj = shared_trajectory(model)
            run = run_metric(sc, "spectral", model)
            err = run.x_est - traj.truth
            e2 = err[:, 0] ** 2 + err[:, 2] ** 2
            rmse.append(np.sqrt(e2[burn:].mean()))
            nees.append(run.nees[burn:].mean())
            f.append(run.value.mean())
            trP = np.trace(run.P_post, axis1=1, axis2=2)
            trPd = np.array([np.trace(model.desired(k)) for k in range(1, sc.scans + 1)])
            share.append(np.mean(trP <= trPd))
            sensors.append(run.enabled.sum())
        assert row["rmse_steady_mean"] == pytest.approx(np.mean(rmse), rel=1e-12)
        s = seed_stats(rmse)
        assert (row["rmse_steady_ci_lo"], row["rmse_steady_ci_hi"]) == pytest.approx(
            (s["ci_lo"], s["ci_hi"]), rel=1e-12
        )
        assert row["mean_nees"] == pytest.approx(np.mean(nees), rel=1e-12)
        assert row["mean_f"] == pytest.approx(np.mean(f), rel=1e-12)
        assert row["share_trP_le_trPd"] == pytest.approx(np.mean(share), rel=1e-12)
        assert row["sensor_scans"] == pytest.approx(np.mean(sensors))
        assert row["sensors_per_scan"] == pytest.approx(np.mean(sensors) / sc.scans)
        # the central structure: a command, a measurement per sensor on, a track, a status
        assert row["messages_per_scan"] == pytest.approx(3 + row["sensors_per_scan"])
        assert row["nees_verdict"] in ("consistent", "conservative", "optimistic")


def test_paired_differences_from_covariance_control_equal_the_direct_runs(paper30, matched):
    """The policies share their seeds: each row gives the paired difference from covariance
    control (per seed, then its 95 % t interval), from the same direct runs as the oracle
    above; the table says which intervals contain 0."""
    from scipy import stats as sps

    rows, _, _ = matched
    burn = paper30.evaluation.burn_in_scans

    def per_seed(policy, budget):
        rmse, on = [], []
        for seed in [paper30.seed + i for i in range(3)]:
            sc = _with(paper30, policy, budget, seed)
            model = build_model(sc)
            run = run_metric(sc, "spectral", model)
            err = run.x_est - shared_trajectory(model).truth
            rmse.append(np.sqrt((err[:, 0] ** 2 + err[:, 2] ** 2)[burn:].mean()))
            on.append(run.enabled.sum() / sc.scans)
        return np.array(rmse), np.array(on)

    ref_rmse, ref_on = per_seed("covariance_control", None)
    by = {r["policy"]: r for r in rows}
    assert "vs_reference" not in by["covariance_control"]
    for policy in ("all_on", "random"):
        r = by[policy]
        rmse, on = per_seed(policy, r["budget"])
        for name, d in (("rmse_steady", rmse - ref_rmse), ("sensors_per_scan", on - ref_on)):
            m = d.mean()
            assert r[f"{name}_vs_reference_mean"] == pytest.approx(m, rel=1e-9, abs=1e-12)
            if d.std() > 0:
                lo, hi = sps.t.interval(0.95, 2, loc=m, scale=sps.sem(d))
                assert (r[f"{name}_vs_reference_ci_lo"], r[f"{name}_vs_reference_ci_hi"]) == (
                    pytest.approx((lo, hi), rel=1e-9)
                )
    table = cp.format_table(rows)
    assert "paired against covariance_control" in table
    line = next(x for x in table.splitlines() if x.strip().startswith("all_on  RMSE m"))
    lo, hi = (
        by["all_on"]["rmse_steady_vs_reference_ci_lo"],
        by["all_on"]["rmse_steady_vs_reference_ci_hi"],
    )
    assert line.rstrip().split("sensors/scan")[0].rstrip(", ").endswith(" =") == (lo <= 0 <= hi)


def test_budget_match_is_covariance_controls_mean_sensors(matched):
    rows, _, plan = matched
    by = {r["policy"]: r for r in rows}
    K = round(by["covariance_control"]["sensors_per_scan"])
    assert plan.matched["K"] == K and plan.budgets == {
        "covariance_control": None,
        "all_on": None,
        "random": K,
    }
    assert by["random"]["budget"] == K and by["random"]["budget_source"] == "match"
    assert by["random"]["sensors_per_scan"] == K  # random draws exactly K
    assert by["all_on"]["sensors_per_scan"] == 8 and by["all_on"]["budget"] is None


def test_policies_are_paired_and_the_allocation_ignores_the_seed(matched):
    """Covariance control and all_on decide from covariances only: the same sensors for every
    seed (no spread in sensors or f); the seeds differ in the estimates."""
    rows, outcome, plan = matched
    for p in ("covariance_control", "all_on"):
        trials = outcome.results[plan.point(p)]
        assert len({tuple(t["sensors_scan"]) for t in trials}) == 1
        assert len({t["pos_err2_scan"][-1] for t in trials}) == 3


def test_budget_given_and_refusals(paper30):
    assert cp.budget_for(paper30, "random", 4) == 4
    assert cp.budget_for(paper30, "greedy_information", 4) == 4  # a reward policy gets K too
    assert cp.budget_for(paper30, "all_on", 4) is None
    with pytest.raises(UsageError, match="round_robin .*needs a budget K.*--budget"):
        cp.budget_for(paper30, "round_robin", None)
    with pytest.raises(UsageError, match="unknown policy 'best'"):
        cp.parse_policies("random,best")
    with pytest.raises(UsageError, match="random named twice"):
        cp.parse_policies("random,random")
    with pytest.raises(UsageError, match="--budget"):
        cp.parse_budget("0")
    assert cp.parse_budget(" match") == "match" and cp.parse_budget("3") == 3
    # a baseline scores the sensors' information: not under covariance intersection
    data = normalised(paper30)
    data["fusion"] = {**data["fusion"], "mode": "ci"}
    with pytest.raises(UsageError, match="--policies: random cannot run"):
        cp.check(from_dict(data), ["random"], 3)


def test_a_budget_the_config_cannot_honour_is_refused_naming_it(paper30):
    """A budget below the required sensors was accepted and every run ended in a traceback;
    one above ``max_active`` ran ``max_active`` sensors while the table said the budget."""
    from covnet.config import ConfigError

    data = normalised(paper30)
    data["allocation"] = {**data["allocation"], "policy": "random", "budget": 1,
                          "required": ["S1", "S2"]}  # fmt: skip
    with pytest.raises(ConfigError) as e:
        from_dict(data)
    assert any(p == "allocation.budget" and "2 required" in m for p, m in e.value.problems)
    data = normalised(paper30)
    data["allocation"] = {**data["allocation"], "max_active": 3}
    with pytest.raises(UsageError, match=r"allocation.budget: 5: more than allocation.max_active"):
        cp.check(from_dict(data), ["random"], 5)


def test_trial_points_resume_when_a_policy_is_added(paper30, tmp_path):
    first, o1, _ = cp.compare_outcome(paper30, ["all_on"], "abs_trace", 2, workers=1, out=tmp_path)
    rows, o2, _ = cp.compare_outcome(
        paper30, ["all_on", "round_robin"], "abs_trace", 2, budget=2, workers=1, out=tmp_path
    )
    assert (o1.ran, o2.ran, o2.skipped) == (2, 2, 2)
    assert rows[0] == first[0]
    assert cp.point_of("round_robin", 2) == "policy=round_robin,budget=2"
    assert cp.trial_key(paper30, "abs_trace") == cp.trial_key(
        _with(paper30, "random", 3, paper30.seed), "abs_trace"
    )


def test_budget_match_names_a_damaged_trial_file_once(paper30, tmp_path, capsys):
    """``--budget match`` runs its batch in two parts (the reference, then the others): a
    damaged trial file of another policy was named by both parts, two identical lines."""

    def compare():
        policies = ["covariance_control", "all_on"]
        return cp.compare_outcome(
            paper30, policies, "abs_trace", 2, budget="match", workers=1, out=tmp_path
        )

    compare()
    damaged = sorted((tmp_path / "trials").rglob("policy=all_on/*.json"))[-1]
    damaged.write_bytes(damaged.read_bytes()[:20])  # cut short, as by a full disk
    capsys.readouterr()
    _, again, _ = compare()
    err = capsys.readouterr().err
    assert err.count("could not be read") == 1, err
    assert str(damaged) in err and (again.ran, again.skipped) == (1, 3)


def test_targets_rows_equal_direct_runs():
    sc = _short(MULTI, 12)
    rows, outcome, plan = cp.compare_outcome(
        sc, ["all_on", "round_robin"], "abs_trace", 2, budget=4, workers=1
    )
    from covnet.covariance_control import targets
    from covnet.covariance_control.results import target_trajectory, targets_summary

    for row in rows:
        ospa, gospa, f, share = [], [], [], []
        for seed in row["seeds"]:
            s2 = _with(sc, row["policy"], row["budget"], seed)
            tm = targets.build(s2)
            traj = target_trajectory(tm)
            summ = targets_summary(run_targets(s2, "abs_trace", tm), traj, tm)
            ospa.append(summ["mean_ospa"])
            gospa.append(summ["mean_gospa"])
            f.append(np.mean(summ["value"]))
            tr = [
                np.array(b["trace_P"]) <= np.array(b["trace_Pd"]) for b in summ["targets"].values()
            ]
            share.append(np.mean(tr))
        assert row["targets"] == 3
        assert row["mean_ospa"] == pytest.approx(np.mean(ospa), rel=1e-12)
        assert row["mean_gospa"] == pytest.approx(np.mean(gospa), rel=1e-12)
        assert row["mean_f"] == pytest.approx(np.mean(f), rel=1e-12)
        assert row["share_trP_le_trPd"] == pytest.approx(np.mean(share), rel=1e-12)
        assert row["messages_per_scan"] == pytest.approx(2 + 3 + row["sensors_per_scan"])
    assert rows[1]["sensors_per_scan"] == 4


def test_cli_refusals(paper_path, tmp_path, capsys):
    base = ["compare", str(paper_path), "--out", str(tmp_path / "x")]
    for extra, needle in (
        (["--policies", "random"], "random (K sensors drawn"),
        (["--policies", "random", "--modes", "central"], "not allowed with argument"),
        (["--budget", "3"], "--budget: the policies' budget"),
        (["--policies", "random", "--budget", "few"], "--budget: a number of sensors"),
        (["--policies", "all_on", "--ci-width", "1"], "--ci-width: --policies compares"),
    ):
        with pytest.raises(SystemExit) if "--modes" in extra else _nothing():
            assert main([*base, *extra]) == 2
        assert needle in capsys.readouterr().err, extra
    assert not (tmp_path / "x").exists()  # refused before any directory is made


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_cli_end_to_end(paper_path, tmp_path, monkeypatch):
    """``python -m covnet compare ... --policies ... --budget match --runs 3``: the files."""
    cfg = tmp_path / "paper30.yaml"
    cfg.write_text(paper_path.read_text().replace("scans: 100", "scans: 30"))
    out = tmp_path / "cmp"
    argv = [sys.executable, "-m", "covnet", "compare", str(cfg), "--policies"]
    argv += ["covariance_control,all_on,random", "--budget", "match", "--runs", "3"]
    argv += ["--workers", "2", "--out", str(out)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "K*: matched to covariance control" in done.stdout
    doc = json.loads((out / "compare.json").read_text())
    assert doc["compared"] == "policies" and doc["budget"] == "match"
    K = doc["budget_match"]["K"]
    rows = {r["policy"]: r for r in doc["rows"]}
    assert list(rows) == ["covariance_control", "all_on", "random"]
    assert K == round(rows["covariance_control"]["sensors_per_scan"]) == rows["random"]["budget"]
    assert all(r["runs"] == 3 for r in rows.values())
    assert (out / "compare.csv").read_text().startswith("policy,budget,")
    for fig in ("pareto.png", "curves.png"):
        assert (out / fig).stat().st_size > 10_000, fig
    (out / "pareto.png").unlink()
    titles = []
    real = cp.make_figure
    monkeypatch.setattr(cp, "make_figure", lambda o, r, t: titles.append(t) or real(o, r, t))
    assert main(["plot", str(out)]) == 0  # redrawn from compare.json and curves.npz
    assert (out / "pareto.png").is_file()
    # with the command's own title (it was a generic one)
    want = "paper: allocation policies, metric spectral, 3 paired seeds"
    assert titles == [want] and cp.figure_title(doc) == want


def test_pareto_names_every_policy_without_overprinting(tmp_path, monkeypatch):
    """``--budget match`` puts every budgeted policy on one vertical line (the same K), a few
    metres apart: the names (expected_kl over round_robin, in a 7-policy comparison of
    ``configs/large_multitarget.yaml``) were printed over each other.  Every policy is named
    once, and no two names (nor a name and the title) overlap."""
    import matplotlib.pyplot as plt

    from covnet.covariance_control.compare_policies import make_figure

    ys = {"covariance_control": 10.47, "all_on": 5.31, "random": 13.73, "round_robin": 10.64,
          "greedy_information": 3.92, "uncertainty_reward": 3.94, "expected_kl": 8.55}  # fmt: skip
    rows = []
    for name, y in ys.items():
        x = 64.0 if name == "all_on" else 24.9
        K = None if name in ("all_on", "covariance_control") else 25
        rows.append({"policy": name, "budget": K, "sensors_per_scan_mean": x,
                     "sensors_per_scan_ci_lo": x - 2, "sensors_per_scan_ci_hi": x + 2,
                     "mean_ospa": y, "mean_ospa_mean": y, "mean_ospa_ci_lo": y - 20,
                     "mean_ospa_ci_hi": y + 20})  # fmt: skip
    texts: list[tuple[str, object]] = []
    save = plt.Figure.savefig

    def spy(fig, *args, **kwargs):
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        for ax in fig.axes:
            pieces = [t for t in ax.texts if t.get_text()]
            leg = ax.get_legend()
            if leg is not None:
                pieces += [t for t in leg.get_texts() if t.get_text()]
            texts.extend((t.get_text(), t.get_window_extent(r)) for t in pieces)
            texts.append(("<title>", ax.title.get_window_extent(r)))
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    make_figure(tmp_path, rows, "large_multitarget: allocation policies")
    names = [t for t, _ in texts if t != "<title>"]
    for name in ys:
        assert sum(name in t for t in names) == 1, (name, names)
    for i, (a, ba) in enumerate(texts):
        for b, bb in texts[i + 1 :]:
            assert not ba.overlaps(bb), (a, b)


def test_the_curves_figure_starts_its_axes_at_zero(tmp_path, monkeypatch):
    """OSPA and the sensors on are >= 0; a few seeds' t bands reach below (not drawn)."""
    import matplotlib.figure

    from covnet.covariance_control import compare_policies as cp

    data = {
        "points": np.array(["policy=a", "policy=b"]),
        "seeds": np.array([3, 3]),
        "ospa": np.array([[5.0, 9.0], [4.0, 6.0]]),
        "ospa_lo": np.array([[-20.0, 1.0], [-2.0, 2.0]]),
        "ospa_hi": np.array([[30.0, 17.0], [10.0, 10.0]]),
        "sensors": np.array([[1.0, 2.0], [1.0, 1.0]]),
        "sensors_lo": np.array([[-1.0, 0.5], [0.0, 0.0]]),
        "sensors_hi": np.array([[3.0, 3.5], [2.0, 2.0]]),
    }
    seen = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: seen.append(fig))
    cp.curves_figure(tmp_path, data, [0, 1])
    (fig,) = seen
    assert [ax.get_ylim()[0] for ax in fig.axes] == [0.0, 0.0]
    assert fig.axes[0].get_ylim()[1] >= 30.0


def test_targets_info_traffic_counts_the_local_tracks_the_sensors_send():
    """With ``targets:`` and ``fusion.mode: info`` every enabled sensor sends its local track
    of the target it dwelt on (posterior and prior: :mod:`sensors.covariance`), not its
    returns; the comparison counted the returns, and info looked no dearer than central (2.3
    times fewer bytes than ``covnet up`` sent).  (The bytes, message for message, against the
    nodes' own: ``tests/integration/test_multitarget_up.py``.)"""
    from covnet.covariance_control import targets

    data = normalised(_short(MULTI, 6))
    data["fusion"] = {**data["fusion"], "mode": "info"}
    trial = cp.run_trial(data, "random", 4, 2026, "spectral")
    sc = _with(from_dict(data), "random", 4, 2026)
    tm = targets.build(sc)
    run = run_targets(sc, "spectral", tm)
    K = len(run.assignment)
    assert trial["bytes_per_scan"] == cp.targets_traffic_per_scan(
        tm, run.assignment, run.returns, True
    )["bytes_per_scan"]
    assert trial["messages_per_scan"] == 2 + len(tm.target_ids) + run.enabled.sum() / K
    # a local track (two estimates and covariances) outweighs a dwell's few returns
    data["fusion"]["mode"] = "central"
    central = cp.run_trial(data, "random", 4, 2026, "spectral")
    assert trial["bytes_per_scan"] > 1.5 * central["bytes_per_scan"]


def test_the_mean_f_interval_is_cut_at_zero_as_its_neighbours():
    """``f`` is a distance (every registered metric is >= 0), but a policy whose f varies
    widely over two seeds printed ``575 ± 2e+03`` (``mean_f_ci_lo`` -1427) beside NEES, share,
    RMSE and bytes cut to their range."""
    from covnet.core.metrics import METRICS

    rng = np.random.default_rng(1)
    for fn in (m.fn for m in METRICS.values()):  # >= 0 on random pairs and either way round
        for _ in range(20):
            A, B = (M @ M.T + 0.1 * np.eye(4) for M in rng.normal(size=(2, 4, 4)))
            assert fn(A, B) >= 0.0 and fn(B, A) >= 0.0
    trial = {
        "targets": 1, "pos_err2_scan": [1.0] * 4, "nees_scan": [4.0] * 4,
        "sensors_scan": [3] * 4, "within_scan": [1.0] * 4,
        "messages_per_scan": 6.0, "bytes_per_scan": 900.0,
    }  # fmt: skip
    trials = [{**trial, "seed": s, "value_scan": [v] * 4} for s, v in ((1, 10.0), (2, 1140.0))]
    row = cp.summarise("random", 4, trials, 1)
    assert row["mean_f"] == 575.0
    assert row["mean_f_ci_lo"] == 0.0 and row["mean_f_ci_hi"] > 1140.0
    assert "575 [0, " in cp.format_table([row])
