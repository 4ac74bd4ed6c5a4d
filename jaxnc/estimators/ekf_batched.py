"""EKF predict / diagonal update with batch-last covariance kernels under ``vmap``.

**Experimental; not used by the closed loops.** Measured on a 2-core CPU (issue 9):
the kernels alone are 1.2-2.2x faster than ``ekf``'s forward pass, gradients are
unchanged, and whole Mecanum loops gain 1.0-1.2x, because the Jacobians (jacfwd of
per-seed model code) stay batch-first and XLA copies the axis moves into every
consumer. Kept, with its tests (marked slow) and ``benchmarks/bench_ekf_kernels.py``,
as the starting point for batch-last models.

Drop-in replacements for :func:`jaxnc.estimators.ekf.ekf_predict` and
:func:`jaxnc.estimators.ekf.ekf_update_diag` (same signatures, same results up to
float32 summation order; seed 000 eq. 11-16). Callers keep writing per-seed code and
``jax.vmap`` it; only the covariance arithmetic changes how it is batched.

Why: under ``vmap`` every array is batch-first, e.g. P is (B, 6, 6), and XLA:CPU
vectorises over the minor axis, which then has length 6. The covariance arithmetic
is therefore written once as a *batch-last kernel*: matrix indices lead, any batch
axes trail, every sum over a matrix index is unrolled into slices of the leading
axes (no ``reduce`` over a non-minor axis, no ``dot_general``), so with a trailing
batch axis of length B each operation is a contiguous, vectorised loop over seeds.

How: each kernel is wrapped by :func:`_batch_last`:

* ``jax.custom_batching.custom_vmap``: unbatched, the kernel runs on the per-seed
  arrays (batch shape ``()``). Batched, its rule receives the batch-first operands,
  moves the batch axis last (unbatched operands are broadcast), runs the *same*
  kernel and moves the axis back. XLA's layout assignment usually turns these
  moves into layout choices of the ``lax.scan`` carry rather than copies.
* ``jax.custom_vjp`` on the outside (``custom_vmap`` alone supports no reverse mode):
  the residuals are the inputs and the backward pass is ``jax.vjp`` of the same
  function written per seed with array operations (as in ``ekf``), batched by plain
  ``vmap``: the backward pass costs what it cost before, the forward pass is faster.
  Reverse mode through a ``lax.scan`` of the filter, ``vmap`` of ``grad`` and ``grad``
  of a ``vmap`` work; forward mode (``jax.jvp``/``jacfwd`` through these functions)
  does not (``custom_vjp``).

The Jacobians A = df/dxi, L = df/dn1, H = dh/dxi still come from ``jax.jacfwd`` of the
model's own per-seed methods, batch-first (a model's code cannot be re-batched
generically); ``ekf_predict`` takes both of its Jacobians from one ``jacfwd``.
"""
from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from jaxnc.estimators.ekf import Gaussian

__all__ = ["Gaussian", "ekf_predict", "ekf_update_diag", "predict_cov", "update_diag"]


# -- batch-last kernels: matrix indices lead, batch axes (possibly none) trail --------
def _sum(terms):
    terms = iter(terms)
    acc = next(terms)
    for t in terms:
        acc = acc + t
    return acc


def _mm(a, b):
    """a @ b on the leading two axes, every entry an unrolled sum of products."""
    return jnp.stack([jnp.stack([_sum(a[i, k] * b[k, j] for k in range(a.shape[1])) for j in range(b.shape[1])])
                      for i in range(a.shape[0])])


def _t(a):
    return jnp.swapaxes(a, 0, 1)


def predict_cov(P, A, L, Q):
    """Covariance prediction, seed 000 eq. (12): sym(A P A' + L Q L'), batch-last."""
    C = _mm(_mm(A, P), _t(A)) + _mm(_mm(L, Q), _t(L))
    return 0.5 * (C + _t(C))


def update_diag(P, H, innovation, r):
    """Sequential scalar correction (seed 000 eq. 13-16 with R = diag(r)), batch-last.

    Returns ``(delta, P)``: the correction of the mean and the posterior covariance.
    Same algorithm as ``ekf.ekf_update_diag``: for each output i, with the Jacobian at
    the prior mean, s = h P h' + r_i, k = P h' / s, delta += k (e_i - h delta),
    P <- P - (P h')(P h')' / s (exactly symmetric).
    """
    n = P.shape[0]
    delta = None
    for i in range(H.shape[0]):
        h = H[i]
        PHt = _sum(P[:, j] * h[j][None] for j in range(n))
        s = _sum(h[j] * PHt[j] for j in range(n)) + r[i]
        e = innovation[i] if delta is None else innovation[i] - _sum(h[j] * delta[j] for j in range(n))
        k = PHt / s[None]
        delta = k * e[None] if delta is None else delta + k * e[None]
        P = P - (PHt[:, None] * PHt[None, :]) / s[None, None]
    return delta, P


# -- batching and differentiation -------------------------------------------------------
def _to_last(x, batched, size):
    if batched:
        return jnp.moveaxis(x, 0, -1)
    return jnp.broadcast_to(x[..., None], x.shape + (size,))


def _from_last(x):
    return jnp.moveaxis(x, -1, 0)


def _batch_last(kernel: Callable, compact: Callable) -> Callable:
    """``kernel(*arrays)`` made batch-last under ``vmap`` and reverse-differentiable.

    ``kernel`` must accept arrays with any number of trailing batch axes (the same on
    every argument) and return a pytree of arrays with those trailing axes.
    ``compact`` computes the same function per seed with array operations; the
    backward pass is its ``jax.vjp`` (batched by plain ``vmap``): differentiating the
    unrolled kernel instead gives the same numbers but an expression graph that took
    ~7x longer to compile.
    """

    @custom_vmap
    def forward(*args):
        return kernel(*args)

    @forward.def_vmap
    def _forward_rule(size, in_batched, *args):
        out = kernel(*(_to_last(a, b, size) for a, b in zip(args, in_batched)))
        out = jax.tree.map(_from_last, out)
        return out, jax.tree.map(lambda _: True, out)

    @jax.custom_vjp
    def fn(*args):
        return forward(*args)

    def fn_fwd(*args):
        return forward(*args), args

    def fn_bwd(args, ct):
        return tuple(jax.vjp(compact, *args)[1](ct))

    fn.defvjp(fn_fwd, fn_bwd)
    return fn


# -- the same functions per seed with array operations (for the backward pass) ---------
def _mm_compact(a, b):
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _predict_cov_compact(P, A, L, Q):
    C = _mm_compact(_mm_compact(A, P), A.T) + _mm_compact(_mm_compact(L, Q), L.T)
    return 0.5 * (C + C.T)


def _update_diag_compact(P, H, innovation, r):
    delta = jnp.zeros_like(P[0])
    for i in range(H.shape[0]):
        h = H[i]
        PHt = jnp.sum(P * h[None, :], axis=1)
        s = jnp.sum(h * PHt) + r[i]
        delta = delta + PHt / s * (innovation[i] - jnp.sum(h * delta))
        P = P - (PHt[:, None] * PHt[None, :]) / s
    return delta, P


_predict_cov = _batch_last(predict_cov, _predict_cov_compact)
_update_diag = _batch_last(update_diag, _update_diag_compact)


# -- drop-in EKF steps ------------------------------------------------------------------
def ekf_predict(f: Callable, belief: Gaussian, u, Q, noise_dim: int) -> Gaussian:
    """One prediction step, eq. (11)-(12): mean = f(mean, u, 0), P = A P A' + L Q L'.

    Same as ``ekf.ekf_predict``; the covariance is computed by the batch-last kernel
    :func:`predict_cov`, and A = df/dxi, L = df/dn1 come from one ``jacfwd`` over the
    stacked (xi, n1).
    """
    n = belief.mean.shape[0]
    w0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    mean = f(belief.mean, u, w0)
    J = jax.jacfwd(lambda xw: f(xw[:n], u, xw[n:]))(jnp.concatenate([belief.mean, w0]))
    Q = jnp.asarray(Q, belief.cov.dtype)
    return Gaussian(mean, _predict_cov(belief.cov, J[:, :n], J[:, n:], Q))


def ekf_update_diag(h: Callable, belief: Gaussian, z, r, noise_dim: int) -> Gaussian:
    """Correction for additive measurement noise with covariance ``diag(r)``, eq. (13)-(16).

    Same as ``ekf.ekf_update_diag`` (sequential scalar updates, all linearised at the
    prior mean); the covariance arithmetic runs in the batch-last kernel
    :func:`update_diag`.
    """
    v0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    innovation = z - h(belief.mean, v0)
    H = jax.jacfwd(h, argnums=0)(belief.mean, v0)
    r = jnp.asarray(r, belief.cov.dtype)
    delta, P = _update_diag(belief.cov, H, innovation, r)
    return Gaussian(belief.mean + delta, P)
