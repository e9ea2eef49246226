"""A many-target run's certificate relative to the distance from doing nothing
(``summary.json``: ``gap_nothing``, its median and worst): ``(F - L) / (F(nothing) - F)`` with
``F(nothing) = Σ_t w_t f(P⁻_t, P_d,t)`` from the run's own arrays, and the printed line says
both measures.  (The one-target form: ``test_allocation_search.py``.)"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from covnet.cli.app import main
from covnet.core.metrics import METRICS

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "large_multitarget.yaml"


def test_many_target_gap_relative_to_doing_nothing(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(CONFIG), "--out", str(out), "--no-figures"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    a = np.load(out / "arrays.npz")
    for m, blk in summary["metrics"].items():
        F, L = a[f"value.{m}"], a[f"lower_bound.{m}"]
        K = F.shape[0]
        w, P_pred, P_d = a["weights"][:, :K], a[f"P_pred.{m}"], a["P_d"][:, :K]
        # the run's F is Σ_t w_t f_t of its own per-target values: the same sum for nothing
        assert np.allclose((w * a[f"values.{m}"]).sum(axis=0), F, rtol=1e-12, atol=0.0)
        f = METRICS[m].fn
        nothing = sum(w[t] * f(P_pred[t], P_d[t]) for t in range(w.shape[0]))
        assert np.all(nothing > F)
        want = np.where(F == L, 0.0, (F - L) / (nothing - F))
        assert blk["gap_nothing"] == pytest.approx(want.tolist(), rel=1e-12, abs=0.0)
        assert blk["gap_nothing_median"] == pytest.approx(float(np.median(want)), rel=1e-12)
        assert blk["gap_nothing_worst"] == pytest.approx(float(want.max()), rel=1e-12)
        line = next(ln for ln in printed.splitlines() if f"{m}:" in ln and "search gap" in ln)
        assert "of the distance from doing nothing: median" in line
