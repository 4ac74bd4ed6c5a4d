"""Extended Kalman filter: predict and Joseph-form update.

Seed 000 eq. (11)-(16): prediction with Jacobians A = df/dxi, L = df/dn1; correction
with H = dh/dxi, M = dh/dn2, gain K = P H' (H P H' + M R M')^-1 and the Joseph form
P = (I - K H) P (I - K H)' + K (M R M') K'. Jacobians come from forward-mode
differentiation (``jax.jacfwd``, or one ``jvp`` per live direction) of the model's own
``dynamics(x, u, w)`` / ``measure(x, v)`` methods, so a linear model gives exactly the
Kalman filter. ``ekf_predict`` and ``ekf_update_diag`` accept the Jacobians' sparsity
patterns (``structure``, :mod:`jaxnc.estimators.sparsity`) and then skip the structural
zeros.

The square-root form (:class:`SqrtGaussian`, :func:`ekf_predict_sqrt`,
:func:`ekf_update_sqrt`) carries a factor S with P = S S' and updates it by orthogonal
(QR) transformations of the pre-arrays, so the covariance it represents is positive
semi-definite by construction. The Joseph form above stays the reference (the papers'
equations, and the loops' saved results); the square-root form is for the degenerate
float32 cases where the Joseph form loses definiteness: no process noise and very
precise measurements (docs/build_your_own_loop.md, "Covariance in float32").

Every function checks the static shapes of its noise covariance against the model when
it is traced (ValueError naming ``Q``/``R``/``r``/``noise_dim``/``z`` and the expected
shape), and, when the covariance is concrete (not a tracer), that it is symmetric and positive
semi-definite (``R``: definite).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from jaxnc._validate import psd_rounding
from jaxnc.estimators.covariance import predict_cov, update_diag
from jaxnc.estimators.sparsity import EKFStructure, Pattern, check_shape, embed, jacobian_columns


class Gaussian(NamedTuple):
    """Belief N(mean, cov) of the state."""

    mean: jax.Array
    cov: jax.Array


class SqrtGaussian(NamedTuple):
    """Belief N(mean, S S') carried by a square-root factor ``S`` (float[n, n], lower
    triangular up to column signs): the square-root form's belief. ``cov`` is S S'."""

    mean: jax.Array
    sqrt: jax.Array

    @property
    def cov(self):
        return self.sqrt @ self.sqrt.T

    @classmethod
    def of(cls, g: Gaussian) -> "SqrtGaussian":
        """The square-root belief of ``g`` (its covariance's PSD square root)."""
        return cls(g.mean, _psd_sqrt(g.cov))


def _psd_sqrt(M):
    """A factor F with F F' = M for a symmetric positive semi-definite M (by its
    eigendecomposition: works for a singular M, e.g. zero process noise)."""
    M = jnp.asarray(M)
    lam, V = jnp.linalg.eigh(0.5 * (M + M.T))
    return V * jnp.sqrt(jnp.maximum(lam, 0.0))[None, :]


@jax.custom_jvp
def _tria(M):
    """Lower-triangular T with T T' = M M' (M: float[n, k], k >= n), by QR of M'.

    Its derivative (:func:`_tria_jvp`) is that of the triangular factor of S = M M' (the
    Cholesky factor's, with QR's signs), dT = T Phi(T^-1 dS T^-T), dS = dM M' + M dM', Phi the
    lower triangle with the diagonal halved, computed as T^-1 dM (T^-1 M)' + its transpose.
    JAX's QR derivative divides by R's diagonal and gave NaN where the factor is singular in
    the working precision (a covariance of 1e15 along one direction and 1e-5 along another in
    float32: a filter after seconds without a measurement); here a diagonal entry below
    ``eps`` times the largest is replaced by that floor in the solves (the derivative of such
    a factor has no accuracy in that precision anyway), so it stays finite. Equal to QR's
    derivative elsewhere (tested, float64)."""
    return jnp.linalg.qr(M.T, mode="r").T


@_tria.defjvp
def _tria_jvp(primals, tangents):
    (M,), (dM,) = primals, tangents
    T = _tria(M)
    d = jnp.diagonal(T)
    floor = jnp.finfo(T.dtype).eps * jnp.max(jnp.abs(d))
    floor = jnp.maximum(floor, jnp.finfo(T.dtype).tiny)
    safe = jnp.where(jnp.abs(d) < floor, jnp.where(d < 0, -floor, floor), d)
    Ts = T + jnp.diag(safe - d)
    Y = jsl.solve_triangular(Ts, M, lower=True)             # T^-1 M (Q' of M' = Q R)
    X = jsl.solve_triangular(Ts, dM, lower=True)            # T^-1 dM
    P = X @ Y.T
    P = P + P.T
    L = jnp.tril(P) - 0.5 * jnp.diag(jnp.diagonal(P))       # Phi
    return T, T @ L


def _noise_dim(where: str, noise_dim) -> int:
    if isinstance(noise_dim, bool) or not isinstance(noise_dim, (int, np.integer)) or noise_dim < 1:
        raise ValueError(f"{where}: noise_dim must be an integer >= 1 (the dimension of the model's noise "
                         f"input), got {noise_dim!r}")
    return int(noise_dim)


def _check_cov(where: str, name: str, M, dim: int, *, form: str, definite: bool) -> None:
    """``M`` is (dim, dim) (``form="matrix"``), (dim,) variances (``"vector"``) or either;
    when concrete, positive semi-definite (``definite``: definite)."""
    shape = tuple(np.shape(M))
    ok = {"matrix": ((dim, dim),), "vector": ((dim,),), "either": ((dim, dim), (dim,))}[form]
    if shape not in ok:
        want = {"matrix": f"{dim}x{dim}", "vector": f"a vector of {dim} variances",
                "either": f"{dim}x{dim} or a vector of {dim} variances"}[form]
        raise ValueError(f"{where}: {name} must be {want} (noise_dim={dim}), got shape {shape}")
    if isinstance(M, jax.core.Tracer):
        return
    try:
        a = np.asarray(M, float)
    except (TypeError, ValueError, jax.errors.ConcretizationTypeError):
        return
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: {name} must be finite")
    if a.ndim == 2 and not np.allclose(a, a.T, rtol=0.0, atol=1e-6 * max(np.abs(a).max(), np.finfo(float).tiny)):
        # a covariance is symmetric; an asymmetric one's inverse (R) is not that of its symmetric part
        raise ValueError(f"{where}: {name} must be symmetric (a covariance), got largest |{name} - {name}'| "
                         f"{np.abs(a - a.T).max():g}")
    low = a.min() if a.ndim == 1 else np.linalg.eigvalsh(0.5 * (a + a.T)).min()
    if (definite and low <= 0) or (not definite and low < -(psd_rounding(a) if a.ndim == 2 else 0.0)):
        raise ValueError(f"{where}: {name} must be positive {'definite' if definite else 'semi-definite'} "
                         f"(a covariance), got smallest eigenvalue {low:g}")


def _check_z(where: str, h: Callable, mean, z, noise_dim: int) -> None:
    _check_z_like(where, jax.eval_shape(h, mean, jnp.zeros((noise_dim,), mean.dtype)), z)


def _check_z_like(where: str, zhat, z) -> None:
    """z has the shape of ``zhat`` (h(x, v), or its shape), else a ValueError naming ``where``."""
    if tuple(np.shape(z)) != tuple(np.shape(zhat)):
        raise ValueError(f"{where}: z must have the shape of h(x, v), {tuple(np.shape(zhat))}, got {tuple(np.shape(z))}")


def _symmetrize(P):
    return 0.5 * (P + P.T)


#: the longest inner dimension :func:`_mm` and :func:`matvec` write out term by term
SMALL_MATVEC = 16


def _mm(a, b):
    """a @ b for the small matrices of a filter, as elementwise multiplies and adds.

    Up to :data:`SMALL_MATVEC` terms the sum over the inner dimension is written out
    (``a[:, 0] b[0] + a[:, 1] b[1] + ...``): under ``vmap`` it fuses into one vectorised
    loop with the arithmetic around it, where a ``dot_general`` of small matrices, or a
    multiply-``sum`` that XLA:CPU recognises as one, becomes a matrix-product library
    call per use, slow for a handful of entries (docs/design_notes.md). Longer inner
    dimensions: a broadcast multiply-sum. Results equal ``a @ b`` up to summation order.
    """
    k = a.shape[1]
    if k == 0 or k > SMALL_MATVEC:
        return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)
    acc = a[:, 0, None] * b[None, 0, :]
    for i in range(1, k):
        acc = acc + a[:, i, None] * b[None, i, :]
    return acc


def matvec(a, x):
    """a @ x for a small matrix a float[r, c] and a vector x float[c].

    For c <= :data:`SMALL_MATVEC`, written out as :func:`_mm` does (elementwise multiplies
    and adds, fused under ``vmap`` where ``a @ x`` becomes a library call per use); larger
    c: ``a @ x``. Results equal ``a @ x`` up to summation order.
    """
    a = jnp.asarray(a)
    if a.ndim != 2 or a.shape[1] == 0 or a.shape[1] > SMALL_MATVEC:
        return a @ x
    x = jnp.asarray(x)
    acc = a[:, 0] * x[0]
    for i in range(1, a.shape[1]):
        acc = acc + a[:, i] * x[i]
    return acc


def spd_solve(S, B):
    """X with S X = B, for S float[p, p] symmetric positive definite and B float[p, r]:
    ``cho_solve(cho_factor(S))``.

    A scalar innovation (p = 1) is solved in closed form, X = (B / sqrt(S)) / sqrt(S), the
    same operations as LAPACK's Cholesky factor and two triangular solves (equal bit for
    bit, tested), but elementwise, so under ``vmap`` it fuses with the filter's other
    arithmetic where ``cho_solve`` is a batched LAPACK call per use (docs/design_notes.md).
    """
    if S.shape[0] == 1:
        L = jnp.sqrt(S[0, 0])
        return (B / L) / L
    return jsl.cho_solve(jsl.cho_factor(S, lower=True), B)


def _at(x, jacobian_grad: bool):
    """The point a Jacobian is evaluated at: ``x`` itself, or ``x`` with its derivative cut
    (``jacobian_grad=False``: the Jacobian's value is the same, but gradients treat it as a
    constant, which drops the second derivatives of the model from reverse mode)."""
    return x if jacobian_grad else jax.lax.stop_gradient(x)


def ekf_predict(f: Callable, belief: Gaussian, u, Q, noise_dim: int, *, jacobian_grad: bool = True,
                structure: EKFStructure | None = None) -> Gaussian:
    """One prediction step, eq. (11)-(12): mean = f(mean, u, 0), P = A P A' + L Q L'.

    ``Q`` is the process noise covariance (noise_dim, noise_dim), or a vector of
    variances for a diagonal one (then L Q L' = (L diag(q)) L', one product fewer).

    ``structure`` (static, from :func:`jaxnc.estimators.sparsity.detect_structure`):
    the Jacobians' sparsity patterns. A and L are then computed only along their
    nonzero columns, and A P A' + L Q L' entry by entry on its upper triangle
    (:func:`jaxnc.estimators.covariance.predict_cov`), skipping every product with a
    structural zero: the skipped terms are exact zeros, so the result is the dense one up
    to float32 summation order. ``None``: dense, as matrix products.

    ``jacobian_grad=False`` (static) gives the same values, but gradients of anything
    downstream hold A and L constant: an approximation of the gradient (the covariance's
    dependence on where the model is linearised is dropped) that makes reverse mode through
    a closed loop about 2x cheaper (benchmarks/RESULTS.md).

    Raises ValueError (at trace time) when ``noise_dim`` is not an integer >= 1 or ``Q`` is
    not (noise_dim, noise_dim) / (noise_dim,), or (a concrete Q) not PSD."""
    return predict_with(None, f, belief, u, Q, noise_dim, jacobian_grad=jacobian_grad, structure=structure)


def predict_with(kernel: Callable | None, f: Callable, belief: Gaussian, u, Q, noise_dim: int, *,
                 jacobian_grad: bool = True, structure: EKFStructure | None = None) -> Gaussian:
    """:func:`ekf_predict` with its covariance computed by ``kernel(P, A, L, Q, pa, pl)``
    (``predict_cov``'s signature, the patterns dense without ``structure``; e.g. the
    batch-last kernel of :mod:`jaxnc.estimators.ekf_batched`). ``None``: as
    :func:`ekf_predict` (:func:`~jaxnc.estimators.covariance.predict_cov` with a
    ``structure``, matrix products without)."""
    noise_dim = _noise_dim("ekf_predict", noise_dim)
    _check_cov("ekf_predict", "Q", Q, noise_dim, form="either", definite=False)
    n = belief.mean.shape[0]
    w0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    mean = f(belief.mean, u, w0)
    pa, pl = (Pattern.dense(n, n), Pattern.dense(n, noise_dim)) if structure is None else structure[:2]
    check_shape("ekf_predict", "A", pa, (n, n))
    check_shape("ekf_predict", "L", pl, (n, noise_dim))
    ca, cl = pa.cols, pl.cols
    x0, u0 = _at(belief.mean, jacobian_grad), _at(u, jacobian_grad)
    # one forward-mode product per live direction of (xi, n1): A's columns, then L's
    J = jacobian_columns(lambda xw: f(xw[:n], u0, xw[n:]), jnp.concatenate([x0, w0]),
                         ca + tuple(n + j for j in cl))
    Q = jnp.asarray(Q, belief.cov.dtype)
    if structure is not None or kernel is not None:
        # entry by entry, structural zeros skipped (elementwise under vmap; docs/design_notes.md)
        A = embed(J[:, :len(ca)], ca, n, axis=1)
        L = embed(J[:, len(ca):], cl, noise_dim, axis=1)
        return Gaussian(mean, (kernel or predict_cov)(belief.cov, A, L, Q, pa, pl))
    A, L = J[:, :n], J[:, n:]                               # dense: every direction is live
    if Q.ndim == 1:
        LQL = _mm(L * Q[None, :], L.T)
    else:
        LQL = _mm(_mm(L, Q), L.T)
    cov = _mm(_mm(A, belief.cov), A.T) + LQL
    return Gaussian(mean, _symmetrize(cov))


def ekf_update(h: Callable, belief: Gaussian, z, R, noise_dim: int) -> Gaussian:
    """Correction with measurement z, eq. (13)-(16), Joseph form covariance.

    ``R`` is the covariance of the measurement noise v, (noise_dim, noise_dim); ValueError
    (at trace time) for another shape, a ``noise_dim`` that is not an integer >= 1, a ``z``
    not shaped like h(x, v), or a concrete R that is not positive definite."""
    return ekf_update_terms(h, belief, z, R, noise_dim)[0]


def ekf_update_terms(h: Callable, belief: Gaussian, z, R, noise_dim: int):
    """:func:`ekf_update` and the terms of its eq. (13)-(16) (e.g. for Theorem 1's bounds,
    :func:`jaxnc.stability.estimator_pass`).

    Returns:
      (posterior :class:`Gaussian`, H float[p, n] = dh/dx, M float[p, noise_dim] = dh/dv,
      K float[n, p] the gain of eq. (15)), all at the prior mean.
    Raises: as :func:`ekf_update`.
    """
    noise_dim = _noise_dim("ekf_update", noise_dim)
    _check_cov("ekf_update", "R", R, noise_dim, form="matrix", definite=True)
    v0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    zhat = h(belief.mean, v0)
    _check_z_like("ekf_update", zhat, z)
    H = jax.jacfwd(h, argnums=0)(belief.mean, v0)
    M = jax.jacfwd(h, argnums=1)(belief.mean, v0)
    Rm = _mm(_mm(M, R), M.T)
    PHt = _mm(belief.cov, H.T)
    S = _mm(H, PHt) + Rm
    K = spd_solve(S, PHt.T).T                                     # eq. (15)
    mean = belief.mean + jnp.sum(K * (z - zhat)[None, :], axis=1)
    IKH = jnp.eye(belief.mean.shape[0], dtype=belief.cov.dtype) - _mm(K, H)
    cov = _mm(_mm(IKH, belief.cov), IKH.T) + _mm(_mm(K, Rm), K.T)
    return Gaussian(mean, _symmetrize(cov)), H, M, K


def ekf_update_diag(h: Callable, belief: Gaussian, z, r, noise_dim: int, *, jacobian_grad: bool = True,
                    structure: EKFStructure | None = None) -> Gaussian:
    """Correction for additive measurement noise with diagonal covariance ``diag(r)``.

    Same result as ``ekf_update`` with ``R = diag(r)`` and ``M = I`` (seed 000 eq.
    13-16), computed by processing the measurements one scalar at a time, all linearised
    at the prior mean: :func:`jaxnc.estimators.covariance.update_diag` (its sums as
    reductions), the kernel the batch-last :mod:`jaxnc.estimators.ekf_batched` runs too.
    No matrix is factorised or inverted, which keeps the batched (vmapped) update
    elementwise and fast; the covariance stays exactly symmetric. ``jacobian_grad``: as in
    :func:`ekf_predict`.

    ``structure`` (static): with H's pattern, H is computed only along its nonzero
    columns and each scalar step sums only over the states its row depends on.

    ValueError (at trace time) when ``r`` is not (p,) with p = len(z) = noise_dim, or (a
    concrete r) has an entry <= 0.
    """
    return update_diag_with(None, h, belief, z, r, noise_dim, jacobian_grad=jacobian_grad, structure=structure)


def update_diag_with(kernel: Callable | None, h: Callable, belief: Gaussian, z, r, noise_dim: int, *,
                     jacobian_grad: bool = True, structure: EKFStructure | None = None) -> Gaussian:
    """:func:`ekf_update_diag` with its covariance arithmetic computed by
    ``kernel(P, H, innovation, r, ph)`` (``update_diag``'s signature, returning (delta, P);
    e.g. the batch-last kernel of :mod:`jaxnc.estimators.ekf_batched`). ``None``: as
    :func:`ekf_update_diag` (:func:`~jaxnc.estimators.covariance.update_diag`, its sums as
    reductions)."""
    noise_dim = _noise_dim("ekf_update_diag", noise_dim)
    _check_cov("ekf_update_diag", "r", r, noise_dim, form="vector", definite=True)
    n = belief.mean.shape[0]
    v0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    zhat = h(belief.mean, v0)
    _check_z_like("ekf_update_diag", zhat, z)
    innovation = z - zhat
    ph = Pattern.dense(z.shape[0], n) if structure is None else structure.H
    check_shape("ekf_update_diag", "H", ph, (z.shape[0], n))
    H = jacobian_columns(lambda x: h(x, v0), _at(belief.mean, jacobian_grad), ph.cols)   # H[:, cols]
    H = embed(H, ph.cols, n, axis=1)
    if kernel is None:
        delta, P = update_diag(belief.cov, H, innovation, jnp.asarray(r), ph, unroll=False)
    else:
        delta, P = kernel(belief.cov, H, innovation, jnp.asarray(r, belief.cov.dtype), ph)
    return Gaussian(belief.mean + delta, P)


def ekf_predict_sqrt(f: Callable, belief: SqrtGaussian, u, Q, noise_dim: int) -> SqrtGaussian:
    """:func:`ekf_predict` in square-root form: mean = f(mean, u, 0) and the factor of
    A P A' + L Q L' = [A S, L Q^(1/2)] [A S, L Q^(1/2)]', triangularised by QR, so the
    covariance stays positive semi-definite in float32 (Q may be singular, e.g. zero).
    ``Q``: (noise_dim, noise_dim) or a vector of variances; the same checks as
    :func:`ekf_predict`. Dense Jacobians (no ``structure``)."""
    noise_dim = _noise_dim("ekf_predict_sqrt", noise_dim)
    _check_cov("ekf_predict_sqrt", "Q", Q, noise_dim, form="either", definite=False)
    n = belief.mean.shape[0]
    w0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    mean = f(belief.mean, u, w0)
    J = jax.jacfwd(lambda xw: f(xw[:n], u, xw[n:]))(jnp.concatenate([belief.mean, w0]))
    A, L = J[:, :n], J[:, n:]
    Q = jnp.asarray(Q, belief.sqrt.dtype)
    LQh = L * jnp.sqrt(jnp.maximum(Q, 0.0))[None, :] if Q.ndim == 1 else L @ _psd_sqrt(Q)
    return SqrtGaussian(mean, _tria(jnp.concatenate([A @ belief.sqrt, LQh], axis=1)))


def ekf_update_sqrt(h: Callable, belief: SqrtGaussian, z, R, noise_dim: int) -> SqrtGaussian:
    """:func:`ekf_update` in square-root form (the array algorithm: e.g. Kailath, Sayed &
    Hassibi, "Linear Estimation", section 12.3): the pre-array
    [[(M R M')^(1/2), H S], [0, S]] is triangularised by QR into [[Se, 0], [Kb, S+]], so
    that Se Se' = H P H' + M R M', the gain is K = Kb Se^-1 and the posterior factor is
    S+: P+ = S+ S+' is positive semi-definite by construction, also when the measurement
    is far more precise than the prior (where the Joseph form's float32 result can become
    indefinite, or the rank-one downdate of :func:`ekf_update_diag` cancel to 0).
    ``R``: (noise_dim, noise_dim), or a vector of variances (diagonal); the same checks
    as :func:`ekf_update`."""
    noise_dim = _noise_dim("ekf_update_sqrt", noise_dim)
    _check_cov("ekf_update_sqrt", "R", R, noise_dim, form="either", definite=True)
    n = belief.mean.shape[0]
    v0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    zhat = h(belief.mean, v0)
    _check_z_like("ekf_update_sqrt", zhat, z)
    H = jax.jacfwd(h, argnums=0)(belief.mean, v0)
    M = jax.jacfwd(h, argnums=1)(belief.mean, v0)
    R = jnp.asarray(R, belief.sqrt.dtype)
    MRh = M * jnp.sqrt(R)[None, :] if R.ndim == 1 else M @ _psd_sqrt(R)
    p = H.shape[0]
    if MRh.shape[1] < p:                                    # fewer noise inputs than outputs
        MRh = jnp.concatenate([MRh, jnp.zeros((p, p - MRh.shape[1]), MRh.dtype)], axis=1)
    k = MRh.shape[1]
    pre = jnp.concatenate([jnp.concatenate([MRh, H @ belief.sqrt], axis=1),
                           jnp.concatenate([jnp.zeros((n, k), H.dtype), belief.sqrt], axis=1)], axis=0)
    post = _tria(pre)                                       # (p + n) x (p + n) lower triangular
    Se, Kb, S_post = post[:p, :p], post[p:, :p], post[p:, p:]
    K = jsl.solve_triangular(Se, Kb.T, lower=True, trans=1).T     # K Se = Kb
    return SqrtGaussian(belief.mean + K @ (z - zhat), S_post)
