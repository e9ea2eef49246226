"""allocation.detection: pda above 4 clutter returns in the gate: the q₂ table of a sensor
reaches the largest mean clutter in the gate its config allows (it stopped at μ_G = 4, and
np.interp held q₂(4) above: 0.20 for a bearing sensor at clutter_rate 20 instead of about
0.14); below 4 it is the table it always was, bit for bit."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.core import streams
from covnet.core.association import (
    gate_threshold,
    gate_volume,
    information_reduction_factor,
    information_reduction_table,
)
from covnet.core.detection import clutter_window
from covnet.covariance_control import targets
from covnet.covariance_control.config import from_dict

MULTI = Path(__file__).resolve().parents[2] / "configs" / "multitarget.yaml"
B1, P1 = 8, 0  # a bearing sensor, a position sensor of the shipped scenario
TOL = 0.015  # two estimates of 2000 samples each: about 4 standard errors of the difference


def pda(rate: float, scans: int = 3) -> targets.TargetsModel:
    """The shipped scenario, cut short, scored with ``detection: pda``, every sensor at
    ``clutter_rate`` ``rate``."""
    data = yaml.safe_load(MULTI.read_text())
    data["scans"] = scans
    data["targets"][2].pop("manoeuvres")
    data["allocation"]["detection"] = "pda"
    for s in data["sensors"]:
        s["clutter_rate"] = rate
    return targets.build(from_dict(data))


def oracle(mu: float, seed: int = 11) -> float:
    """q₂ of B1 (pd 0.9, one dimension) at ``mu``, from its own generator."""
    return information_reduction_factor(0.9, 1, mu, np.random.default_rng(seed), 0.99, 2000)


def test_q2_above_4_is_the_factor_there_and_below_q2_at_4():
    """The table at μ_G = 10, 50 and its last point (the largest μ_G the config allows: a
    bearing sensor's clutter_rate, 60) against the single-μ estimate with its own draws."""
    tm = pda(60.0)
    grid, tab = tm.q_grid(B1), tm.q_table(B1)
    assert grid[-1] == 60.0 == targets.max_clutter_in_gate(60.0, 1, (True,), 0.99, 6.0)
    q4 = float(np.interp(4.0, grid, tab))
    for mu in (10.0, 50.0, 60.0):
        q = float(np.interp(mu, grid, tab))
        assert q == pytest.approx(oracle(mu), abs=TOL)
        assert q < q4 - 0.05
    assert np.all(tab[81:] < q4)


def test_a_bearing_dwell_in_heavy_clutter_is_scored_with_q2_at_its_clutter():
    """Through targets.information: a bearing sensor at clutter_rate 100 has μ_G = 100 ρ =
    42.9 in the gate (its window is ± 6 σ, uncapped); its J is q₂(42.9) H'R⁻¹H, not q₂(4)."""
    tm = pda(100.0)
    preds = targets.predict_all(tm, targets.initial_estimates(tm))
    J, feas = targets.information(tm, preds)
    t = int(np.flatnonzero(feas[B1])[0])
    s = tm.sensors[B1]
    S = targets._innovation_cov(tm, B1, preds[t])
    w = targets.window(tm, B1, preds[t])
    assert w is not None
    mu = s.clutter_rate / w.volume * gate_volume(S, 0.99)
    rho = 2.0 * math.sqrt(gate_threshold(1, 0.99)) / 12.0
    assert mu == pytest.approx(100.0 * rho, rel=1e-9) and mu > 40.0
    W = s.whitened_jacobian(preds[t].x[None, :])[0]
    ref = W.T @ W
    nz = np.abs(ref) > 1e-12 * np.abs(ref).max()
    q = float(np.median(J[B1, t][nz] / ref[nz]))
    assert q == pytest.approx(oracle(mu), abs=TOL)
    assert q < oracle(4.0) - 0.05


def test_q2_up_to_4_is_the_old_table_bit_for_bit():
    """On μ_G <= 4 the table is information_reduction_table's from the stream
    (seed, QFACTOR, j), as before; the hash is the old code's table for these sensors."""
    tm = pda(60.0)
    digest = hashlib.sha256()
    for j in (P1, 4, B1):
        s = tm.sensors[j]
        old = information_reduction_table(
            s.pd, s.dim_z, targets._Q_GRID, streams.stream(tm.base.seed, targets.QFACTOR, j), 0.99
        )
        np.testing.assert_array_equal(tm.q_table(j)[:81], old)
        np.testing.assert_array_equal(tm.q_grid(j)[:81], targets._Q_GRID)
        digest.update(tm.q_table(j)[:81].tobytes())
    assert digest.hexdigest() == OLD_TABLES_SHA256


def test_q2_table_is_deterministic_whatever_the_call_order():
    """Same config and seed, the same table, whichever sensor is asked first and whether the
    allocator asked before."""
    a, b = pda(60.0), pda(60.0)
    qa = [a.q_table(j).copy() for j in (P1, 4, B1)]
    preds = targets.predict_all(b, targets.initial_estimates(b))
    targets.information(b, preds)
    qb = [b.q_table(j).copy() for j in (B1, 4, P1)][::-1]
    for x, y in zip(qa, qb, strict=True):
        assert len(x) > 81
        np.testing.assert_array_equal(x, y)


def test_the_bound_on_clutter_in_the_gate_holds_for_the_code_s_window_and_gate():
    """max_clutter_in_gate against clutter_window and gate_volume for random S: a position
    sensor's μ_G never exceeds r min(1, ρ); a bearing sensor's can exceed r ρ once its
    window is capped at ± π, which is why its table goes to r."""
    rng = np.random.default_rng(4)
    tm = pda(60.0)
    pos, brg = tm.sensors[P1], tm.sensors[B1]
    x = np.array([9000.0, 0.0, 7000.0, 0.0])
    g = gate_threshold(2, 0.99)
    for k in (6.0, 1.0):
        rho = math.pi * g / (2.0 * k) ** 2  # c_2 γ / (2k)²
        worst = 0.0
        for _ in range(300):
            A = rng.standard_normal((2, 2)) * rng.uniform(0.1, 100.0, 2)
            S = A @ A.T + 1e-6 * np.eye(2)
            w = clutter_window(pos, x, S, k)
            worst = max(worst, 60.0 / w.volume * gate_volume(S, 0.99))
        assert 0.5 * 60.0 * rho < worst <= 60.0 * rho * (1.0 + 1e-12)
        top = targets.max_clutter_in_gate(60.0, 2, (False, False), 0.99, k)
        # k = 1: the gate can overflow the window (ρ > 1), the table held at r
        assert top == pytest.approx(60.0 * min(1.0, rho), rel=1e-12)
    S = np.array([[1.0]])  # bearing σ 1 rad: the ± 6σ window is the whole circle
    mu = 60.0 / clutter_window(brg, x, S, 6.0).volume * gate_volume(S, 0.99)
    assert mu > 60.0 * 2.0 * math.sqrt(gate_threshold(1, 0.99)) / 12.0
    assert targets.max_clutter_in_gate(60.0, 1, (True,), 0.99, 6.0) == 60.0
    assert targets.max_clutter_in_gate(3.0, 1, (True,), 0.99, 6.0) == 3.0
    assert targets.q_grid_extension(3.0).size == 0


OLD_TABLES_SHA256 = "f303af3691f1821de6d6f14b85d237b501dc307bf2b7929a346985e221b66a57"
