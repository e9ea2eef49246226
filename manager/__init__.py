"""The fusion manager process: predict, allocate, command, fuse, publish.

The process loop arrives with the runtime (``covnet up``); the steps it will call are
:func:`covnet.covariance_control.model.decide` and :func:`covnet.covariance_control.model.fuse`, the
same ones the in-process simulator uses.
"""
