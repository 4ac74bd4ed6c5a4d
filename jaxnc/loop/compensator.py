"""A discrete linear compensator part: any linear controller designed as a state-space or transfer-function model.

:class:`LinearController` runs at the slow instants (period h = N T). It measures
``y = xhat[index]`` (p entries of the estimator's output: measurements with
:class:`~jaxnc.loop.Passthrough`, states with an observer or an :class:`~jaxnc.loop.EKF`),
tracks ``r = reference.at(kN, T)`` (a :mod:`jaxnc.references` object; 0 when None) and sends
one action of m entries (m the plant's ``input_dim``). At every slow instant k:

    e_k = r_k - y_k
    v_k = C x_k + D e_k,          u_k = clip(v_k, u_min, u_max)
    x_{k+1} = A x_k + B e_k + K_aw (u_k - v_k)

with x the compensator's state (n entries, x_0 = ``x0``). ``K_aw`` (n x m, zero by default)
is the anti-windup gain of the back-calculation form for a general controller (Åström and
Wittenmark, *Computer-Controlled Systems*, 3rd ed., section 9.4: the controller's state is
driven by the difference between the saturated and the computed output; it does nothing
while u is not saturated). A PI written as A = 1, B = h Ki, C = 1, D = Kp with K_aw = h Kb is
:class:`~jaxnc.loop.PID`'s back-calculation with ``hold=False``.

It computes at every slow instant, whether or not the estimator received something (its
A, B, C, D are designed for the period h; skipping instants would change its dynamics):
between measurements it acts on the estimator's output as it is (a prediction, or the last
measurement with ``Passthrough``), and every packet is sent. A lead-lag, a notch, a loop-shaped
or an output-feedback LQG controller designed with python-control goes in with
:meth:`LinearController.from_control`. (Seed 004's dual-rate PI runs its sub-controllers with
the SISO :class:`jaxnc.design.dualrate.DiscreteSS` inside :class:`~jaxnc.loop.PursuitPI`.)

All matrices, limits and the reference are differentiable leaves.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_components, check_given, check_instance, check_range, index_tuple, unbounded
from jaxnc.loop.base import AbstractController, Packet
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.references import AbstractReference, at_channels, check_channels

__all__ = ["LinearController"]

_MATRICES = ("A", "B", "C", "D", "K_aw", "x0")


@_dataclass
class LinearController(AbstractController):
    """A discrete linear compensator on the tracking error (the equations in the module docstring).

    Attributes:
      A: float[n, n], B: float[n, p], C: float[m, n], D: float[m, p] (None: zero), the
        compensator's discrete state-space matrices at the loop's slow period h = N T;
        n >= 1 states, p = ``len(index)`` measured entries, m actions.
      K_aw: float[n, m] or None (zero), the anti-windup (back-calculation) gain; it acts only
        through the controller's own limits u_min / u_max (a nonzero K_aw without them is refused).
      x0: float[n] or None (zero), the compensator's initial state.
      reference: a :class:`jaxnc.references.AbstractReference` with 1 or p channels; None: 0.
      u_min, u_max: float, float[m] or None (unbounded), the output limits, u_min <= u_max.
      index: static int or tuple of p distinct ints >= 0, the estimator-output entries measured.
      dt: static float or None, the period the matrices were designed for (seconds); when
        given, a Loop whose slow period N T differs is refused. :meth:`from_control` sets it.

    It computes in :attr:`dtype` (float32, or float64 when a matrix, limit or the reference
    is a float64 array under x64).

    Raises:
      ValueError: naming the field, when a matrix is missing, not finite or of a shape that
        does not fit the others (A square, B with n rows and p columns, C with n columns,
        D m x p, K_aw n x m, x0 n entries), an index that is not a non-negative int or a
        tuple of distinct ones, a reference that is not a :mod:`jaxnc.references` object or
        has neither 1 nor p channels, u_min > u_max, a nonzero K_aw with u_min and u_max
        unbounded (None or inf: it would never act), a ``dt`` that is not a positive number;
        when a Loop is built, a ``dt`` that differs from N T, an index beyond the estimate,
        or m differing from the plant's input size.
    """

    A: Any
    B: Any
    C: Any
    D: Any = None
    K_aw: Any = None
    x0: Any = None
    reference: Any = None
    u_min: Any = None
    u_max: Any = None
    index: Any = _static(0)
    dt: Any = _static(None)

    def __post_init__(self):
        object.__setattr__(self, "index", index_tuple("LinearController.index", self.index,
                                                      "the estimator-output entries measured"))
        if self.dt is not None:
            if isinstance(self.dt, bool) or not isinstance(self.dt, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(self.dt) or self.dt <= 0:
                raise ValueError(f"LinearController.dt must be a positive number of seconds or None, got {self.dt!r}")
            object.__setattr__(self, "dt", float(self.dt))
        if self.reference is not None:
            check_instance("LinearController.reference", self.reference, AbstractReference,
                           "a jaxnc.references object (Step, Ramp, Sine, PiecewiseLinear, Recorded) or None")
        for name in ("A", "B", "C"):
            check_given(f"LinearController.{name}", getattr(self, name), "a matrix (the compensator's state-space form)")
        for name in _MATRICES + ("u_min", "u_max"):
            check_range(f"LinearController.{name}", getattr(self, name), finite=name not in ("u_min", "u_max"))
        p = len(self.index)
        if any(isinstance(getattr(self, n), jax.Array) for n in _MATRICES):
            return                                           # JAX arrays (batched leaves) are not checked
        A, B, C = (np.asarray(getattr(self, n)) for n in ("A", "B", "C"))
        if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] < 1:
            raise ValueError(f"LinearController.A must be a square matrix (n x n, n >= 1), got shape {A.shape}")
        n = A.shape[0]
        if B.ndim != 2 or B.shape != (n, p):
            raise ValueError(f"LinearController.B must be {n} x {p} (A's {n} states x the {p} entries of index "
                             f"{self.index}), got shape {B.shape}")
        if C.ndim != 2 or C.shape[1] != n:
            raise ValueError(f"LinearController.C must be m x {n} (the actions x A's {n} states), got shape {C.shape}")
        m = C.shape[0]
        want = {"D": (m, p), "K_aw": (n, m), "x0": (n,)}
        for name, shape in want.items():
            v = getattr(self, name)
            if v is not None and np.shape(v) != shape:
                raise ValueError(f"LinearController.{name} must have shape {shape} (n = {n} states, m = {m} actions, "
                                 f"p = {p} measured entries), got {np.shape(v)}")
        for name in ("u_min", "u_max"):
            v = getattr(self, name)
            if v is not None and np.ndim(v) > 0 and np.shape(v) not in ((1,), (m,)):
                raise ValueError(f"LinearController.{name} must be a number or have {m} entries (one per action), "
                                 f"got shape {np.shape(v)}")
        lo, hi = self.u_min, self.u_max
        if lo is not None and hi is not None and np.any(np.asarray(lo) > np.asarray(hi)):
            raise ValueError(f"LinearController.u_min must be <= u_max, got {np.asarray(lo).tolist()} and "
                             f"{np.asarray(hi).tolist()}")
        check_channels("LinearController", self.reference, p)
        if self.K_aw is not None and not isinstance(self.K_aw, jax.Array) and np.any(np.asarray(self.K_aw) != 0) \
                and unbounded(lo) and unbounded(hi):
            raise ValueError("LinearController.K_aw acts through u - v, u = clip(v, u_min, u_max), and u_min and u_max "
                             "are unbounded: it would never act (a saturation in a LimitedActuator does not reach "
                             "it); give u_min / u_max (the actuator's limits) or leave K_aw None")
        for name in _MATRICES:                    # numbers and lists become arrays (float32 unless float64 given)
            v = getattr(self, name)
            if v is not None and not isinstance(v, np.ndarray):
                object.__setattr__(self, name, np.asarray(v, np.float32))

    @classmethod
    def from_control(cls, sys, h: float | None = None, *, method: str = "tustin",
                     prewarp_frequency: float | None = None, **kw) -> "LinearController":
        """From a python-control ``StateSpace`` or ``TransferFunction`` (the compensator C(z) or C(s)).

        A continuous-time system is discretised at the loop's slow period ``h`` with
        ``control.c2d(sys, h, method, prewarp_frequency=...)`` (``"tustin"`` by default, the
        usual choice for a controller; ``"zoh"``, ``"foh"``, ``"backward_diff"``... as
        python-control); a discrete one must have ``dt == h`` (or h None). ``dt`` is set to
        the period, so a Loop running at another period is refused. ``prewarp_frequency``
        (rad/s, Tustin only, below the Nyquist frequency pi / h): the frequency at which the
        discrete response equals the continuous one, e.g. a notch's centre (plain Tustin moves
        it to (2 / h) atan(w h / 2)). The matrices are float32 arrays, float64 under
        ``jax_enable_x64`` (then it computes in float64: a float32 realisation of a slow
        pole, e.g. a lag's 0.99999 at h = 1 ms, moves the DC gain by 0.1 %). Other keywords
        are :class:`LinearController`'s.

        Raises:
          ValueError: ``h`` missing for a continuous-time system, differing from a discrete
            system's dt, or not positive; a ``prewarp_frequency`` that is not in (0, pi / h),
            given with a method other than Tustin or for a discrete system; a system
            python-control cannot convert.
        """
        import control
        try:
            ss = control.ss(sys)
        except Exception as e:  # noqa: BLE001 -- re-raised with the cause attached
            raise ValueError(f"LinearController.from_control: cannot convert {type(sys).__name__} to state space ({e})") \
                from e
        if h is not None:
            check_range("LinearController.from_control: h", h, 0.0, None, low_open=True)
        if ss.dt in (0, None):
            if h is None:
                raise ValueError("LinearController.from_control: h (the loop's slow period N T, seconds) is required "
                                 "to discretise a continuous-time system")
            if prewarp_frequency is not None:
                if method not in ("tustin", "bilinear"):
                    raise ValueError(f"LinearController.from_control: prewarp_frequency applies to method='tustin', "
                                     f"got method={method!r}")
                check_range("LinearController.from_control: prewarp_frequency", prewarp_frequency, 0.0,
                            np.pi / float(h), low_open=True, high_open=True)
            ss = control.c2d(ss, float(h), method, prewarp_frequency=prewarp_frequency)
        elif prewarp_frequency is not None:
            raise ValueError("LinearController.from_control: prewarp_frequency applies to discretising a "
                             "continuous-time system; this one is discrete already")
        elif ss.dt is True:
            if h is None:
                raise ValueError("LinearController.from_control: the system is discrete with an unspecified period "
                                 "(dt=True); give h, the loop's slow period N T")
        elif h is not None and abs(float(ss.dt) - float(h)) > 1e-9 * float(h):
            raise ValueError(f"LinearController.from_control: the system is discrete with dt={ss.dt}, h={h} differs")
        dt = float(h) if h is not None else float(ss.dt)
        if ss.nstates < 1:
            raise ValueError("LinearController.from_control: the system has no states (a static gain: use "
                             "StateFeedback or PID with Kp)")
        # float32, or float64 under x64 (it then computes in float64, as the class does for float64 arrays)
        f = lambda a: np.asarray(a, jax.dtypes.canonicalize_dtype(np.float64))
        kw.setdefault("index", tuple(range(ss.ninputs)) if ss.ninputs > 1 else 0)
        return cls(A=f(ss.A), B=f(ss.B), C=f(ss.C), D=f(ss.D), dt=dt, **kw)

    @property
    def channels(self) -> int:
        """p, the number of measured entries (``len(index)``)."""
        return len(self.index)

    @property
    def dtype(self):
        """The dtype it computes in (float32 unless a matrix, limit or the reference is a
        float64 array and x64 is on)."""
        leaves = [getattr(self, n) for n in _MATRICES + ("u_min", "u_max")]
        leaves = [v for v in leaves + jax.tree.leaves(self.reference) if v is not None]
        return jnp.result_type(jnp.float32, *leaves)

    def init(self, ctx) -> jax.Array:
        if self.dt is not None and abs(self.dt - ctx.N * ctx.T) > 1e-6 * self.dt:
            raise ValueError(f"LinearController.dt: the compensator was designed for a period of {self.dt:g} s but "
                             f"the loop's slow period is N T = {ctx.N} x {ctx.T:g} = {ctx.N * ctx.T:g} s; "
                             f"discretise it at {ctx.N * ctx.T:g} s")
        n = np.shape(self.A)[0]
        x0 = jnp.zeros((n,), self.dtype) if self.x0 is None else jnp.asarray(self.x0, self.dtype)
        return x0

    def step(self, state, xhat, fresh, k, ctx):
        xhat = jnp.asarray(xhat)
        check_components("LinearController.index", self.index, xhat.shape[-1], "the estimator's estimate")
        dt = self.dtype
        y = xhat[jnp.asarray(self.index)].astype(dt)
        r = at_channels(self.reference, k * ctx.N, ctx.T, self.channels).astype(dt)
        A, B, C = (jnp.asarray(getattr(self, n), dt) for n in ("A", "B", "C"))
        e = r - y
        v = C @ state
        if self.D is not None:
            v = v + jnp.asarray(self.D, dt) @ e
        limited = self.u_min is not None or self.u_max is not None
        u = jnp.clip(v, self.u_min, self.u_max) if limited else v
        x = A @ state + B @ e
        if self.K_aw is not None and limited:
            x = x + jnp.asarray(self.K_aw, dt) @ (u - v)
        return x, Packet(u[None, :], (k * ctx.N).astype(jnp.int32)), jnp.ones((), jnp.float32)
