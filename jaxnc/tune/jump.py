"""The corrected pathwise gradient with hard PETC triggers (``estimator="corrected"``).

With hard triggers a parameter theta moves the closed loop in two ways: smoothly, through
the dynamics with every decision held, and by moving the instants at which the sensor's
decisions beta_k = 1[g_k > 0] flip. The exact derivative of the mean objective is the sum
of both (smoothed perturbation analysis, Fu & Hu 1997; the "alternative path" of Arya et
al., NeurIPS 2022):

    d E[J] / d theta = E[ dJ/dtheta |_decisions held ]
                       + sum_k E[ sum_r phi(xi_r) (J^{k=1} - J^{k=0})(xi_r) (dg_k/dtheta)(xi_r) / |dg_k/dxi|(xi_r) ],

the second term conditioning decision k on its own measurement noise: z_k = hx_k + v_k,
v_{k,i} = std_i xi, every other draw held. Along xi the PETC gap is a quadratic
(:func:`jaxnc.loop.triggers.petc_crossings`), so its crossings xi_r are exact, phi is the
standard normal density, and J^{k=b}(xi_r) is the run with the noise set *at* the
crossing and decision k forced to b (every later decision hard, as it falls): redrawing the
noise from the whole flipped tail instead is biased (docs/tuning_loops.md). Each output i
with noise gives an unbiased term; their mean is used.

One alternative pair per run keeps the cost bounded (the pruning of Arya et al.): among
all (instant, output, root) candidates one is drawn with probability proportional to the
L1 norm of its weight w = phi (dg/dtheta) / |dg/dxi| / p_noisy, and the jump term is
w (J^1 - J^0) / P(candidate). The estimate per seed is therefore unbiased for
d E[J] / d theta with respect to every leaf, gains and thresholds alike, as far as the
objective's discontinuities are the sensor trigger's decisions. Not corrected: decisions
of a ``controller_trigger`` and failures that move with theta (a run leaving the
monitor's bounds earlier or later); :func:`jaxnc.tune.check.gradient_check` tells whether
that matters on a loop.

Requirements, checked by :func:`corrected_supported`: the sensor's trigger is a
:class:`jaxnc.loop.Petc` (a :class:`jaxnc.loop.Periodic` has no decision to correct: the
estimate is then the pathwise gradient), the measurement noise is additive, z = h(x) + v,
and at least one output has noise.

Cost per seed: the objective's run with its reverse-mode gradient, one run of the loop
with forward-mode tangents (the trigger's signal, d tangents), and the two alternative
runs.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc.loop.base import AbstractTrigger
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.links import Link
from jaxnc.loop.triggers import Periodic, Petc, petc_crossings, petc_decide, petc_forced, petc_gap, petc_update

__all__ = ["corrected_grad", "corrected_supported", "sensor_signal", "crossing_weights"]

#: fold_in constant of the key that draws the alternative (apart from the run's streams)
_ALT_STREAM = 104_729


@_dataclass
class _Pinned(AbstractTrigger):
    """A :class:`Petc` whose decision at slow instant ``at`` is ``value`` (0/1) on the
    signal moved by ``shift`` (float[p]); every other instant decides as ``inner`` does."""

    inner: Any
    at: Any = 0
    value: Any = 0.0
    shift: Any = 0.0

    def init(self, ctx):
        return self.inner.init(ctx)

    def step(self, state, s, k):
        here = k == self.at
        s = s + jnp.where(here, jnp.asarray(self.shift, s.dtype), jnp.zeros_like(s))
        beta = jnp.where(here, jnp.asarray(self.value, s.dtype), petc_decide(self.inner, state, s, k))
        return petc_update(state, s, beta), beta


@_dataclass
class _ShiftedLink(Link):
    """A :class:`Link` that carries the payload of slow instant ``at`` moved by ``shift``
    (the sensor's measurement with its noise set at a crossing)."""

    at: Any = 0
    shift: Any = 0.0

    def send(self, state, data, stamp, k, send, delay, t_send):
        data = data + jnp.where(k == self.at, jnp.asarray(self.shift, data.dtype), jnp.zeros_like(data))
        return super().send(state, data, stamp, k, send, delay, t_send)


def _shifted(link: Link, at, shift) -> _ShiftedLink:
    return _ShiftedLink(**{f.name: getattr(link, f.name) for f in dataclasses.fields(Link)}, at=at, shift=shift)


def corrected_supported(loop) -> str:
    """Why the corrected estimator cannot run on ``loop`` ("" when it can): the loop must be
    a :class:`jaxnc.loop.Loop` whose sensor trigger is a :class:`Petc` (or
    :class:`Periodic`), with additive measurement noise on at least one output."""
    from jaxnc import loop as nc
    if not isinstance(loop, nc.Loop):
        return f"it needs a jaxnc.loop.Loop, got {type(loop).__name__}"
    if isinstance(loop.trigger, Periodic):
        return ""
    if not isinstance(loop.trigger, Petc):
        return f"the sensor's trigger must be a Petc or Periodic, got {type(loop.trigger).__name__}"
    if loop.trigger.relaxed:
        return "the sensor's trigger is relaxed (a soft forward pass has no decisions to correct)"
    try:
        std = np.asarray(loop.plant.v_std, float)
    except Exception as e:                                            # noqa: BLE001 (reported)
        return f"the plant's measurement noise could not be read ({type(e).__name__})"
    if not np.any(std > 0):
        return "no output has measurement noise (the decisions have no density to condition on)"
    p = loop.plant
    x0 = p.init(jax.random.PRNGKey(0))
    dv = jnp.asarray(np.linspace(0.5, 1.5, std.size), jnp.float32) * jnp.asarray(np.maximum(std, 1e-3), jnp.float32)
    diff = np.asarray(p.measure(x0, dv)) - np.asarray(p.measure(x0, jnp.zeros_like(dv)))
    if not np.allclose(diff, np.asarray(dv), rtol=1e-4, atol=1e-6):
        return "the measurement noise is not additive (z = h(x) + v is needed)"
    return ""


def sensor_signal(loop, key):
    """(z float[S, p], v float[S, p], last float[S, p], forced bool[S]) of the sensor's
    :class:`Petc` on the run of ``loop`` with ``key``: the measurement, its noise, the
    value last sent before each instant (zbar) and whether the instant sends whatever the
    gap. zbar and forced are the trigger's own state replayed on the run's decisions."""
    from jaxnc import loop as nc
    d = nc.draw(loop, key)
    lp = dataclasses.replace(loop, cost=None, record=nc.Record(signals=("z", "sent_sc")))
    tr = nc.simulate(lp, key, d)
    trig = loop.trigger
    S = loop.steps // loop.N
    st0 = trig.init(loop.ctx._replace(signal_dim=loop.ctx.output_dim))

    def replay(st, inp):
        z, sent, k = inp
        return petc_update(st, z, sent), (st.last, petc_forced(trig, st, k))

    _, (last, forced) = jax.lax.scan(replay, st0, (tr.z, tr.sent_sc, jnp.arange(S, dtype=jnp.int32)))
    return tr.z, d.v, last, forced


def crossing_weights(gaps_of: Callable, theta):
    """The jump term's weights of every candidate crossing, by forward-mode AD.

    Args:
      gaps_of: ``gaps_of(theta) -> (last, z, v, std, sigma, delta, reading, forced)`` of the
        sensor's trigger (float[S, p] signals, std float[p], forced bool[S]; ``reading``
        static), traced in theta.
      theta: float[d].

    Returns:
      (w float[S, p, 2, d], xi float[S, p, 2]): w = phi(xi) (dg/dtheta at fixed xi) /
      |dg/dxi| / (outputs with noise), zero where there is no crossing or the instant is
      forced; xi the standardised noise of each crossing.
    """
    def gaps(t):
        last, z, v, std, sigma, delta, reading, forced = gaps_of(t)
        S, p = z.shape
        xi, slope, valid = jax.vmap(lambda l, zz, vv: petc_crossings(l, zz, vv, std, sigma, delta, reading))(
            last, z, v)
        xi = jax.lax.stop_gradient(xi)
        eye = jnp.eye(p, dtype=z.dtype)

        def g_at(l, zz, vv, i_row, x):     # the gap with output i's noise at x (the others as measured)
            zi = zz + i_row * (std * x - vv)
            return petc_gap(l, zi, sigma, delta, reading)
        g = jax.vmap(lambda l, zz, vv, xk: jax.vmap(lambda row, xr: jax.vmap(lambda x: g_at(l, zz, vv, row, x))(xr))(
            eye, xk))(last, z, v, xi)
        valid = valid & ~forced[:, None, None]
        n_noisy = jnp.maximum(jnp.sum(std > 0), 1).astype(z.dtype)
        dens = jnp.where(valid, jnp.exp(-0.5 * xi * xi) / jnp.sqrt(2 * jnp.pi) / jnp.where(valid, slope, 1.0), 0.0)
        return g, (jax.lax.stop_gradient(dens / n_noisy), xi, v, std)

    dg, (dens, xi, v, std) = jax.jacfwd(gaps, has_aux=True)(theta)
    return dens[..., None] * dg, xi, v, std


def corrected_grad(loop_of: Callable, cost: Callable, theta, key, *, alternatives: int = 1):
    """One seed's corrected pathwise gradient of ``cost`` (module docstring).

    Args:
      loop_of: ``loop_of(theta float[d]) -> jaxnc.loop.Loop`` with hard triggers (a
        :class:`Petc` or :class:`Periodic` sensor trigger, additive measurement noise).
      cost: ``cost(loop, key) -> scalar``, one run of the loop (it must simulate ``loop``
        with ``key``, as :func:`jaxnc.loop.run` and the schemes' ``run`` do).
      theta: float[d]; key: the seed's key.
      alternatives: static, alternative pairs drawn per seed (independently, with
        replacement; the jump term is their mean), >= 1; 0: every candidate crossing
        (the exact conditional sum, 2 runs per instant, output and root: for reference).

    Returns:
      (value, grad float[d]): the hard objective and its estimated gradient.
    """
    theta = jnp.asarray(theta)
    value, g_path = jax.value_and_grad(lambda t: cost(loop_of(t), key))(theta)
    lp0 = loop_of(theta)
    if isinstance(lp0.trigger, Periodic):
        return value, g_path

    def gaps_of(t):
        lp = loop_of(t)
        z, v, last, forced = sensor_signal(lp, key)
        std = jax.lax.stop_gradient(jnp.asarray(lp.plant.v_std, jnp.float32))
        return last, z, jax.lax.stop_gradient(v), std, lp.trigger.sigma, lp.trigger.delta, lp.trigger.reading, forced

    w, xi, v, std = crossing_weights(gaps_of, theta)
    S, p = xi.shape[:2]
    wf = w.reshape(-1, w.shape[-1])
    a = jnp.sum(jnp.abs(wf), axis=-1)                                   # [S p 2]
    total = jnp.sum(a)

    def jump_of(c):
        """w_c (J^1 - J^0) at candidate c = (instant, output, root), flat index."""
        k_c, rest = c // (p * 2), c % (p * 2)
        i_c, r_c = rest // 2, rest % 2
        shift = (std[i_c] * xi[k_c, i_c, r_c] - v[k_c, i_c]) * (jnp.arange(p) == i_c).astype(v.dtype)

        def alt(b):
            lp = dataclasses.replace(lp0, trigger=_Pinned(lp0.trigger, k_c, b, shift),
                                     uplink=_shifted(lp0.uplink, k_c, shift))
            return cost(lp, key)
        F = jax.lax.stop_gradient(jax.vmap(alt)(jnp.asarray([1.0, 0.0], jnp.float32)))
        return wf[c] * (F[0] - F[1])

    if alternatives == 0:
        cands = jnp.arange(a.shape[0])
        jump = jnp.sum(jax.vmap(lambda c: jnp.where(a[c] > 0, jump_of(c), 0.0))(cands), axis=0)
        return value, g_path + jump
    logits = jnp.where(a > 0, jnp.log(jnp.where(a > 0, a, 1.0)), -jnp.inf)
    logits = jnp.where(total > 0, logits, jnp.zeros_like(logits))
    cs = jax.random.categorical(jax.random.fold_in(key, _ALT_STREAM), logits, shape=(alternatives,))
    per = jax.vmap(lambda c: jump_of(c) * (total / jnp.where(a[c] > 0, a[c], 1.0)))(cs)
    jump = jnp.where(total > 0, jnp.mean(per, axis=0), 0.0)
    return value, g_path + jump
