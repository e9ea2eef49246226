"""Batches of seeds (``covnet mc``, ``sweep``, ``compare``): the process pool and its
worker, the trial store and the seeds added until the intervals are narrow, the Dask
cluster, and the statistics over seeds of every table."""
