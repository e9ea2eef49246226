"""The pure numerical core: numpy and scipy only, no I/O, no clocks, no global random state.

Shapes are fixed: a state ``x`` is ``(n,)``, a covariance ``P`` is ``(n, n)``; batches go on
leading axes.  Randomness enters only as an explicit ``numpy.random.Generator``.
"""
