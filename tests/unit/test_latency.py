"""Latency experiments (covnet.covariance_control.latency_sim, covnet.covariance_control.sweep):
ideal links are the plain run, the counts add up, out-of-sequence re-filtering equals in-order
processing, loss-aware allocation, determinism, the sweep's files and the CLI."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from covnet.batches.stats import seed_stats
from covnet.cli.app import main
from covnet.config import ConfigError
from covnet.covariance_control.config import from_dict, load, normalised
from covnet.covariance_control.decentral_sim import run_centre
from covnet.covariance_control.fusion_rules import measurement_from_track
from covnet.covariance_control.latency_sim import delivery_probabilities, run_latency
from covnet.covariance_control.model import build_model, truth_trajectory
from covnet.covariance_control.simulate import run_metric
from covnet.covariance_control.sweep import (
    SPREAD,
    grid,
    link_for,
    point_scenario,
    sweep,
    sweep_outcome,
)


def _sc(paper_path, scans=40, mode="central", **latency):
    data = normalised(load(paper_path))
    data["scans"] = scans
    data["fusion"]["mode"] = mode
    data["network"]["latency"] = {**data["network"]["latency"], **latency}
    return from_dict(data)


def _link(delay_s=0.0, loss=0.0, kind="exponential"):
    return link_for(1000 * delay_s, kind, loss)


def test_ideal_links_are_exactly_the_plain_run(paper_path):
    sc = _sc(paper_path, scans=100)
    plain = run_metric(sc, "spectral")
    run, counts = run_latency(sc, "spectral")
    np.testing.assert_array_equal(run.enabled, plain.enabled)
    np.testing.assert_array_equal(run.x_est, plain.x_est)  # bit for bit
    np.testing.assert_array_equal(run.P_post, plain.P_post)
    c = counts.as_dict()
    assert c["measured"] == c["on_time"] == c["commanded"] == plain.enabled.sum()
    assert c["lost"] == c["late_refiltered"] == c["late_dropped"] == c["deadline_misses"] == 0


@pytest.mark.parametrize("mode", ["info", "ci"])
def test_ideal_links_decentralized_equal_the_plain_run(paper_path, mode):
    sc = _sc(paper_path, mode=mode)
    plain = run_centre(sc, "abs_trace")
    run, _ = run_latency(sc, "abs_trace")
    np.testing.assert_array_equal(run.enabled, plain.enabled)
    assert np.max(np.abs(run.x_est - plain.x_est)) / np.max(np.abs(plain.x_est)) < 1e-12


@pytest.mark.parametrize("late", ["oosm", "drop"])
@pytest.mark.parametrize("mode", ["central", "info", "ci"])
def test_every_measurement_is_accounted_for(paper_path, late, mode):
    link = _link(0.4, 0.15)
    sc = _sc(paper_path, mode=mode, uplink=link, downlink=_link(0.2, 0.05), late=late)
    _, counts = run_latency(sc, "spectral")
    c = counts.as_dict()
    # loss reduces the fused measurements by exactly the counted number
    fused = c["on_time"] + c["late_refiltered"]
    assert fused == c["measured"] - c["lost"] - c["late_dropped"]
    assert sum(counts.per_scan_fused) == c["on_time"]
    assert c["lost"] > 0 and c["late_refiltered"] + c["late_dropped"] > 0
    if late == "drop" or mode == "ci":
        assert c["late_refiltered"] == 0
    else:
        assert c["late_refiltered"] > 0


def test_refiltered_late_measurements_give_the_in_order_filter(paper_path):
    """Every measurement 1.5 periods late (deadline 0.8 T): scan k's measurements arrive before
    scan k+1's deadline and are re-filtered into scan k, so the estimate at scan k+1's deadline
    (nothing on time) is the prediction of the in-order posterior of scan k, bit for bit."""
    from covnet.covariance_control.model import (
        fuse,
        initial_estimate,
        measure,
        predict_step,
        truth_trajectory,
    )

    sc = _sc(paper_path, scans=30, uplink=_link(1.5, kind="constant"), late="oosm")
    run, counts = run_latency(sc, "spectral")
    assert counts.on_time == 0 and counts.late_refiltered == counts.measured - run.enabled[-1].sum()
    model = build_model(sc)
    truth = truth_trajectory(model)
    est = initial_estimate(model, sc.filter.initial_estimate)
    for i in range(sc.scans - 1):
        pred = predict_step(model, est)
        meas = [
            (j, measure(model, j, i + 1, truth[i]), model.R[j])
            for j in np.flatnonzero(run.enabled[i])
        ]
        est = fuse(model, pred, meas)  # in order: scan i+1 with all its measurements
        nxt = predict_step(model, est)
        np.testing.assert_array_equal(run.x_est[i + 1], nxt.x)
        np.testing.assert_array_equal(run.P_post[i + 1], nxt.P)


def test_measurement_recovered_from_a_local_track(paper_path):
    from covnet.core.gaussian import Gaussian
    from covnet.core.kalman import update

    model = build_model(_sc(paper_path))
    prior = Gaussian(np.array([1.0, 2.0, 3.0, 4.0]), np.diag([50.0, 4.0, 60.0, 5.0]))
    z = np.array([10.0, -20.0])
    post = update(prior, z, model.H, model.R[2])
    z2, R2 = measurement_from_track(post, prior)
    np.testing.assert_allclose(z2, z, rtol=1e-9)
    np.testing.assert_allclose(R2, model.R[2], rtol=1e-9)


def test_loss_aware_allocation_is_the_allocation_with_noisier_sensors(paper_path):
    """Scaling J_j by p_j is allocating as if R_j were R_j / p_j: the two decide alike."""
    from covnet.covariance_control.latency_sim import loss_aware_model
    from covnet.covariance_control.model import decide

    sc = _sc(paper_path, uplink=_link(0.0, 0.5), downlink=_link(0.0, 0.0))
    p = delivery_probabilities(sc)
    assert np.allclose(p, 0.5, atol=0.02)
    model = build_model(sc)
    aware = loss_aware_model(model, p)
    np.testing.assert_allclose(aware.gains, p[:, None, None] * model.gains)
    data = normalised(sc)
    for j, s in enumerate(data["sensors"]):
        s["sigma_x_m"] /= np.sqrt(p[j])
        s["sigma_y_m"] /= np.sqrt(p[j])
    noisy = build_model(from_dict(data))
    P_seq = run_metric(sc, "spectral").P_pred
    for k in range(3, 40):
        a = decide(aware, P_seq[k - 1], k, "spectral")
        b = decide(noisy, P_seq[k - 1], k, "spectral")
        assert a.subset == b.subset, k


def test_deterministic_for_a_seed(paper_path):
    sc = _sc(paper_path, uplink=_link(0.3, 0.1), downlink=_link(0.2, 0.1))
    a, ca = run_latency(sc, "spectral")
    b, cb = run_latency(sc, "spectral")
    np.testing.assert_array_equal(a.x_est, b.x_est)
    assert ca.as_dict() == cb.as_dict()


def test_missed_command_policies(paper_path):
    """Half the commands are lost; a sensor notices the gap at its next command and fills the
    missed scans by its policy (those measurements are late by construction)."""
    down = _link(0.0, 0.5)
    out = {}
    for policy in ("keep_last", "off", "on"):
        _, c = run_latency(_sc(paper_path, downlink=down, missed_command=policy), "spectral")
        out[policy] = c.as_dict()
        assert c.commands_missed > 50
    assert out["off"]["fallback_sent"] == 0
    assert out["on"]["fallback_sent"] == out["on"]["commands_missed"]
    assert 0 < out["keep_last"]["fallback_sent"] < out["keep_last"]["commands_missed"]
    for c in out.values():  # every fallback measurement is late: re-filtered or dropped
        assert c["late_refiltered"] + c["late_dropped"] >= c["fallback_sent"]
        # so none is fused on time: unsolicited (covnet up's network.json too) counted the
        # fallbacks sent in covnet run, fused on time in covnet up
        assert c["unsolicited"] == 0


def test_bad_latency_config_names_the_field(paper_path):
    data = normalised(load(paper_path))
    data["network"]["latency"] = {"uplink": {"loss": 1.5}}
    with pytest.raises(ConfigError, match=r"network.latency.uplink"):
        from_dict(data)
    data["network"]["latency"] = {"uplink": {"delay": {"kind": "constant", "value_s": "0.1"}}}
    with pytest.raises(ConfigError, match=r"delay.value_s must be a number"):
        from_dict(data)
    data["network"]["latency"] = {"sensors": {"S9": {}}}
    with pytest.raises(ConfigError, match=r"network.latency.sensors.S9"):
        from_dict(data)
    # a delay without its kind: the field named, not a TypeError from the constructor
    data["network"]["latency"] = {"uplink": {"delay": {"value_s": 0.1}}}
    with pytest.raises(ConfigError, match=r"network.latency.uplink.*delay.kind is required"):
        from_dict(data)
    data["network"]["latency"] = {"downlink": {"delay": {}}}
    with pytest.raises(ConfigError, match=r"network.latency.downlink.*delay.kind is required"):
        from_dict(data)


def test_zero_point_of_a_sweep_is_the_plain_run(paper_path):
    sc = _sc(paper_path, scans=30)
    data = normalised(sc)
    data["sweep"] = {
        "delay_ms": [0, 300],
        "loss": [0.0],
        "modes": ["central"],
        "account_for_loss": [False],
        "seeds": 2,
    }
    sc = from_dict(data)
    rows = sweep(sc, metric="spectral", workers=1)
    assert [r["delay_ms"] for r in rows] == [0.0, 300.0]
    zero = rows[0]
    err2 = []
    for r in range(2):  # the plain in-process run of each seed
        point = point_scenario(sc, grid(sc.sweep)[0], sc.seed + r)
        e = run_metric(point, "spectral").x_est - truth_trajectory(build_model(point))
        err2.append(np.mean(e[:, 0] ** 2 + e[:, 2] ** 2))
    assert zero["rmse_position"] == pytest.approx(float(np.sqrt(np.mean(err2))), rel=1e-12)
    assert zero["deadline_miss_rate"] == zero["late"] == zero["lost"] == 0
    assert rows[1]["late"] > 0


def test_sweep_rows_give_the_spread_of_every_drawn_count(paper_path):
    """Every quantity the sweep figure draws has its 95 % interval over seeds: the deadline
    misses, late and lost measurements as well as the errors (they vary with the seed's delays
    and losses); each the t interval of the per-seed values."""
    sc = _sc(paper_path, scans=30)
    data = normalised(sc)
    data["sweep"] = {
        "delay_ms": [300],
        "loss": [0.2],
        "modes": ["central"],
        "account_for_loss": [False],
        "seeds": 4,
    }
    rows, outcome = sweep_outcome(from_dict(data), metric="spectral", workers=1)
    (row,) = rows
    runs = outcome.results[row["point"]]
    for k in ("deadline_miss_rate", "late", "lost"):
        values = [r[k] for r in runs]
        assert len(set(values)) > 1, k  # a spread to show
        want = seed_stats(values, SPREAD[k])
        assert row[f"{k}_mean"] == row[k] == pytest.approx(want["mean"], rel=1e-12)
        assert (row[f"{k}_ci_lo"], row[f"{k}_ci_hi"]) == (want["ci_lo"], want["ci_hi"])
        assert row[f"{k}_ci_lo"] < row[k] < row[f"{k}_ci_hi"]


def test_cli_sweep_writes_table_and_figure(paper_path, tmp_path, capsys):
    cfg = tmp_path / "s.yaml"
    import yaml

    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 20
    data["sweep"] = {
        "delay_ms": [0, 200],
        "loss": [0.0, 0.2],
        "modes": ["central", "ci"],
        "account_for_loss": [False],
        "seeds": 1,
    }
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "sw"
    assert main(["sweep", str(cfg), "--out", str(out), "--workers", "1"]) == 0
    assert "late/run" in capsys.readouterr().out
    doc = json.loads((out / "sweep.json").read_text())
    assert len(doc["rows"]) == 8 and doc["seeds"] == 1
    with (out / "sweep.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 8
    assert (out / "sweep.png").stat().st_size > 20_000
    assert main(["sweep", str(cfg), "--out", str(out), "--seeds", "0", "--force"]) == 2


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_sweep_grid_point_its_config_refuses_stops_the_sweep_before_any_run(
    paper_path, tmp_path, capsys, workers
):
    """``search: greedy`` (what configs/large.yaml ships) and the default grid's ``ci``: half
    the grid ran, then exit 2 on one worker, a traceback and exit 1 on two, never naming the
    point nor the key to change."""
    import yaml

    data = yaml.safe_load(paper_path.read_text())
    data["allocation"]["search"] = "greedy"
    cfg = tmp_path / "g.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "sw"
    argv = ["sweep", str(cfg), "--seeds", "1", "--workers", workers, "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert "grid point mode=ci cannot run (24 of the 48 points)" in err, err
    assert "allocation.search: greedy needs" in err and "sweep.modes without ci" in err, err
    assert not out.exists()
    from covnet import api
    from covnet.errors import UsageError

    with pytest.raises(UsageError, match="grid point mode=ci cannot run"):
        api.sweep(str(cfg), seeds=1, workers=1, out=out)
    assert not out.exists()


def test_check_refuses_a_sweep_mode_the_policy_refuses(paper_path, tmp_path, capsys):
    """``covnet check`` said 0 for a config whose own ``sweep.modes`` holds ``ci``, which its
    ``allocation.policy: random`` refuses (as it refuses ``fusion.mode: ci``).  The default
    grid is not the config's to refuse: a ``sweep:`` section of seeds alone stopped ``covnet
    run`` and ``check`` of the shipped large.yaml (search greedy: hunt 13); ``covnet sweep``
    refuses its points before any run."""
    import yaml

    data = yaml.safe_load(paper_path.read_text())
    data["allocation"].update(policy="random", budget=4)
    data["sweep"] = {"modes": ["central", "info", "ci"], "account_for_loss": [False], "seeds": 1}
    with pytest.raises(ConfigError) as err:
        from_dict(data)
    assert [p for p, _ in err.value.problems] == ["sweep.modes[2]"], err.value.problems
    assert err.value.problems[0][1].startswith("ci: allocation.policy: a baseline such as random ")
    cfg = tmp_path / "r.yaml"
    cfg.write_text(yaml.safe_dump(data))
    assert main(["check", str(cfg)]) == 2
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "sw")]) == 2
    assert capsys.readouterr().err.count("sweep.modes[2]: ci: allocation.policy") == 2
    data["sweep"]["modes"] = ["central", "info"]  # both information forms: accepted
    sc = from_dict(data)
    assert from_dict(normalised(sc)).sweep == sc.sweep  # its defaults spelled out: the same
    # the default grids (modes central and ci; account_for_loss false and true) are accepted
    # by the config, and refused by covnet sweep before any run or file
    data["sweep"] = {"seeds": 1}
    sc = from_dict(data)
    assert from_dict(normalised(sc)).sweep == sc.sweep
    cfg.write_text(yaml.safe_dump(data))
    assert main(["check", str(cfg)]) == 0
    capsys.readouterr()
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "sw2")]) == 2
    err_text = capsys.readouterr().err
    assert "mode=ci" in err_text and "sweep.modes" in err_text, err_text
    assert not (tmp_path / "sw2").exists()


def test_a_sweep_section_of_seeds_alone_leaves_covnet_run_alone(tmp_path, paper_path, capsys):
    """large.yaml (``allocation.search: greedy``, which ``ci`` refuses) with ``sweep: {seeds:
    2}`` added: ``covnet check`` and ``covnet run`` exited 2 on the default ``modes`` grid.
    ``covnet check`` says, beside exit 0, that ``covnet sweep`` refuses the grid and which
    axis to give (it said nothing, and the sweep refused it: hunt 12)."""
    import yaml

    data = yaml.safe_load((paper_path.parent / "large.yaml").read_text())
    data["sweep"] = {"seeds": 2}
    data["scans"] = 3
    cfg = tmp_path / "large_sweep.yaml"
    cfg.write_text(yaml.safe_dump(data))
    capsys.readouterr()
    assert main(["check", str(cfg)]) == 0
    err = capsys.readouterr().err
    assert "covnet sweep would refuse its grid" in err and "give sweep.modes without ci" in err
    assert main(["run", str(cfg), "--out", str(tmp_path / "r"), "--no-figures"]) == 0
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists()
    # a grid the policy can run: no note
    data["sweep"] = {"seeds": 2, "modes": ["central"]}
    cfg.write_text(yaml.safe_dump(data))
    capsys.readouterr()
    assert main(["check", str(cfg)]) == 0
    assert "sweep" not in capsys.readouterr().err
    assert main(["check", str(paper_path)]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    ("axis", "values", "needle"),
    [
        ("delay_ms", [0, 0], "0.0 is given twice"),
        ("delay_ms", [0.1, 0.10000001], "0.10000001 and 0.1 are one point"),
        ("loss", [0.1, 0.1], "given twice"),
        ("modes", ["central", "ci", "central"], "'central' is given twice"),
        ("account_for_loss", [False, False], "given twice"),
    ],
)
def test_a_sweep_axis_names_each_grid_point_once(paper_path, axis, values, needle):
    """Repeated (or, to the 6 digits that name a point's trials, equal) values of an axis were
    merged into one grid point silently: "4 grid points x 2 seeds = 8 runs" ran 4, and of
    0.1 and 0.10000001 ms only one ran."""
    data = normalised(load(paper_path))
    data["sweep"] = {axis: values}
    with pytest.raises(ConfigError) as err:
        from_dict(data)
    assert f"sweep.{axis}" in str(err.value) and needle in str(err.value), str(err.value)


@pytest.mark.parametrize(
    "a, b",
    [
        ({"kind": "constant", "value_s": 1}, {"kind": "constant", "value_s": 1.0}),
        ({"kind": "exponential", "mean_s": 0.2}, {"kind": "exponential", "mean_s": 0.2,
                                                  "offset_s": 0}),  # fmt: skip
        ({"kind": "uniform", "high_s": 0.3}, {"kind": "uniform", "low_s": 0.0, "high_s": 0.3}),
    ],
)
def test_a_delay_written_two_ways_is_one_config(paper_path, a, b):
    """The delay table was kept as written: 1 against 1.0, a default written out or left out,
    gave other config hashes for bit-identical runs.  It is the table the core reads now."""
    from covnet.covariance_control.config import config_hash

    hashes = []
    for delay in (a, b):
        data = normalised(load(paper_path))
        data["network"]["latency"]["uplink"] = {"delay": delay}
        sc = from_dict(data)
        hashes.append(config_hash(sc))
    assert hashes[0] == hashes[1]
    assert all(isinstance(v, float) for k, v in normalised(sc)["network"]["latency"]["uplink"][
        "delay"].items() if k != "kind")  # fmt: skip
