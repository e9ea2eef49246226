"""The wire: what crosses a process boundary.  The keys (:mod:`covnet.wire.keys`), the
message schemas (:mod:`covnet.wire.schemas`) and their bytes (:mod:`covnet.wire.codec`),
all three under one name in :mod:`covnet.wire.messages`."""
