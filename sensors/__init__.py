"""Sensor processes (one per sensor): measure the truth when commanded, publish over the bus.

The process loop arrives with the runtime (``covnet up``); the measurement model it will call is
:func:`covnet.covariance_control.model.measure`, the same one the in-process simulator uses.
"""
