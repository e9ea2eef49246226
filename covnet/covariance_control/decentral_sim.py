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
prediction with the tracks of ``D ∩ ({n} ∪ neighbours(n))``.

The network processes (manager, sensors, peers) call the same functions of
:mod:`covnet.covariance_control.decentral`, so a lockstep network run reproduces these loops.
"""

from __future__ import annotations

import time

from covnet.covariance_control.config import Scenario
from covnet.covariance_control.decentral import Mirror, decide_rule, neighbours, reach_matrix
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import (
    Model,
    build_model,
    initial_estimate,
    measure,
    predict_step,
    truth_trajectory,
)
from covnet.covariance_control.simulate import MetricRun, RunRows, run_metric


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
    model = model or build_model(sc)
    if not sc.fusion.has_centre:
        nodes = run_peer(sc, metric, model)
        return nodes[model.sensor_ids[0]], nodes
    return run_metric(sc, metric, model), None


def run_peer(sc: Scenario, metric: str, model: Model | None = None) -> dict[str, MetricRun]:
    """Every peer node's run (keyed by sensor id); all share the agreed enabled sets."""
    model = model or build_model(sc)
    fusion, rule = sc.fusion, rule_for(sc.fusion)
    truth = truth_trajectory(model)
    N, Ns = model.scans, len(model.sensor_ids)
    nbrs = neighbours(fusion, model.sensor_ids)
    rows = [RunRows(N, Ns) for _ in range(Ns)]
    est0 = initial_estimate(model, sc.filter.initial_estimate)
    fused = [est0] * Ns
    local = [est0] * Ns
    mirror = Mirror.start(model, reach_matrix(fusion, model.sensor_ids))
    for i in range(N):
        k = i + 1
        P_nodes, P_loc = mirror.predicted(model)
        t0 = time.perf_counter()
        alloc = decide_rule(rule, model, P_nodes, P_loc, k, metric, reach=mirror.reach)
        dt = time.perf_counter() - t0
        local_pred = [predict_step(model, g) for g in local]
        tracks = {
            j: rule.local(model, j, local_pred[j], measure(model, j, k, truth[i]))
            for j in alloc.subset
        }
        for n in range(Ns):
            pred = predict_step(model, fused[n])
            heard = [(j, tracks[j]) for j in (n, *nbrs[n]) if j in tracks]
            fused[n] = rule.fuse(model, pred, heard)
            rows[n].put(
                i, alloc.subset, alloc.value, pred, fused[n], truth[i], dt, alloc.n_evaluated
            )
        local = [tracks[j].post if j in tracks else local_pred[j] for j in range(Ns)]
        mirror.advance(rule, model, alloc.subset)
    return {sid: r.run(metric) for sid, r in zip(model.sensor_ids, rows, strict=True)}
