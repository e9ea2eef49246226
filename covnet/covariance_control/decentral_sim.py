"""The in-process runs of the decentralized modes (``info``, ``ci``, ``peer``).

Centre modes (``info``, ``ci``) are the kind's one engine with a track rule
(:mod:`covnet.covariance_control.engine`, stepped by :mod:`covnet.covariance_control.drive`),
per scan ``k``::

    local filters   x_j⁻, P_j⁻ = predict(x_j, P_j)               every sensor, every scan
    fusion centre   x_f⁻, P_f⁻ = predict(x_f, P_f)
    allocate        D = argmin_i f(P_i, P_d), P_i the rule's covariance of subset i
    sensors j ∈ D   z_j(k) from stream (j, k); x_j, P_j = update(x_j⁻, P_j⁻, z_j)
                    publish LocalTrack(post, prior)
    fusion centre   x_f, P_f = rule(x_f⁻, P_f⁻, tracks of D)

Peer mode: no centre.  Every node computes the same decision from the covariance mirror
(:class:`covnet.covariance_control.decentral.Mirror`: every node's fused covariance, which depends
only on the enabled history), scoring a subset by its worst node; then node ``n`` fuses its own
prediction with the tracks of ``D ∩ ({n} ∪ neighbours(n))``: the engine's peer entry, fusing
for every node in this process, for its own node in each peer process (:mod:`sensors.peer`).

Every run here is the kind's one engine stepped by :func:`covnet.covariance_control.drive.run`;
these names remain for the callers that choose a mode.
"""

from __future__ import annotations

from covnet.covariance_control.config import Scenario
from covnet.covariance_control.drive import run
from covnet.covariance_control.model import Model
from covnet.covariance_control.simulate import MetricRun, run_metric


def run_centre(sc: Scenario, metric: str, model: Model | None = None) -> MetricRun:
    """A fusion centre fusing local tracks with ``sc.fusion``'s track rule (``info``, ``ci``):
    the kind's engine in this process (:func:`covnet.covariance_control.drive.run`)."""
    return run_metric(sc, metric, model)


def run_mode(
    sc: Scenario, metric: str, model: Model | None = None
) -> tuple[MetricRun, dict[str, MetricRun] | None]:
    """The run of ``sc.fusion.mode``: ``(run, None)`` for a fusion centre (any rule of the
    registry, ideal or slow links: the kind's engine in this process); in ``peer`` mode
    ``(run of the first node, every node's run)``."""
    r = run(sc, metric, model)
    return r.run, r.nodes


def run_peer(sc: Scenario, metric: str, model: Model | None = None) -> dict[str, MetricRun]:
    """Every peer node's run (keyed by sensor id); all share the agreed enabled sets: the
    kind's engine in this process, fusing for every node."""
    nodes = run(sc, metric, model).nodes
    assert nodes is not None  # peer mode
    return nodes
