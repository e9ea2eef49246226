"""The passive association study around :mod:`covnet.core.passive`: configs
(``configs/passive.yaml``, ``kind: passive``), scenes, the Monte Carlo protocol, the benchmark,
figures and the commands (:mod:`covnet.passive.commands`; the registry entry:
:mod:`covnet.passive.kind`).

Importing this package never imports zenoh.
"""
