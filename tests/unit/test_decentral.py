"""Decentralized modes in one process (covnet.covariance_control.decentral,
covnet.covariance_control.decentral_sim): the information rule reproduces the central filter, the CI
allocator is the plain loop, peer nodes agree and their covariances are what every node's mirror
predicts, runs are deterministic."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
import yaml

from covnet import kinds
from covnet.cli.app import main
from covnet.config import ConfigError
from covnet.core.allocation.exact import Constraints
from covnet.core.fusion import covariance_intersection
from covnet.core.gaussian import Gaussian
from covnet.core.metrics import get_metric
from covnet.covariance_control.config import from_dict, load, normalised
from covnet.covariance_control.decentral import (
    Mirror,
    decide_rule,
    feasible_subsets,
    local_posterior_covs,
    neighbours,
    reach_matrix,
)
from covnet.covariance_control.decentral_sim import run_centre, run_mode, run_peer
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import build_model
from covnet.covariance_control.simulate import run_metric


def _scenario(paper_path, scans=30, seed=None, **fusion):
    data = normalised(load(paper_path))
    data["scans"] = scans
    if seed is not None:
        data["seed"] = seed
    data["fusion"] = {**data["fusion"], **fusion}
    return from_dict(data)


def _rel(a, b):
    return np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))


# --------------------------------------------------------------------------------------------
# information-matrix fusion == the central filter
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("metric", ["spectral", "abs_trace", "svd"])
def test_info_rule_reproduces_the_central_filter(paper_path, metric):
    central = _scenario(paper_path, scans=100)
    info = kinds.apply_options(kinds.of(central), central, "paper", fusion="info")
    a = run_metric(central, metric)
    b = run_centre(info, metric)
    # the spec's near-ties at scans 1-2: compare the decisions from scan 3 on
    np.testing.assert_array_equal(a.enabled[2:], b.enabled[2:])
    assert _rel(b.x_est, a.x_est) < 1e-9
    assert _rel(b.P_post, a.P_post) < 1e-9


def test_info_peer_on_a_full_graph_is_central_at_every_node(paper_path):
    central = _scenario(paper_path, scans=40)
    peer = kinds.apply_options(kinds.of(central), central, "paper", fusion="peer")
    assert peer.fusion.peer.graph == "full" and peer.fusion.rule == "info"
    ref = run_metric(central, "spectral")
    nodes = run_peer(peer, "spectral")
    for sid, r in nodes.items():
        np.testing.assert_array_equal(r.enabled[2:], ref.enabled[2:], err_msg=sid)
        assert _rel(r.x_est, ref.x_est) < 1e-9, sid
        assert _rel(r.P_post, ref.P_post) < 1e-9, sid


# --------------------------------------------------------------------------------------------
# the CI allocator: batched == a plain loop with the tie rule
# --------------------------------------------------------------------------------------------


def _plain_ci_decision(model, fusion, P_prior, P_local_prior, scan, metric, constraints):
    """Every feasible subset in preference order, CI one subset at a time, first within tie."""
    post = local_posterior_covs(model, P_local_prior)
    f = get_metric(metric)
    rows = []
    n = len(model.sensor_ids)
    for size in range(1, n + 1):
        for s in itertools.combinations(range(n), size):
            if set(s) & constraints.excluded or not constraints.required <= set(s):
                continue
            if constraints.max_active is not None and size > constraints.max_active:
                continue
            tracks = [Gaussian(np.zeros(4), P_prior)] + [Gaussian(np.zeros(4), post[j]) for j in s]
            P = covariance_intersection(tracks, fusion.ci_objective).P
            rows.append((s, float(f(P, model.desired(scan)))))
    f_star = min(v for _, v in rows)
    thr = f_star + model.tie_rtol * max(abs(f_star), np.finfo(float).tiny)
    return next(s for s, v in rows if v <= thr)


@pytest.mark.parametrize("objective", ["det", "trace", "fast"])
@pytest.mark.parametrize(
    "constraints",
    [Constraints(), Constraints(excluded=frozenset({1, 4}), required=frozenset({2}), max_active=3)],
)
def test_ci_decision_equals_the_plain_loop(paper_path, objective, constraints):
    sc = _scenario(paper_path, mode="ci", ci_objective=objective)
    model = build_model(sc)
    mirror = Mirror.start(model)
    P = model.P0
    rng = np.random.default_rng(3)
    model = replace(model, constraints=constraints)
    for k in range(1, 8):
        P_prior = model.F @ P @ model.F.T + model.Q
        _, P_loc = mirror.predicted(model)
        alloc = decide_rule(rule_for(sc.fusion), model, P_prior, P_loc, k, "spectral")
        plain = _plain_ci_decision(model, sc.fusion, P_prior, P_loc, k, "spectral", constraints)
        assert alloc.subset == plain, k
        delivered = sorted(rng.choice(8, size=3, replace=False).tolist())
        mirror.advance(rule_for(sc.fusion), model, delivered)
        P = alloc.P


def test_feasible_subsets_order_and_constraints():
    subsets, masks = feasible_subsets(4, Constraints(excluded=frozenset({3}), max_active=2))
    assert subsets == ((0,), (1,), (2,), (0, 1), (0, 2), (1, 2))
    assert masks.sum(axis=1).tolist() == [1, 1, 1, 2, 2, 2]
    assert feasible_subsets(3, Constraints(required=frozenset({1})))[0] == (
        (1,),
        (0, 1),
        (1, 2),
        (0, 1, 2),
    )


# --------------------------------------------------------------------------------------------
# peer mode
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rule", ["info", "ci"])
def test_peer_nodes_covariances_are_what_the_mirror_predicts(paper_path, rule):
    """Every node decides from the mirror: it must be each node's actual fused covariance."""
    sc = _scenario(paper_path, scans=25, mode="peer", peer={"rule": rule, "graph": "ring"})
    model = build_model(sc)
    nodes = run_peer(sc, "spectral")
    mirror = Mirror.start(model, reach_matrix(sc.fusion, model.sensor_ids))
    enabled = next(iter(nodes.values())).enabled
    for i in range(sc.scans):
        mirror.advance(rule_for(sc.fusion), model, np.flatnonzero(enabled[i]).tolist())
        for n, sid in enumerate(model.sensor_ids):
            assert _rel(mirror.P_fused[n], nodes[sid].P_post[i]) < 1e-9, (sid, i + 1)


def test_peer_ring_nodes_agree_and_stay_consistent(paper_path):
    sc = _scenario(paper_path, scans=60, mode="peer", peer={"graph": "ring"})
    nodes = run_peer(sc, "spectral")
    first = next(iter(nodes.values()))
    for r in nodes.values():
        np.testing.assert_array_equal(r.enabled, first.enabled)
        assert np.all(np.isfinite(r.x_est))
    # each node's own estimate is exact for what it heard: NEES near the state dimension
    mean_nees = np.mean([r.nees[10:].mean() for r in nodes.values()])
    assert 2.0 < mean_nees < 6.5


def test_neighbours_of_each_graph(paper_path):
    sc = _scenario(paper_path, mode="peer")
    ids = sc.sensor_ids
    full = neighbours(sc.fusion, ids)
    assert full[0] == (1, 2, 3, 4, 5, 6, 7)
    ring = neighbours(_scenario(paper_path, mode="peer", peer={"graph": "ring"}).fusion, ids)
    assert ring[0] == (1, 7) and ring[3] == (2, 4)
    star = neighbours(
        _scenario(paper_path, mode="peer", peer={"graph": "star", "hub": "S3"}).fusion, ids
    )
    assert star[2] == (0, 1, 3, 4, 5, 6, 7) and star[0] == (2,)
    custom = _scenario(
        paper_path, mode="peer", peer={"graph": "custom", "edges": [["S1", "S2"], ["S2", "S8"]]}
    )
    c = neighbours(custom.fusion, ids)
    assert c[1] == (0, 7) and c[4] == ()


# --------------------------------------------------------------------------------------------
# determinism, configuration, CLI
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "fusion", [{"mode": "info"}, {"mode": "ci"}, {"mode": "peer", "peer": {"graph": "ring"}}]
)
def test_deterministic_and_decisions_independent_of_the_seed(paper_path, fusion):
    a, _ = run_mode(_scenario(paper_path, scans=20, **fusion), "abs_trace")
    b, _ = run_mode(_scenario(paper_path, scans=20, **fusion), "abs_trace")
    c, _ = run_mode(_scenario(paper_path, scans=20, seed=99, **fusion), "abs_trace")
    np.testing.assert_array_equal(a.x_est, b.x_est)
    np.testing.assert_array_equal(a.P_post, b.P_post)
    np.testing.assert_array_equal(a.enabled, c.enabled)  # covariances never see the data
    assert not np.array_equal(a.x_est, c.x_est)


@pytest.mark.parametrize(
    ("peer", "path"),
    [
        ({"graph": "custom"}, "fusion.peer.edges"),
        ({"graph": "ring", "edges": [["S1", "S2"]]}, "fusion.peer.edges"),
        ({"graph": "custom", "edges": [["S1", "S9"]]}, "fusion.peer.edges[0][1]"),
        ({"graph": "custom", "edges": [["S1", "S1"]]}, "fusion.peer.edges[0]"),
        ({"graph": "star", "hub": "X"}, "fusion.peer.hub"),
        ({"graph": "mesh"}, "fusion.peer.graph"),
    ],
)
def test_bad_peer_config_names_the_field(paper_path, peer, path):
    with pytest.raises(ConfigError) as exc:
        _scenario(paper_path, mode="peer", peer=peer)
    assert any(p == path for p, _ in exc.value.problems), exc.value.problems


def _cli_run(paper_path, out, mode):
    args = ["run", str(paper_path), "--fusion", mode, "--metric", "abs_trace"]
    assert main([*args, "--out", str(out), "--no-figures"]) == 0
    return json.loads((out / "summary.json").read_text())


def test_cli_run_with_each_fusion_mode(paper_path, tmp_path, capsys):
    summary = _cli_run(paper_path, tmp_path / "ci", "ci")
    assert summary["fusion"] == "ci-det"
    assert "fusion ci-det" in capsys.readouterr().out
    summary = _cli_run(paper_path, tmp_path / "peer", "peer")
    assert summary["fusion"] == "peer-info-full"
    assert summary["peer"]["abs_trace"]["agreement"] is True
    assert set(summary["peer"]["abs_trace"]["nodes"]) == set(summary["sensor_ids"])


def test_cli_rejects_an_unknown_fusion_mode(paper_path, capsys):
    assert main(["run", str(paper_path), "--fusion", "gossip"]) == 2
    err = capsys.readouterr().err
    assert "--fusion: unknown fusion mode 'gossip'" in err and "central" in err


@pytest.mark.parametrize("fusion", ["central", "ci"])
def test_a_failed_required_sensor_is_out_of_every_subset(paper_path, fusion):
    """A required sensor that failed stopped being required but was not excluded: the
    allocator went on choosing the dead sensor (in every subset from scan 51 on under `covnet
    up`, its information counted in the value: 3.2 where the fused covariance gave 7.0)."""
    from covnet.covariance_control.model import decide, predict_cov

    sc = _scenario(paper_path, mode="ci")
    model = build_model(sc)
    s3 = model.sensor_ids.index("S3")
    model = replace(model, constraints=Constraints(required=frozenset({s3})))
    assert model.constraints.without(frozenset({s3})) == Constraints(excluded=frozenset({s3}))
    rule = rule_for(sc.fusion)
    P_prior = predict_cov(model, model.P0)
    _, P_local = Mirror.start(model).predicted(model)
    chosen: set[int] = set()
    for k in (1, 20, 51, 52, 60):  # the desired covariance tightens at scan 51
        if fusion == "central":
            d = decide(model, P_prior, k, "spectral", unavailable=frozenset({s3}))
        else:
            d = decide_rule(rule, model, P_prior, P_local, k, "spectral", frozenset({s3}))
        assert s3 not in d.subset, (k, d.subset)
        chosen |= set(d.subset)
    assert chosen  # the others are allocated


@pytest.mark.parametrize("fusion", ["central", "ci"])
def test_every_sensor_failed_is_a_scan_with_nobody_on(paper_path, fusion):
    from covnet.covariance_control.model import decide, predict_cov

    sc = _scenario(paper_path, mode="ci")
    model = build_model(sc)
    everyone = frozenset(range(len(model.sensor_ids)))
    P_prior = predict_cov(model, model.P0)
    _, P_local = Mirror.start(model).predicted(model)
    if fusion == "central":
        d = decide(model, P_prior, 60, "spectral", unavailable=everyone)
    else:
        d = decide_rule(rule_for(sc.fusion), model, P_prior, P_local, 60, "spectral", everyone)
    assert d.subset == () and np.array_equal(d.P, P_prior)
    assert d.value == get_metric("spectral")(P_prior, model.desired(60))


def test_the_progress_line_and_the_summary_print_one_rate(paper_path, tmp_path, capsys):
    """153 of 240 sensor-scans (63.75 %) was printed 63.8 % in the progress line and 63.7 % in
    the summary of the same run."""
    sc = tmp_path / "ring.yaml"
    raw = yaml.safe_load(paper_path.read_text())
    raw.update(scans=30, fusion={"mode": "peer", "peer": {"graph": "ring", "rule": "info"}})
    raw["allocation"]["metrics"] = ["abs_trace"]
    sc.write_text(yaml.safe_dump(raw))
    assert main(["run", str(sc), "--no-figures", "--out", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    rates = [ln.split("rate")[1].split("%")[0].strip() for ln in out.splitlines() if " rate " in ln]
    assert len(rates) == 2 and rates[0] == rates[1] == "63.7", out
