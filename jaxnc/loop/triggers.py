"""Triggers of a loop: periodic, PETC with a time-triggered safety condition.

:class:`Petc` is the mixed condition of seed 000 eq. (3)-(4) (and of seed 003 eq. 5-6
for the sensor, eq. 21-22 for the controller side, on the first action of a packet):

    ||zbar_{k-1} - z_k||^2 > sigma ||z_k||^2 + delta,   zbar_k = beta_k z_k + (1 - beta_k) zbar_{k-1},

``reading="sum"``: one condition on the sums over outputs (sigma, delta per output,
seed 000 eq. 4); ``reading="each"``: it fires when the condition holds for any output
alone. ``max_silence`` > 0 adds the time-triggered safety condition of seed 003 eq. (7):
it also fires when the signal has not been sent for ``max_silence`` slow instants
(``max_silence = 1``: it sends at every instant, a periodic sensor). The first instant
always sends (zbar_0 = z_0).

The step function has zero gradient almost everywhere. With ``temperature`` > 0 the
decision is straight-through (:func:`fires_straight_through`): the exact hard value
forward, the gradient of sigmoid(gap / temperature) backward (squared norms in the gap,
so the gradient is finite when z = zbar); ``relaxed=True`` makes the forward pass soft as
well (:func:`soft_decision`, the sigmoid relaxation).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

import numpy as np

from jaxnc._validate import array_fields, check_bool, check_given, check_int, check_nonneg, check_range, concrete
from jaxnc.loop.base import AbstractTrigger, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["Periodic", "Petc", "PetcState", "petc_gap", "petc_crossings", "petc_forced", "petc_decide", "petc_update",
           "soft_decision", "fires_straight_through"]


def soft_decision(gap, temperature):
    """sigmoid(gap / temperature) in the dtype of ``gap``; 0 where ``temperature`` is 0."""
    tau = jnp.maximum(jnp.asarray(temperature, gap.dtype), 1e-12)
    return jnp.where(jnp.asarray(temperature) > 0, jax.nn.sigmoid(gap / tau), 0.0)


def fires_straight_through(gap, temperature):
    """1[gap > 0] as a float; with ``temperature`` > 0 its gradient is that of
    :func:`soft_decision` (hard + (soft - sg(soft)): the forward value is exactly 0 or 1).

    A ``temperature`` known to be 0 at trace time (a concrete number, not a tracer) gives
    the hard decision alone, without the soft term: the same value, and a derivative that
    was exactly 0 anyway, but none for reverse mode to carry through everything the
    decision weights (the link's packets, the filter's blends; docs/design_notes.md,
    "The exact gradient: hard decisions, a recomputed prediction")."""
    hard = (gap > 0).astype(gap.dtype)
    if concrete(temperature) and not np.any(np.asarray(temperature)):
        return hard
    soft = soft_decision(gap, temperature)
    return hard + (soft - jax.lax.stop_gradient(soft))


def petc_gap(last, s, sigma, delta, reading: str = "sum"):
    """Left minus right side of the PETC condition (fires when > 0), seed 000 eq. (4):
    ``sum (last - s)^2 - sum (sigma s^2 + delta)`` (``reading="sum"``), or the largest of
    the per-output gaps (``"each"``). last, s: float[p]; sigma, delta: float or float[p]."""
    per = (last - s) ** 2 - (sigma * s * s + delta)
    if reading == "each":
        return jnp.max(per)
    return jnp.sum((last - s) ** 2) - jnp.sum(sigma * s * s + delta * jnp.ones_like(s))


def petc_crossings(last, z, v, std, sigma, delta, reading: str = "sum"):
    """Where the PETC gap crosses zero as one output's measurement noise moves.

    The measurement is z = hx + v with v_i = std_i xi_i, xi_i ~ N(0, 1). For output i,
    with every other output at its measured value, the gap of :func:`petc_gap` as a
    function of xi_i alone is the quadratic A xi^2 + B xi + C with (a = zbar_i - hx_i,
    b = hx_i, s = std_i) A = (1 - sigma_i) s^2, B = -2 s (a + sigma_i b) and
    C = a^2 - sigma_i b^2 - delta_i plus, for ``reading="sum"``, the other outputs' terms
    (for ``"each"`` a crossing exists only where every other output's own gap is < 0).

    Args:
      last: float[p], zbar (the last value sent); z, v: float[p], the measurement and its
        noise; std: float[p], the noise's standard deviation (0: no crossing);
      sigma, delta: float or float[p]; reading: ``"sum"`` or ``"each"``.

    Returns:
      (xi float[p, 2], slope float[p, 2], valid bool[p, 2]): the standardised noise of each
      crossing (two roots of the quadratic; one for a linear gap), |d gap / d xi| there
      (sqrt(B^2 - 4 A C) at both roots) and whether the root exists.
    """
    p = z.shape[-1]
    sig = jnp.broadcast_to(jnp.asarray(sigma, z.dtype), (p,))
    dl = jnp.broadcast_to(jnp.asarray(delta, z.dtype), (p,))
    s = jnp.asarray(std, z.dtype)
    hx = z - v
    per = (last - z) ** 2 - (sig * z * z + dl)           # each output's own gap, at the measured z
    a, b = last - hx, hx
    A = (1.0 - sig) * s * s
    B = -2.0 * s * (a + sig * b)
    C = a * a - sig * b * b - dl
    others_ok = jnp.ones((p,), bool)
    if reading == "each":
        masked = jnp.where(jnp.eye(p, dtype=bool), -jnp.inf, per[None, :])
        others_ok = jnp.max(masked, axis=1) < 0
    else:
        C = C + jnp.sum(per) - per
    disc = B * B - 4.0 * A * C
    sq = jnp.sqrt(jnp.maximum(disc, 0.0))
    q = -0.5 * (B + jnp.where(B >= 0, sq, -sq))
    ok = (disc > 0) & (s > 0) & others_ok
    safe = lambda d: jnp.where(d != 0, d, 1.0)
    xi = jnp.stack([q / safe(A), C / safe(q)], axis=-1)
    valid = jnp.stack([ok & (A != 0), ok & (q != 0)], axis=-1) & jnp.isfinite(xi)
    return jnp.where(valid, xi, 0.0), jnp.broadcast_to(sq[:, None], (p, 2)), valid


class PetcState(NamedTuple):
    """The state of a :class:`Petc` trigger: the last value sent (zbar) and the silence since."""

    last: jax.Array      # zbar: the last value sent
    silent: jax.Array    # int32: slow instants since the last send


@_dataclass
class Periodic(AbstractTrigger):
    """Sends every ``every`` slow instants (static; 1 = always), starting at k = 0."""

    every: int = _static(1)

    def __post_init__(self):
        check_int("Periodic.every", self.every, 1, 1_000_000)

    def init(self, ctx):
        return ()

    def step(self, state, s, k):
        return state, (jnp.mod(k, self.every) == 0).astype(jnp.float32)


@_dataclass
class Petc(AbstractTrigger):
    """Periodic event-triggered condition (module docstring).

    Attributes:
      sigma, delta: float or float[p], >= 0 (relative and absolute thresholds; the condition
        is on squared norms, so delta is in the signal's units squared, summed over the
        outputs with ``reading="sum"``: delta = 0.02 V^2 waits for a change of 0.14 V).
      temperature: >= 0; > 0 gives a straight-through (or, ``relaxed``, soft) decision.
      max_silence: int >= 0, the safety condition's k_max (0: off; 1: send every
        instant). A leaf, so loops differing only in it share one compiled program.
      reading: static, ``"sum"`` or ``"each"``.
      relaxed: static; the forward pass is the sigmoid too (needs temperature > 0).
    """

    field_shapes = {"sigma": ((), ("signal",)), "delta": ((), ("signal",)), "temperature": ((),),
                    "max_silence": ((),)}

    sigma: Any = 0.0
    delta: Any = 0.0
    temperature: Any = 0.0
    max_silence: Any = 0
    reading: str = _static("sum")
    relaxed: bool = _static(False)

    def __post_init__(self):
        for n in ("sigma", "delta", "temperature"):
            check_given(f"Petc.{n}", getattr(self, n))
        check_bool("Petc.relaxed", self.relaxed)
        array_fields(self, "sigma", "delta")
        check_nonneg("Petc.sigma", self.sigma)
        check_nonneg("Petc.delta", self.delta)
        check_nonneg("Petc.temperature", self.temperature)
        check_range("Petc.max_silence", self.max_silence, 0, 1_000_000)
        if concrete(self.max_silence):
            ms = np.asarray(self.max_silence)
            if ms.shape != () or ms.dtype == bool or ms != np.round(ms):
                raise ValueError(f"Petc.max_silence must be a whole number of slow instants (an int, not a bool), "
                                 f"got {ms.tolist()}")
            object.__setattr__(self, "max_silence", np.int32(ms))
        if self.reading not in ("sum", "each"):
            raise ValueError(f"Petc.reading must be one of sum, each, got {self.reading!r}")
        if self.relaxed:
            try:
                if float(self.temperature) <= 0:
                    raise ValueError("Petc.temperature must be > 0 when relaxed=True, "
                                     f"got {float(self.temperature):g}")
            except TypeError:
                pass

    def init(self, ctx):
        return PetcState(jnp.zeros((ctx.signal_dim,), jnp.float32), jnp.zeros((), jnp.int32))

    def step(self, state, s, k):
        beta = petc_decide(self, state, s, k)
        return petc_update(state, s, beta), beta


def petc_forced(trig: Petc, state: PetcState, k):
    """bool: instant ``k`` sends whatever the gap (the first instant, or the safety
    condition's ``max_silence``), so its decision does not depend on the thresholds."""
    ms = jnp.asarray(trig.max_silence)
    return (k == 0) | ((ms > 0) & (state.silent + 1 >= ms))


def petc_decide(trig: Petc, state: PetcState, s, k):
    """The decision of ``trig`` (0/1 float, straight-through or soft as configured) on
    signal ``s`` at instant ``k``, forced instants included (:func:`petc_forced`)."""
    g = petc_gap(state.last, s, trig.sigma, trig.delta, trig.reading)
    beta = soft_decision(g, trig.temperature) if trig.relaxed else fires_straight_through(g, trig.temperature)
    return jnp.where(petc_forced(trig, state, k), jnp.ones((), s.dtype), beta)


def petc_update(state: PetcState, s, beta):
    """A :class:`Petc`'s state after decision ``beta`` on signal ``s``: zbar = beta s +
    (1 - beta) zbar, and the silence counter."""
    last = blend(beta, s, state.last)
    silent = jnp.where(beta > 0.5, 0, state.silent + 1).astype(jnp.int32)
    return PetcState(last, silent)
