"""The passive association study around :mod:`covnet.core.passive`: configs
(``configs/passive.yaml``, ``kind: passive``), scenes, the Monte Carlo protocol, the benchmark,
figures and the command entry points (:mod:`covnet.passive.cli`).

Importing this package never imports zenoh.
"""
