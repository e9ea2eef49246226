"""Link models: one-way delay, jitter, loss and reordering of the packets on one link direction.

Pure (numpy only, no I/O): the same :class:`LinkSpec` drives the application-level emulation in
covnet's bus and the real emulated network path of :mod:`covnet.processes.netem`.

Definitions, for packet ``i`` of one link direction sent at ``s_i`` (non-decreasing):

- delay ``D_i ~ DelayDist`` (each draw clipped at ``>= 0``), jitter ``J_i ~ N(0, jitter_s²)``,
  total one-way delay ``d_i = max(D_i + J_i, 0)``, base arrival ``b_i = s_i + d_i``;
- lost ``L_i = (u_i < loss)`` with ``u_i ~ U[0, 1)``, i.i.d.;
- reordered ``O_i = (r_i < reorder)`` with ``r_i ~ U[0, 1)``: such a packet may overtake earlier
  ones and is delivered at ``b_i``;
- every other packet keeps FIFO order: it is delivered no earlier than any earlier packet that
  was not lost, ``t_i = max(b_i, M_i)`` with ``M_i = max{t_j : j < i, not L_j}``
  (``-inf`` for none).  Because ``t_j >= b_j``, ``M_i = max{b_j : j < i, not L_j}``.

With ``reorder = 0`` delivery times are non-decreasing (a FIFO link); with ``reorder = 1`` every
packet keeps its own delay (independent delays, as ``tc netem`` with jitter gives).

Random draws, identical in :func:`schedule` and :class:`LinkState` so both agree exactly: packets
are taken in blocks of :data:`BLOCK`; for each block, in this order, the generator gives

1. ``BLOCK`` loss uniforms ``u`` (``rng.random``),
2. ``BLOCK`` delays ``D`` (:meth:`DelayDist.sample`),
3. ``BLOCK`` standard normals ``z`` for the jitter, ``J = jitter_s · z``,
4. ``BLOCK`` reorder uniforms ``r``,

and packet ``i`` uses entry ``i mod BLOCK`` of block ``i // BLOCK``.  All four are drawn whatever
the parameters (common random numbers): raising ``loss`` loses a superset of the packets and
leaves every survivor's own delay ``d_i`` unchanged (its FIFO wait can only shrink), and the
delays ``d_i`` depend on neither ``loss`` nor ``reorder``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from covnet.core.streams import stream

LINK = 10  #: stream domain of link draws: key (LINK, link_index, direction)
BLOCK = 256  #: packets per block of random draws (see the module docstring)

KINDS = ("constant", "uniform", "normal", "exponential", "empirical")
#: the parameters each kind reads; any other parameter must keep its default
_PARAMS: dict[str, tuple[str, ...]] = {
    "constant": ("value_s",),
    "uniform": ("low_s", "high_s"),
    "normal": ("mean_s", "std_s"),
    "exponential": ("mean_s", "offset_s"),
    "empirical": ("samples_s",),
}


def _std_normal_pdf(x: float) -> float:
    return math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)


def _std_normal_cdf(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


@dataclass(frozen=True)
class DelayDist:
    """One-way delay distribution, seconds, every draw clipped at ``>= 0``.

    - ``constant``: ``value_s``;
    - ``uniform``: ``U[low_s, high_s]``;
    - ``normal``: ``max(N(mean_s, std_s²), 0)``;
    - ``exponential``: ``offset_s + Exp(mean)`` with mean ``mean_s``;
    - ``empirical``: uniform resampling of ``samples_s`` (e.g. measured delays).

    Every parameter is finite and ``>= 0``; a kind only takes its own parameters (a ``mean_s`` on
    a ``constant`` is an error, not ignored).
    """

    kind: str
    value_s: float = 0.0
    low_s: float = 0.0
    high_s: float = 0.0
    mean_s: float = 0.0
    std_s: float = 0.0
    offset_s: float = 0.0
    samples_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"DelayDist.kind must be one of {', '.join(KINDS)}; got {self.kind!r}")
        own = _PARAMS[self.kind]
        for f in fields(self):
            if f.name == "kind":
                continue
            value = getattr(self, f.name)
            if f.name == "samples_s":
                value = tuple(float(v) for v in np.asarray(value, dtype=np.float64).ravel())
                object.__setattr__(self, "samples_s", value)
                bad = [v for v in value if not (math.isfinite(v) and v >= 0.0)]
            else:
                value = float(value)
                object.__setattr__(self, f.name, value)
                bad = [] if math.isfinite(value) and value >= 0.0 else [value]
            if bad:
                raise ValueError(
                    f"DelayDist.{f.name} must be finite and >= 0 seconds; got {bad[0]!r}"
                )
            if f.name not in own and value != f.default:
                raise ValueError(
                    f"DelayDist.{f.name} is not a parameter of kind {self.kind!r} "
                    f"(which takes {', '.join(own)}); got {value!r}"
                )
        if self.kind == "uniform" and self.low_s > self.high_s:
            raise ValueError(
                f"DelayDist.low_s must be <= high_s; got low_s={self.low_s}, high_s={self.high_s}"
            )
        if self.kind == "empirical" and not self.samples_s:
            raise ValueError("DelayDist.samples_s must hold at least one delay for 'empirical'")

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        """``n`` delays (seconds, ``>= 0``).  Draws from ``rng``: none for ``constant``;
        ``n`` uniforms, normals or exponentials; ``n`` integers for ``empirical``."""
        d: NDArray[np.float64]
        if self.kind == "constant":
            d = np.full(n, self.value_s)
        elif self.kind == "uniform":
            d = rng.uniform(self.low_s, self.high_s, n)
        elif self.kind == "normal":
            d = rng.normal(self.mean_s, self.std_s, n)
        elif self.kind == "exponential":
            d = self.offset_s + rng.exponential(self.mean_s, n)
        else:
            d = np.asarray(self.samples_s)[rng.integers(0, len(self.samples_s), n)]
        return np.maximum(d, 0.0)

    def mean(self) -> float:
        """Expected delay after clipping, exact.  Only ``normal`` can be clipped (its other
        parameters are ``>= 0``); with ``α = μ/σ``, ``E[max(X, 0)] = μ Φ(α) + σ φ(α)``."""
        if self.kind == "constant":
            return self.value_s
        if self.kind == "uniform":
            return 0.5 * (self.low_s + self.high_s)
        if self.kind == "normal":
            mu, sd = self.mean_s, self.std_s
            if sd == 0.0:
                return mu
            a = mu / sd
            return mu * _std_normal_cdf(a) + sd * _std_normal_pdf(a)
        if self.kind == "exponential":
            return self.offset_s + self.mean_s
        return float(np.mean(self.samples_s))

    def var(self) -> float:
        """Variance after clipping, exact: uniform ``(high - low)²/12``, exponential
        ``mean_s²``, empirical the population variance of ``samples_s``, clipped normal
        ``(μ² + σ²) Φ(α) + μ σ φ(α) - mean()²``."""
        if self.kind == "constant":
            return 0.0
        if self.kind == "uniform":
            return (self.high_s - self.low_s) ** 2 / 12.0
        if self.kind == "normal":
            mu, sd = self.mean_s, self.std_s
            if sd == 0.0:
                return 0.0
            a = mu / sd
            m2 = (mu * mu + sd * sd) * _std_normal_cdf(a) + mu * sd * _std_normal_pdf(a)
            return max(m2 - self.mean() ** 2, 0.0)
        if self.kind == "exponential":
            return self.mean_s**2
        return float(np.var(self.samples_s))

    def to_dict(self) -> dict[str, Any]:
        """``kind`` and the kind's own parameters (JSON/YAML-ready)."""
        out: dict[str, Any] = {"kind": self.kind}
        for name in _PARAMS[self.kind]:
            value = getattr(self, name)
            out[name] = list(value) if name == "samples_s" else value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DelayDist:
        """Inverse of :meth:`to_dict`; an unknown key or a missing ``kind`` is a
        ``ValueError``."""
        if "kind" not in data:
            raise ValueError(f"DelayDist.kind is required: one of {', '.join(KINDS)}")
        return cls(**_known_keys(cls, data))


@dataclass(frozen=True)
class LinkSpec:
    """One direction of one link (e.g. sensor S3 -> manager); see the module docstring.

    ``jitter_s``: std of an extra zero-mean normal added to each delay (sum clipped at 0);
    ``loss``: i.i.d. drop probability in ``[0, 1)``; ``reorder``: probability in ``[0, 1]`` that a
    packet may overtake earlier ones (the rest keep FIFO order).
    """

    delay: DelayDist = field(default_factory=lambda: DelayDist("constant"))
    jitter_s: float = 0.0
    loss: float = 0.0
    reorder: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.delay, DelayDist):
            raise ValueError(f"LinkSpec.delay must be a DelayDist; got {type(self.delay).__name__}")
        checks: tuple[tuple[str, Callable[[float], bool], str], ...] = (
            ("jitter_s", lambda v: 0.0 <= v < math.inf, "finite and >= 0 seconds"),
            ("loss", lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
            ("reorder", lambda v: 0.0 <= v <= 1.0, "in [0, 1]"),
        )
        for name, ok, expected in checks:
            value = float(getattr(self, name))
            if not ok(value):  # nan fails every comparison
                raise ValueError(f"LinkSpec.{name} must be {expected}; got {value!r}")
            object.__setattr__(self, name, value)

    @property
    def is_ideal(self) -> bool:
        """No delay (every delay draw is 0), no jitter, no loss: the link changes nothing."""
        return self.delay.mean() == 0.0 and self.jitter_s == 0.0 and self.loss == 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON/YAML-ready form; :meth:`from_dict` reads it back."""
        return {
            "delay": self.delay.to_dict(),
            "jitter_s": self.jitter_s,
            "loss": self.loss,
            "reorder": self.reorder,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LinkSpec:
        """Inverse of :meth:`to_dict`; ``delay`` may be omitted (no delay), unknown keys are a
        ``ValueError``."""
        kw = _known_keys(cls, data)
        if "delay" in kw and not isinstance(kw["delay"], DelayDist):
            kw["delay"] = DelayDist.from_dict(kw["delay"])
        return cls(**kw)


def _known_keys(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(
            f"{cls.__name__} has no field {', '.join(map(repr, unknown))}; "
            f"expected some of {', '.join(sorted(names))}"
        )
    return dict(data)


@dataclass(frozen=True, eq=False)
class Schedule:
    """What a link does to ``n`` packets: delivery times (seconds, ``nan`` where lost)."""

    deliver_at: NDArray[np.float64]
    lost: NDArray[np.bool_]


def _draw_block(
    link: LinkSpec, rng: np.random.Generator
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.bool_]]:
    """One block of draws, in the documented order: (lost, total delay d, reordered)."""
    u = rng.random(BLOCK)
    d = link.delay.sample(rng, BLOCK)
    z = rng.standard_normal(BLOCK)
    r = rng.random(BLOCK)
    return u < link.loss, np.maximum(d + link.jitter_s * z, 0.0), r < link.reorder


def _check_time(t: NDArray[np.float64]) -> None:
    if not np.all(np.isfinite(t)):
        raise ValueError("send_times must be finite")
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise ValueError("send_times must be non-decreasing")


def schedule(link: LinkSpec, send_times: NDArray[np.float64], rng: np.random.Generator) -> Schedule:
    """Delivery times of packets sent at ``send_times`` (1-D, finite, non-decreasing), by the
    definitions and the draw order of the module docstring: ``t_i = s_i + d_i`` for a reordered
    packet, ``t_i = max(s_i + d_i, M_i)`` for the others, ``nan`` for a lost one.  Equal to feeding
    the same times one by one to :meth:`LinkState.on_send` with a generator in the same state."""
    s = np.asarray(send_times, dtype=np.float64)
    if s.ndim != 1:
        raise ValueError(f"send_times must be 1-D; got shape {s.shape}")
    _check_time(s)
    n = s.shape[0]
    blocks = [_draw_block(link, rng) for _ in range(-(-n // BLOCK))]
    if blocks:
        lost, d, reordered = (np.concatenate(parts)[:n] for parts in zip(*blocks, strict=True))
    else:
        lost, d, reordered = np.zeros(0, bool), np.zeros(0), np.zeros(0, bool)
    base = s + d
    # M_i: the latest base arrival of the earlier packets that were not lost
    kept = np.where(lost, -np.inf, base)
    prior = np.concatenate(([-np.inf], np.maximum.accumulate(kept)[:-1]))[:n]
    deliver = np.where(reordered, base, np.maximum(base, prior))
    return Schedule(deliver_at=np.where(lost, np.nan, deliver), lost=lost)


class LinkState:
    """The incremental form of :func:`schedule` for a live emulator that sees packets one at a
    time: :meth:`on_send` uses the same draws in the same order, so its answers equal the batch
    schedule of the same send times exactly."""

    def __init__(self, link: LinkSpec, rng: np.random.Generator) -> None:
        self.link = link
        self.rng = rng
        self._latest = -math.inf  # M: latest base arrival of the packets not lost so far
        self._last_send = -math.inf
        self._i = BLOCK
        self._block: tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.bool_]] | None = None

    def on_send(self, t_send: float) -> float | None:
        """Delivery time of a packet sent at ``t_send`` (not before the previous send), or
        ``None`` when the link loses it."""
        t = float(t_send)
        if not math.isfinite(t) or t < self._last_send:
            raise ValueError(
                f"t_send must be finite and >= the previous send time {self._last_send}; got {t}"
            )
        self._last_send = t
        if self._i == BLOCK:
            self._block, self._i = _draw_block(self.link, self.rng), 0
        assert self._block is not None
        lost, d, reordered = (a[self._i] for a in self._block)
        self._i += 1
        if lost:
            return None
        base = float(np.float64(t) + d)
        out = base if reordered else max(base, self._latest)
        self._latest = max(self._latest, base)
        return out


UP, DOWN = 0, 1
"""Link directions: towards the fusion centre (a sensor's uplink) and from it (its downlink)."""


def measures_on_missed(policy: str, last_on: bool) -> bool:
    """``network.latency.missed_command``: whether a sensor measures a scan whose command never
    reached it, ``keep_last`` (as its newest command said), ``off`` or ``on``."""
    return {"keep_last": last_on, "off": False, "on": True}[policy]


def link_stream(seed: int, link_index: int, direction: int) -> np.random.Generator:
    """The generator of link ``link_index`` in direction ``direction`` (e.g. 0 towards the
    manager, 1 from it): key ``(LINK, link_index, direction)``, apart from measurement noise."""
    if link_index < 0 or direction < 0:
        raise ValueError(
            f"link_index and direction must be >= 0; got link_index={link_index}, "
            f"direction={direction}"
        )
    return stream(seed, LINK, link_index, direction)
