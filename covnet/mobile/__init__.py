"""The ``mobile`` scenario's I/O side: config, in-process run, results, figures, Monte Carlo,
benchmark and the commands (:mod:`covnet.mobile.commands`; the registry entry:
:mod:`covnet.mobile.kind`).

The numerics live in the pure core, :mod:`covnet.core.mobile`.
"""
