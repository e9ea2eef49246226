"""Mobile sensors choosing motion modes and targets by linear programming (spec
``mobile_selection.md``, after CN105159314A).

Pure core, numpy and scipy only:

* :mod:`covnet.core.mobile.models`: the mode table, platform motion, target motion, the
  distance-grown measurement noise ``R`` and the bell detection probability ``Pd``;
* :mod:`covnet.core.mobile.cost`: the batched cost tensor ``c_ijρ`` ``(M, N, 9)`` and the null
  costs ``c0_i``;
* :mod:`covnet.core.mobile.decision`: the decision problem, the patent's LP + rounding +
  post-step, its closed form without capacities, the exact MILP, and the :data:`SOLVERS`
  registry.

Indices: target ``i = 0..M-1``, sensor ``j = 0..N-1``, mode ``ρ = 0..8``.
"""
