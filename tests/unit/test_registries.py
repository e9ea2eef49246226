"""A registry entry added at run time lives in its process only (:mod:`covnet.core.registries`):
a batch of several workers (new interpreters) is refused before it starts, naming the entry;
one worker runs it (hunt 14: ``api.sweep(metric='mine', workers=2)`` failed every task after
the config was accepted, and a replaced entry would have run the file's)."""

from __future__ import annotations

import numpy as np
import pytest

from covnet import api
from covnet.core import registries
from covnet.core.metrics import METRICS, Metric
from covnet.errors import UsageError
from covnet.kinds import REGISTRY
from tests.conftest import REPO


def _mine(A, B):
    return np.abs(np.trace(np.asarray(A) - np.asarray(B), axis1=-2, axis2=-1))


def test_the_shipped_registries_are_unchanged():
    assert registries.changed_at_run_time() == []
    import covnet.core.allocation.policy_registry  # noqa: F401
    import covnet.core.sensor_models  # noqa: F401
    import covnet.covariance_control.fusion_rules  # noqa: F401
    import covnet.covariance_control.searches  # noqa: F401

    assert len(registries._SHIPPED) >= 6 and registries.changed_at_run_time() == []


def test_added_replaced_and_removed_entries_are_named(monkeypatch):
    monkeypatch.setitem(METRICS, "mine", Metric("mine", _mine))
    monkeypatch.setitem(METRICS, "kl", Metric("kl", _mine))
    monkeypatch.delitem(REGISTRY, "passive")
    assert registries.changed_at_run_time() == [
        "covnet.core.metrics.METRICS['mine'] added",
        "covnet.core.metrics.METRICS['kl'] replaced",
        "covnet.kinds.REGISTRY['passive'] removed",
    ]


def _lat(tmp_path):
    import yaml

    data = yaml.safe_load((REPO / "configs" / "latency.yaml").read_text())
    data["scans"] = 6
    data["sweep"] = {"delay_ms": [0], "loss": [0.0], "modes": ["central"],
                     "account_for_loss": [False], "seeds": 2}  # fmt: skip
    path = tmp_path / "lat.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_batch_of_several_workers_is_refused_before_it_starts(monkeypatch, tmp_path, capsys):
    from covnet.cli.app import main

    monkeypatch.setitem(METRICS, "mine", Metric("mine", _mine))
    cfg = _lat(tmp_path)
    with pytest.raises(UsageError) as err:
        api.sweep(cfg, metric="mine", workers=2, out=tmp_path / "sw")
    assert str(err.value).startswith(
        "covnet.core.metrics.METRICS['mine'] added in this process: a batch on several workers "
        "runs in new interpreters"
    ) and str(err.value).endswith("or run the batch in this process (workers 1)"), err.value
    assert not (tmp_path / "sw").exists()
    out = tmp_path / "mc"
    assert main(["mc", str(cfg), "--trials", "2", "--workers", "2", "--out", str(out)]) == 2
    assert "(--workers 1)" in capsys.readouterr().err and not out.exists()
    # one worker: this process, which has it
    assert api.sweep(cfg, metric="mine", workers=1).rows
