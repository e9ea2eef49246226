"""The in-process mobile run end to end: covnet run, results, figure, determinism in and across
processes, failed sensors, too little capacity, unobservable targets, Monte Carlo, bench."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet import kinds
from covnet.cli.app import main
from covnet.config import ConfigError
from covnet.errors import UsageError
from covnet.mobile import bench
from covnet.mobile.commands import bench_run, mc_run
from covnet.mobile.config import from_dict, load
from covnet.mobile.model import build_model, decide, initial_tracks
from covnet.mobile.montecarlo import aggregate, run_seeds
from covnet.mobile.plots import FIGURE
from covnet.mobile.results import summarise
from covnet.mobile.simulate import TIMING_FIELDS, run

REPO = Path(__file__).resolve().parents[2]
MOBILE = REPO / "configs" / "mobile.yaml"


def short(scans: int = 12, **changes) -> dict:
    data = yaml.safe_load(MOBILE.read_text())
    data.update(scans=scans, **changes)
    return data


def write_cfg(tmp_path: Path, data: dict, name: str = "mobile-short.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def deterministic(r) -> dict[str, np.ndarray]:
    return {k: v for k, v in r.arrays().items() if k not in TIMING_FIELDS}


def assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def run_cmd(cfg_path: Path, out: Path, solver: str | None, seed: int | None) -> int:
    """``covnet run CFG --out OUT [--solver S] [--seed N]``."""
    argv = ["run", str(cfg_path), "--out", str(out)]
    argv += ["--solver", solver] if solver else []
    argv += ["--seed", str(seed)] if seed is not None else []
    return main(argv)


@pytest.mark.parametrize("solver", ["lp", "milp"])
def test_run_cmd_end_to_end(tmp_path, capsys, solver):
    cfg_path = write_cfg(tmp_path, short(12))
    out = tmp_path / "run"
    assert run_cmd(cfg_path, out, solver, 3) == 0
    for f in ("summary.json", "arrays.npz", "config.json", "run.json", FIGURE):
        assert (out / f).is_file(), f
    s = json.loads((out / "summary.json").read_text())
    assert (s["kind"], s["seed"], s["solver"], s["scans"]) == ("mobile", 3, solver, 12)
    assert set(s["targets"]) == {"T1", "T2", "T3"}
    t1 = s["targets"]["T1"]
    for key in ("rmse_position_m", "rmse_position_second_half_m", "missed_detection_rate",
                "missed_detection_rate_first_half", "missed_detection_rate_second_half",
                "miss_given_assigned"):  # fmt: skip
        assert np.isfinite(t1[key]), key
    assert s["platform_travel_m"]["S3"] == 0.0  # the far corner never moves
    assert s["usage_cost_total"] > 0
    opt = s["optimality"]
    assert opt["decisions"] == 12 and len(opt["per_decision"]["J_star"]) == 12
    assert opt["max_gap"] >= -1e-9
    assert "decision_time_s" not in s  # wall-clock facts go to run.json
    info = json.loads((out / "run.json").read_text())
    assert set(info["decision_time_s"]) == {"cost_tensor", "solver", "comparison"}
    stored = json.loads((out / "config.json").read_text())  # what the run used, options included
    assert (stored["solver"], stored["seed"]) == (solver, 3)
    with np.load(out / "arrays.npz") as arr:
        assert arr["modes"].shape == (12, 4) and arr["x_est"].shape == (13, 3, 4)
    text = capsys.readouterr().out
    assert "run directory:" in text and "optimality:" in text and "figure:" in text
    assert "decision time (median)" in text
    assert run_cmd(cfg_path, out, solver, 3) == 2
    assert "not empty" in capsys.readouterr().err


def test_run_cmd_bad_config_raises_config_error(tmp_path):
    bad = short(5)
    bad["sensors"][0]["speed_mps"] = -2.0
    with pytest.raises(ConfigError) as info:
        kinds.load(write_cfg(tmp_path, bad))
    assert ("sensors[0].speed_mps", "must be >= 0, got -2.0") in info.value.problems
    kind, cfg = kinds.load(write_cfg(tmp_path, short(5)))
    with pytest.raises(UsageError, match="--solver: unknown solver"):
        kinds.apply_options(kind, cfg, "short", solver="simplex")


_CHILD = """
import sys, numpy as np, yaml
from covnet.mobile.config import from_dict
from covnet.mobile.simulate import TIMING_FIELDS, run
r = run(from_dict(yaml.safe_load(open(sys.argv[1]))))
np.savez(sys.argv[2], **{k: v for k, v in r.arrays().items() if k not in TIMING_FIELDS})
"""


def test_determinism_in_process_and_across_processes(tmp_path):
    data = short(15, seed=4)
    cfg = from_dict(data)
    a = deterministic(run(cfg))
    b = deterministic(run(cfg))
    assert_same(a, b)
    cfg_path = write_cfg(tmp_path, data)
    out = tmp_path / "child.npz"
    subprocess.run([sys.executable, "-c", _CHILD, str(cfg_path), str(out)], check=True, cwd=REPO)
    with np.load(out) as child:
        assert_same(a, {k: child[k] for k in child.files})
    assert summarise(cfg, run(cfg)) == summarise(cfg, run(cfg))  # no wall-clock inside


def test_lp_and_milp_share_the_truth_and_the_start():
    data = short(6, compare_exact=False)
    lp = run(from_dict({**data, "solver": "lp"}))
    milp = run(from_dict({**data, "solver": "milp"}))
    np.testing.assert_array_equal(lp.truth, milp.truth)
    np.testing.assert_array_equal(lp.x_est[0], milp.x_est[0])
    assert np.all(np.isnan(lp.J_star)) and np.all(lp.conflicts >= 0)


def test_a_failed_sensor_leaves_the_problem():
    model = build_model(load(MOBILE))
    x, P = initial_tracks(model)
    alive = np.array([True, False, True, True])
    step = decide(model, x, P, model.sensors.position, alive=alive)
    d = step.decision
    assert step.problem.N == 3
    assert np.all(d.assign >= 0) and np.all(d.assign != 1)
    assert d.modes[1] == 0
    # nobody alive: every target unobserved, every sensor stays
    step = decide(model, x, P, model.sensors.position, alive=np.zeros(4, dtype=bool))
    assert np.all(step.decision.assign == -1) and np.all(step.decision.modes == 0)


def test_too_little_capacity_reports_unobserved_targets_and_goes_on():
    data = short(8)
    for s, k in zip(data["sensors"], [1, 0, 0, 0], strict=True):
        s["capacity"] = k
    cfg = from_dict(data)
    r = run(cfg)
    assert np.all((r.assign >= 0).sum(axis=1) == 1)
    assert np.all(r.modes[:, 1:] == 0)
    s = summarise(cfg, r)
    assert s["overall"]["unobserved_scans"] == 2 * 8
    assert s["overall"]["missed_detection_rate"] >= 2 / 3
    assert s["optimality"]["max_gap"] <= 1e-9  # capacity 1: the LP is exact


def test_an_unobservable_target_is_still_covered():
    data = short(6)
    data["targets"].append({"id": "FAR", "x0": [1.0e5, 0.0, 1.0e5, 0.0], "sigma_a_mps2": 0.05})
    cfg = from_dict(data)
    r = run(cfg)
    assert np.all(r.assign[:, 3] >= 0)
    assert np.all(r.pd_true[:, 3] < 1e-12) and not r.detected[:, 3].any()
    s = summarise(cfg, r)
    assert s["targets"]["FAR"]["missed_detection_rate"] == 1.0
    assert np.isfinite(s["targets"]["FAR"]["rmse_position_m"])


def test_montecarlo_pool_equals_in_process(tmp_path, capsys):
    cfg = from_dict(short(5, compare_exact=True))
    seen = []
    inline = run_seeds(cfg, [0, 1], workers=1, progress=lambda d, n, s: seen.append((d, n, s)))
    pooled = run_seeds(cfg, [0, 1], workers=2)
    strip = [{k: v for k, v in r.items() if k != "decision_time_s"} for r in (*inline, *pooled)]
    assert strip[0] == strip[2] and strip[1] == strip[3] and strip[0] != strip[1]
    assert [s for _, _, s in seen] == [0, 1] and seen[-1][:2] == (2, 2)
    agg = aggregate(inline)
    assert agg["optimality"]["decisions"] == 10
    assert (
        agg["overall"]["missed_detection_rate"]["min"]
        <= (agg["overall"]["missed_detection_rate"]["mean"])
    )
    out = tmp_path / "mc"
    assert mc_run(load(write_cfg(tmp_path, short(4))), out, 2, True, workers=1) == 0
    doc = json.loads((out / "montecarlo.json").read_text())
    assert doc["seeds"] == [0, 1] and len(doc["per_seed"]) == 2
    captured = capsys.readouterr()
    assert "[mc] 2/2 trials" in captured.err and "Monte Carlo:" in captured.out
    calls: list[tuple[int, int, int]] = []
    cb = lambda d, n, s: calls.append((d, n, s))  # noqa: E731
    assert mc_run(load(write_cfg(tmp_path, short(3))), tmp_path / "mc2", 1, cb, workers=1) == 0
    assert calls == [(1, 1, 0)] and capsys.readouterr().err == ""


def test_bench_rows_and_command(monkeypatch, capsys):
    row = bench.bench_case(4, 3, 2, problems=1, repeat=1, milp=True)
    for key in ("cost_ms", "lp_ms", "decision_ms", "lp_highs_ms", "milp_ms"):
        assert row[key] > 0, key
    assert row["closed_form_ms"] is None and row["lp_post_worse"] in (0, 1)
    original = bench.run
    monkeypatch.setattr(bench, "run", lambda **kw: original(sensors=(4,), targets=(3,), **kw))
    assert bench_run(False, problems=1, repeat=1) == 0
    text = capsys.readouterr().out
    assert "goal: whole decision" in text and "goal: closed form" in text
    assert bench_run(True, milp=False, problems=1, repeat=1) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) == 3 and "goals" in lines[-1] and lines[0]["milp_ms"] is None


def test_covnet_cli_routes_mobile_configs(tmp_path, capsys):
    """`covnet run FILE --solver` and `covnet mc` reach the mobile runner; `--metric` on a
    mobile file is a usage error (for `covnet up` too: tests/integration/test_mobile_up.py)."""
    cfg_path = write_cfg(tmp_path, short(8))
    assert (
        main(
            ["run", str(cfg_path), "--solver", "milp", "--out", str(tmp_path / "r"), "--no-figures"]
        )
        == 0
    )
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["solver"] == "milp"
    assert main(["run", str(cfg_path), "--metric", "svd", "--out", str(tmp_path / "x")]) == 2
    capsys.readouterr()
    assert main(["up", str(cfg_path), "--metric", "svd", "--out", str(tmp_path / "u")]) == 2
    assert "--metric: a mobile scenario does not take this option" in capsys.readouterr().err


def test_mc_json_lines_and_no_figures(tmp_path, capsys):
    from covnet.cli.app import main

    out = tmp_path / "mc"
    cfg = write_cfg(tmp_path, short(4))
    argv = ["mc", str(cfg), "--trials", "2", "--workers", "1", "--out", str(out)]
    assert main([*argv, "--json", "--no-figures"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rows[-1]["target"] == "overall" and all(r["seeds"] == 2 for r in rows)
    assert not list(out.glob("*.png"))


def test_the_mc_figure_cuts_its_axes_at_the_quantities_limits(tmp_path, monkeypatch):
    """Two seeds' Student intervals drew an RMSE axis down to -20 m and a missed-detection
    rate above 1 (configs/mobile.yaml, --trials 2)."""
    import matplotlib.figure

    from covnet.mobile import plots

    def seed(rmse: float, rate: float) -> dict:
        b = {"rmse_position_m": rmse, "rmse_position_second_half_m": rmse,
             "missed_detection_rate": rate, "missed_detection_rate_second_half": rate}  # fmt: skip
        return {"target_ids": ["T1"], "targets": {"T1": b}, "overall": b}

    doc = {"scenario": "m", "solver": "lp", "per_seed": [seed(1.0, 0.05), seed(30.0, 0.95)]}
    (tmp_path / "montecarlo.json").write_text(json.dumps(doc))
    seen = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: seen.append(fig))
    plots.mc_figure(tmp_path)
    (fig,) = seen
    rmse, rate = fig.axes[:2]
    assert rmse.get_ylim()[0] == 0.0 and rmse.get_ylim()[1] > 100.0  # the bands' tops shown
    assert rate.get_ylim() == (0.0, 1.0)


def test_a_comparison_whose_milp_timed_out_is_left_out_and_counted(tmp_path, monkeypatch, capsys):
    """An exact solve that hit its time limit was compared as if it were J*: 'LP + post-step
    worse in 0/5, gap 0 %' where the solved MILPs gave 3 of 5 worse.  Such a decision has no
    J* now: the optimality figures leave it out and say how many they left out."""
    from dataclasses import replace

    from covnet.core.mobile import decision as dec_module

    real, calls = dec_module.solve_milp, []

    def second_times_out(mp, options):
        sol = real(mp, options)
        calls.append(1)
        return replace(sol, status=1, message="Time limit reached.") if len(calls) == 2 else sol

    monkeypatch.setattr(dec_module, "solve_milp", second_times_out)
    out = tmp_path / "run"
    assert main(["run", str(write_cfg(tmp_path, short(scans=4))), "--out", str(out)]) == 0
    opt = json.loads((out / "summary.json").read_text())["optimality"]
    assert opt["decisions"] == 3 and opt["exact_not_optimal"] == 1
    assert opt["per_decision"]["J_star"][1] is None and opt["per_decision"]["gap"][1] is None
    assert None not in opt["per_decision"]["J_star"][::2]
    assert "(1 more left out: the MILP proved no optimum" in capsys.readouterr().out


def _every_milp_times_out(monkeypatch):
    from dataclasses import replace

    from covnet.core.mobile import decision as dec_module

    real = dec_module.solve_milp
    monkeypatch.setattr(
        dec_module,
        "solve_milp",
        lambda mp, options: replace(real(mp, options), status=1, message="Time limit reached."),
    )


def test_a_run_whose_every_milp_timed_out_still_says_how_many(tmp_path, monkeypatch, capsys):
    """Every compared decision timed out: summary.json had no optimality block at all, so the
    count of those left out was lost and the printout said nothing."""
    _every_milp_times_out(monkeypatch)
    out = tmp_path / "run"
    assert main(["run", str(write_cfg(tmp_path, short(scans=3))), "--out", str(out)]) == 0
    opt = json.loads((out / "summary.json").read_text())["optimality"]
    assert opt["decisions"] == 0 and opt["exact_not_optimal"] == 3
    assert opt["mean_gap"] is None and opt["per_decision"]["J_star"] == [None] * 3
    said = capsys.readouterr().out
    assert "no MILP proved an optimum within its time limit (3 compared decisions" in said, said


def test_mc_pools_the_seeds_that_solved_and_counts_every_time_out(tmp_path, monkeypatch):
    """One seed whose compared decisions all timed out removed the optimality summary of the
    whole batch."""
    from covnet.mobile.montecarlo import aggregate, run_seed, split_timing

    data = short(scans=3)
    solved = run_seed(data, 1, None)
    _every_milp_times_out(monkeypatch)
    timed_out = run_seed(data, 2, None)
    assert timed_out["optimality"]["decisions"] == 0
    alone = aggregate(split_timing([solved])[0])["optimality"]
    both = aggregate(split_timing([solved, timed_out])[0])["optimality"]
    assert both["decisions"] == alone["decisions"] == 3
    assert both["mean_gap"] == alone["mean_gap"] and both["exact_not_optimal"] == 3
    assert aggregate(split_timing([timed_out])[0])["optimality"]["mean_gap"] is None
