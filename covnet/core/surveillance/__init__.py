"""Surveillance: targets that appear and leave, track management, JPDA, search cells and
continuity metrics (spec ``surveillance.md``).  The pure numerical core (numpy and scipy); the
engine wires it.

- :mod:`.jpda`: joint probabilistic data association over clusters of tracks sharing returns;
- :mod:`.tracks`: initiation, M-of-N confirmation, deletion, the track set;
- :mod:`.search_cells`: the search grid, the undetected mass ``u_c``, the allocator's cell term;
- :mod:`.births`: truth with appearing and leaving targets and a Poisson birth process;
- :mod:`.continuity`: cardinality, time to confirm, breaks and id switches.
"""

from __future__ import annotations

from covnet.core.surveillance.births import (
    BirthProcess,
    BirthRegion,
    ScheduledTarget,
    TruthHistory,
    TruthTarget,
    simulate_truth,
)
from covnet.core.surveillance.continuity import (
    ContinuityFrame,
    ContinuityReport,
    ScanSummary,
    evaluate_continuity,
)
from covnet.core.surveillance.jpda import (
    MAX_JOINT_EVENTS,
    JPDACluster,
    JPDAResult,
    TrackGate,
    clusters_of,
    jpda_marginals,
    jpda_update,
    track_gate,
)
from covnet.core.surveillance.search_cells import (
    SearchGrid,
    after_search,
    birth_intensity_per_cell,
    cell_found,
    cell_value,
    coverage_of,
    grow,
    remove_found,
    uniform_mass,
)
from covnet.core.surveillance.tracks import (
    INITIATORS,
    Initiator,
    Track,
    TrackManager,
    TrackRules,
    TrackState,
    can_initiate,
    check_covariance,
    initiate,
    is_hit,
    position_from_return,
    position_trace,
    record_dwell,
)

__all__ = [
    "BirthProcess",
    "BirthRegion",
    "ContinuityReport",
    "ContinuityFrame",
    "INITIATORS",
    "Initiator",
    "JPDACluster",
    "JPDAResult",
    "MAX_JOINT_EVENTS",
    "ScanSummary",
    "ScheduledTarget",
    "SearchGrid",
    "Track",
    "TrackGate",
    "TrackManager",
    "TrackRules",
    "TrackState",
    "TruthHistory",
    "TruthTarget",
    "after_search",
    "birth_intensity_per_cell",
    "can_initiate",
    "cell_found",
    "cell_value",
    "check_covariance",
    "clusters_of",
    "coverage_of",
    "evaluate_continuity",
    "grow",
    "initiate",
    "is_hit",
    "jpda_marginals",
    "jpda_update",
    "position_from_return",
    "position_trace",
    "record_dwell",
    "remove_found",
    "simulate_truth",
    "track_gate",
    "uniform_mass",
]
