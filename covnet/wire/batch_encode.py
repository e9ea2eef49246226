"""A sensor's :class:`~covnet.wire.schemas.Measurement` encoded from a template built once per
sensor: the same bytes as :func:`covnet.wire.codec.encode` of the same message, without
building the message (issue 29, "Bus": the sensor processes' CPU per measurement).

Why the bytes are the same
--------------------------
:func:`~covnet.wire.codec.encode` packs the map ``{"v": 1, "k": "meas", <field>: <value>,
...}`` with the fields in declaration order and the optional ones that are ``None`` left out.
A msgpack map is its header followed by its keys and values one after another, each packed on
its own, so the payload is the concatenation

    header(n) + pack("v") + pack(1) + pack("k") + pack("meas") + pack("sensor_id") + pack(id)
    + pack("scan") + pack(scan) + pack("t") + pack(t) + pack("z") + ext(z) + pack("R") + ext(R)
    + pack("t_sent_ns") + pack(t_sent_ns) + pack("episode") + pack(episode)
    + pack("seq") + pack(seq)

(``target_ids`` and ``platform`` unset).  Everything but the five numbers and ``z`` is fixed
for a sensor, and so is the head of ``z``'s ext (``ExtType(1, [b"<f8", [1, dz], raw])``: its
length depends on ``dz`` only, its raw bytes come last), so a :class:`MeasurementTemplate`
packs those pieces once and, per message, the numbers with msgpack's own packer and ``z``'s
16 ``dz`` raw bytes.  The pieces are made by the same packer settings as the codec's
(``use_bin_type=True``, floats as float64), and the template is checked at construction
against :func:`~covnet.wire.codec.encode` of a probe message (no template when they differ:
the caller encodes as before).

What is checked
---------------
Building a :class:`~covnet.wire.schemas.Measurement` validates it; a template skips that only
where the outcome is known: the sensor id and ``R`` are validated once, at construction (a
message is built from them); per message :meth:`MeasurementTemplate.encode` takes only exact
ints in ``[0, 2**63)``, a finite ``float`` ``t`` and a finite C-ordered float64 ``z`` of shape
``(1, dz)``, and returns ``None`` for anything else, so that the caller builds and encodes the
message as before (which then raises what it raised).  A test compares the bytes with
:func:`~covnet.wire.codec.encode` on random values, at every msgpack int width.
"""

from __future__ import annotations

import struct
import sys

import msgpack
import numpy as np

from covnet.wire.codec import SCHEMA_VERSION, _array_ext, encode
from covnet.wire.schemas import _INT64_MAX, Measurement, _spec

__all__ = ["MeasurementTemplate"]

#: the fields of a measurement the template writes, in the schema's order (``target_ids`` and
#: ``platform``, between ``episode`` and ``seq``, unset); another schema gets no template
_FIELDS = ("sensor_id", "scan", "t", "z", "R", "t_sent_ns", "episode", "seq")
_LITTLE = sys.byteorder == "little"


class MeasurementTemplate:
    """``encode(scan, t, z, t_sent_ns, episode, seq)`` is ``codec.encode(Measurement(sensor_id,
    scan, t, z, R, t_sent_ns, episode, seq=seq))`` bit for bit, or ``None`` when a value is
    outside what the template checks (module docstring).  :meth:`of` returns ``None`` when no
    template can be made (then encode as before)."""

    __slots__ = (
        "_head", "_mid", "_z_head", "_tail", "_ep", "_seq", "_zshape", "_dz", "_floats", "_pack",
    )  # fmt: skip

    @classmethod
    def of(cls, sensor_id: str, R: np.ndarray) -> MeasurementTemplate | None:
        """The template of sensor ``sensor_id`` with noise ``R`` ``(dz, dz)``; ``None`` if the
        schema is not the one this module writes, or a probe message's bytes differ."""
        names = tuple(name for name, _, _ in _spec(Measurement).fields)
        unset = {"target_ids", "platform"}
        if not _LITTLE or tuple(n for n in names if n not in unset) != _FIELDS:
            return None
        if len(names) != len(_FIELDS) + len(unset):
            return None
        out = cls(sensor_id, R)
        probe = Measurement(
            sensor_id, 300, 1.5, np.full(out._zshape, -2.25), R, 70_000, episode=2, seq=129
        )
        if out.encode(300, 1.5, probe.z, 70_000, 2, 129) != encode(probe):
            return None
        return out

    def __init__(self, sensor_id: str, R: np.ndarray) -> None:
        dz = int(np.shape(R)[0])
        # validated as a message validates them (raises the constructor's WireError)
        one = Measurement(sensor_id, 0, 0.0, np.zeros((1, dz)), R, 0, episode=0, seq=1)
        packer = msgpack.Packer(use_bin_type=True)
        pack = packer.pack
        n = 2 + len(_FIELDS)  # "v", "k" and the fields
        head = packer.pack_map_header(n)
        head += pack("v") + pack(SCHEMA_VERSION) + pack("k") + pack(Measurement.KIND)
        head += pack("sensor_id") + pack(one.sensor_id) + pack("scan")
        self._head = head
        self._mid = pack("t") + b"\xcb"  # a float is always a msgpack float64 here
        # z's ext: its raw bytes come last, so its head is the packed ext without them
        z_ext = pack(_array_ext(one.z, pack))
        self._z_head = pack("z") + z_ext[: len(z_ext) - 8 * dz]
        self._tail = pack("R") + pack(_array_ext(one.R, pack)) + pack("t_sent_ns")
        self._ep, self._seq = pack("episode"), pack("seq")
        self._zshape, self._dz = (1, dz), (dz,)
        #: this template's packer (ints only; a sensor encodes from one thread at a time)
        self._pack = msgpack.Packer(use_bin_type=True).pack
        self._floats = struct.Struct(f"<{dz}d")

    def encode(
        self, scan: int, t: float, z: np.ndarray, t_sent_ns: int, episode: int, seq: int
    ) -> bytes | None:
        """The payload (class docstring), or ``None``: encode the message as before."""
        if type(z) is not np.ndarray or z.shape != self._zshape:
            return None
        return self.encode_row(scan, t, z[0], t_sent_ns, episode, seq)

    def encode_row(
        self, scan: int, t: float, row: np.ndarray, t_sent_ns: int, episode: int, seq: int
    ) -> bytes | None:
        """:meth:`encode` with ``z = row[None, :]`` (``row``: ``(dz,)``): its bytes are the
        row's."""
        if type(row) is not np.ndarray or row.dtype is not _FLOAT64 or row.shape != self._dz:
            return None
        for i in (scan, t_sent_ns, episode, seq):
            if type(i) is not int or not 0 <= i <= _INT64_MAX:
                return None
        if type(t) is not float or t - t != 0.0:  # not finite
            return None
        raw = row.tobytes()  # C order, native (little-endian) float64: the codec's bytes
        for v in self._floats.unpack(raw):
            if v - v != 0.0:  # NaN or infinite: the constructor's non_finite
                return None
        pack = self._pack
        return b"".join(
            (
                self._head,
                pack(scan),
                self._mid,
                _F64.pack(t),
                self._z_head,
                raw,
                self._tail,
                pack(t_sent_ns),
                self._ep,
                pack(episode),
                self._seq,
                pack(seq),
            )
        )


#: msgpack's float64 after its 0xcb: the big-endian double
_F64 = struct.Struct(">d")
_FLOAT64 = np.dtype(np.float64)
