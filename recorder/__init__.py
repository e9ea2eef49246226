"""The recorder process: every message of a run, as received, into ``recording.mcap``."""
