"""Non-uniform multi-rate estimator (NUMRE) as a loop estimator (seed 003, eq. 9-15).

A Kalman filter for a single-output linear model whose measurement arrives after a
time-varying number N of periods (the multiplicity, eq. 9, N = k - k_lm with k_lm the
instant of the previous arrival). Between arrivals it only predicts the mean with the
actions, x <- A x + B u; on arrival it corrects with the gain K(N) of the lifted model
(eq. 10-12), from the posterior covariance of the previous arrival:

    M = A^N P (A^N)' + We(N),   K(N) = M C' / (C M C' + V),   x <- x + K(N) (y - C x),

and P <- (I - K C) M (I - K C)' + K V K' (Joseph form). With ``we_form="white"`` We(N) is
the covariance of the lifted white process noise, so the filter equals a Kalman filter
that predicts every period and corrects only at arrivals. The kernels (tables of A^N and
We(N), the gain, the correction) are :mod:`jaxnc.estimators.numre`.

The correction takes the newest delivered measurement as y_k of the arrival instant k
(links without delay, as in the paper: declared ``undelayed_uplink``, so a ``Loop`` whose
uplink can delay a packet raises when it is built), and the loop's slow period must be the
model's period (``Loop.N = 1``).
"""
from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_choice, check_finite, check_given, check_int, check_nonneg, psd_rounding
from jaxnc.estimators.numre import NumreTables, numre_correct, numre_tables
from jaxnc.loop.base import AbstractEstimator, Inbox, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["Numre", "NumreState"]


def _check_covariance(name: str, M, dim: int, *, scalar: bool = False) -> None:
    """``M`` (finite, checked before) a dim x dim symmetric positive semi-definite matrix, or
    (``scalar``) a non-negative number; ValueError naming ``name``."""
    a = np.asarray(M, float)
    if scalar and a.size == 1:
        a = a.reshape(1, 1)
    if a.shape != (dim, dim):
        want = f"a number >= 0 or {dim}x{dim}" if scalar else f"{dim}x{dim}"
        raise ValueError(f"{name} must be {want} (a covariance), got shape {a.shape}")
    if not np.allclose(a, a.T, atol=1e-9 * max(1.0, float(np.abs(a).max()))):
        raise ValueError(f"{name} must be symmetric (a covariance)")
    low = float(np.linalg.eigvalsh(a).min())
    if low < -psd_rounding(a):       # a singular covariance's zero eigenvalues round to either sign
        raise ValueError(f"{name} must be positive semi-definite (a covariance), got smallest eigenvalue {low:g}")


class NumreState(NamedTuple):
    """The state of a :class:`Numre` filter: the estimate, its covariance and the last arrival."""

    mean: jax.Array      # float[n]: x(k|k) after a correction, else the prior x(k|k_lm) propagated
    cov: jax.Array       # float[n, n]: the posterior covariance at k_lm
    k_lm: jax.Array      # int32: the last instant a measurement arrived


@_dataclass
class Numre(AbstractEstimator):
    """NUMRE (module docstring); build it with :meth:`design`.

    Attributes:
      tables: :class:`~jaxnc.estimators.numre.NumreTables` (A^N, We(N) for N <= n_max, C, V);
        a gap longer than ``tables.n_max`` is corrected with K(n_max).
      A: float[n, n]; B: float[n, m], the model over one period.
      mean0: float[n]; cov0: float[n, n], the prior at k = 0: a measurement arriving at
        k = 0 is corrected with M = cov0 (N = 0), the first one at k > 0 with
        M = A^k cov0 (A^k)' + We(k).
      inputs: static, ``"believed"`` (the actions of the controller's own packets, what a
        filter on the control side knows) or ``"applied"`` (a filter at the actuator).

    ``correct(state, inbox, k) -> (state, x)``: x float[n], the corrected mean at an
    arrival, the propagated prior otherwise. Raises ValueError (at ``init``, i.e. when the
    Loop is built) for ``Loop.N != 1``.
    """

    tables: NumreTables
    A: Any
    B: Any
    mean0: Any
    cov0: Any
    inputs: str = _static("believed")

    undelayed_uplink: ClassVar[bool] = True

    def __post_init__(self):
        check_choice("Numre.inputs", self.inputs, ("believed", "applied"))

    @classmethod
    def design(cls, A, B, Bw, C, W, V, n_max: int, *, cov0, mean0=None, we_form: str = "white",
               inputs: str = "believed") -> "Numre":
        """The filter of the model x+ = A x + B u + Bw w, y = C x + v, Cov(w) = W (scalar or
        float[q, q], Bw float[n] or float[n, q]), Var(v) = V (single output: C float[n]; V a
        number, float[1] or float[1, 1]), with tables up to the multiplicity ``n_max``: a gap
        between arrivals longer than n_max is corrected with K(n_max) and We(n_max), not the
        Kalman filter's gain (choose n_max >= the longest gap, e.g. the run's steps, for the
        exact filter).

        Raises ValueError, naming the argument, for n_max < 1, a non-finite entry of any
        matrix or of mean0, an A that is not square, a B, Bw or C whose rows do not match A's
        n (C: one output row of n entries), a W that is not a non-negative scalar or a q x q
        covariance (q = Bw's columns), a negative V or one of more than one entry, V = 0 with
        C cov0 C' = 0 (the gain at k = 0 would be 0/0), a cov0 that is not an n x n covariance
        (symmetric positive semi-definite), a mean0 without n entries, or an unknown
        ``we_form``."""
        check_int("Numre.n_max", n_max, 1)
        check_nonneg("Numre.V", V)
        for name, v in (("A", A), ("B", B), ("Bw", Bw), ("C", C), ("W", W), ("cov0", cov0)):
            check_given(f"Numre.{name}", v)
            check_finite(f"Numre.{name}", v)
        check_finite("Numre.mean0", mean0)          # None: zeros
        A = np.asarray(A, float)
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ValueError(f"Numre.A must be a square matrix float[n, n], got shape {A.shape}")
        n = A.shape[0]
        C = np.asarray(C, float)
        if C.size != n:
            raise ValueError(f"Numre.C must be one output row of {n} entries (single output), got shape {C.shape}")
        B, Bw = np.asarray(B, float), np.asarray(Bw, float)
        for name, M in (("B", B), ("Bw", Bw)):
            if M.ndim not in (1, 2) or M.shape[0] != n:
                raise ValueError(f"Numre.{name} must be float[{n}] or float[{n}, k] (A is {n}x{n}), got shape {M.shape}")
        q = 1 if Bw.ndim == 1 else Bw.shape[1]
        _check_covariance("Numre.W", W, q, scalar=q == 1)
        _check_covariance("Numre.cov0", cov0, n)
        check_given("Numre.V", V)
        check_finite("Numre.V", V)
        _check_covariance("Numre.V", V, 1, scalar=True)     # a number, float[1] or float[1, 1]: one output
        V = float(np.asarray(V, float).reshape(()))
        if V == 0.0 and float(C.reshape(n) @ np.asarray(cov0, float) @ C.reshape(n)) <= 0.0:
            raise ValueError("Numre.V = 0 needs C cov0 C' > 0: a measurement arriving at k = 0 is corrected with "
                             "K = cov0 C' / (C cov0 C' + V) = 0/0 (nan estimates from then on); give V > 0 or a cov0 "
                             "uncertain along C")
        mean0 = np.zeros(n) if mean0 is None else np.asarray(mean0, float)
        if mean0.shape != (n,):
            raise ValueError(f"Numre.mean0 must have {n} entries (A is {n}x{n}), got shape {mean0.shape}")
        tables = numre_tables(A, Bw, C.reshape(n), W, V, n_max, we_form=we_form)
        f = lambda a: jnp.asarray(a, jnp.float32)
        return cls(tables, f(A), f(B.reshape(n, -1)), f(mean0), f(cov0), inputs=inputs)

    def init(self, ctx) -> NumreState:
        if ctx.N != 1:
            raise ValueError(f"Numre needs the loop's slow period to be the model's period (Loop.N = 1), got "
                             f"N = {ctx.N}")
        if ctx.output_dim != 1:
            raise ValueError(f"Numre is a single-output filter (C float[n]): the plant must have output_dim = 1, "
                             f"got {ctx.output_dim} (the others would be ignored)")
        return NumreState(jnp.asarray(self.mean0), jnp.asarray(self.cov0), jnp.zeros((), jnp.int32))

    def correct(self, state: NumreState, inbox: Inbox, k):
        z, _, w = inbox.newest()
        # N = 0 only at k = 0 (k_lm starts at 0): the prior there is (mean0, cov0) itself
        N = jnp.clip(k - state.k_lm, 0, self.tables.n_max)
        mean, cov, _ = numre_correct(self.tables, state.mean, state.cov, z[0], N)
        new = blend(w, NumreState(mean, cov, jnp.asarray(k, jnp.int32)), state)
        return new, new.mean

    def predict(self, state: NumreState, u_applied, u_believed, k):
        u = u_believed if self.inputs == "believed" else u_applied
        x = state.mean
        for j in range(u.shape[0]):            # the fast periods of the slow one (static)
            x = self.A @ x + self.B @ u[j]
        return state._replace(mean=x)
