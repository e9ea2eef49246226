"""What a batch's workers know: every registry as covnet's files build it.

A batch's workers are new interpreters (:mod:`covnet.batches.pool`: never a fork) or a Dask
cluster's: each imports covnet and has each registry (``METRICS``, ``FUSION_RULES``,
``POLICIES``, ``SEARCHES``, ``SENSOR_MODELS``, the kinds) as its module builds it.  An entry a
program adds, replaces or removes at run time (``METRICS["mine"] = Metric(...)`` in a notebook)
is in that program's process only: ``covnet run``, ``covnet up`` (forked nodes) and a batch of
one worker use it, but a batch of several workers failed every task after the config was
accepted (a new metric), or would have run the file's entry instead (a replaced one).  Each
registry module calls :func:`ship` once it is built; :func:`changed_at_run_time` lists how the
registries of this process differ from what they were when shipped, and
:func:`covnet.batches.trials.batch_options` refuses a batch of several workers while any
does, before anything runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["changed_at_run_time", "ship"]

_SHIPPED: dict[str, tuple[Mapping[str, Any], dict[str, Any]]] = {}


def ship(name: str, registry: Mapping[str, Any]) -> None:
    """``registry`` (named ``name`` in messages, e.g. ``covnet.core.metrics.METRICS``) as its
    module built it: a snapshot of its entries, kept beside the live mapping."""
    _SHIPPED[name] = (registry, dict(registry))


def changed_at_run_time() -> list[str]:
    """Each entry of a shipped registry added, replaced (another object) or removed in this
    process since, as ``NAME['key'] added``; empty when none."""
    out: list[str] = []
    for name, (live, shipped) in sorted(_SHIPPED.items()):
        for key in sorted(set(live) - set(shipped)):
            out.append(f"{name}[{key!r}] added")
        for key in sorted(set(shipped) - set(live)):
            out.append(f"{name}[{key!r}] removed")
        for key in sorted(set(live) & set(shipped)):
            if live[key] is not shipped[key]:
                out.append(f"{name}[{key!r}] replaced")
    return out
