"""``covnet replay RUN_DIR`` of a mobile network run, and its rebuild from a recording (the
launcher's, after a manager crash): the manager's own steps
(:class:`covnet.mobile.network.MobileSteps`) over what the recording holds, written by the
manager's own writer (:func:`covnet.mobile.network.write_network_run`).

What is taken from the recording (decoded strictly; :mod:`covnet.runs.replay_kit`): per scan ``k``
the manager's Status (``failed``: the sensors that leave the problem; ``fused``: whose
measurements it used), its Command (a cross-check of the decision: enabled set, each sensor's
mode and targets), its Tracks (a cross-check, one per target) and the sensors' Measurements
(``z`` with ``target_ids``, the ``platform`` state ``[qx, qy, q̇x, q̇y]`` the sensor reported;
the manager's test: platform present, detections of commanded targets only).  Everything else
(the truth, the cost tensor, the decisions, the true Pd of each pair) is recomputed from the
config, so the recomputation is, per scan (:func:`covnet.runs.replay_kit.recompute_scans`)::

    x⁻, P⁻ = predict_tracks(x, P);  D = decide(model, x⁻, P⁻, platforms, alive = not failed)
    platforms = reported (a silent sensor's dead-reckoned from its mode)
    x, P   = update_track(x⁻_i, P⁻_i, z_i) for every target i detected by its sensor

and ``summary.json`` (a function of the config, the seed and these messages) is compared byte
for byte.  Not reproduced (wall-clock facts, in ``arrays.npz``'s ``cost_s``, ``solve_s``,
``compare_s`` and ``run.json``): the decision times; ``network.json`` of a replay has empty
counters (a replay has no network).
"""

from __future__ import annotations

from covnet.mobile.config import KIND
from covnet.mobile.network import MobileSteps, write_network_run
from covnet.runs.replay_kit import StepsReplay

__all__ = ["command", "rebuild", "replay_run"]


REPLAY = StepsReplay(KIND, MobileSteps, write_network_run)
rebuild = REPLAY.rebuild
"""``rebuild(cfg, run_id, episodes, recording, out, run_info=None) -> ReplayReport``
(:meth:`covnet.runs.replay_kit.KindReplay.rebuild`)."""
replay_run = REPLAY.replay_run
"""``replay_run(run_dir, out=None) -> ReplayReport``: replay and compare ``summary.json``."""
command = REPLAY.command
"""``covnet replay RUN_DIR`` of a mobile run."""
