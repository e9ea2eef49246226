"""The passive scenario's network runtime (``covnet up configs/passive.yaml``): the world, sensor
and manager loops over a :class:`~covnet.bus.Bus`.

Random streams: scan ``k`` (1-based) is trial ``k - 1`` of :func:`covnet.passive.scene.draw`, the
one generator ``default_rng([seed, k - 1])`` that ``covnet run`` (trial 0) and the Monte Carlo
use.  Each sensor process draws that scan's whole scene from it (given the world's target
positions) and keeps only its own list: the draw order is fixed, so every process holds the
identical scene, the lists it publishes are exactly the ones the in-process run associates, and
the Monte Carlo's common random numbers stay as they are.  The price is drawing three lists
instead of one (microseconds).  The manager draws the same scene once more, for scoring only
(the labels: which target, or clutter, each measurement came from); it never sends it.

Per scan ``k`` (lockstep)::

    manager  Command(k, enabled = the sensors alive)                          -> world, sensors
    world    Truth(k, target_ids T1..T5, states = positions (N, 3) km)        -> sensors
    sensor   its list of (azimuth, elevation) pairs, shuffled, with misses and clutter
             Measurement(k, z (n, 2) rad, R = diag(σ_α², σ_ε²))              -> manager
    manager  once all three lists are in: associate (association.method), triangulate;
             Track(k) per associated triple (x: position km, P: its covariance km²,
             target_id "i1-i2-i3": the measurement index in each list), Status(k).
             A sensor failed or silent: the scan is not associated (counted).

The processes are the usual ``python -m covnet.world`` / ``python -m sensors`` /
``python -m manager``: their mains route a ``kind: passive`` config to these loops.
"""
