"""Static association of azimuth/elevation measurements from three passive sensors
(``docs/maths/passive_association.md``): the fast cotangent method and its baselines.

* :mod:`.model`: records (``PassiveScan``, ``AssocParams``, ``Association``) and angle geometry;
* :mod:`.cotangent`: azimuth test, elevation (height) test, indicator analysis, the pipeline;
* :mod:`.sd`: ML triangulation, the S-D tuple costs (with the target-prior term), greedy;
* :mod:`.lagrangian`: Lagrangian relaxation with lower/upper bounds;
* :mod:`.exact`: the exact MILP through HiGHS;
* :mod:`.methods`: the ``METHODS`` registry.
"""

from covnet.core.passive.methods import METHODS, MethodFn
from covnet.core.passive.model import Association, AssocParams, PassiveScan

__all__ = ["METHODS", "Association", "AssocParams", "MethodFn", "PassiveScan"]
