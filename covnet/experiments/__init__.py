"""Experiments built on the core: benchmarks, Monte Carlo runs, sweeps."""
