"""Surveillance: targets that appear and leave, track management, JPDA, search cells, and the
continuity metrics (spec ``surveillance.md``).  The pure numerical core; the engine wires it."""
