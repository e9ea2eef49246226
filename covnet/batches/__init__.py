"""Batches of seeds (``covnet mc``, ``sweep``, ``compare``): the process pool and its
worker, the trial store and the seeds added until the intervals are narrow, the Dask
cluster, and the statistics over seeds of every table."""

#: the most seeds (or trials, runs) one point of a batch takes, from the command line, the API
#: or a config's ``sweep.seeds``: a batch lists each point's runs before it starts, so a
#: mistyped count would fill the memory instead of running
MAX_SEEDS = 10_000


def point_text(value: object) -> str:
    """A grid point's value as its trials' file names spell it (``true``/``false``, a float
    to 6 significant digits, else ``str``): two values with the same text are one point."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)
