"""The registry of passive association methods: ``METHODS[name](scan, params) -> Association``.

To add a method: write a plain function ``(PassiveScan, AssocParams) -> Association`` (its
equations in the docstring) and add one line to ``METHODS``; configs name it, and the generic
tests (``tests/property/test_passive_methods.py``) iterate over ``sorted(METHODS)``.

* ``cot``: the fast cotangent tests + indicator analysis (spec §4-§7);
* ``lr``: Lagrangian relaxation of the S-D assignment (§8.3), with bounds;
* ``milp``: the exact S-D optimum via HiGHS (§8.4);
* ``greedy``: cheapest-first disjoint tuples on the S-D costs (§8.5).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from covnet.core.passive.cotangent import associate_cot
from covnet.core.passive.exact import associate_milp
from covnet.core.passive.lagrangian import associate_lr
from covnet.core.passive.model import Association, AssocParams, PassiveScan
from covnet.core.passive.sd import greedy

MethodFn = Callable[[PassiveScan, AssocParams], Association]

METHODS: Mapping[str, MethodFn] = {
    "cot": associate_cot,
    "lr": associate_lr,
    "milp": associate_milp,
    "greedy": greedy,
}
