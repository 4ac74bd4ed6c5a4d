"""The EKF's covariance kernels, written on matrices whose indices lead and whose batch axes
(none, or trailing ones as :mod:`jaxnc.estimators.ekf_batched` uses) trail: the one home
of the prediction, seed 000 eq. (12), and of the diagonal (sequential scalar) update,
eq. (13)-(16) with R = diag(r), for the per-seed :mod:`jaxnc.estimators.ekf` and the
batch-last :mod:`jaxnc.estimators.ekf_batched` alike.

:func:`predict_cov` handles matrices as Python lists of their entries, each an array of the
batch shape. Only the upper triangle is computed, entry (j, i) is the same array as (i, j)
(exactly symmetric), and products with structurally zero Jacobian entries (a
:class:`~jaxnc.estimators.sparsity.Pattern`) are never formed. Every operation is
elementwise: under ``vmap`` the per-seed call becomes loops over seeds with no reductions
over matrix axes (docs/design_notes.md).

Only the upper triangle of ``P`` is read, so reverse mode puts the cotangent of a
symmetric input on it: entry (i, j), i < j, carries what a dense formula splits between
(i, j) and (j, i). Gradients along symmetric directions (the only ones a covariance
moves in) are the same.

:func:`update_diag` works on whole (n, n, *batch) arrays; its sums over a matrix index are
either unrolled into slices (batch-last: no reduction over a non-minor axis) or reductions
(per seed, and the batch-last form's backward pass), a static choice of how, not of what.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc.estimators.sparsity import Pattern, take

__all__ = ["predict_cov", "update_diag"]


def _sum(terms):
    terms = iter(terms)
    acc = next(terms)
    for t in terms:
        acc = acc + t
    return acc


def _mask(pattern: Pattern | None, shape) -> np.ndarray:
    return np.ones(shape, bool) if pattern is None else pattern.array


def _stack(rows):
    return jnp.stack([jnp.stack(r) for r in rows])


def _entries(M):
    """``M`` (two leading matrix indices) as a list of rows, each a list of its entries.

    Unstacked (``lax.unstack``), not indexed entry by entry: the forward pass is the same
    slices, but reverse mode stacks the entries' cotangents back in one concatenation,
    where an indexed entry's cotangent is padded to the whole matrix and the pads summed
    (work quadratic in the entries, docs/design_notes.md)."""
    return [list(jax.lax.unstack(row)) for row in jax.lax.unstack(M)]


def _sym_entries(P):
    """Entries of symmetric ``P``, the lower triangle referring to the upper one."""
    n = P.shape[0]
    Pe = _entries(P)
    E = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            E[i][j] = E[j][i] = Pe[i][j]
    return E


def predict_cov(P, A, L, Q, pa: Pattern | None = None, pl: Pattern | None = None, *, diagonal: bool | None = None):
    """Covariance prediction, seed 000 eq. (12): A P A' + L Q L', batch-last.

    ``Q`` is (nw, nw) or a vector of variances (diagonal), either with the batch axes of
    the other arguments trailing or with none; ``diagonal`` (static) says which, None: Q is
    diagonal when it is 1-D (Q with batch axes needs it). ``pa``, ``pl`` (static) the
    patterns of A and L (None: dense): products with their structural zeros are skipped.
    Matrices are handled as Python lists of their entries (each an array of the batch
    shape); only the upper triangle is computed, and entry (j, i) is the same array as
    (i, j): the result is exactly symmetric.
    """
    n, nw = P.shape[0], L.shape[1]
    ma, ml = _mask(pa, (n, n)), _mask(pl, (n, nw))
    Pe = _sym_entries(P)
    A, L = _entries(A), _entries(L)
    diagonal = (Q.ndim == 1) if diagonal is None else diagonal
    Q = list(jax.lax.unstack(Q)) if diagonal else _entries(Q)
    zero = jnp.zeros(P.shape[2:], P.dtype)
    # AP = A P on the rows A can be nonzero in
    AP = {i: [_sum(A[i][k] * Pe[k][j] for k in np.flatnonzero(ma[i])) for j in range(n)]
          for i in range(n) if ma[i].any()}
    if diagonal:
        LQ = {i: {k: L[i][k] * Q[k] for k in np.flatnonzero(ml[i])} for i in range(n)}
        LQL = lambda i, j: [LQ[i][k] * L[j][k] for k in np.flatnonzero(ml[i] & ml[j])]
    else:
        LQ = {i: [_sum(L[i][k] * Q[k][l] for k in np.flatnonzero(ml[i])) for l in range(nw)]
              for i in range(n) if ml[i].any()}
        LQL = lambda i, j: [LQ[i][k] * L[j][k] for k in np.flatnonzero(ml[j])] if i in LQ else []
    C = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            terms = [AP[i][l] * A[j][l] for l in np.flatnonzero(ma[j])] if i in AP else []
            terms += LQL(i, j)
            C[i][j] = C[j][i] = _sum(terms) if terms else zero
    return _stack(C)


def _dot(x, h, live, axis: int, unroll: bool):
    """sum over j in ``live`` (static) of x[..., j, ...] (j on ``axis``) times h[j]; ``h`` has
    the index j leading and ``x``'s batch axes trailing. ``unroll``: a chain of slices and
    adds in the order of ``live``; else one multiply and a reduction over ``axis``. Products
    are written x h on axis 1, h x on axis 0 (docs/design_notes.md, "One diagonal update")."""
    lead = (None,) * axis
    if unroll:
        at = (slice(None),) * axis
        terms = ((x[at + (j,)], h[j][lead]) for j in live)
    else:
        terms = [(take(x, live, axis), take(h, live, 0)[lead])]
    terms = [a * b if axis else b * a for a, b in terms]
    return _sum(terms) if unroll else jnp.sum(terms[0], axis=axis)


def _lead(x, k: int, unroll: bool):
    """``x`` (batch axes only) with ``k`` leading axes, to broadcast against matrix entries;
    the reduction form leaves a 0-d ``x`` (no batch axes) as it is. Each form keeps the
    operations, and so XLA:CPU's rounding, of the code it replaced (docs/design_notes.md,
    "One diagonal update")."""
    return x[(None,) * k] if unroll or x.ndim else x


def update_diag(P, H, innovation, r, ph: Pattern | None = None, *, unroll: bool = True):
    """Sequential scalar correction, seed 000 eq. (13)-(16) with R = diag(r).

    For each output i in turn, with the Jacobian and the prediction at the prior mean:
    s = h P h' + r_i, k = P h' / s, delta += k (e_i - h delta), P <- P - (P h')(P h')' / s,
    where h = H[i] and e the innovation (sequential processing of independent
    measurements, e.g. Bar-Shalom, Li & Kirubarajan, "Estimation with Applications to
    Tracking and Navigation", section 7.2). Each step is an exactly symmetric rank-one
    downdate, equal to the Joseph form for the optimal gain; the result is the batch
    linearised update in exact arithmetic. Nothing is factorised or inverted.

    Args:
      P: float[n, n, *batch], the prior covariance; H: float[m, n, *batch] = dh/dx;
        innovation: float[m, *batch] = z - h(mean, 0); r: float[m] or float[m, *batch],
        the measurement variances.
      ph: static, the pattern of H (None: dense): each row's sums run over its nonzero
        columns only, and a row without any is skipped (z_i does not depend on the state).
      unroll: static; True writes every sum over a matrix index as slices and adds (the
        batch-last form, fast with the batch axes trailing), False as reductions (per
        seed under ``vmap``), the mean's correction then starting from zeros. Same
        operations in the same order otherwise.

    Returns:
      (delta float[n, *batch], the correction of the mean; the posterior covariance
      float[n, n, *batch]).
    """
    n, m = P.shape[0], H.shape[0]
    mh = _mask(ph, (m, n))
    delta = None if unroll else jnp.zeros(P.shape[1:], P.dtype)
    for i in range(m):
        live = tuple(int(j) for j in np.flatnonzero(mh[i]))
        if not live:                           # z_i does not depend on the state
            continue
        h = H[i]
        PHt = _dot(P, h, live, 1, unroll)
        s = _dot(PHt, h, live, 0, unroll) + r[i]
        e = innovation[i] if delta is None else innovation[i] - _dot(delta, h, live, 0, unroll)
        k = PHt / _lead(s, 1, unroll)
        delta = k * _lead(e, 1, unroll) if delta is None else delta + k * _lead(e, 1, unroll)
        P = P - (PHt[:, None] * PHt[None, :]) / _lead(s, 2, unroll)
    if delta is None:
        return jnp.zeros(P.shape[1:], P.dtype), P
    return delta, P
