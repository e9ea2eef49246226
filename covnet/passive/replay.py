"""``covnet replay RUN_DIR`` of a passive network run, and its rebuild from a recording (the
launcher's, after a manager crash): the manager's own steps
(:class:`covnet.passive.network.PassiveSteps`) over what the recording holds, written by the
manager's own writer (:func:`covnet.passive.network.write_network_run`).

What is taken from the recording (decoded strictly; :mod:`covnet.runs.replay_kit`): per scan ``k``
the manager's Status (``failed``; ``fused``: whose lists it had), its Command (a cross-check:
the enabled set), its Tracks (a cross-check: one per associated triple, ``target_id``
``"i1-i2-i3"``) and the sensors' lists of (azimuth, elevation) pairs (the manager's test,
:func:`covnet.passive.network.usable_list`, applied when reading).  The scene each scan was
drawn from (for scoring) is recomputed from the config, ``default_rng([seed, k - 1])``, as the
manager draws it; the association is, per scan (:func:`covnet.runs.replay_kit.recompute_scans`)::

    all three lists in:  triples = METHODS[method](lists);  x, P = triangulate(triples)
    else:                not associated (the sensors missing listed)

and ``association.json`` (every scan's lists, triples, positions, score and cost, and the
totals) is compared byte for byte.  Not reproduced (wall-clock facts, in ``run.json``): the
association times; ``network.json`` of a replay has empty counters (a replay has no network).
"""

from __future__ import annotations

from covnet.passive.config import KIND
from covnet.passive.network import ASSOCIATION, PassiveSteps, usable_list, write_network_run
from covnet.runs.replay_kit import StepsReplay

__all__ = ["command", "rebuild", "replay_run"]

REPLAY = StepsReplay(
    KIND, PassiveSteps, write_network_run, acceptable=usable_list, compared=(ASSOCIATION,)
)
rebuild = REPLAY.rebuild
"""``rebuild(cfg, run_id, episodes, recording, out, run_info=None) -> ReplayReport``
(:meth:`covnet.runs.replay_kit.KindReplay.rebuild`)."""
replay_run = REPLAY.replay_run
"""``replay_run(run_dir, out=None) -> ReplayReport``: replay and compare
``association.json``."""
command = REPLAY.command
"""``covnet replay RUN_DIR`` of a passive run."""
