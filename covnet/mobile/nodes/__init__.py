"""The mobile scenario's network runtime (``covnet up configs/mobile.yaml``): the world, sensor
and manager loops over a :class:`~covnet.bus.Bus`.  The per-scan maths are the functions of
:mod:`covnet.mobile.model` that :mod:`covnet.mobile.simulate` calls, with the same random
streams, so a network run reproduces ``covnet run`` for the same seed and solver.

Per scan ``k`` (lockstep)::

    manager  predict every track, decide over the sensors alive (liveliness + heartbeats)
             Command(k, enabled = the alive sensors, modes, targets)            -> world, sensors
    world    moves every platform by its commanded mode (absent: stay)
             Truth(k, targets' states, sensor_ids, platforms [qx, qy, q̇x, q̇y])   -> sensors
    sensor   measures only its commanded targets from the truth geometry
             Measurement(k, z of its detections, target_ids, platform)           -> manager
    manager  updates each observed track; Track(k) per target, Status(k)

The processes are the usual ``python -m covnet.world`` / ``python -m sensors`` /
``python -m manager``: their mains route a ``kind: mobile`` config to these loops.
"""
