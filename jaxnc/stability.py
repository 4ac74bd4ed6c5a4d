"""Stochastic stability: Theorem 1 of seed 000 and Kalman filtering with intermittent observations.

Two independent pieces.

**Theorem 1 (seed 000, eq. 18-20, Appendix A).** The NUDREKF prediction error is
exponentially bounded in mean square, eq. (A.21), if the Jacobians, gains and
covariances obey the bounds of eq. (18) and the scalar conditions (19)-(20) hold for
some a1, a2, a3 > 0. Here the bounds are *measured* along simulated trajectories:

* :func:`estimator_pass` re-runs the filter (eq. 11-16, Joseph form) along a given true
  trajectory with its own Bernoulli arrival process (one sample every N fast steps,
  lost with probability DP) and, optionally, the PETC condition (eq. 4), recording
  A_k, L_k, H_k, M_k, K_k, P_{k|k-1}, P_{k|k}, the errors and the flags;
* :func:`measure_bounds` reduces one record to the constants of eq. (18) (spectral
  norms / extreme singular values, since H, L, K, M are not square);
  :func:`worst_case` combines seeds (min of lower bounds, max of upper bounds);
* :func:`check_theorem1` searches a1, a2, a3 and evaluates (19), (20), eta, nu and the
  stationary value of the bound; :func:`bound_a21` is the bound (A.21) over k.

Two readings are reported for (19): the inequality *as printed* in the paper, whose
numerator starts with ``1 - abar^2``, and the one that follows from the proof's own
requirement c1 < 1 (eq. A.14-A.15), whose numerator starts with ``abar^2 - 1``. They
agree only when abar = 1; the paper's printed form is easier to satisfy when abar > 1.

**Kalman filtering with intermittent observations** (Sinopoli et al., IEEE TAC 2004).
With arrivals gamma_k ~ Bernoulli(lambda), E[P_k] stays bounded iff lambda > lambda_c,
where ``1 - 1/rho(A)^2 = lambda_min <= lambda_c <= lambda_max``; lambda_max is the
infimum of the lambda for which the modified algebraic Riccati equation (MARE)
P = A P A' + Q - lambda A P C'(C P C' + R)^-1 C P A' has a solution. The lower bound is
tight when C is invertible and for scalar systems. :func:`mare_step`,
:func:`mare_iterate`, :func:`lambda_min`, :func:`lambda_max`, :func:`lyapunov_lower`
and :func:`random_riccati` (Monte-Carlo of the error covariance) implement it.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import (check_int, check_nonneg, check_positive, check_range, concrete, jit_when_eager,
                             psd_rounding)
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update_terms
from jaxnc.loop.links import Bernoulli
from jaxnc.loop.triggers import PetcState, petc_decide

__all__ = [
    "FilterRecord", "estimator_pass", "trajectory_inputs", "mecanum_pass", "Bounds", "measure_bounds", "worst_case",
    "Theorem1Check", "check_theorem1", "bound_a21", "lhs19",
    "mare_step", "mare_iterate", "lambda_min", "lambda_max", "lyapunov_lower", "random_riccati",
]


# ============================================================================ Theorem 1


class FilterRecord(NamedTuple):
    """What Theorem 1 needs at every fast step k = 0..K-1 of one estimator pass.

    Measurement quantities (H, M, K, P_post) belong to instant k, prediction quantities
    (A, L, P_pred, err_pred) to the step k -> k+1, as in eq. (11)-(16) and (A.1).
    """

    A: jax.Array          # [K, n, n]   df/dxi at xi_{k|k}, eq. (12)
    L: jax.Array          # [K, n, w]   df/dn1, eq. (12)
    H: jax.Array          # [K, m, n]   dh/dxi at xi_{k|k-1}, eq. (16)
    M: jax.Array          # [K, m, m]   dh/dn2, eq. (16)
    K: jax.Array          # [K, n, m]   gain eq. (15) (computed at every step, applied when updated)
    P_post: jax.Array     # [K, n, n]   P_{k|k}  (= P_{k|k-1} when nothing arrived)
    P_pred: jax.Array     # [K, n, n]   P_{k+1|k}, eq. (11)
    err_post: jax.Array   # [K, n]      xi_k - xi_{k|k}
    err_pred: jax.Array   # [K, n]      xi_{k+1} - xi_{k+1|k}  (the error of eq. A.21)
    slow: jax.Array       # [K] bool    a sampling instant (k mod N = 0)
    arrived: jax.Array    # [K] bool    lambda_k: sampling instant and packet not lost
    gamma: jax.Array      # [K] bool    gamma_k: the PETC condition held (True without a trigger)
    updated: jax.Array    # [K] bool    gamma_k * lambda_k: the filter corrected


def trajectory_inputs(traj):
    """(xs, us, moving) for :func:`estimator_pass` from a :class:`jaxnc.loop.Trajectory`
    that recorded x and u (e.g. ``schemes.mecanum.mecanum_loop(..., full=True)``).

    ``traj.x[t + 1] = f(traj.x[t], traj.u[t], w_t)``, so xs has K states and us the K - 1
    inputs between them. ``moving`` marks the steps whose applied action is non-zero and
    that precede the completion of the path (``traj.done_step``): the motion-scaled process
    noise of the plant vanishes at rest.
    """
    xs, us = traj.x, traj.u[:-1]
    k = jnp.arange(us.shape[0])
    moving = (jnp.max(jnp.abs(us), axis=-1) > 0) & (k < traj.done_step)
    return xs, us, moving


def estimator_pass(model, xs, us, key, *, N, dp, Q, R, v_std, P0, trigger=None) -> FilterRecord:
    """EKF/NUDREKF along a given true trajectory, recording Theorem 1's quantities.

    ``model`` has ``dynamics(x, u, w)`` and ``measure(x, v)``; ``xs`` [K+1, n] are true
    states with ``xs[k+1] = f(xs[k], us[k], w_k)``; ``us`` [K, p] the applied inputs
    (known to the filter, as in eq. 11). Every N fast steps the sensor samples
    z_k = h(xs[k]) + v_k with ``v_k ~ N(0, diag(v_std^2))``; the packet is lost with
    probability ``dp`` in [0, 1) (eq. 5, :class:`jaxnc.loop.Bernoulli`) and, with a PETC
    ``trigger`` (a :class:`jaxnc.loop.Petc`), only sent when its decision on eq. (4) fires
    (:func:`jaxnc.loop.triggers.petc_decide` against the last sample sent, evaluated every
    fast step and recorded as ``gamma``; the first sample is always sent; no silence
    counter is kept, so a ``max_silence`` > 1 is not applied). The filter corrects (eq. 13)
    when the sample is sent and arrives, and predicts (eq. 11) every fast step with ``Q``
    and ``R`` (the covariances it assumes). The initial estimate is xs[0] + e0 with
    e0 ~ N(0, P0).

    N and dp may be traced (one compilation serves a whole grid). Randomness: key is
    split into (initial error, measurement noise, losses).
    """
    check_range("estimator_pass.dp", dp, 0.0, 1.0, high_open=True)
    check_range("estimator_pass.N", N, 1, None)
    xs, us = jnp.asarray(xs), jnp.asarray(us)
    dtype = xs.dtype
    Kn, n = us.shape[0], xs.shape[1]
    Q, R, P0 = (jnp.asarray(a, dtype) for a in (Q, R, P0))
    v_std = jnp.asarray(v_std, dtype)
    m, wdim = R.shape[0], Q.shape[0]
    k0, kv, kl = jax.random.split(key, 3)
    e0 = jnp.linalg.cholesky(P0) @ jax.random.normal(k0, (n,), dtype)
    v = jax.random.normal(kv, (Kn, m), dtype) * v_std[None, :]
    lost = Bernoulli(dp).sample(kl, Kn)              # the links' loss model, seed 000 eq. (5)
    ks = jnp.arange(Kn)
    slow = (ks % N) == 0
    arrived = slow & ~lost

    def step(c, inp):
        belief, z_last = c
        k, x, x_next, u, v_k, slow_k, arr_k = inp
        z = model.measure(x, v_k)
        if trigger is None:
            g = jnp.ones((), bool)
        else:
            # the Petc's own decision against the last sample sent (k = 0 always sends)
            g = petc_decide(trigger, PetcState(z_last, jnp.zeros((), jnp.int32)), z, k) > 0.5
        sent = slow_k & g
        z_last = jnp.where(sent, z, z_last)
        corrected, H, M, K = ekf_update_terms(model.measure, belief, z, R, m)
        upd = sent & arr_k
        post = jax.tree.map(lambda a, b: jnp.where(upd, a, b), corrected, belief)
        w0 = jnp.zeros((wdim,), dtype)
        A = jax.jacfwd(model.dynamics, argnums=0)(post.mean, u, w0)
        L = jax.jacfwd(model.dynamics, argnums=2)(post.mean, u, w0)
        pred = ekf_predict(model.dynamics, post, u, Q, wdim)
        out = (A, L, H, M, K, post.cov, pred.cov, x - post.mean, x_next - pred.mean, g)
        return (pred, z_last), out

    z0 = model.measure(xs[0], jnp.zeros((m,), dtype))
    belief0 = Gaussian(xs[0] + e0, P0)
    _, outs = jax.lax.scan(step, (belief0, z0), (ks, xs[:-1], xs[1:], us, v, slow, arrived))
    A, L, H, M, K, P_post, P_pred, err_post, err_pred, g = outs
    return FilterRecord(A, L, H, M, K, P_post, P_pred, err_post, err_pred, slow, arrived, g & slow,
                        g & slow & arrived)


def mecanum_pass(loop, traj, key, *, N, dp, trigger=None):
    """:func:`estimator_pass` along a Mecanum closed-loop run (a loop of
    ``schemes.mecanum.mecanum_loop(..., full=True)`` and its trajectory) with the loop's own
    filter (model, covariances, initial uncertainty) and the robot's true measurement noise.

    Returns ``(bounds, err2, moving)``: the eq. (18) constants over the moving steps,
    ||xi_{k+1} - xi_{k+1|k}||^2 per step and the mask. Pure JAX: vmap over (traj, key)."""
    est = loop.estimator
    Qf, Rf = jnp.diag(jnp.asarray(est.Q)), jnp.diag(jnp.asarray(est.R))
    xs, us, moving = trajectory_inputs(traj)
    rec = estimator_pass(est.model, xs, us, key, N=N, dp=dp, Q=Qf, R=Rf, v_std=loop.plant.v_std,
                         P0=jnp.asarray(est.cov0), trigger=trigger)
    return measure_bounds(rec, Qf, Rf, moving), jnp.sum(rec.err_pred ** 2, axis=-1), moving


class Bounds(NamedTuple):
    """Constants of eq. (18), measured. Matrix inequalities X <= c I for non-square or
    non-symmetric X are read as ||X||_2 <= c (largest singular value) and c I <= X as
    sigma_min(X) >= c; for the symmetric P, Q, R they are eigenvalue bounds."""

    abar: jax.Array
    h_lo: jax.Array
    h_hi: jax.Array
    kbar: jax.Array
    l_lo: jax.Array
    l_hi: jax.Array
    mbar: jax.Array
    p_lo: jax.Array      # min eig P_{k|k} (masked steps after a masked step)
    p_hi: jax.Array      # max eig P_{k+1|k}
    q_lo: jax.Array
    q_hi: jax.Array
    rbar: jax.Array
    lam: jax.Array       # E[lambda_k]: fraction of fast steps with an arrival (<= 1/N)
    gamma: jax.Array     # average sensor communication rate: fraction of samples sent
    p_order: jax.Array   # min eig (P_{k|k-1} - P_{k|k}) >= 0 expected (eq. 18, third line)


_LOWER = ("h_lo", "l_lo", "p_lo", "q_lo", "p_order")
_MEAN = ("lam", "gamma")


def _eigvalsh(S, sweeps: int = 10):
    """Ascending eigenvalues of small symmetric matrices ``[..., n, n]`` by cyclic Jacobi
    rotations written in plain XLA ops (``sweeps`` full sweeps; quadratic convergence makes
    10 ample for the n <= 9 used here).

    Not ``jnp.linalg.eigvalsh``: on CPU, jaxlib 0.10.2 runs a batched ``syevd`` custom call
    by splitting the batch over XLA's intra-op thread pool and blocking the calling pool
    thread until the pieces finish (``jax::ParallelBatchMap``). :func:`measure_bounds` has
    several independent such calls, which XLA runs concurrently; once every pool thread
    (two on a 2-core machine) is blocked in one, nobody runs the queued pieces and the
    program deadlocks with the CPU idle (seen in notebooks/stability_bounds.ipynb, full mode).
    """
    A = jnp.asarray(S)
    n = A.shape[-1]
    A = 0.5 * (A + jnp.swapaxes(A, -1, -2))
    if n == 1:
        return A[..., 0]
    A = jnp.moveaxis(A, (-2, -1), (0, 1))          # [n, n, ...]: rows and columns are leading slices
    pairs = np.array([(p, q) for p in range(n - 1) for q in range(p + 1, n)], np.int32)
    pairs = jnp.asarray(np.tile(pairs, (sweeps, 1)))

    def rotate(i, A):       # one rotation in a loop, not unrolled: small programs, quick compiles
        p, q = pairs[i, 0], pairs[i, 1]
        app, aqq, apq = A[p, p], A[q, q], A[p, q]
        nz = apq != 0
        theta = (aqq - app) / (2 * jnp.where(nz, apq, 1))
        # t = tan of the angle that zeroes A[p, q], the smaller root (Numerical Recipes 11.1)
        t = jnp.where(theta >= 0, 1.0, -1.0) / (jnp.abs(theta) + jnp.sqrt(1 + theta * theta))
        t = jnp.where(nz, t, 0).astype(A.dtype)
        c = jax.lax.rsqrt(1 + t * t)[None]          # broadcast over a row / column
        s = t[None] * c
        Ap, Aq = A[:, p], A[:, q]
        A = A.at[:, p].set(c * Ap - s * Aq).at[:, q].set(s * Ap + c * Aq)
        Ap, Aq = A[p], A[q]
        return A.at[p].set(c * Ap - s * Aq).at[q].set(s * Ap + c * Aq)

    A = jax.lax.fori_loop(0, pairs.shape[0], rotate, A)
    return jnp.sort(jnp.stack([A[i, i] for i in range(n)], axis=-1), axis=-1)


def _gram_eigs(X):
    # singular values^2 of X from the smaller Gram matrix (eigenvalues, not an SVD call)
    G = jnp.swapaxes(X, -1, -2) @ X if X.shape[-2] >= X.shape[-1] else X @ jnp.swapaxes(X, -1, -2)
    return jnp.maximum(_eigvalsh(G), 0.0)


def _smax(X):
    return jnp.sqrt(_gram_eigs(X)[..., -1])


def _smin(X):
    # sigma_min of a tall H (full column rank) or of a wide L (L L' > 0)
    return jnp.sqrt(_gram_eigs(X)[..., 0])


def measure_bounds(rec: FilterRecord, Q, R, mask=None) -> Bounds:
    """Eq. (18) constants of one record over the steps where ``mask`` holds (all by default).

    Quantities of the correction (H, K, M) are taken at sampling instants only, P_{k|k}
    (``p_lo``) at masked steps whose previous step is masked too: P_{k|k} carries the
    prediction over step k-1, and after a step at rest, where the plant's motion-scaled
    process noise vanishes, its velocity block is exactly 0. ``lam`` and ``gamma`` are
    over the masked steps. Pure JAX: vmap it over seeds.
    """
    Kn = rec.slow.shape[0]
    mask = jnp.ones((Kn,), bool) if mask is None else jnp.asarray(mask, bool)
    ms = mask & rec.slow
    after_masked = mask & jnp.concatenate([mask[:1], mask[:-1]])
    big = jnp.asarray(jnp.inf, rec.A.dtype)
    mx = lambda a, w: jnp.max(jnp.where(w, a, -big))
    mn = lambda a, w: jnp.min(jnp.where(w, a, big))
    Pe_post = _eigvalsh(rec.P_post)
    Pe_pred = _eigvalsh(rec.P_pred)
    # P_{k|k} <= P_{k|k-1}: compare the posterior at k with the prediction into k
    P_prior = jnp.concatenate([rec.P_post[:1], rec.P_pred[:-1]], axis=0)
    order = _eigvalsh(P_prior - rec.P_post)[:, 0]
    qe = _eigvalsh(jnp.asarray(Q, rec.A.dtype))
    re = _eigvalsh(jnp.asarray(R, rec.A.dtype))
    return Bounds(
        abar=mx(_smax(rec.A), mask), h_lo=mn(_smin(rec.H), ms), h_hi=mx(_smax(rec.H), ms),
        kbar=mx(_smax(rec.K), ms), l_lo=mn(_smin(rec.L), mask), l_hi=mx(_smax(rec.L), mask),
        mbar=mx(_smax(rec.M), ms), p_lo=mn(Pe_post[:, 0], after_masked), p_hi=mx(Pe_pred[:, -1], mask),
        q_lo=qe[0], q_hi=qe[-1], rbar=re[-1],
        lam=jnp.sum(rec.arrived & mask) / jnp.maximum(jnp.sum(mask), 1),
        gamma=jnp.sum(rec.gamma & ms) / jnp.maximum(jnp.sum(ms), 1),
        p_order=mn(order, ms))


def worst_case(b: Bounds) -> Bounds:
    """Combine per-seed bounds (leading axis): min of lower bounds, max of upper bounds,
    mean of the rates lam and gamma. Returns numpy float64 scalars."""
    out = {}
    for f in Bounds._fields:
        a = np.asarray(getattr(b, f), np.float64).reshape(-1)
        out[f] = float(a.mean() if f in _MEAN else (a.min() if f in _LOWER else a.max()))
    return Bounds(**out)


class Theorem1Check(NamedTuple):
    """Outcome of the Theorem 1 conditions for given bounds, sigma, delta (all floats/bools)."""

    a1: float
    a2: float
    a3: float
    lam: float               # E[lambda_k] used in (19)
    lam_max: float           # 1/N
    lhs19_paper: float       # left side of (19) as printed (numerator 1 - abar^2 + ...)
    lhs19: float             # left side implied by c1 < 1 (numerator abar^2 - 1 + ...)
    cond19_paper: bool
    cond19: bool
    c1: float                # contraction factor of E[P] in (A.14); < 1 iff cond19
    mu: float
    eta: float
    nu: float
    cond20: bool
    holds_paper: bool        # (19) as printed and (20)
    holds: bool              # (19) from c1 < 1 and (20)
    stationary: float        # limit of (A.21): nu p_hi (1 - eta) / eta (inf when it does not hold)
    vacuous: bool            # conditions fail, or the bound exceeds ``scale``
    reason: str


def lhs19(b, sigma, gamma, a1, a2):
    """Left sides of (19): (as printed, implied by c1 < 1). Broadcasts over a1, a2."""
    a2b = b.abar ** 2
    x = (1.0 - gamma) * a2b * (1.0 + a1) * (1.0 + b.kbar * b.h_hi) ** 2 \
        + (1.0 + 1.0 / a1 + 1.0 / a2) * b.kbar ** 2 * sigma * b.h_hi ** 2
    return (1.0 - a2b + x) / (gamma * a2b), (a2b - 1.0 + x) / (gamma * a2b)


def _eta_nu(b, sigma, delta, a3):
    mu = b.l_lo ** 2 * b.q_lo / (b.abar ** 2 * b.p_hi + b.l_lo ** 2 * b.q_lo)
    eta = mu + a3 * mu - a3 - b.kbar * sigma / a3
    # nu as printed; the paper's "l^2 qbar" is read with the upper bound lbar
    nu = b.kbar ** 2 * delta / a3 + (b.abar ** 2 * b.kbar ** 2 * b.rbar + b.l_hi ** 2 * b.q_hi) / b.p_hi
    return mu, eta, nu


def check_theorem1(b: Bounds, *, sigma: float, delta: float, N: int, gamma: float | None = None,
                   lam: float | None = None, scale: float | None = None,
                   grid=None) -> Theorem1Check:
    """Search a1, a2, a3 > 0 and check (19), (20) of Theorem 1 (seed 000).

    ``sigma = max sigma(i)``, ``delta = sum delta(i)`` (0, 0 without PETC). ``gamma`` and
    ``lam`` default to the measured ``b.gamma`` and ``b.lam``. a1, a2 minimise the left side
    of (19) on a log grid; a3 minimises the stationary bound nu p_hi (1 - eta)/eta among the
    a3 with 0 < eta <= 1 (with delta = 0 this maximises eta; then the best is
    a3 = sqrt(kbar sigma / (1 - mu)), eta = mu - 2 sqrt((1 - mu) kbar sigma), included as a
    candidate; with sigma = delta = 0 the supremum eta -> mu is approached by the smallest
    grid a3). ``scale``: a value of E||xi~||^2 that any estimate achieves trivially (e.g.
    the squared size of the workspace); a stationary bound above it is *vacuous*.
    """
    check_nonneg("sigma", sigma)
    check_nonneg("delta", delta)
    check_int("check_theorem1: N", N, 1)
    b = Bounds(*(float(np.asarray(v)) for v in b))
    gamma = b.gamma if gamma is None else float(gamma)
    lam = b.lam if lam is None else float(lam)
    check_range("gamma", gamma, 0.0, 1.0, low_open=True)
    check_range("check_theorem1: lam", lam, 0.0, 1.0)
    grid = np.logspace(-6, 6, 241) if grid is None else np.asarray(grid, np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        a1g, a2g = np.meshgrid(grid, grid, indexing="ij")
        _, l19 = lhs19(b, sigma, gamma, a1g, a2g)
        i = np.unravel_index(np.nanargmin(l19), l19.shape)
        a1, a2 = float(a1g[i]), float(a2g[i])
        lp, lc = (float(v) for v in lhs19(b, sigma, gamma, a1, a2))
        lam_max = 1.0 / N
        ok_lam = lam <= lam_max * (1 + 1e-9)
        cond19_paper, cond19 = bool(lp < lam and ok_lam), bool(lc < lam and ok_lam)
        # c1 of (A.14): abar^2 - gamma lam abar^2 + X, with X = gamma abar^2 lhs19 - (abar^2 - 1)
        c1 = b.abar ** 2 - gamma * lam * b.abar ** 2 + (gamma * b.abar ** 2 * lc - (b.abar ** 2 - 1.0))
        mu0, _, _ = _eta_nu(b, sigma, delta, 1.0)
        # eta > 0 needs a3 < mu / (1 - mu), which may be far below the grid: add a relative grid
        cands = np.concatenate([grid, mu0 / max(1.0 - mu0, 1e-300) * np.logspace(-6, 0, 61, endpoint=False)])
        if sigma > 0 and mu0 < 1:
            cands = np.append(cands, np.sqrt(b.kbar * sigma / (1.0 - mu0)))
        cands = cands[np.isfinite(cands) & (cands > 0)]
        mu, etas, nus = _eta_nu(b, sigma, delta, cands)
        feas = (etas > 0) & (etas <= 1) & np.isfinite(nus)
        stat = np.where(feas, nus * b.p_hi * (1 - etas) / np.where(feas, etas, 1.0), np.inf)
        j = int(np.argmin(stat)) if feas.any() else int(np.nanargmax(etas))
    a3, eta, nu = float(cands[j]), float(etas[j]), float(nus[j])
    cond20 = bool(feas.any())
    holds_paper, holds = cond19_paper and cond20, cond19 and cond20
    stationary = float(stat[j]) if holds else np.inf
    reasons = []
    if not ok_lam:
        reasons.append(f"lambda = {lam:.4g} > 1/N = {lam_max:.4g}")
    if not cond19:
        reasons.append(f"(19) fails: needs lambda > {lc:.4g} (c1 < 1), have {lam:.4g}")
    if not cond19_paper:
        reasons.append(f"(19) as printed fails: needs lambda > {lp:.4g}")
    if not cond20:
        reasons.append(f"(20) fails: best eta = {eta:.3g} (mu = {float(mu):.3g}) is not in (0, 1]")
    vac = not holds
    if holds and scale is not None and stationary > scale:
        vac = True
        reasons.append(f"bound {stationary:.3g} exceeds the trivial scale {scale:.3g}")
    return Theorem1Check(a1=a1, a2=a2, a3=a3, lam=lam, lam_max=lam_max, lhs19_paper=lp, lhs19=lc,
                         cond19_paper=cond19_paper, cond19=cond19, c1=float(c1), mu=float(mu), eta=eta, nu=nu,
                         cond20=cond20, holds_paper=holds_paper, holds=holds, stationary=stationary,
                         vacuous=bool(vac), reason="; ".join(reasons) if reasons else "conditions hold")


def bound_a21(k, *, eta, nu, p_lo, p_hi, e0):
    """Right side of (A.21) at k (array of ints >= 0):

        (p_hi / p_lo) e0 (1 - eta)^k + nu p_hi sum_{i=1}^{k-1} (1 - eta)^i,

    with e0 = E||xi~_{1|0}||^2; the sum is ((1-eta) - (1-eta)^k) / eta for k >= 1."""
    k = jnp.asarray(k)
    r = 1.0 - jnp.asarray(eta)
    rk = r ** k
    geo = jnp.where(k >= 2, (r - rk) / jnp.asarray(eta), 0.0)
    return (p_hi / p_lo) * e0 * rk + nu * p_hi * geo


# ============================================================================ intermittent observations


def mare_step(P, A, C, Q, R, lam):
    """Modified Riccati map g_lam(P) = A P A' + Q - lam A P C'(C P C' + R)^-1 C P A'
    (Sinopoli et al. 2004, eq. 10); lam = 1 is the Kalman filter's Riccati map.

    P, A, Q float[n, n], C float[p, n], R float[p, p] (a scalar is 1 x 1: a scalar R with
    p > 1 would otherwise be added to every entry of C P C'). Raises ValueError when the
    shapes do not fit (naming the matrix), or a concrete lam is outside [0, 1]."""
    A, C, Q, R = _system_jax("mare_step", A, C, Q, R)
    P = _fit_p0("mare_step", P, A.shape[0], Q.dtype)
    _check_lam("mare_step", lam)
    return _mare(P, A, C, Q, R, jnp.asarray(lam, Q.dtype))


def _mare(P, A, C, Q, R, lam):
    APC = A @ P @ C.T
    S = C @ P @ C.T + R
    G = A @ P @ A.T + Q - lam * APC @ jnp.linalg.solve(S, APC.T)
    # symmetrise: the map amplifies round-off in the antisymmetric part until it diverges
    return 0.5 * (G + G.T)


def mare_iterate(A, C, Q, R, lam, steps: int, P0=None):
    """``steps`` iterations of :func:`mare_step` from P0 (0 by default). Returns (P, change)
    where change is the relative change of the last iteration, max |P_k - P_{k-1}| /
    max |P_k| (small: converged; not small, non-finite or a growing trace: no fixed point,
    lam below lambda_max). Matrices are cast to one floating dtype (integers to the default
    float). Shapes and lam as :func:`mare_step`; ``steps`` an integer >= 1 (ValueError
    otherwise; -1 returned P0 with change inf)."""
    A, C, Q, R = _system_jax("mare_iterate", A, C, Q, R)
    _check_lam("mare_iterate", lam)
    if not isinstance(steps, jax.core.Tracer):
        check_int("mare_iterate: steps", steps, 1)
    lam = jnp.asarray(lam, Q.dtype)       # a float64 lam with float32 matrices under x64: one carry dtype
    P0 = jnp.zeros_like(Q) if P0 is None else _fit_p0("mare_iterate", P0, A.shape[0], Q.dtype)
    return _mare_iterate_loop(P0, A, C, Q, R, lam, steps)


# eagerly (a sweep over lam in a notebook) one program per shape and step count, not one per call
@jit_when_eager(static_argnums=(6,))
def _mare_iterate_loop(P0, A, C, Q, R, lam, steps):
    def body(_, c):
        P, _d = c
        Pn = _mare(P, A, C, Q, R, lam)
        # largest entries, not Frobenius norms: the square in ||Pn|| overflowed to inf once Pn
        # passed 1.8e19 (float32), and a diverging iteration read change = finite / inf = 0
        big = jnp.max(jnp.abs(Pn))
        return Pn, jnp.max(jnp.abs(Pn - P)) / jnp.maximum(big, jnp.finfo(Pn.dtype).tiny)

    return jax.lax.fori_loop(0, steps, body, (P0, jnp.asarray(jnp.inf, Q.dtype)))


def _fit(fn: str, A, C=None, Q=None, R=None) -> None:
    """A n x n, C p x n, Q n x n, R p x p (2-D arrays); ValueError naming the argument."""
    n = A.shape[0]
    if A.ndim != 2 or A.shape != (n, n):
        raise ValueError(f"{fn}: A must be a square matrix (n x n), got shape {A.shape}")
    if C is not None and (C.ndim != 2 or C.shape[1] != n):
        raise ValueError(f"{fn}: C must be p x n with n = {n} (A's size), got shape {C.shape}")
    if Q is not None and Q.shape != (n, n):
        raise ValueError(f"{fn}: Q must be n x n = {n} x {n} (A's size), got shape {Q.shape}")
    if R is not None:
        p = C.shape[0]
        if R.shape != (p, p):
            raise ValueError(f"{fn}: R must be p x p = {p} x {p} (C's rows), got shape {R.shape}")


def _check_values(fn: str, r_definite: bool, **mats) -> None:
    """Concrete matrices finite, Q symmetric PSD, R symmetric PSD (``r_definite``: PD);
    ValueError naming the argument."""
    for name, M in mats.items():
        if M is None or not concrete(M):
            continue
        M = np.asarray(M, np.float64)
        if not np.all(np.isfinite(M)):
            raise ValueError(f"{fn}: {name} must be finite")
        if name in ("Q", "R"):
            definite = name == "R" and r_definite
            low = np.linalg.eigvalsh(0.5 * (M + M.T)).min()
            what = f"symmetric positive {'definite' if definite else 'semi-definite'} (a covariance)"
            # symmetric to 1e-6 of its largest entry (a float32 product such as G G' is not exactly)
            if not np.allclose(M, M.T, rtol=0.0, atol=1e-6 * np.abs(M).max()):
                raise ValueError(f"{fn}: {name} must be {what}, got largest |{name} - {name}'| "
                                 f"{np.abs(M - M.T).max():g}")
            if (definite and low <= 0) or (not definite and low < -psd_rounding(M)):
                raise ValueError(f"{fn}: {name} must be {what}, got smallest eigenvalue {low:g}")


def _check_lam(fn: str, lam) -> None:
    """A concrete arrival rate in [0, 1] (a traced one is not checked)."""
    if concrete(lam):
        check_range(f"{fn}: lam", lam, 0.0, 1.0)


def _fit_p0(fn: str, P0, n: int, dtype):
    """P0 as a 2-D array of ``dtype`` (the system's), n x n; ValueError otherwise."""
    P0 = jnp.atleast_2d(jnp.asarray(P0))
    if P0.shape != (n, n):
        raise ValueError(f"{fn}: P must be n x n = {n} x {n} (A's size), got shape {P0.shape}")
    return P0.astype(dtype)


def _system_jax(fn: str, A, C, Q, R) -> tuple:
    """(A, C, Q, R) as JAX 2-D arrays (a scalar is 1 x 1), checked to fit (:func:`_fit`) and,
    when concrete, finite with Q PSD and R PSD."""
    A, C, Q, R = (jnp.atleast_2d(jnp.asarray(a)) for a in (A, C, Q, R))
    _fit(fn, A, C, Q, R)
    _check_values(fn, False, A=A, C=C, Q=Q, R=R)
    # one floating dtype (integers such as mare_iterate(2, 1, 1, 1, ...) become the default float):
    # an integer Q made the iteration's carry an integer and failed with OverflowError
    dt = jnp.result_type(A, C, Q, R, float)
    return tuple(m.astype(dt) for m in (A, C, Q, R))


def _system(fn: str, A, C=None, Q=None, R=None) -> tuple:
    """(A, C, Q, R) as float64 2-D arrays (a scalar is 1 x 1), checked to fit: A n x n,
    C p x n, Q n x n, R p x p; finite, Q symmetric PSD, R symmetric PD. ValueError naming
    the argument otherwise."""
    A = np.atleast_2d(np.asarray(A, np.float64))
    if C is None:
        _fit(fn, A)
        _check_values(fn, True, A=A)
        return (A,)
    C, Q, R = (np.atleast_2d(np.asarray(a, np.float64)) for a in (C, Q, R))
    _fit(fn, A, C, Q, R)
    _check_values(fn, True, A=A, C=C, Q=Q, R=R)
    return A, C, Q, R


def lambda_min(A) -> float:
    """Lower bound on the critical arrival rate, 1 - 1/max|eig(A)|^2 (0 for a stable A).
    ``A`` float[n, n] (a scalar is 1 x 1); ValueError when it is not square."""
    (A,) = _system("lambda_min", A)
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    if rho < 1.0:           # stable (a nilpotent A, rho = 0, divided by zero)
        return 0.0
    return 1.0 - 1.0 / rho ** 2


def lambda_max(A, C, Q, R, *, tol: float = 1e-3, steps: int = 20000, blowup: float = 1e12) -> float:
    """Upper bound lambda_max: the smallest lam for which the MARE iteration from P = 0
    converges (it is monotone, so it converges iff the MARE has a solution). Bisection on
    [lambda_min, 1] to ``tol`` in float64 NumPy, an analysis-time computation. Near the
    threshold the iteration slows down, so the value is an upper estimate within ``tol``
    plus the effect of the finite ``steps``. As in Sinopoli et al. (2004), (A, Q^1/2) is
    taken controllable: a mode the noise does not excite stays known exactly from P = 0
    (so for an unstable mode that Q does not excite, e.g. A = diag(1.5, 0.5) with
    Q = diag(0, 1), the result, 0, lies below :func:`lambda_min`, which assumes P0 > 0).
    The result does not depend on the scale of the noise: (Q, R) and c (Q, R) give the same.

    Args:
      A: float[n, n]; C: float[p, n]; Q: float[n, n] symmetric PSD; R: float[p, p] symmetric
        PD (scalars are 1 x 1).
      tol: > 0, the bisection's resolution; steps: iterations per trial rate.
      blowup: an iteration whose trace exceeds ``blowup`` times the trace of the Kalman
        filter's stationary prior covariance (the iteration's limit at lam = 1) is taken to
        diverge; relative, so that it does not depend on the scale of Q and R.
    Returns:
      0.0 when the iteration converges without any measurement (lam = 0: A's noisy modes are
      stable; decided by doubling, however slowly they decay, not by ``steps``); ``inf`` when it does not converge even with every measurement (lam = 1: an
      unstable or marginal mode that the noise excites and C does not see, i.e. (A, C) not
      detectable): no arrival rate bounds the error covariance.
    Raises:
      ValueError: the matrices do not fit or are not finite, Q not PSD or R not PD (naming
        which), ``tol`` or ``blowup`` <= 0, ``steps`` not an integer >= 1, or ``steps`` too
        few for the iteration to settle even at lam = 1 (whose limit exists: the doubling
        algorithm decides lam = 1).
    """
    A, C, Q, R = _system("lambda_max", A, C, Q, R)
    check_positive("lambda_max.tol", tol)
    check_positive("lambda_max.blowup", blowup)
    check_int("lambda_max.steps", steps, 1)

    def iterate(lam, limit):
        """(converged, P) after at most ``steps`` iterations from 0; divergence when the
        trace exceeds ``limit`` or is not finite."""
        P, At, Ct = np.zeros_like(Q), A.T.copy(), C.T.copy()
        scalar = R.shape == (1, 1)          # one output: the solve is a division
        with np.errstate(over="ignore", invalid="ignore"):       # overflow is divergence, read below
            for _ in range(steps):
                AP = A @ P
                APC = AP @ Ct
                S = C @ P @ Ct + R
                Pn = AP @ At + Q - lam * APC @ (APC.T / S[0, 0] if scalar else np.linalg.solve(S, APC.T))
                Pn = 0.5 * (Pn + Pn.T)    # see mare_step
                tr = Pn.trace()
                if not np.isfinite(tr) or tr > limit:
                    return False, Pn
                # largest entries, not Frobenius norms: their squares would overflow to inf <= inf
                if np.abs(Pn - P).max() <= 1e-10 * np.abs(Pn).max():
                    return True, Pn
                P = Pn
        return False, P

    # lam = 1 (the Kalman filter) first, by doubling: it decides in a few dozen steps whether
    # the Riccati iteration has a limit, where the plain iteration may need far more than
    # ``steps`` (a slowly converging filter read inf); its limit sets the divergence limit
    # of the others relative to the covariance's own scale
    ok1, P1 = _dare_doubling(A, C, Q, R)
    if not ok1:                  # then no lam <= 1 converges either (monotone in lam)
        return float("inf")
    limit = blowup * np.trace(P1)
    # lam = 0 (no measurement) by doubling too: the iteration is then the Lyapunov sum
    # sum_i A^i Q A'^i, bounded iff the modes Q excites are stable. The plain iteration from 0
    # settles only as fast as rho(A)^2k: a stable A with rho = 0.9999 read about ``tol``, and a
    # stable A with a slow mode C does not see was refused ("raise steps")
    ok0, _ = _dare_doubling(A, np.zeros_like(C), Q, R)
    if ok0:
        return 0.0

    def converges(lam):
        return iterate(lam, limit)[0]

    if not converges(1.0):
        raise ValueError(f"lambda_max: the Riccati iteration from 0 does not settle within steps={steps} even "
                         f"with every measurement (its limit exists); raise steps")
    lo, hi = lambda_min(A), 1.0
    if converges(lo + 1e-12) and lo > 0:
        return lo
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if converges(mid):
            hi = mid
        else:
            lo = mid
    return hi


def _dare_doubling(A, C, Q, R, doublings: int = 64) -> tuple:
    """(converged, P): the limit of the Kalman filter's Riccati iteration P+ = A P A' + Q -
    A P C'(C P C' + R)^-1 C P A' (float64 NumPy) by the structure-preserving doubling
    algorithm (:func:`jaxnc.estimators.steady_state.dlqe`'s, on (A', C')): H_k is the
    iteration after 2^k steps. Converged when a doubling changes H by less than 1e-9 of
    it; not when H overflows or keeps growing (a mode the noise excites and C does not
    see)."""
    n = A.shape[0]
    Ak, G, H = A.T.copy(), C.T @ np.linalg.solve(R, C), Q.copy()
    I = np.eye(n)
    with np.errstate(over="ignore", invalid="ignore"):
        for _ in range(doublings):
            W = I + G @ H
            WA, WG = np.linalg.solve(W, Ak), np.linalg.solve(W, G)
            Hn = H + Ak.T @ H @ WA
            Hn = 0.5 * (Hn + Hn.T)
            Ak, G = Ak @ WA, G + Ak @ WG @ Ak.T
            G = 0.5 * (G + G.T)
            if not np.all(np.isfinite(Hn)) or not np.all(np.isfinite(Ak)):
                return False, Hn
            if np.abs(Hn - H).max() <= 1e-9 * np.abs(Hn).max():
                return True, Hn
            H = Hn
    return False, H


def lyapunov_lower(A, Q, lam):
    """Lower bound S on lim E[P_k]: the solution of S = (1 - lam) A S A' + Q (Sinopoli et al.
    2004, Theorem 4), or inf when (1 - lam) rho(A)^2 >= 1. A, Q float[n, n] (scalars are
    1 x 1), Q symmetric PSD; lam in [0, 1]. ValueError naming the argument otherwise."""
    from scipy.linalg import solve_discrete_lyapunov
    A, Q = (np.atleast_2d(np.asarray(a, np.float64)) for a in (A, Q))
    _fit("lyapunov_lower", A, Q=Q)
    _check_values("lyapunov_lower", True, A=A, Q=Q)
    check_range("lyapunov_lower: lam", lam, 0.0, 1.0)
    rho = np.max(np.abs(np.linalg.eigvals(A)))
    if (1 - lam) * rho ** 2 >= 1:
        return np.full_like(Q, np.inf)
    return solve_discrete_lyapunov(np.sqrt(1 - lam) * A, Q)


def random_riccati(key, A, C, Q, R, lam, steps: int, P0=None):
    """Error covariance of the Kalman filter with Bernoulli(lam) arrivals (it does not
    depend on the measured values): P_{k+1} = A P A' + Q - gamma_k A P C'(C P C' + R)^-1 C P A'.
    Returns trace(P_k), k = 1..steps. vmap over keys for a Monte-Carlo; lam may be traced.
    Overflow gives inf: divergence is data. Shapes as :func:`mare_step` (scalars are 1 x 1;
    R may be singular where C P C' is not, e.g. R = 0 with an invertible C and P0 = Q > 0);
    ValueError when they do not fit, for a concrete lam outside [0, 1], or ``steps`` not an
    integer >= 1 (-1 failed inside XLA with "invalid tensor dimension size")."""
    A, C, Q, R = _system_jax("random_riccati", A, C, Q, R)
    _check_lam("random_riccati", lam)
    check_int("random_riccati: steps", steps, 1)
    P0 = Q if P0 is None else _fit_p0("random_riccati", P0, A.shape[0], Q.dtype)
    return _random_riccati_loop(key, P0, A, C, Q, R, lam, steps)


@jit_when_eager(static_argnums=(7,))      # as _mare_iterate_loop
def _random_riccati_loop(key, P0, A, C, Q, R, lam, steps):
    gam = (jax.random.uniform(key, (steps,)) < lam).astype(Q.dtype)

    def body(P, g):
        Pn = _mare(P, A, C, Q, R, g)
        return Pn, jnp.trace(Pn)

    _, tr = jax.lax.scan(body, P0, gam)
    return tr
