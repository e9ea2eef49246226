"""Interoperation with other frameworks, each an optional extra imported only by its users.

- :mod:`covnet.interop.stonesoup` (``pip install 'covnet[stonesoup]'``): covnet's
  covariance-control objective as a Stone Soup reward function.

Nothing here is imported by covnet itself.
"""
