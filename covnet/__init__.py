"""covnet: a distributed sensor-network simulator for covariance-control sensor allocation.

Importing :mod:`covnet` never imports zenoh; only :mod:`covnet.wire.zenoh_bus` does.  It pins
OpenBLAS's kernel set before NumPy loads (:mod:`covnet.blas_kernel`), so that the same config
and seed give the same bits on every x86-64 machine, and asks it for one thread (covnet's
matrices are small and its processes many).
"""

from covnet import blas_kernel

blas_kernel.pin()
blas_kernel.one_thread()

__version__ = "0.1.0"
