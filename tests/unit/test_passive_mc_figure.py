"""The passive ``mc`` figure: its error bars are ``results.json``'s intervals of the per-trial
share (they were half their width moved onto the pooled ``p``, the interval of nothing), and
its title gives the trials the cells ran (with ``--ci-width``: 12-18, where it said 6)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.container import ErrorbarContainer

from covnet.passive import plots


def _row(sigma, method, p, mean, lo, hi, trials):
    return {
        "formation": "cross", "d_km": 1.0, "sigma_mrad": sigma, "clutter": True,
        "method": method, "p": p, "median_time_s": 0.001, "trials": trials,
        "p_trial_mean": mean, "p_trial_ci_lo": lo, "p_trial_ci_hi": hi,
    }  # fmt: skip


def test_the_bars_are_the_tables_intervals_and_the_title_the_trials_run(tmp_path, saved_figures):
    rows = [
        _row(1.0, "cot", 0.962, 0.958, 0.867, 1.0, 12),
        _row(1.0, "greedy", 0.887, 0.900, 0.752, 1.0, 12),
        _row(3.0, "cot", 0.80, 0.81, 0.70, 0.92, 18),
        _row(3.0, "greedy", 0.833, 0.844, 0.715, 0.974, 18),
    ]
    doc = {
        "trials": 6, "trials_range": [12, 18], "workers": 1, "rows": rows,
        "machine": {"processor": "x86_64"},
    }  # fmt: skip
    (tmp_path / "results.json").write_text(json.dumps(doc))
    figs = saved_figures(plots)
    plots.mc_figures(tmp_path)
    fig = figs[0]
    assert "12-18 runs per cell" in fig._suptitle.get_text()
    drawn = {}
    for ax in fig.axes:
        for c in ax.containers:
            if isinstance(c, ErrorbarContainer):
                (x, y) = c.lines[0].get_data()
                (seg,) = c.lines[2][0].get_segments()
                drawn[(round(float(y[0]), 6), ax.get_title())] = (seg[0][1], seg[1][1])
    want = {
        (r["p_trial_mean"], f"cross, clutter on, σ = {r['sigma_mrad']:g} mrad"): (
            r["p_trial_ci_lo"], r["p_trial_ci_hi"]
        )
        for r in rows
    }
    assert set(drawn) == set(want)
    for k, (lo, hi) in want.items():
        assert drawn[k] == pytest.approx((lo, hi)), k
    assert np.isfinite(list(drawn.values())).all()
