"""The sensor role (``python -m sensors --id ID``): one sensor per process.

:mod:`sensors.protocol` is what every sensor does (commands in, truth in, measurements out,
heartbeats, liveliness); :mod:`sensors.covariance`, :mod:`sensors.mobile` and
:mod:`sensors.passive` give it their kind's measurement; :mod:`sensors.peer` is a peer node.
"""
