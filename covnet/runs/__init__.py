"""Run directories and what goes in them: the ``--out`` rules and shared file names,
recordings and their replay, the per-scan columns of a run's results, and what Foxglove
draws (the visual channels, and the live view)."""
