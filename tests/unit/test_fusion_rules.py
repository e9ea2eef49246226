"""The fusion-rule registry (``FUSION_RULES``): every rule against its own contract, and a
user's rule plugged in by one registry line working through ``covnet run`` and ``covnet
compare`` (no other file changed)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from recipe_entries import Naive

from covnet.cli.app import main
from covnet.core.gaussian import Gaussian, symmetrise
from covnet.core.kalman import update_sequential
from covnet.covariance_control.compare import modes
from covnet.covariance_control.config import load
from covnet.covariance_control.fusion_rules import (
    FUSION_RULES,
    Central,
    CovarianceIntersection,
    InformationFusion,
    fusion_modes,
    measurement_from_track,
    rule_for,
    track_rules,
)
from covnet.covariance_control.model import build_model, predict_step

RULES = sorted(FUSION_RULES)


class _Settings:
    ci_objective = "det"


@pytest.fixture(scope="module")
def model(paper_path):
    return build_model(load(paper_path))


def _scene(model, rng):
    """A fusion point's prediction, each sensor's local prediction, and one measurement each."""
    prior = predict_step(model, Gaussian(rng.normal(0, 30, 4), model.P0))
    local = [predict_step(model, Gaussian(rng.normal(0, 30, 4), 0.5 * model.P0)) for _ in model.R]
    z = [model.H @ prior.x + rng.normal(0, 20, 2) for _ in model.R]
    return prior, local, z


def _subsets(n, size=3):
    return [s for k in range(1, size + 1) for s in itertools.combinations(range(n), k)]


@pytest.mark.parametrize("name", RULES)
def test_the_allocator_scores_the_covariance_the_rule_reaches(model, name):
    """For every subset: the batched candidate covariance == the rule's fused covariance of that
    subset == the covariance its centre step actually reaches (which does not depend on the
    measured values)."""
    rule = FUSION_RULES[name](_Settings())
    rng = np.random.default_rng(7)
    prior, local, z = _scene(model, rng)
    payloads = [rule.local(model, j, local[j], z[j]) for j in range(len(z))]
    P_local_post = np.stack(
        [p.post.P if rule.tracks else local[j].P for j, p in enumerate(payloads)]
    )
    subsets = _subsets(len(z))
    masks = np.zeros((len(subsets), len(z)), dtype=bool)
    for i, s in enumerate(subsets):
        masks[i, list(s)] = True
    cands = rule.candidates(model, prior.P, P_local_post, masks)
    for i, s in enumerate(subsets):
        P_mirror = rule.fused_covariance(model, prior.P, P_local_post, s)
        fused = rule.fuse(model, prior, [(j, payloads[j]) for j in reversed(s)])  # any order
        np.testing.assert_allclose(cands[i], P_mirror, rtol=1e-9, atol=1e-9, err_msg=str(s))
        np.testing.assert_allclose(fused.P, P_mirror, rtol=1e-9, atol=1e-9, err_msg=str(s))
        np.testing.assert_array_equal(fused.P, symmetrise(fused.P))
    assert rule.fuse(model, prior, []) == prior or np.array_equal(
        rule.fuse(model, prior, []).P, prior.P
    )


@pytest.mark.parametrize("name", [n for n in RULES if FUSION_RULES[n].information_form])
def test_information_form_rules_score_the_information_form(model, name):
    """A rule in the information form is allocated by the exact fast search on
    (P⁻⁻¹ + Σ J_j)⁻¹: its candidates must be exactly that."""
    rule = FUSION_RULES[name](_Settings())
    P = predict_step(model, Gaussian(np.zeros(4), model.P0)).P
    masks = np.eye(len(model.R), dtype=bool)[:5] | np.eye(len(model.R), k=2, dtype=bool)[:5]
    cands = rule.candidates(model, P, np.stack([P] * len(model.R)), masks)
    for i, row in enumerate(masks):
        J = model.gains[row].sum(axis=0)
        np.testing.assert_allclose(cands[i], np.linalg.inv(np.linalg.inv(P) + J), rtol=1e-10)


@pytest.mark.parametrize("name", [n for n in RULES if FUSION_RULES[n].refilters_late])
def test_a_late_message_refilters_as_its_measurement(model, name):
    """What the out-of-sequence buffer re-filters for a late message (its late measurement,
    through sequential updates) is the centre step on that message."""
    rule = FUSION_RULES[name](_Settings())
    prior, local, z = _scene(model, np.random.default_rng(11))
    # a track rule's local prediction is the fusion point's, as for a sensor that has always
    # reported to it (then the track's new information is exactly the measurement's)
    payloads = [rule.local(model, j, prior, z[j]) for j in (1, 4, 6)]
    received = list(zip((1, 4, 6), payloads, strict=True))
    late = [rule.late_measurement(p) for p in payloads]
    assert all(m is not None for m in late)
    via_buffer = update_sequential(prior, [(zj, model.H, R) for zj, R in late])
    fused = rule.fuse(model, prior, received)
    np.testing.assert_allclose(via_buffer.x, fused.x, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(via_buffer.P, fused.P, rtol=1e-9, atol=1e-9)


def test_rules_without_an_exact_late_update_say_so():
    for name, cls in FUSION_RULES.items():
        if not cls.refilters_late:
            assert cls(_Settings()).late_measurement(None) is None, name


def test_measurement_from_track_recovers_the_measurement(model):
    prior = predict_step(model, Gaussian(np.array([1.0, 2.0, 3.0, 4.0]), model.P0))
    z = np.array([10.0, -5.0])
    track = InformationFusion(_Settings()).local(model, 2, prior, z)
    z2, R2 = measurement_from_track(track.post, track.prior)
    np.testing.assert_allclose(z2, z, rtol=1e-8)
    np.testing.assert_allclose(R2, model.R[2], rtol=1e-8)


def test_registry_names_everywhere(paper_path):
    """The config, the peer rules and covnet compare take their names from the registry."""
    assert fusion_modes() == (*FUSION_RULES, "peer")
    assert track_rules() == ("info", "ci")
    assert set(modes()) == {*FUSION_RULES, "ci-fast", "peer-info", "peer-ci"}
    assert Central(_Settings()).label() == "central"
    assert CovarianceIntersection(_Settings()).label() == "ci-det"
    sc = load(paper_path)
    assert isinstance(rule_for(sc.fusion), Central)


def test_a_new_rule_is_one_registry_line(monkeypatch, tmp_path, paper_path, capsys):
    """Register a rule (its class and one FUSION_RULES line) and it runs from the CLI, in a
    peer network too, and covnet compare offers it: nothing else had to change."""
    monkeypatch.setitem(FUSION_RULES, "naive", Naive)
    out = tmp_path / "naive"
    argv = ["run", str(paper_path), "--fusion", "naive", "--metric", "spectral"]
    assert main([*argv, "--out", str(out), "--no-figures"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["fusion"] == "naive"
    assert json.loads((out / "config.json").read_text())["fusion"]["mode"] == "naive"
    # double counting makes the filter optimistic: its mean NEES (18.9 for this seed) is far
    # above the 4 of a consistent filter (the info rule's is 4.3), and it enables fewer sensors
    # (25 % against 56.5 %) because it believes it knows more than it does
    block = summary["metrics"]["spectral"]
    assert block["mean_nees"] > 10 and block["allocation_rate"] < 0.4
    assert "peer-naive" in modes() and "naive" in track_rules()
    capsys.readouterr()
