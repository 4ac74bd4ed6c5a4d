"""Batched EKF with the seed axis last: a whole-sequence filter and its kernels.

Written *batch-last* (matrix indices lead, the seed axis trails, every sum over a matrix
index unrolled into slices of the leading axes: no ``reduce`` over a non-minor axis, no
``dot_general``), each operation is one contiguous, vectorised loop over seeds (why, and
what it measured: docs/design_notes.md).

:func:`ekf_filter` filters many seeds' recorded sequences: it moves the seed axis last
once, runs the whole ``lax.scan`` batch-last, Jacobians included (forward-mode ``jvp`` of
the model's own methods on batch-last arrays, optionally with their sparsity,
``structure=``, :mod:`jaxnc.estimators.sparsity`), and moves it back; for a single seed
use the per-seed ``ekf`` functions. It needs model methods that accept trailing batch
axes (``x`` of shape (n, B)), as :class:`jaxnc.plants.mecanum.Mecanum`'s do; it checks
that before tracing.

Drop-in replacements for :func:`jaxnc.estimators.ekf.ekf_predict` and
:func:`jaxnc.estimators.ekf.ekf_update_diag` (same signatures, ``structure`` and
``jacobian_grad`` included, same results up to float32 summation order; seed 000 eq.
11-16). Callers keep writing per-seed code and ``jax.vmap`` it; only the covariance
arithmetic changes how it is batched. The loop's ``EKF(form="sequential",
batch_last=True)`` corrects with :func:`ekf_update_diag` (the prediction's drop-in measured
no faster in a closed loop: benchmarks/RESULTS.md, "Helper lay").

How: each kernel is wrapped by :func:`_batch_last`:

* ``jax.custom_batching.custom_vmap``: unbatched, the kernel runs on the per-seed
  arrays (batch shape ``()``). Batched, its rule receives the batch-first operands,
  moves the batch axis last (unbatched operands are broadcast), runs the *same*
  kernel and moves the axis back.
* ``jax.custom_jvp`` on the outside (``custom_vmap`` alone supports no differentiation):
  the derivative is ``jax.jvp`` of the same function written per seed with array
  operations (as in ``ekf``), batched by plain ``vmap``; forward mode (``jax.jvp``,
  ``jacfwd``) uses it as it is and reverse mode transposes it. (Until 2026-12-04 a
  ``custom_vjp``, which refused forward mode: the seed-000 loop, whose filter uses these
  kernels by default since then, would have refused ``jacfwd``.)
"""
from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from jaxnc._validate import jit_when_eager
from jaxnc.estimators.covariance import predict_cov, update_diag
from jaxnc.estimators.ekf import Gaussian, _check_cov, predict_with, update_diag_with
from jaxnc.estimators.sparsity import EKFStructure, Pattern, check_shape, embed, jacobian_columns

__all__ = ["Gaussian", "ekf_filter", "ekf_predict", "ekf_update_diag", "predict_cov", "update_diag"]


# -- batch-last kernels: matrix indices lead, batch axes (possibly none) trail --------
# ``predict_cov`` (entry by entry) and ``update_diag`` (the sequential scalar update) live
# in jaxnc.estimators.covariance, shared with the per-seed ``ekf.ekf_predict`` and
# ``ekf.ekf_update_diag``; structurally zero entries (a Pattern) are never read.


# -- batching and differentiation -------------------------------------------------------
def _to_last(x, batched, size):
    if batched:
        return jnp.moveaxis(x, 0, -1)
    return jnp.broadcast_to(x[..., None], x.shape + (size,))


def _from_last(x):
    return jnp.moveaxis(x, -1, 0)


def _batch_last(kernel: Callable, compact: Callable) -> Callable:
    """``kernel(*arrays)`` made batch-last under ``vmap``, and differentiable.

    ``kernel`` must accept arrays with any number of trailing batch axes (the same on
    every argument) and return a pytree of arrays with those trailing axes.
    ``compact`` computes the same function per seed with array operations; the
    derivatives are its ``jax.jvp`` (batched by plain ``vmap``; reverse mode transposes
    it): differentiating the unrolled kernel instead gives the same numbers but an
    expression graph that took ~7x longer to compile.
    """

    @custom_vmap
    def forward(*args):
        return kernel(*args)

    @forward.def_vmap
    def _forward_rule(size, in_batched, *args):
        out = kernel(*(_to_last(a, b, size) for a, b in zip(args, in_batched)))
        out = jax.tree.map(_from_last, out)
        return out, jax.tree.map(lambda _: True, out)

    return _derivatives_by(forward, compact)


def _derivatives_by(forward: Callable, reference: Callable) -> Callable:
    """``forward`` whose derivatives are those of ``reference``, the same function written
    with array operations: its ``jvp`` (a ``custom_jvp``), so forward mode (``jax.jvp``,
    ``jacfwd``) works, and reverse mode transposes it."""
    @jax.custom_jvp
    def fn(*args):
        return forward(*args)

    # under a checkpoint, reverse mode recomputes reference's primal in its backward pass
    # instead of storing its intermediates at every step (as the custom_vjp this replaced did)
    tangent = jax.checkpoint(lambda p, t: jax.jvp(reference, p, t)[1])

    @fn.defjvp
    def _fn_jvp(primals, tangents):
        return forward(*primals), tangent(primals, tangents)

    return fn


# -- the same functions per seed with array operations (for the derivatives) -----------
def _mm_compact(a, b):
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _predict_cov_compact(P, A, L, Q):
    LQ = L * Q[None, :] if Q.ndim == 1 else _mm_compact(L, Q)
    C = _mm_compact(_mm_compact(A, P), A.T) + _mm_compact(LQ, L.T)
    return 0.5 * (C + C.T)


#: the sequential update per seed, its sums as reductions (the derivatives' form)
_update_diag_compact = functools.partial(update_diag, unroll=False)


@functools.cache
def _predict_last(pa: Pattern | None, pl: Pattern | None, diagonal: bool, dense: bool) -> Callable:
    kernel = functools.partial(predict_cov, pa=pa, pl=pl, diagonal=diagonal)   # Q may gain the batch axis
    return _batch_last(kernel, _predict_cov_compact if dense else kernel)


@functools.cache
def _update_last(ph: Pattern | None) -> Callable:
    return _batch_last(functools.partial(update_diag, ph=ph), functools.partial(update_diag, ph=ph, unroll=False))


def predict_kernel(P, A, L, Q, pa: Pattern | None = None, pl: Pattern | None = None):
    """:func:`predict_cov` (the same arguments; the patterns static) run batch-last under
    ``vmap`` (:func:`_batch_last`): the kernel of :func:`ekf_predict` with a ``structure``,
    for :func:`jaxnc.estimators.ekf.predict_with`. Per seed it is ``predict_cov`` itself,
    and its derivative is ``predict_cov``'s per-seed one, as for
    :func:`jaxnc.estimators.ekf.ekf_predict` with the structure."""
    return _predict_last(pa, pl, jnp.ndim(Q) == 1, False)(P, A, L, Q)


def _predict_kernel_dense(P, A, L, Q, pa=None, pl=None):
    """:func:`predict_kernel` without a structure (the patterns are dense): its derivative
    is that of the dense matrix form, as for :func:`jaxnc.estimators.ekf.ekf_predict`
    without one (whose gradient with respect to a full ``Q`` is symmetric)."""
    return _predict_last(pa, pl, jnp.ndim(Q) == 1, True)(P, A, L, Q)


def update_kernel(P, H, innovation, r, ph: Pattern | None = None):
    """:func:`update_diag` (the same arguments; the pattern static) run batch-last under
    ``vmap``, its sums unrolled: the kernel of :func:`ekf_update_diag`, for
    :func:`jaxnc.estimators.ekf.update_diag_with`. Its derivative is the per-seed one of
    the reduction form, the one :func:`jaxnc.estimators.ekf.ekf_update_diag` runs."""
    return _update_last(ph)(P, H, innovation, r)


# -- drop-in EKF steps ------------------------------------------------------------------
def ekf_predict(f: Callable, belief: Gaussian, u, Q, noise_dim: int, *, jacobian_grad: bool = True,
                structure: EKFStructure | None = None) -> Gaussian:
    """One prediction step, eq. (11)-(12): mean = f(mean, u, 0), P = A P A' + L Q L'.

    Same as ``ekf.ekf_predict`` (the same arguments), the covariance computed by the
    batch-last kernel :func:`predict_cov` (:func:`predict_kernel`).
    """
    kernel = _predict_kernel_dense if structure is None else predict_kernel
    return predict_with(kernel, f, belief, u, Q, noise_dim, jacobian_grad=jacobian_grad, structure=structure)


def ekf_update_diag(h: Callable, belief: Gaussian, z, r, noise_dim: int, *, jacobian_grad: bool = True,
                    structure: EKFStructure | None = None) -> Gaussian:
    """Correction for additive measurement noise with covariance ``diag(r)``, eq. (13)-(16).

    Same as ``ekf.ekf_update_diag`` (the same arguments; sequential scalar updates, all
    linearised at the prior mean); the covariance arithmetic runs in the batch-last kernel
    :func:`update_diag` (:func:`update_kernel`).
    """
    return update_diag_with(update_kernel, h, belief, z, r, noise_dim,
                            jacobian_grad=jacobian_grad, structure=structure)


# -- the whole filter, batch-last ---------------------------------------------------------
def _reverse_by_compact(kernel: Callable, compact: Callable, in_axes: tuple) -> Callable:
    """``kernel`` on batch-last arrays, its derivatives those of ``compact``.

    ``in_axes`` says, per argument, -1 (seed axis last) or None (shared by all seeds).
    Reverse mode through the unrolled kernels gives the same numbers but compiles
    minutes instead of seconds (an expression graph of thousands of slices); these
    derivatives are the per-seed array code's under ``vmap``, as for ``ekf``.
    """
    return _derivatives_by(kernel, jax.vmap(compact, in_axes=in_axes, out_axes=-1))


def _jacobian(fn, x, cols=None):
    """d fn / d x for batch-last ``x`` of shape (n, *batch): (n_out, n, *batch).

    One forward-mode product per input direction in ``cols`` (static; None: all) on a
    *leading* axis, so the seed axis stays minor; the other columns are zeros. The
    model's code sees batch-last arrays only.
    """
    n = x.shape[0]
    cols = tuple(range(n)) if cols is None else tuple(cols)
    return embed(jacobian_columns(fn, x, cols, axis=1), cols, n, axis=1)


def _check_model(f, h, n, nu, nw, m, dtype):
    """Evaluate f and h abstractly on a batch of b seeds to fail early with a clear message; b
    differs from every size of the model, so a per-seed model that contracts or broadcasts
    against the batch axis (``x @ A.T``) fails here rather than mixing seeds when B equals a size."""
    b = min(set(range(2, 7)) - {n, nu, nw, m})
    x, u = jax.ShapeDtypeStruct((n, b), dtype), jax.ShapeDtypeStruct((nu, b), dtype)
    w, v = jax.ShapeDtypeStruct((nw, b), dtype), jax.ShapeDtypeStruct((m, b), dtype)
    for name, fn, args, want in (("f", f, (x, u, w), (n, b)), ("h", h, (x, v), (m, b))):
        try:
            out = jax.eval_shape(fn, *args)
            shape = out.shape
        except Exception as e:  # noqa: BLE001 -- re-raised with the cause attached
            raise ValueError(
                f"ekf_filter: the model function {name} must accept batch-last arrays "
                f"(x of shape (n, B), every other argument (dim, B)) and broadcast over the trailing "
                f"axis; calling it on a batch of {b} failed: {e}") from e
        if shape != want:
            raise ValueError(f"ekf_filter: the model function {name} returned shape {shape} for a batch of "
                             f"{b} seeds; expected {want} (batch axis last)")


def ekf_filter(f: Callable, h: Callable, belief0: Gaussian, us, zs, valid, Q, r, *,
               noise_dim: int, return_means: bool = False, structure: EKFStructure | None = None):
    """EKF over whole sequences for many seeds, run with the seed axis last (seed 000 eq. 11-16).

    For k = 0 .. K-1: predict with ``us[:, k]`` (eq. 11-12, A = df/dxi, L = df/dn1 at
    the mean, process noise covariance ``Q``), then, where ``valid[:, k]``, correct with
    ``zs[:, k]`` by sequential scalar updates with ``R = diag(r)`` (eq. 13-16, as
    :func:`jaxnc.estimators.ekf.ekf_update_diag`); a dropped measurement leaves the
    prediction. Equal, up to float32 summation order, to ``vmap`` over seeds of a
    ``lax.scan`` of ``ekf.ekf_predict`` and ``ekf.ekf_update_diag``; reverse-mode
    differentiable.

    Args:
      f: ``f(x, u, w) -> x'`` and ``h``: ``h(x, v) -> z`` (additive ``v``), written for
        one seed but broadcasting over trailing batch axes: called with ``x`` of shape
        (n, B), ``u`` (nu, B), ``w`` (noise_dim, B), ``v`` (m, B).
      belief0: initial beliefs, ``mean`` (B, n), ``cov`` (B, n, n).
      us: inputs (B, K, nu); zs: measurements (B, K, m); valid: (B, K) booleans.
      Q: (noise_dim, noise_dim) process noise covariance, or (noise_dim,) variances of a
        diagonal one; r: (m,) measurement variances.
      noise_dim: dimension of the process noise ``w`` (static).
      return_means: also return the filtered means (B, K, n) (memory K·n·B).
      structure: the sparsity patterns of A, L and H (static; from
        :func:`jaxnc.estimators.sparsity.detect_structure` on the per-seed model):
        Jacobian columns and products that are structurally zero are skipped (same
        values up to float32 summation order). None: dense.

    Returns:
      the final beliefs (batch-first), and the means if ``return_means``.

    Raises:
      ValueError: shapes that do not fit (naming the argument), a model that does not
        broadcast over the batch axis, and (when concrete) a Q that is not PSD or an r with
        an entry <= 0 (naming ``Q`` / ``r``).
    """
    mean0, cov0 = jnp.asarray(belief0.mean), jnp.asarray(belief0.cov)
    us, zs, valid = jnp.asarray(us), jnp.asarray(zs), jnp.asarray(valid)
    if mean0.ndim != 2 or cov0.shape != mean0.shape + mean0.shape[-1:]:
        raise ValueError(f"ekf_filter: belief0 must have mean (B, n) and cov (B, n, n); got {mean0.shape}, {cov0.shape}")
    B, n = mean0.shape
    if us.ndim != 3 or zs.ndim != 3 or us.shape[:2] != zs.shape[:2] or us.shape[0] != B or valid.shape != us.shape[:2]:
        raise ValueError(f"ekf_filter: us (B, K, nu), zs (B, K, m) and valid (B, K) must share B = {B} and K; "
                         f"got {us.shape}, {zs.shape}, {valid.shape}")
    m, nu = zs.shape[-1], us.shape[-1]
    dtype = cov0.dtype
    Q, r = jnp.asarray(Q, dtype), jnp.asarray(r, dtype)
    if Q.shape not in ((noise_dim, noise_dim), (noise_dim,)) or r.shape != (m,):
        raise ValueError(f"ekf_filter: Q must be ({noise_dim}, {noise_dim}) or ({noise_dim},) (diagonal) and r ({m},); "
                         f"got {Q.shape}, {r.shape}")
    _check_cov("ekf_filter", "Q", Q, noise_dim, form="either", definite=False)    # when concrete: PSD
    _check_cov("ekf_filter", "r", r, m, form="vector", definite=True)             # variances > 0
    if structure is not None:
        for name, pat, want in zip("ALH", structure, ((n, n), (n, noise_dim), (m, n))):
            check_shape("ekf_filter", name, pat, want)
    _check_model(f, h, n, nu, noise_dim, m, dtype)
    return _filter(f, h, noise_dim, return_means, structure, mean0, cov0, us, zs, valid, Q, r)


@jit_when_eager(static_argnums=(0, 1, 2, 3, 4))     # eagerly one program per model and shapes, not one per call
def _filter(f, h, noise_dim: int, return_means: bool, structure, mean0, cov0, us, zs, valid, Q, r):
    """:func:`ekf_filter`'s run on checked arguments (traced in the caller's trace)."""
    B, n = mean0.shape
    m = zs.shape[-1]
    pa, pl, ph = (None, None, None) if structure is None else structure
    # live Jacobian directions: A's columns, then L's (offset n) in the stacked (xi, n1)
    dirs = None if structure is None else pa.cols + tuple(n + j for j in pl.cols)
    hcols = None if structure is None else ph.cols
    predict_last = _reverse_by_compact(functools.partial(predict_cov, pa=pa, pl=pl), _predict_cov_compact,
                                       (-1, -1, -1, None))
    update_last = _reverse_by_compact(functools.partial(update_diag, ph=ph), _update_diag_compact,
                                      (-1, -1, -1, None))

    def step(carry, inp):
        x, P = carry
        u, z, ok = inp
        xw = jnp.concatenate([x, jnp.zeros((noise_dim, B), x.dtype)])
        fxw = lambda a: f(a[:n], u, a[n:])
        J = _jacobian(fxw, xw, dirs)
        x = fxw(xw)
        P = predict_last(P, J[:, :n], J[:, n:], Q)
        hx = lambda a: h(a, jnp.zeros((m, B), a.dtype))
        delta, Pc = update_last(P, _jacobian(hx, x, hcols), z - hx(x), r)
        x, P = jnp.where(ok[None], x + delta, x), jnp.where(ok[None, None], Pc, P)
        return (x, P), (x if return_means else None)

    xs = (jnp.moveaxis(us, 0, -1), jnp.moveaxis(zs, 0, -1), jnp.moveaxis(valid, 0, -1))
    (x, P), means = jax.lax.scan(step, (jnp.moveaxis(mean0, 0, -1), jnp.moveaxis(cov0, 0, -1)), xs)
    final = Gaussian(jnp.moveaxis(x, -1, 0), jnp.moveaxis(P, -1, 0))
    return (final, jnp.moveaxis(means, -1, 0)) if return_means else final
