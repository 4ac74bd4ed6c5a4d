"""General plants for a loop: a user's discrete or continuous nonlinear model, and LTI.

* :class:`Discrete` wraps ``f(x, u, w)`` and ``h(x, v)`` given as functions (static
  fields: define them at module level, so that the same function object, and one
  compiled program, is reused across loops);
* :class:`Continuous` integrates dx/dt = f(x, u, w) over the fast period T with
  ``substeps`` classical Runge-Kutta (RK4) steps, u and w held over the period (ZOH);
* :class:`LTI` is x+ = A x + B u + G w, z = C x + D u + v, from matrices
  (:meth:`LTI.from_continuous`: exact zero-order-hold discretisation, matrix
  exponential of the block matrix [[A, B], [0, 0]] T) or from a python-control
  ``StateSpace`` / ``TransferFunction`` (:meth:`LTI.from_control`, ``control.c2d`` with
  ``"zoh"``).

All three are :class:`~jaxnc.loop.base.AbstractPlant`: the runner draws standard normal
noises and scales them by ``w_std`` / ``v_std``; the same object is an estimator's model.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxnc._validate import (array_fields, check_callable, check_finite, check_given, check_int, check_nonneg,
                             check_positive, fields_concrete)
from jaxnc.estimators.ekf import matvec
from jaxnc.loop.base import AbstractPlant
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["Discrete", "Continuous", "LTI", "rk4"]


def _vec(name, v, n):
    a = np.asarray(v, np.float32)
    if a.ndim == 0:
        a = np.full((n,), a, np.float32)
    if a.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have {n} entries, got shape {a.shape}")
    check_nonneg(name, a)
    return a


def _dims(f, h, x0, input_dim, noise_dim):
    """Output dimension of h, checked by evaluating f and h once on zeros."""
    x0 = jnp.asarray(x0, jnp.float32)
    u0, w0 = jnp.zeros((input_dim,), jnp.float32), jnp.zeros((noise_dim,), jnp.float32)
    try:
        x1 = jax.eval_shape(f, x0, u0, w0)
    except Exception as e:  # noqa: BLE001 - re-raised with the user-facing name
        raise ValueError(f"f(x, u, w) failed on x0 (shape {x0.shape}), u of shape ({input_dim},), "
                         f"w of shape ({noise_dim},): {e}") from e
    if not isinstance(x1, jax.ShapeDtypeStruct):
        raise ValueError(f"f(x, u, w) must return one array (the next state), got {jax.tree.structure(x1)}")
    if x1.shape != x0.shape:
        raise ValueError(f"f(x, u, w) must return the state's shape {x0.shape}, got {x1.shape}")
    if x1.dtype != jnp.float32:
        raise ValueError(f"f(x, u, w) must return float32 values (the state's dtype), got {x1.dtype}")
    return x0


@_dataclass
class Discrete(AbstractPlant):
    """x_{t+1} = f(x_t, u_t, w_t), z = h(x, v) (additive noise is the usual h(x, v) = g(x) + v).

    Attributes:
      x0: float[n], the initial state; x0_std: float[n] (or scalar) or None, the std of a
        random initial state x0 + x0_std * N(0, I) (None: x0 exactly).
      w_std: float[noise_dim] (or scalar), std of w; v_std: float[output_dim], std of v.
      f, h: static functions (module docstring).
      input_dim, noise_dim, output_dim: static dimensions.
    """

    x0: Any
    w_std: Any
    v_std: Any
    f: Callable = _static()
    h: Callable = _static()
    input_dim: int = _static(1)
    noise_dim: int = _static(1)
    output_dim: int = _static(1)
    x0_std: Any = None

    def __post_init__(self):
        cls = type(self).__name__
        check_callable(f"{cls}.f", self.f, "a function f(x, u, w)")
        check_callable(f"{cls}.h", self.h, "a function h(x, v)")
        for n in ("x0", "w_std", "v_std"):
            check_given(f"{cls}.{n}", getattr(self, n))
        check_finite(f"{cls}.x0", self.x0)
        array_fields(self, "x0", "w_std", "v_std", "x0_std")
        check_int("Discrete.input_dim", self.input_dim, 1, 10_000)
        check_int("Discrete.noise_dim", self.noise_dim, 1, 10_000)
        check_int("Discrete.output_dim", self.output_dim, 1, 10_000)
        if fields_concrete(self):
            object.__setattr__(self, "x0", np.asarray(self.x0, np.float32))
            if self.x0.ndim != 1:
                raise ValueError(f"{cls}.x0 must be a vector (the state), got shape {self.x0.shape}")
            x0 = _dims(self.f, self.h, self.x0, self.input_dim, self.noise_dim)
            try:
                z = jax.eval_shape(self.h, x0, jnp.zeros((self.output_dim,), jnp.float32))
            except Exception as e:  # noqa: BLE001 - re-raised with the user-facing name
                raise ValueError(f"h(x, v) failed on x0 (shape {x0.shape}), v of shape ({self.output_dim},): "
                                 f"{e}") from e
            if not isinstance(z, jax.ShapeDtypeStruct) or z.shape != (self.output_dim,):
                raise ValueError(f"h(x, v) must return output_dim={self.output_dim} values, got "
                                 f"{z.shape if isinstance(z, jax.ShapeDtypeStruct) else jax.tree.structure(z)}")
            if z.dtype != jnp.float32:
                raise ValueError(f"h(x, v) must return float32 values, got {z.dtype}")
            object.__setattr__(self, "w_std", _vec("w_std", self.w_std, self.noise_dim))
            object.__setattr__(self, "v_std", _vec("v_std", self.v_std, self.output_dim))
            if self.x0_std is not None:
                object.__setattr__(self, "x0_std", _vec(f"{cls}.x0_std", self.x0_std, self.x0.shape[0]))

    @property
    def state_dim(self) -> int:
        return int(self.x0.shape[0])

    def dynamics(self, x, u, w):
        return self.f(x, u, w)

    def measure(self, x, v):
        return self.h(x, v)


def rk4(f, x, u, w, dt, n: int):
    """``n`` classical Runge-Kutta steps of length dt / n of dx/dt = f(x, u, w)."""
    h = dt / n

    def body(x, _):
        k1 = f(x, u, w)
        k2 = f(x + 0.5 * h * k1, u, w)
        k3 = f(x + 0.5 * h * k2, u, w)
        k4 = f(x + h * k3, u, w)
        return x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4), None

    x, _ = jax.lax.scan(body, x, None, length=n)
    return x


@_dataclass
class Continuous(Discrete):
    """dx/dt = f(x, u, w) integrated over the fast period ``T`` by ``substeps`` RK4 steps
    (u and w held over the period); z = h(x, v) at the sampling instants.

    Attributes (beyond :class:`Discrete`'s): T, the fast period in seconds (> 0);
    substeps, static int >= 1.
    """

    T: Any = 0.01
    substeps: int = _static(4)

    def __post_init__(self):
        check_given("Continuous.T", self.T, "a number > 0 (seconds)")
        check_positive("Continuous.T", self.T)
        check_int("Continuous.substeps", self.substeps, 1, 100_000)
        super().__post_init__()

    @property
    def step_period(self):
        return self.T

    def dynamics(self, x, u, w):
        return rk4(self.f, x, u, w, jnp.asarray(self.T, x.dtype), self.substeps)


@jax.jit
def _linear_terms(plant, x, u):
    """(f(x, u, 0), h(x, 0), df/dx, df/du, df/dw, dh/dx) of ``plant`` (:meth:`LTI.linearize`):
    one compiled program per plant structure, so linearising at many points compiles once."""
    w0 = jnp.zeros((int(plant.noise_dim),), jnp.float32)
    v0 = jnp.zeros((int(plant.output_dim),), jnp.float32)
    A, B, G = jax.jacfwd(plant.dynamics, argnums=(0, 1, 2))(x, u, w0)
    C = jax.jacfwd(lambda x: plant.measure(x, v0))(x)
    return plant.dynamics(x, u, w0), plant.measure(x, v0), A, B, G, C


@_dataclass
class LTI(AbstractPlant):
    """x+ = A x + B u + G w + offset, z = C x + D u + z_offset + v (discrete, period T).

    Attributes: A float[n, n], B float[n, m], C float[p, n], D float[p, m] (must be 0 or
    None: z is sampled before u is applied), G float[n, q] (default identity: w is
    additive state noise), x0 float[n], w_std float[q], v_std float[p], x0_std float[n] or
    None (a random initial state x0 + x0_std * N(0, I)), T seconds (the
    period it was sampled at, checked against the loop's; None: the loop's), state_names (static, optional): a tuple of n distinct names of the
    states, e.g. carried from a python-control model (:meth:`from_control`); offset
    float[n] and z_offset float[p] (default None: none), the constant terms of an affine
    model, e.g. the linearisation of a nonlinear plant around an operating point
    (:meth:`linearize`), so that the linear observers (``Luenberger``, ``SteadyStateKF``)
    estimate the plant's own state, not its deviation. Raises ValueError (naming the field)
    for shapes that do not match, a non-finite entry, a nonzero D, negative stds, T <= 0 or
    state_names that are not n distinct strings.
    """

    A: Any
    B: Any
    C: Any
    D: Any = None
    G: Any = None
    x0: Any = None
    w_std: Any = 0.0
    v_std: Any = 0.0
    T: Any = None
    state_names: Any = _static(None)
    x0_std: Any = None
    offset: Any = None
    z_offset: Any = None

    @property
    def step_period(self):
        return self.T

    def __post_init__(self):
        for n in ("A", "B", "C"):
            check_given(f"LTI.{n}", getattr(self, n), "a matrix of numbers")
        if self.state_names is not None:
            names = self.state_names
            if isinstance(names, str) or not all(isinstance(v, str) for v in names) or len(set(names)) != len(names):
                raise ValueError(f"LTI.state_names must be None or a sequence of distinct strings, got {names!r}")
            object.__setattr__(self, "state_names", tuple(names))
        for n in ("A", "B", "C", "D", "G", "x0", "offset", "z_offset"):
            check_finite(f"LTI.{n}", getattr(self, n))
        for n in ("w_std", "v_std"):
            check_given(f"LTI.{n}", getattr(self, n))
        array_fields(self, "A", "B", "C", "D", "G", "x0", "w_std", "v_std", "x0_std", "offset", "z_offset")
        if not fields_concrete(self):
            return
        A = np.atleast_2d(np.asarray(self.A, np.float32))
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"LTI.A must be square, got shape {A.shape}")
        B = np.asarray(self.B, np.float32)
        if B.ndim > 2 or (B.ndim == 2 and B.shape[0] != n) or (B.ndim < 2 and B.size != n):
            raise ValueError(f"LTI.B must have {n} rows (one per state), got shape {B.shape}")
        B = B.reshape(n, -1)
        C = np.atleast_2d(np.asarray(self.C, np.float32))
        if C.ndim != 2 or C.shape[1] != n:
            raise ValueError(f"LTI.C must have {n} columns (one per state), got shape {C.shape}")
        m, p = B.shape[1], C.shape[0]
        if self.D is not None and np.any(np.asarray(self.D) != 0):
            raise ValueError("LTI.D must be 0 (or None): z = C x + v is sampled before u is applied, a "
                             "networked loop has no direct feedthrough")
        D = np.zeros((p, m), np.float32)
        G = np.eye(n, dtype=np.float32) if self.G is None else np.asarray(self.G, np.float32)
        if G.ndim > 2 or (G.ndim == 2 and G.shape[0] != n) or (G.ndim < 2 and G.size != n):
            raise ValueError(f"LTI.G must have {n} rows (one per state), got shape {G.shape}")
        G = G.reshape(n, -1)
        x0 = np.zeros(n, np.float32) if self.x0 is None else np.asarray(self.x0, np.float32)
        if x0.shape != (n,):
            raise ValueError(f"LTI.x0 must have {n} entries, got shape {x0.shape}")
        if self.T is not None:
            check_positive("LTI.T", self.T)
        if self.state_names is not None and len(self.state_names) != n:
            raise ValueError(f"LTI.state_names must name the {n} states, got {len(self.state_names)} names")
        for name, v in (("A", A), ("B", B), ("C", C), ("D", D), ("G", G)):
            object.__setattr__(self, name, v)
        object.__setattr__(self, "x0", x0)
        object.__setattr__(self, "w_std", _vec("LTI.w_std", self.w_std, G.shape[1]))
        object.__setattr__(self, "v_std", _vec("LTI.v_std", self.v_std, p))
        if self.x0_std is not None:
            object.__setattr__(self, "x0_std", _vec("LTI.x0_std", self.x0_std, n))
        for name, size, what in (("offset", n, "state"), ("z_offset", p, "output")):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, np.float32)
                if v.shape != (size,):
                    raise ValueError(f"LTI.{name} must have {size} entries (one per {what}), got shape {v.shape}")
                object.__setattr__(self, name, v)

    @property
    def state_dim(self) -> int:
        return int(self.A.shape[0])

    @property
    def input_dim(self) -> int:
        return int(self.B.shape[1])

    @property
    def output_dim(self) -> int:
        return int(self.C.shape[0])

    @property
    def noise_dim(self) -> int:
        return int(self.G.shape[1])

    def dynamics(self, x, u, w):
        x1 = matvec(self.A, x) + matvec(self.B, u) + matvec(self.G, w)
        return x1 if self.offset is None else x1 + self.offset

    def measure(self, x, v):
        # D u is not known at sampling time in a networked loop: z = C x + v (D must be 0)
        z = matvec(self.C, x)
        return (z if self.z_offset is None else z + self.z_offset) + v

    @classmethod
    def linearize(cls, plant, x_op, u_op, **kw) -> "LTI":
        """The first-order model of ``plant`` (a plant whose state is a vector: ``Discrete``,
        ``Continuous``, an ``LTI``) around the operating point (x_op, u_op), w = 0, v = 0:

            x+ = f(x_op, u_op, 0) + A (x - x_op) + B (u - u_op) + G w,
            z  = h(x_op, 0) + C (x - x_op) + v,

        A = df/dx, B = df/du, G = df/dw, C = dh/dx (``jax.jacfwd`` of the plant's own step over
        its period, so a ``Continuous`` plant's integrator is linearised exactly, not its
        vector field), as an affine :class:`LTI` (``offset`` = f(x_op, u_op, 0) - A x_op - B u_op,
        ``z_offset`` = h(x_op, 0) - C x_op): exact at the operating point, which need not be an
        equilibrium. The plant's noise stds, period and initial state are kept unless given in
        ``kw`` (other keywords are :class:`LTI`'s).

        Args:
          plant: the plant model; x_op float[n], u_op float[m] (a scalar for m = 1).

        Raises:
          ValueError: naming ``x_op`` or ``u_op`` for a size other than the plant's state or
            input, or a non-finite entry; for a plant whose state is not a vector of
            ``state_dim`` numbers; for a model whose step or measurement is not finite there.
        """
        n, m = int(plant.state_dim), int(plant.input_dim)
        x_op = np.asarray(x_op, np.float32).reshape(-1) if np.ndim(x_op) else np.full((1,), x_op, np.float32)
        u_op = np.asarray(u_op, np.float32).reshape(-1) if np.ndim(u_op) else np.full((m,), u_op, np.float32)
        for name, v, size, what in (("x_op", x_op, n, "state_dim"), ("u_op", u_op, m, "input_dim")):
            if v.shape != (size,):
                raise ValueError(f"LTI.linearize: {name} must have {size} entries (the plant's {what}), "
                                 f"got {v.shape[0]}")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"LTI.linearize: {name} must be finite, got {v}")
        x0 = jax.eval_shape(lambda: plant.init(jax.random.PRNGKey(0)))
        if not (isinstance(x0, jax.ShapeDtypeStruct) and x0.shape == (n,)):
            raise ValueError(f"LTI.linearize: the plant's state must be a vector of its {n} numbers (a Discrete, "
                             f"Continuous or LTI plant); {type(plant).__name__}'s is not")
        f_op, h_op, A, B, G, C = (np.asarray(a, np.float64) for a in _linear_terms(plant, x_op, u_op))
        for name, a in (("its step f(x_op, u_op, 0)", f_op), ("its measurement h(x_op, 0)", h_op),
                        ("its Jacobians", np.concatenate([A.ravel(), B.ravel(), G.ravel(), C.ravel()]))):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"LTI.linearize: the plant's {name} is not finite at x_op = {x_op}, u_op = {u_op}")
        x_op64, u_op64 = x_op.astype(np.float64), u_op.astype(np.float64)
        kw.setdefault("w_std", np.asarray(plant.w_std, np.float32))
        kw.setdefault("v_std", np.asarray(plant.v_std, np.float32))
        kw.setdefault("T", getattr(plant, "step_period", None))
        if "x0" not in kw and getattr(plant, "x0", None) is not None and np.shape(plant.x0) == (n,):
            kw["x0"] = np.asarray(plant.x0, np.float32)
        return cls(A=A, B=B, C=C, G=G, offset=f_op - A @ x_op64 - B @ u_op64, z_offset=h_op - C @ x_op64, **kw)

    @classmethod
    def from_continuous(cls, A, B, C, T: float, **kw) -> "LTI":
        """Exact ZOH discretisation of dx/dt = A x + B u: Ad = e^{A T}, Bd = int_0^T e^{A s} ds B.

        A float[n, n]; B float[n, m] (or n entries: one input); C float[p, n]; T > 0 seconds;
        other keywords are :class:`LTI`'s (``G``, ``w_std``, ``v_std`` describe the discrete
        noise as given, ``offset`` the discrete step's constant term as given: a continuous
        model's constant input d enters as ``offset`` = int_0^T e^{A s} ds d). Raises ValueError naming the argument for a non-square A, a B
        without n rows, or T <= 0 (B of shape (m, n) was reshaped into n x m without an error,
        scrambling its entries)."""
        check_positive("T", T)
        A = np.atleast_2d(np.asarray(A, float))
        n = A.shape[0]
        if A.ndim != 2 or A.shape != (n, n):
            raise ValueError(f"LTI.from_continuous: A must be square (n x n), got shape {A.shape}")
        B = np.asarray(B, float)
        if B.ndim > 2 or (B.ndim == 2 and B.shape[0] != n) or (B.ndim < 2 and B.size != n):
            raise ValueError(f"LTI.from_continuous: B must have {n} rows (one per state of A), got shape {B.shape}")
        B = B.reshape(n, -1)
        m = B.shape[1]
        M = np.zeros((n + m, n + m))
        M[:n, :n], M[:n, n:] = A, B
        E = scipy.linalg.expm(M * T)
        return cls(A=E[:n, :n], B=E[:n, n:], C=C, T=T, **kw)

    @classmethod
    def from_control(cls, sys, T: float | None = None, *, realization: str | None = None, **kw) -> "LTI":
        """From a python-control ``StateSpace`` or ``TransferFunction``.

        A continuous-time system is discretised at ``T`` with ``control.c2d(sys, T,
        "zoh")``, which keeps its state coordinates; a discrete one must have ``dt == T``
        (or T None); one of unspecified period (``dt=True``) takes ``T``, or the loop's
        period when T is None.

        State coordinates:

        * a ``StateSpace`` keeps its own coordinates (``realization=None``), and its
          state labels become ``state_names``;
        * a ``TransferFunction`` has no state coordinates of its own: ``realization``
          chooses python-control's canonical form (``control.canonical_form``) of the
          continuous (or discrete) model, before discretisation:
          ``"observable"`` (x[0] is the output, z = x[0] + v) or ``"reachable"`` (the
          controllable canonical form, python-control's own ``control.ss(tf)``
          realisation, where x[0] is not the output in general). ``None`` gives
          ``"reachable"`` with a ``UserWarning`` saying so. ``state_names`` is then None.
          A ``StateSpace`` given a ``realization`` is transformed the same way.
          (python-control's ``"modal"`` form needs slycot and is not offered.)

        Keywords ``x0`` and, when ``G`` is not given (one noise per state), ``w_std``
        may be a mapping {state name: value} for a model whose states are named (or
        given ``state_names``); the states not named get 0. The other keywords are
        :class:`LTI`'s.

        Raises:
          ValueError: ``T`` missing for a continuous-time system or differing from a
            discrete system's dt, a direct feedthrough D != 0, an unknown
            ``realization``, a realization of a MIMO transfer function, or a mapping
            naming a state the model does not have.
        """
        import warnings

        import control
        from jaxnc._validate import check_choice
        if realization is not None:
            realization = check_choice("from_control: realization", realization, ("observable", "reachable"))
        if isinstance(sys, control.TransferFunction) and realization is None:
            warnings.warn("LTI.from_control: a transfer function has no state coordinates; using python-control's "
                          "reachable (controllable) canonical form, whose x[0] is not the output in general. "
                          "Pass realization='observable' (x[0] = output) or realization='reachable' to choose.",
                          UserWarning, stacklevel=2)
        ss = control.ss(sys)
        names = tuple(ss.state_labels) if isinstance(sys, control.StateSpace) and realization is None else None
        if realization is not None:
            if not ss.issiso():
                raise ValueError(f"from_control: realization={realization!r} needs a single-input single-output "
                                 f"model, got {ss.ninputs} inputs and {ss.noutputs} outputs")
            ss = control.canonical_form(ss, realization)[0]
        if ss.dt in (0, None):
            if T is None:
                raise ValueError("T is required to discretise a continuous-time system")
            check_positive("T", T)
            ss = control.c2d(ss, T, "zoh")
        elif T is not None and ss.dt is not True and abs(float(ss.dt) - float(T)) > 1e-12:
            raise ValueError(f"the system is discrete with dt={ss.dt}, T={T} differs")
        # a discrete model of unspecified period (dt=True) takes the loop's (None); it read 1 s, and a
        # Loop at any other T refused it ("must equal the plant's step period (... = 1 s)")
        dt = float(T) if T is not None else (None if ss.dt is True else float(ss.dt))
        if np.any(np.asarray(ss.D) != 0):
            raise ValueError("from_control: the system has a direct feedthrough D != 0; a sampled "
                             "networked loop needs D = 0")
        names = kw.pop("state_names", names)
        for key in ("x0", "w_std"):
            if isinstance(kw.get(key), dict):
                if names is None:
                    raise ValueError(f"from_control: {key} given by state name, but the model's states are not "
                                     f"named (a StateSpace in its own coordinates names them)")
                if key == "w_std" and kw.get("G") is not None:
                    raise ValueError("from_control: w_std given by state name needs one noise per state (G not given)")
                unknown = sorted(set(kw[key]) - set(names))
                if unknown:
                    raise ValueError(f"from_control: {key} names unknown state(s) {unknown}; the states are "
                                     f"{list(names)}")
                kw[key] = [float(kw[key].get(s, 0.0)) for s in names]
        return cls(A=ss.A, B=ss.B, C=ss.C, T=dt, state_names=names, **kw)
