"""Processes: ``covnet up``'s launcher and supervisor, forks, network namespaces and
emulated links (:mod:`covnet.processes.netem`), what every node process shares, Ctrl-C and
SIGTERM in every command, and the manager's runtime counts."""
