"""The manager role (``python -m manager``): the network's router and its fusion manager.

:mod:`manager.loop` is the scan skeleton every kind runs (membership, command, collect, fuse,
report); :mod:`manager.covariance`, :mod:`manager.mobile` and :mod:`manager.passive` plug in
their kind's maths; :mod:`manager.peer_monitor` watches a network without a fusion centre.
"""
