"""Covariance prediction written entry by entry: seed 000 eq. (12), P' = A P A' + L Q L'.

Matrices are Python lists of their entries, each an array of any batch shape (none, or
trailing batch axes as :mod:`jaxnc.estimators.ekf_batched` uses). Only the upper
triangle is computed, entry (j, i) is the same array as (i, j) (exactly symmetric), and
products with structurally zero Jacobian entries (a :class:`~jaxnc.estimators.sparsity.Pattern`)
are never formed. Every operation is elementwise: under ``vmap`` the per-seed call
becomes loops over seeds with no reductions over matrix axes (docs/design_notes.md).

Only the upper triangle of ``P`` is read, so reverse mode puts the cotangent of a
symmetric input on it: entry (i, j), i < j, carries what a dense formula splits between
(i, j) and (j, i). Gradients along symmetric directions (the only ones a covariance
moves in) are the same.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxnc.estimators.sparsity import Pattern

__all__ = ["predict_cov"]


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


def _sym_entries(P):
    """Entries of symmetric ``P``, the lower triangle referring to the upper one."""
    n = P.shape[0]
    E = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            E[i][j] = E[j][i] = P[i, j]
    return E


def predict_cov(P, A, L, Q, pa: Pattern | None = None, pl: Pattern | None = None):
    """Covariance prediction, seed 000 eq. (12): A P A' + L Q L', batch-last.

    ``Q`` is (nw, nw) or a vector of variances (diagonal); ``pa``, ``pl`` (static) the
    patterns of A and L (None: dense): products with their structural zeros are skipped.
    Matrices are handled as Python lists of their entries (each an array of the batch
    shape); only the upper triangle is computed, and entry (j, i) is the same array as
    (i, j): the result is exactly symmetric.
    """
    n, nw = P.shape[0], L.shape[1]
    ma, ml = _mask(pa, (n, n)), _mask(pl, (n, nw))
    Pe = _sym_entries(P)
    zero = jnp.zeros(P.shape[2:], P.dtype)
    # AP = A P on the rows A can be nonzero in
    AP = {i: [_sum(A[i, k] * Pe[k][j] for k in np.flatnonzero(ma[i])) for j in range(n)]
          for i in range(n) if ma[i].any()}
    if Q.ndim == 1:
        LQ = {i: {k: L[i, k] * Q[k] for k in np.flatnonzero(ml[i])} for i in range(n)}
        LQL = lambda i, j: [LQ[i][k] * L[j, k] for k in np.flatnonzero(ml[i] & ml[j])]
    else:
        LQ = {i: [_sum(L[i, k] * Q[k, l] for k in np.flatnonzero(ml[i])) for l in range(nw)]
              for i in range(n) if ml[i].any()}
        LQL = lambda i, j: [LQ[i][k] * L[j, k] for k in np.flatnonzero(ml[j])] if i in LQ else []
    C = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            terms = [AP[i][l] * A[j, l] for l in np.flatnonzero(ma[j])] if i in AP else []
            terms += LQL(i, j)
            C[i][j] = C[j][i] = _sum(terms) if terms else zero
    return _stack(C)
