"""covnet: a distributed sensor-network simulator for covariance-control sensor allocation.

Importing :mod:`covnet` never imports zenoh; only :mod:`covnet.zenoh_bus` does.
"""

__version__ = "0.1.0"
