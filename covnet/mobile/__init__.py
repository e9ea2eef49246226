"""The ``mobile`` scenario's I/O side: config, in-process run, results, figures, Monte Carlo,
benchmark and the entry points the CLI calls (:mod:`covnet.mobile.cli`).

The numerics live in the pure core, :mod:`covnet.core.mobile`.
"""
