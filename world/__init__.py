"""The world role (``python -m world``): the ground truth of the run, for the sensors.

One module per kind: :mod:`world.covariance`, :mod:`world.mobile`, :mod:`world.passive`.
"""
