"""Benchmarks of the network: ``covnet bench up``, ``bench soak``, ``bench cluster``, and
the closed-loop pub/sub probe."""
