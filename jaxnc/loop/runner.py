"""The closed loop, written once: :class:`Loop`, :func:`simulate`, :func:`run`.

:func:`simulate` is one ``lax.scan`` over the slow periods (NT) with the N fast periods
(T) inside, calling the roles of :mod:`jaxnc.loop.base` in the order given there. All
exogenous randomness (plant and sensor noise, every packet's loss and delay) is drawn
before the scan from the run's key by :func:`draw`, one stream per purpose
(``fold_in(key, i)``, the order of :data:`STREAMS`), so two loops run with the same key
meet the same realisation wherever their roles agree (common random numbers), and a
seed's run does not depend on the batch it is in.

A run *fails* when the true state or the action becomes non-finite, or the state leaves
``Monitor.bounds``; a non-finite action is replaced by zero and, from
then on the plant is frozen at its last good state (``Monitor.freeze``), so divergence
is data (inf in :class:`Metrics`), never an exception or a NaN in a batch. Which of the two
ended a run is kept: ``Trajectory.fail_action`` / ``Metrics.unstable_action`` (a non-finite
action: the controller, its estimate or the actuator broke down numerically, e.g. a
covariance lost in float32) against the plant's state.
"""
from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import dataclasses
import hashlib
import warnings
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import (array_fields, check_bool, check_callable, check_finite, check_given, check_instance,
                             check_int, check_range, concrete, jit_when_eager)
from jaxnc.loop.actuators import PacketActuator
from jaxnc.loop.base import (AbstractActuator, AbstractController, AbstractEstimator, AbstractMonitor, AbstractPlant,
                             AbstractTrigger, Inbox, Packet)
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.loop.limits import LimitedActuator
from jaxnc.loop.links import Link, LinkDraws, NoDelay, NoLoss, draw_link, link_delay_bounds, steps_within
from jaxnc.prng import unrolled

__all__ = ["Loop", "Record", "Monitor", "Quadratic", "FunctionCost", "Context", "Draws", "Trajectory", "Metrics", "draw", "simulate",
           "run", "run_seed", "evaluate", "live_periods", "STREAMS", "SIGNALS", "PARTS"]

#: the draw streams of a run: stream i uses ``fold_in(key, i)``
STREAMS = ("process", "measurement", "uplink", "downlink", "plant_init")


class Context(NamedTuple):
    """Static facts about the loop that components need to build their state.

    ``signal_dim`` is the size of the signal a trigger watches (the runner sets it: the
    measurement's for the sensor's trigger, an action's for the controller's; 0 elsewhere);
    ``uplink_capacity`` the uplink's ring length C (the packets an estimator can look back on)."""

    N: int
    steps: int
    T: float
    state_dim: int
    input_dim: int
    output_dim: int
    signal_dim: int = 0
    uplink_capacity: int = 0


SIGNALS = ("x", "u", "z", "xhat", "sent_sc", "recv_sc", "sent_ca", "recv_ca")
PARTS = ("plant", "estimator", "controller", "actuator", "monitor")


@dataclasses.dataclass(frozen=True)
class Record:
    """What a run keeps (the declared recording spec, as diffrax's ``SaveAt``).

    Attributes:
      signals: names of :class:`Trajectory` signals to keep, among :data:`SIGNALS`
        (the others come back empty, and are neither computed nor stored).
      plant: ``fn(plant, x)`` of the plant's state after each fast period's step, kept in
        ``Trajectory.parts["plant"]`` [K, ...]; None: nothing.
      estimator: ``fn(estimator, state)`` at the end of each slow period (after the
        prediction), ``parts["estimator"]`` [S, ...].
      controller: ``fn(controller, state)`` after each step, ``parts["controller"]`` [S, ...].
      actuator: ``fn(actuator, state, t)`` after each output, ``parts["actuator"]`` [K, ...].
      monitor: ``fn(monitor, state)`` after each fast period, ``parts["monitor"]`` [K, ...].

    The functions are static (part of the compiled program): define them at module level
    so that equal specs compare equal.
    """

    signals: tuple = SIGNALS
    plant: Any = None
    estimator: Any = None
    controller: Any = None
    actuator: Any = None
    monitor: Any = None

    def __post_init__(self):
        if isinstance(self.signals, str) or not isinstance(self.signals, (tuple, list)) \
                or any(n not in SIGNALS for n in self.signals):
            raise ValueError(f"Record.signals must be a tuple of names among {', '.join(SIGNALS)}, "
                             f"got {self.signals!r}")
        object.__setattr__(self, "signals", tuple(self.signals))
        for role in PARTS:
            fn = getattr(self, role)
            if fn is not None:
                check_callable(f"Record.{role}", fn, f"a function of the {role} and its state, or None")

    @classmethod
    def of(cls, record) -> "Record":
        """A :class:`Record` from ``Loop.record``'s short forms: True (every signal), False
        (only the summaries), a tuple of signal names, or a Record itself."""
        if isinstance(record, Record):
            return record
        if record is True:
            return cls()
        if record is False:
            return cls(signals=())
        if isinstance(record, tuple) and all(n in SIGNALS for n in record):
            return cls(signals=record)
        raise ValueError(f"Loop.record must be True, False, a tuple of names among {', '.join(SIGNALS)} or a "
                         f"jaxnc.loop.Record, got {record!r}")


@_dataclass
class Monitor(AbstractMonitor):
    """Failure detection, no state: non-finite state, or |x_i| > bounds_i for any i (bounds
    float[n], inf where unbounded; None: only non-finite); never complete. ``freeze``
    (static): hold the plant at its last good state once failed (and stop the monitor:
    :class:`~jaxnc.loop.AbstractMonitor`)."""

    field_shapes: ClassVar[dict] = {"bounds": ((), ("state",))}

    bounds: Any = None
    freeze: bool = _static(True)

    def __post_init__(self):
        check_bool("Monitor.freeze", self.freeze)
        check_range("Monitor.bounds", self.bounds, 0.0, None, low_open=True, finite=False)   # None: unbounded
        array_fields(self, "bounds")

    def init(self, ctx):
        return ()

    def step(self, state, x, u, t):
        bad = ~jnp.all(jnp.isfinite(x))
        if self.bounds is not None:
            bad = bad | jnp.any(jnp.abs(x) > self.bounds)
        return state, bad, jnp.zeros((), bool)


@_dataclass
class FunctionCost:
    """A plain Python function ``fn(x float[K, n], u float[K, m]) -> scalar`` as a loop's
    cost: static (part of the compiled program, compared by identity), so a ``Loop`` holding
    it can be passed to ``jit``/``run_batched``. ``Loop(cost=fn)`` wraps a function in it."""

    fn: Any = _static()

    def __call__(self, x, u):
        return self.fn(x, u)


def _weighted_square(v, W):
    """v' W v over the last axis of ``v`` (W a vector: the diagonal), as elementwise products
    and sums only: no dot product, whose summation order XLA chooses by the batch's shape."""
    n = v.shape[-1]
    if W.ndim == 1:
        terms = [v[..., i] * v[..., i] * W[i] for i in range(n)]
    else:
        terms = [v[..., i] * W[i, j] * v[..., j] for i in range(n) for j in range(n)]
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def _pairwise_mean(values):
    """The mean of every entry of ``values`` by pairwise summation written as elementwise
    adds of halves (zero-padded to a power of two): the same bits in every lane of a
    ``vmap`` whatever the batch's size (``jnp.mean``'s reduction is compiled per batch
    shape and its order, hence its last bits, change with it), and as accurate as a
    pairwise sum."""
    a = jnp.ravel(values)
    n = a.shape[0]
    size = 1 << max(n - 1, 0).bit_length()
    a = jnp.concatenate([a, jnp.zeros(size - n, a.dtype)])
    while a.shape[0] > 1:
        half = a.shape[0] // 2
        a = a[:half] + a[half:]
    return a[0] / n


@_dataclass
class Quadratic:
    """Cost J = (1/K) sum_t (x_t - x_ref)' Q (x_t - x_ref) + u_t' R u_t over the fast instants.

    Q float[n, n] or float[n] (diagonal), R float[m, m] or float[m]. Computed with
    elementwise operations only (a pairwise sum over t), so a seed's cost is the same bits
    in a batch of any size (any ``chunk_size`` of :func:`jaxnc.montecarlo.run_batched`)
    whenever its trajectory is."""

    field_shapes: ClassVar[dict] = {"Q": (("state",), ("state", "state")), "R": (("input",), ("input", "input")),
                                    "x_ref": ((), ("state",))}

    Q: Any
    R: Any
    x_ref: Any = 0.0

    def __post_init__(self):
        for n in ("Q", "R", "x_ref"):
            check_given(f"Quadratic.{n}", getattr(self, n))
            check_finite(f"Quadratic.{n}", getattr(self, n))
        array_fields(self, "Q", "R", "x_ref")
        for n in ("Q", "R"):
            if concrete(getattr(self, n)):
                M = np.asarray(getattr(self, n), float)
                if M.ndim > 2 or (M.ndim == 2 and M.shape[0] != M.shape[1]):
                    raise ValueError(f"Quadratic.{n} must be a vector of weights or a square matrix, got shape {M.shape}")
                if M.ndim < 2:
                    check_range(f"Quadratic.{n}", M, 0.0, None)
                elif not np.allclose(M, M.T) or np.linalg.eigvalsh(M).min() < -1e-9 * max(1.0, np.abs(M).max()):
                    raise ValueError(f"Quadratic.{n} must be symmetric positive semi-definite")

    def __call__(self, x, u):
        e = x - jnp.asarray(self.x_ref, x.dtype)
        Q, R = jnp.asarray(self.Q), jnp.asarray(self.R)
        return _pairwise_mean(_weighted_square(e, Q) + _weighted_square(u, R))


@_dataclass
class Loop:
    """A networked closed loop: one value per role, and the static sizes.

    Attributes:
      plant: the true plant (:class:`~jaxnc.loop.base.AbstractPlant`).
      trigger: the sensor's trigger (:mod:`jaxnc.loop.triggers`).
      uplink: sensor -> controller :class:`~jaxnc.loop.links.Link`.
      estimator: :mod:`jaxnc.loop.estimators`.
      controller: :mod:`jaxnc.loop.controllers`.
      downlink: controller -> actuator link.
      actuator: :mod:`jaxnc.loop.actuators` (its horizon must equal the controller's).
      controller_trigger: optional trigger on the first action of each packet, evaluated
        only at the instants the controller would send (its state unchanged otherwise) (seed 003
        eq. 21-22); None: every computed packet is sent.
      monitor: failure detection. A monitor that declares ``position_field`` (``PathMonitor``:
        ``xy``) and leaves that field None is given the plant's declared ``position_index``
        here (a plant that declares none is refused), and again from the new plant when the
        loop is rebuilt with another (``dataclasses.replace(loop, plant=...)``).
      cost: a function (x float[K, n], u float[K, m]) -> scalar, e.g. :class:`Quadratic`
        (a pytree whose numbers are leaves), a plain Python function (kept static: part of
        the compiled program, so define it at module level to reuse one program), or None.
      N: static, fast periods per slow period (>= 1).
      steps: static, fast periods simulated (a multiple of N).
      T: static, the fast period in seconds (links quantise delays to it).
      record: static, what a run keeps: a :class:`Record` (signals, and functions of the
        roles' states kept in ``Trajectory.parts``), or its short forms True (every signal),
        False (only the summaries) or a tuple of signal names among
        ``x u z xhat sent_sc recv_sc sent_ca recv_ca``, e.g. ``("xhat", "sent_sc")`` for a
        loop whose metrics need only those: what is not recorded is not computed or stored.
      remat: static; True wraps each slow period in ``jax.checkpoint`` (saving nothing), so
        reverse mode recomputes a period's forward pass instead of storing its intermediates.
        Forward runs are unchanged (bit for bit); gradients equal up to float rounding. It
        pays where a period is heavy and costs where it is light: measure
        (benchmarks/bench_grad_remat.py); the :class:`~jaxnc.loop.EKF`'s prediction is
        recomputed in any case, which took the cart-pole's gain (docs/design_notes.md).
    """

    plant: Any
    trigger: Any
    uplink: Link
    estimator: Any
    controller: Any
    downlink: Link
    actuator: Any
    controller_trigger: Any = None
    monitor: Monitor = Monitor()
    cost: Any = None
    N: int = _static(1)
    steps: int = _static(100)
    T: float = _static(1.0)
    record: Any = _static(True)
    remat: bool = _static(False)

    def __post_init__(self):
        for name, cls, what in _ROLES:
            check_instance(f"Loop.{name}", getattr(self, name), cls, what)
        if self.controller_trigger is not None:
            check_instance("Loop.controller_trigger", self.controller_trigger, AbstractTrigger,
                           "a trigger (a jaxnc.loop.AbstractTrigger: Periodic, Petc) or None")
        check_instance("Loop.monitor", self.monitor, AbstractMonitor, "a monitor (a jaxnc.loop.AbstractMonitor: "
                       "Monitor)")
        if self.cost is not None:
            check_callable("Loop.cost", self.cost, "a function cost(x, u) -> scalar (e.g. jaxnc.loop.Quadratic) or None")
            if jax.tree.leaves(self.cost) == [self.cost]:       # a plain function: part of the program
                object.__setattr__(self, "cost", FunctionCost(self.cost))
        object.__setattr__(self, "record", Record.of(self.record))
        check_bool("Loop.remat", self.remat)
        check_int("Loop.N", self.N, 1, 100_000)
        check_int("Loop.steps", self.steps, self.N, None)
        if self.steps % self.N:
            raise ValueError(f"Loop.steps must be a multiple of N={self.N}, got {self.steps}")
        if isinstance(self.T, (np.floating, np.integer)):
            object.__setattr__(self, "T", float(self.T))        # a numpy scalar: a plain float (static)
        if isinstance(self.T, bool) or not (isinstance(self.T, (int, float)) and np.isfinite(self.T) and self.T > 0):
            raise ValueError(f"Loop.T must be a number > 0 (seconds), got {self.T!r}")
        models = [("plant", self.plant)] + [        # the parts' models step one fast period too
            (role + jax.tree_util.keystr(path), part)
            for role in ("estimator", "controller")
            for path, part in jax.tree_util.tree_flatten_with_path(
                getattr(self, role), is_leaf=lambda v: isinstance(v, AbstractPlant))[0]
            if isinstance(part, AbstractPlant)]
        for where, model in models:
            model_T = model.step_period
            if model_T is not None and concrete(model_T) and np.ndim(model_T) == 0 \
                    and abs(float(model_T) - float(self.T)) > 1e-6 * float(self.T):      # float32 rounding
                raise ValueError(f"Loop.T ({float(self.T):g} s) must equal the {where}'s step period "
                                 f"({type(model).__name__}.step_period = {float(model_T):g} s)")
        field = self.monitor.position_field      # declared (PathMonitor: "xy"); None: reads no position
        # a monitor whose position a Loop filled is filled again from this loop's plant, so that
        # dataclasses.replace(loop, plant=other) does not keep the former plant's index
        if field is not None and (getattr(self.monitor, field) is None
                                  or _POSITION_FILLED.get(id(self.monitor)) is self.monitor):
            at = self.plant.position_index       # declared by a plant with a planar position (DiffDrive, Mecanum)
            if at is None:
                raise ValueError(f"Loop.monitor.{field} must be given: {type(self.monitor).__name__} watches a planar "
                                 f"position and the plant {type(self.plant).__name__} declares none (its "
                                 f"position_index is None); give {type(self.monitor).__name__}({field}=i), i the index "
                                 f"of the position's first coordinate in the plant's state vector")
            object.__setattr__(self, "monitor", dataclasses.replace(self.monitor, **{field: int(at)}))
            _POSITION_FILLED[id(self.monitor)] = self.monitor
        if self.cost is not None and not ({"x", "u"} <= set(self.record.signals)):
            raise ValueError(f"Loop.cost needs the signals x and u recorded, but Loop.record keeps only "
                             f"{self.record.signals}: add them, or set cost=None")
        if self.controller.keeps_copy:      # its copy of what it sent sees neither of these
            if self.controller_trigger is not None:
                raise ValueError(f"Loop.controller_trigger must be None: {type(self.controller).__name__} keeps its "
                                 f"own copy of what it sent (keeps_copy), which a controller-side trigger would not gate")
            if isinstance(self.actuator, LimitedActuator):
                raise ValueError(f"Loop.actuator must not be a LimitedActuator: {type(self.controller).__name__} keeps "
                                 f"its own copy of what it sent (keeps_copy), which the limits would not reach")
        H = self.controller.horizon
        if isinstance(self.actuator.horizon, int) and self.actuator.horizon != H:
            raise ValueError(f"Loop.actuator.horizon ({self.actuator.horizon}) must equal the controller's "
                             f"horizon ({H})")
        P = self.controller.period_steps
        if P is not None and int(P) != self.N:
            raise ValueError(f"Loop.N ({self.N}) must equal the fast periods per slow period the controller is built "
                             f"for ({type(self.controller).__name__}.period_steps = {int(P)})")
        inner = self.actuator.actuator if isinstance(self.actuator, LimitedActuator) else self.actuator
        if isinstance(inner, PacketActuator) and inner.on_exhausted == "zero" and inner.span == "fast" \
                and inner.horizon < self.N:
            raise ValueError(f"Loop.actuator: on_exhausted='zero' with span='fast' plays a packet's {inner.horizon} "
                             f"action(s) for {inner.horizon} fast period(s) and then applies zero, so with N={self.N} "
                             f"the plant would get zero in {self.N - inner.horizon} of the {self.N} fast periods of "
                             f"every slow period, lost packet or not: use ZeroOrder() (span='period': each action "
                             f"over the loop's period), HoldLast(), or packets of N or more actions "
                             f"(Predictive(horizon>={self.N}))")
        ahead = int(self.controller.stamps_ahead)
        if isinstance(inner, PacketActuator) and ahead > 0:
            lo = max(0, int(link_delay_bounds(self.downlink, self.T)[0]))
            need = ahead + 1 - min(lo, ahead)   # a packet arriving lo after it is computed waits ahead - lo
            if inner.capacity < need:
                raise ValueError(f"Loop.actuator.capacity must be >= {need}: {type(self.controller).__name__} stamps "
                                 f"its packets {ahead} fast period(s) ahead and the downlink delays them at least "
                                 f"{lo}, so a packet waits up to {ahead - min(lo, ahead)} fast period(s) for its "
                                 f"stamp while newer ones arrive; with capacity {inner.capacity} each is replaced "
                                 f"before it is due and the plant never gets it (e.g. HoldLast(capacity={need}) "
                                 f"or PacketActuator(capacity={need}))")
        if isinstance(inner, PacketActuator) and ahead > 0 and self.downlink.order != "all":
            lo, hi = link_delay_bounds(self.downlink, self.T)
            lo = max(0, int(lo))
            if hi is None or int(hi) - lo >= self.N:
                spread = f"{lo} to {int(hi)}" if hi is not None else f"{lo} or more (no bound)"
                raise ValueError(f"Loop.downlink.order must be 'all': {type(self.controller).__name__} stamps its "
                                 f"packets {ahead} fast period(s) ahead and the downlink delays them {spread} fast "
                                 f"periods, so two packets can arrive in one instant or out of order; "
                                 f"order={self.downlink.order!r} delivers only the newest of them, and the older "
                                 f"one's action, still due, would never be applied (use Link(..., order='all'))")
        for name in ("uplink", "downlink"):
            link = getattr(self, name)
            for role in ("loss", "delay"):       # a recorded trace must cover the run's slow instants
                have = getattr(link, role).packets()
                if have is not None and have < self.steps // self.N:
                    raise ValueError(f"Loop.{name}.{role} ({type(getattr(link, role)).__name__}) holds {have} "
                                     f"packets, but the run sends one per slow instant: {self.steps // self.N} "
                                     f"(steps={self.steps} / N={self.N}); give a trace of at least that many "
                                     f"entries or shorten the run")
            lo, hi = link_delay_bounds(link, self.T)
            ring = lambda d: -(-d // self.N) + 1        # slow periods a packet can be in flight, plus its own
            # a packet stays in its slot for C slow periods: the uplink is read at slow instants,
            # the downlink at every fast instant (it needs C N > d)
            reach = ring if name == "uplink" else (lambda d: -(-(d + 1) // self.N))
            if link.delay.in_steps and link.tau_max is not None and concrete(link.tau_max):
                with jax.ensure_compile_time_eval():     # the draws' own limit (floor, not the ring's ceil)
                    kept = int(steps_within(link.tau_max, self.T))
                top = kept if hi is None else min(hi, kept)
            else:
                top = hi                        # the longest delay a delivered packet can have
            if top is not None and top < lo:    # tau_max below the delay law's minimum
                raise ValueError(f"Loop.{name}.tau_max ({float(link.tau_max):g} s, {top} fast periods of "
                                 f"T={float(self.T):g} s) is below every delay its model "
                                 f"{type(link.delay).__name__} draws (at least {lo} fast periods), so every packet "
                                 f"would be discarded: raise tau_max or shorten the delays")
            if link.capacity is None:       # sized here: the smallest ring the delay bounds allow
                size = max(2, reach(lo), ring(hi) if hi is not None else 2,
                           self.estimator.lookback + 1 if name == "uplink" else 1)
                link = dataclasses.replace(link, capacity=size)
                object.__setattr__(self, name, link)
            if link.capacity < reach(lo):
                raise ValueError(f"Loop.{name}.capacity must be >= {reach(lo)}: every packet is delayed at least "
                                 f"{lo} fast periods (N={self.N}), so a ring of {link.capacity} reuses its slot "
                                 f"before it arrives and nothing is ever delivered")
            if hi is not None and link.capacity < ring(hi):
                raise ValueError(f"Loop.{name}.capacity must be >= {ring(hi)} for delays up to {hi} fast periods "
                                 f"with N={self.N}, got {link.capacity}")
            late = -(-lo // self.N)         # slow periods the earliest packet is late when read
            if name == "uplink" and self.estimator.by_stamp and late > self.estimator.lookback:
                raise ValueError(
                    f"Loop.estimator ({type(self.estimator).__name__}) uses a measurement at most "
                    f"{self.estimator.lookback} slow periods late (by its time stamp), but Loop.uplink delays every "
                    f"packet at least {lo} fast periods (N={self.N}), so each is read {late} slow periods late "
                    f"and the estimator would never correct: use EKF(buffer>={late}) or UKF(buffer>={late}), or "
                    f"an estimator that takes the newest arrival (Passthrough)")
            if name == "uplink" and self.estimator.undelayed_uplink and (hi is None or hi > 0):
                raise ValueError(
                    f"Loop.estimator ({type(self.estimator).__name__}) takes the newest arrival as the measurement "
                    f"of the instant it arrives, so its uplink must not delay, but Loop.uplink's "
                    f"{type(link.delay).__name__} delays packets up to "
                    f"{'an unbounded number of' if hi is None else hi} fast periods: use NoDelay, or an estimator "
                    f"that uses time stamps (EKF(buffer=...), UKF(buffer=...))")
            if hi is None and link.tau_max is None:     # allowed, and visible: an unbounded law's tail is lost
                warnings.warn(f"Loop.{name}: the delay model {type(link.delay).__name__} has no bound and the link "
                              f"no tau_max, so a packet still in flight when its slot in the ring of {link.capacity} "
                              f"is reused (delayed about {link.capacity - 1} slow periods or more) is lost; set "
                              f"tau_max or a larger capacity to decide", UserWarning, stacklevel=3)
        if not any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(self)):
            self._check_dims()      # also with leaves that are not arrays (a plain-object law)

    def _check_dims(self):
        """The roles fit together (:func:`_check_fit`): traced once per structure (tree, leaf
        shapes and dtypes); a loop of a structure that passed with other numbers in its leaves
        runs only :func:`_check_values` (every role's ``init(ctx)``, where a part checks its
        numbers against the loop's N: a ``Luenberger`` gain, a ``SteadyStateKF``'s
        detectability; and the links' draws), and a loop already checked with the same
        numbers nothing."""
        leaves, treedef = jax.tree.flatten(self)
        values = tuple(_leaf_key(a) for a in leaves)
        key = (treedef, values)
        if key in _FITTED:
            return
        shapes = (treedef, tuple(v[:2] for v in values))      # (type, id) for an object: kept whole
        if shapes in _FITTED_SHAPES:
            _check_values(self)
        else:
            _check_fit(self)
        if len(_FITTED) > 256:
            _FITTED.clear()
            _FITTED_SHAPES.clear()
        _FITTED.add(key)
        _FITTED_SHAPES.add(shapes)

    @property
    def ctx(self) -> Context:
        p = self.plant
        return Context(self.N, self.steps, float(self.T), int(p.state_dim), int(p.input_dim), int(p.output_dim),
                       uplink_capacity=int(self.uplink.capacity))


def _first_estimate(loop: Loop, ctx: Context):
    """The estimator's output at k = 0 on an empty inbox (for shapes)."""
    return loop.estimator.correct(loop.estimator.init(ctx), _first_inbox(loop, ctx), jnp.int32(0))[1]


def _shapes(tree) -> str:
    leaves = jax.tree.leaves(tree)
    got = [f"{a.dtype}{list(a.shape)}" for a in leaves]
    return got[0] if len(got) == 1 else "(" + ", ".join(got) + ")"


def _same_structure(name: str, before, after) -> None:
    """A role's state keeps its structure, shapes and dtypes from one step to the next."""
    sig = lambda t: (jax.tree.structure(t), [(a.shape, a.dtype) for a in jax.tree.leaves(t)])
    if sig(before) != sig(after):
        raise ValueError(f"{name} returns a state of {_shapes(after)}, but its init gave {_shapes(before)}: "
                         f"a state must keep its shapes and dtypes from step to step")


def _stage(name: str, what: str, fn):
    """jax.eval_shape(fn), re-raising any failure as a ValueError naming the role."""
    try:
        return jax.eval_shape(fn)
    except Exception as e:  # noqa: BLE001 - re-raised naming the role
        raise ValueError(f"{name} {what}: {_one_line(e)}") from e


def _check_field_shapes(name: str, part, dims: dict) -> None:
    """A part's declared ``field_shapes`` ({field: allowed shapes as tuples of dimension
    names}) against the loop's sizes."""
    for field, allowed in type(part).field_shapes.items():
        v = getattr(part, field)
        if v is None or not concrete(v):
            continue
        shape = np.shape(v)
        options = [tuple(dims[d] for d in a) for a in allowed]
        if shape not in options:
            said = " or ".join("a scalar" if not a else f"shape {tuple(dims[d] for d in a)} ("
                              + ", ".join(f"{d} = {dims[d]}" for d in a) + ")" for a in allowed)
            raise ValueError(f"{name}.{field} has shape {shape}; in this loop it must be {said}")


def _check_fit(loop: Loop) -> None:
    """Every role fits the others, checked on shapes and dtypes only (``jax.eval_shape``
    over one step of every role), when the loop is built: the plant's step keeps its
    state and returns floats, its measurement has ``output_dim`` floats; each link's loss
    and delay models draw one value per slow instant (:func:`_check_draws`); each part's
    declared ``field_shapes`` match the loop's sizes; every role's state keeps its shapes
    and dtypes from step to step (the actuator's when it receives packets too); the
    controller acts on the estimator's output and its packets are float[horizon, input_dim];
    the actuator outputs float32[input_dim]; the monitor's flags are bool scalars; the cost
    is a scalar. A mismatch raises a ValueError naming
    the part, the field and both sizes."""
    ctx = loop.ctx
    n, m, p = ctx.state_dim, ctx.input_dim, ctx.output_dim
    plant = loop.plant
    f32 = lambda shape: jnp.zeros(shape, jnp.float32)
    pkey = _plant_key(plant)
    x0 = _PLANTS.get(pkey)      # a plant already checked with these numbers (one plant in several loops)
    if x0 is None:
        x0 = _stage("Loop.plant", "cannot build its initial state", lambda: plant.init(jax.random.PRNGKey(0)))
        xv = _stage("Loop.plant", "cannot give its state vector", lambda: plant.state_vector(_zeros(x0)))
        if not isinstance(xv, jax.ShapeDtypeStruct) or xv.shape != (n,):
            raise ValueError(f"Loop.plant's state vector is {_shapes(xv)}, its state_dim is {n}: the initial state "
                             f"(e.g. x0) must be a vector of {n} numbers")
        x1 = _stage("Loop.plant", f"cannot step (u float32[{m}], w float32[{plant.noise_dim}])",
                    lambda: plant.dynamics(_zeros(x0), f32((m,)), f32((plant.noise_dim,))))
        _same_structure("Loop.plant's step", x0, x1)
        for name, size, what, read in (("w_std", plant.noise_dim, "noise_dim", lambda: plant.w_std),
                                       ("v_std", p, "output_dim", lambda: plant.v_std)):
            std = _stage("Loop.plant", f"has no {name} (the std of its noise, declared data)",
                         lambda read=read: jnp.asarray(read(), jnp.float32))
            if std.shape != (size,):
                raise ValueError(f"Loop.plant.{name} has shape {std.shape}, its {what} is {size}: one std per entry")
        z = _stage("Loop.plant", f"cannot measure (v float32[{p}])", lambda: plant.measure(_zeros(x0), f32((p,))))
        if not isinstance(z, jax.ShapeDtypeStruct) or z.shape != (p,) or z.dtype != jnp.float32:
            raise ValueError(f"Loop.plant's measurement is {_shapes(z)}; it must be float32[{p}] (output_dim={p})")
        if len(_PLANTS) > 64:
            _PLANTS.clear()
        _PLANTS[pkey] = x0
    dims = dict(state=n, input=m, output=p)
    for name in ("plant", "trigger", "estimator", "actuator", "controller_trigger", "monitor", "cost"):
        part = getattr(loop, name)
        if part is not None and (name != "cost" or isinstance(part, Quadratic)):
            _check_field_shapes(f"Loop.{name}", part, dict(dims, signal=p if name == "trigger" else m))
    t0, e0, c0, ct0, a0, m0 = _role_inits(loop)          # every other role's init(ctx) and the links' draws
    # the sensor's trigger
    t1, send = _stage("Loop.trigger", f"cannot decide on a measurement float32[{p}]",
                      lambda: loop.trigger.step(_zeros(t0), f32((p,)), jnp.int32(1)))
    _same_structure("Loop.trigger's step", t0, t1)
    if send.shape != ():
        raise ValueError(f"Loop.trigger's send decision is {_shapes(send)}; it must be a scalar 0/1 float")
    # estimator and controller
    e1, xhat = _stage("Loop.estimator", f"does not fit the plant (state_dim={n}, output_dim={p}, input_dim={m})",
                      lambda: loop.estimator.correct(_zeros(e0), _first_inbox(loop, ctx), jnp.int32(0)))
    _same_structure("Loop.estimator's correct", e0, e1)
    shapes = _shapes(xhat)
    if isinstance(xhat, jax.ShapeDtypeStruct) and xhat.ndim == 1:
        _check_field_shapes("Loop.controller", loop.controller, dict(dims, estimate=xhat.shape[0]))
        name = loop.controller.prediction_model                 # declared (Predictive, LeadFeedback: "model")
        model = getattr(loop.controller, name) if name is not None else None
        if isinstance(model, AbstractPlant) and isinstance(model.state_dim, int) and model.state_dim != xhat.shape[0]:
            raise ValueError(f"Loop.controller.{name} has state_dim={model.state_dim}; it predicts the estimator's "
                             f"estimate, which has {xhat.shape[0]} entries")
    c1, pkt, send_ca = _stage("Loop.controller", f"cannot act on the estimator's estimate {shapes}",
                              lambda: loop.controller.step(_zeros(c0), _zeros(xhat), jnp.float32(1), jnp.int32(0), ctx))
    _same_structure("Loop.controller's step", c0, c1)
    if not isinstance(pkt, Packet):
        raise ValueError(f"Loop.controller's step must return (state, jaxnc.loop.Packet(actions, stamp), send), got "
                         f"{type(pkt).__name__} as its packet")
    if not (isinstance(send_ca, jax.ShapeDtypeStruct) and send_ca.shape == ()):
        raise ValueError(f"Loop.controller's send decision is {_shapes(send_ca)}; it must be a scalar 0/1 float")
    if not (isinstance(pkt.stamp, jax.ShapeDtypeStruct) and pkt.stamp.shape == ()
            and jnp.issubdtype(pkt.stamp.dtype, jnp.integer)):
        raise ValueError(f"Loop.controller's packet stamp is {_shapes(pkt.stamp)}; it must be an int32 scalar, the fast "
                         f"instant of the packet's first action (e.g. k * ctx.N), not seconds")
    u = pkt.data
    if isinstance(u, jax.ShapeDtypeStruct) and u.ndim != 2:
        raise ValueError(f"Loop.controller's packet is {_shapes(u)}; its actions must be float[horizon, input_dim] = "
                         f"float[{loop.controller.horizon}, {m}]")
    if isinstance(u, jax.ShapeDtypeStruct) and u.shape[-1:] != (m,):
        raise ValueError(f"Loop.controller's actions have shape {u.shape[1:]}, the plant takes input_dim={m} inputs")
    if isinstance(u, jax.ShapeDtypeStruct) and u.shape[:1] != (loop.controller.horizon,):
        raise ValueError(f"Loop.controller's packet has {u.shape[0]} actions, its horizon is {loop.controller.horizon}")
    us = f32((loop.N, m))
    e2 = _stage("Loop.estimator", f"cannot predict over a period (actions float32[{loop.N}, {m}])",
                lambda: loop.estimator.predict(_zeros(e1), us, us, jnp.int32(0)))
    _same_structure("Loop.estimator's prediction", e0, e2)
    if loop.controller.keeps_copy:
        ub = _stage("Loop.controller", "cannot say what it sent (keeps_copy)", lambda: loop.controller.sent(_zeros(c1)))
        if not isinstance(ub, jax.ShapeDtypeStruct) or ub.shape != (loop.N, m):
            raise ValueError(f"Loop.controller's sent actions are {_shapes(ub)}; they must be float32[{loop.N}, {m}] "
                             f"(N, input_dim)")
    if loop.controller_trigger is not None and isinstance(u, jax.ShapeDtypeStruct):
        ct1, _ = _stage("Loop.controller_trigger", f"cannot decide on an action float32[{m}]",
                        lambda: loop.controller_trigger.step(_zeros(ct0), f32((m,)), jnp.int32(1)))
        _same_structure("Loop.controller_trigger's step", ct0, ct1)
    # actuator
    box = _stage("Loop.downlink", f"cannot carry the controller's packets {_shapes(pkt.data)}",
                 lambda: loop.downlink.inbox(loop.downlink.init(_zeros(pkt.data)), jnp.int32(0))[0])
    ar = _stage("Loop.actuator", f"cannot receive the controller's packets {_shapes(pkt.data)}",
                lambda: loop.actuator.receive(_zeros(a0), _zeros(box)))
    _same_structure("Loop.actuator's receive", a0, ar)
    a1, ua = _stage("Loop.actuator", "cannot output an action", lambda: loop.actuator.output(_zeros(a0), jnp.int32(0)))
    _same_structure("Loop.actuator's output", a0, a1)
    if not isinstance(ua, jax.ShapeDtypeStruct) or ua.shape != (m,) or ua.dtype != jnp.float32:
        raise ValueError(f"Loop.actuator's action is {_shapes(ua)}; the plant takes float32[{m}]")
    m1, bad, done = _stage("Loop.monitor", f"cannot watch a state vector float32[{n}]",
                           lambda: loop.monitor.step(_zeros(m0), f32((n,)), f32((m,)), jnp.int32(0)))
    _same_structure("Loop.monitor's step", m0, m1)
    if bad.shape != () or done.shape != () or bad.dtype != bool or done.dtype != bool:
        raise ValueError(f"Loop.monitor's step must return scalar bool flags (failed, done), got {_shapes((bad, done))}")
    if loop.cost is not None:
        K = loop.steps
        J = _stage("Loop.cost", f"cannot evaluate cost(x float32[{K}, {n}], u float32[{K}, {m}])",
                   lambda: loop.cost(f32((K, n)), f32((K, m))))
        if not isinstance(J, jax.ShapeDtypeStruct) or J.shape != ():
            raise ValueError(f"Loop.cost must return a scalar, got {_shapes(J)}")


def _check_values(loop: Loop) -> None:
    """What of :func:`_check_fit` depends on a loop's numbers, not only on its shapes, for a
    loop whose structure passed it: the plant's ``init`` (unless this plant, with these
    numbers, passed) and :func:`_role_inits`."""
    if _plant_key(loop.plant) not in _PLANTS:
        _stage("Loop.plant", "cannot build its initial state", lambda: loop.plant.init(jax.random.PRNGKey(0)))
    _role_inits(loop)


def _role_inits(loop: Loop) -> tuple:
    """Every role's ``init(ctx)`` but the plant's (where a part checks its numbers against
    the loop, e.g. a ``Luenberger`` gain against N) and the links' draws
    (:func:`_check_draws`), each re-raised as a ValueError naming the role. Returns the
    initial states' shapes (trigger, estimator, controller, controller trigger or None,
    actuator, monitor)."""
    ctx = loop.ctx
    _check_draws(loop)
    t0 = _stage("Loop.trigger", "cannot build its state",
                lambda: loop.trigger.init(ctx._replace(signal_dim=ctx.output_dim)))
    e0 = _stage("Loop.estimator", f"cannot build its state (state_dim={ctx.state_dim}, output_dim={ctx.output_dim})",
                lambda: loop.estimator.init(ctx))
    c0 = _stage("Loop.controller", "cannot build its state", lambda: loop.controller.init(ctx))
    ct0 = None
    if loop.controller_trigger is not None:
        ct0 = _stage("Loop.controller_trigger", "cannot build its state",
                     lambda: loop.controller_trigger.init(ctx._replace(signal_dim=ctx.input_dim)))
    a0 = _stage("Loop.actuator", "cannot build its state", lambda: loop.actuator.init(ctx))
    m0 = _stage("Loop.monitor", "cannot build its state", lambda: loop.monitor.init(ctx))
    return t0, e0, c0, ct0, a0, m0


def _check_draws(loop: Loop) -> None:
    """Each link's loss and delay models draw one value per slow instant of the run, of the
    protocol's types (:class:`~jaxnc.loop.AbstractLoss`, :class:`~jaxnc.loop.AbstractDelay`):
    a scalar would be broadcast to every packet (all lost, or all equally late), and float
    steps would be truncated, not quantised up."""
    S = loop.steps // loop.N
    key = lambda: jax.random.split(unrolled(jax.random.PRNGKey(0)))[0]     # a key of the kind draw() passes
    for name in ("uplink", "downlink"):
        link = getattr(loop, name)
        where = f"Loop.{name}.loss ({type(link.loss).__name__})"
        lost = _stage(where, f"cannot draw the run's {S} packets (sample(key, {S}))", lambda: link.loss.sample(key(), S))
        if not isinstance(lost, jax.ShapeDtypeStruct) or lost.shape != (S,) or lost.dtype != bool:
            raise ValueError(f"{where}.sample(key, n) draws {_shapes(lost)} for the run's n = {S} slow instants "
                             f"(steps={loop.steps} / N={loop.N}); it must return bool[n] = bool[{S}], one per packet")
        where = f"Loop.{name}.delay ({type(link.delay).__name__})"
        drawn = _stage(where, f"cannot draw the run's {S} packets (sample(key, {S}, T))",
                       lambda: link.delay.sample(key(), S, loop.T))
        ok = isinstance(drawn, (tuple, list)) and len(drawn) == 2 and all(
            isinstance(a, jax.ShapeDtypeStruct) and a.shape == (S,) for a in drawn)
        if not (ok and jnp.issubdtype(drawn[0].dtype, jnp.integer) and jnp.issubdtype(drawn[1].dtype, jnp.floating)):
            raise ValueError(f"{where}.sample(key, n, T) draws {_shapes(drawn)} for the run's n = {S} slow instants "
                             f"(steps={loop.steps} / N={loop.N}); it must return (steps int32[n], seconds float32[n]) "
                             f"= (int32[{S}], float32[{S}]): whole fast periods, quantised up, and seconds")


def _zeros(tree):
    return jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), tree)


def _first_inbox(loop: Loop, ctx: Context):
    """The uplink's inbox at k = 0, before anything was sent (for shapes)."""
    inbox, _ = loop.uplink.inbox(loop.uplink.init(jnp.zeros((ctx.output_dim,), jnp.float32)), jnp.int32(0))
    return inbox


_ROLES = (("plant", AbstractPlant, "a plant (a jaxnc.loop.AbstractPlant: LTI, Discrete, Continuous)"),
          ("trigger", AbstractTrigger, "a trigger (a jaxnc.loop.AbstractTrigger: Periodic, Petc)"),
          ("uplink", Link, "a jaxnc.loop.Link"),
          ("estimator", AbstractEstimator, "an estimator (a jaxnc.loop.AbstractEstimator: EKF, Passthrough)"),
          ("controller", AbstractController,
           "a controller (a jaxnc.loop.AbstractController: StateFeedback, Function, Predictive)"),
          ("downlink", Link, "a jaxnc.loop.Link"),
          ("actuator", AbstractActuator, "an actuator (a jaxnc.loop.AbstractActuator: PacketActuator, HoldLast)"))


_POSITION_FILLED = weakref.WeakValueDictionary()    # id -> monitor whose position field a Loop filled
_FITTED: set = set()     # loops (treedef, leaf shapes, dtypes and values) whose roles were found to fit
_FITTED_SHAPES: set = set()     # the same loops keyed on (treedef, leaf shapes and dtypes) alone
_PLANTS: dict = {}       # plants (treedef, leaf values) found to fit -> their initial state's shapes


def _leaf_key(a):
    """A leaf as (shape, dtype, hash of its bytes); a plain Python object as (type, id)."""
    try:
        v = np.asarray(a) if isinstance(a, (np.ndarray, np.generic, jax.Array, int, float, complex)) else None
    except TypeError:       # e.g. a typed PRNG key
        v = None
    if v is None or v.dtype == object:
        return type(a), id(a)       # a plain Python object: checked once per object
    return v.shape, str(v.dtype), hashlib.sha1(np.ascontiguousarray(v).tobytes()).hexdigest()


def _plant_key(plant) -> tuple:
    """The key of :data:`_PLANTS`: the plant's tree structure and :func:`_leaf_key` of each leaf."""
    leaves, treedef = jax.tree.flatten(plant)
    return treedef, tuple(_leaf_key(a) for a in leaves)


def _one_line(e: BaseException) -> str:
    return f"{type(e).__name__}: {' '.join(str(e).split())}"


class Draws(NamedTuple):
    """A run's exogenous randomness (S = steps / N slow periods)."""

    w: jax.Array          # float[S, N, q] process noise (scaled)
    v: jax.Array          # float[S, p] measurement noise (scaled)
    uplink: LinkDraws     # delays of the sensor packets
    downlink: LinkDraws   # delays of the control packets
    init_key: jax.Array   # key for the plant's initial state


class _Normals(NamedTuple):
    """A run's draws with the plant's noise unscaled and flat (what :func:`simulate` slices per
    slow period): ``w`` float[S N q] and ``v`` float[S p] in :class:`Draws`' row-major order,
    the standard normals over sqrt(2) (:func:`_half_normal`); the links' draws and the initial
    key as in Draws."""

    w: jax.Array
    v: jax.Array
    uplink: LinkDraws
    downlink: LinkDraws
    init_key: jax.Array


def _normals(loop: Loop, key) -> _Normals:
    """:func:`draw`'s streams, the noise unscaled and flat: a draw with a long minor axis is one
    vectorised loop on XLA:CPU, where [S, N, q] with a short q (7 for seed 000's robot) is a
    scalar loop several times slower (benchmarks/RESULTS.md, helper dr)."""
    S, N, p = loop.steps // loop.N, loop.N, loop.plant
    # the streams' keys by one fold_in over their indices (one hash for all: the same keys)
    fast = unrolled(key)
    ks = jax.vmap(lambda i: jax.random.fold_in(fast, i))(jnp.arange(len(STREAMS), dtype=jnp.uint32))
    k = {name: ks[i] for i, name in enumerate(STREAMS)}
    return _Normals(_half_normal(k["process"], S * N * p.noise_dim), _half_normal(k["measurement"], S * p.output_dim),
                    draw_link(loop.uplink, k["uplink"], S, loop.T), draw_link(loop.downlink, k["downlink"], S, loop.T),
                    _as_key_of(k["plant_init"], key))


#: jax.random.normal's factor: normal = sqrt(2) erfinv(u), u uniform on (-1, 1)
_SQRT2 = np.float32(np.sqrt(2))


def _half_normal(key, size: int):
    """float[size]: ``jax.random.normal(key, (size,)) / sqrt(2)``, i.e. erfinv(u) of its
    uniform u (:data:`_SQRT2`); :func:`_scaled_noise` multiplies by sqrt(2) times the standard
    deviation, what XLA:CPU makes of ``normal(...) * std`` (the constant moved onto the
    smaller operand), so that the noise is the same bits as that product."""
    lo = np.nextafter(np.float32(-1.0), np.float32(0.0))
    return jax.lax.erf_inv(jax.random.uniform(key, (size,), jnp.float32, lo, np.float32(1.0)))


def _scaled_noise(plant, zw, zv, t0, N: int, M: int):
    """(w float[N, q], v float[M p] flat): ``zw`` float[N q] of the N fast periods from instant
    ``t0`` and ``zv`` float[M p] of M slow instants (:func:`_half_normal`) times sqrt(2) and the
    plant's standard deviations, w zero where the noise does not enter (``noise_period``)."""
    w_std, v_std = (jnp.asarray(a, jnp.float32) * _SQRT2 for a in (plant.w_std, plant.v_std))
    w = (zw * jnp.tile(w_std, N)).reshape(N, plant.noise_dim)
    if plant.noise_period != 1:
        t = t0 + jnp.arange(N)
        w = jnp.where((t % plant.noise_period == 0)[:, None], w, 0.0)
    v = zv * jnp.tile(v_std, M)
    # each product rounded before a plant adds it (no fused multiply-add) or scales it again (no
    # constants merged), as when the noise was read from memory: the select is the identity,
    # but XLA:CPU neither contracts nor reassociates across it
    return _rounded(w), _rounded(v)


def _rounded(a):
    return jnp.where(a != a, jnp.float32(np.nan), a)


@jit_when_eager
def draw(loop: Loop, key) -> Draws:
    """All of a run's random draws, one stream per purpose (:data:`STREAMS`). Every draw
    (the streams' ``fold_in``, the noise, the links' ``split`` and samples) goes through
    :func:`jaxnc.prng.unrolled` (the same bits, the hash unrolled: fused with what uses it
    instead of a loop of several kernels); the plant's initial key keeps ``key``'s kind.
    One compiled program when called on concrete values (:func:`jit_when_eager`)."""
    S, N, p = loop.steps // loop.N, loop.N, loop.plant
    raw = _normals(loop, key)
    w, v = _scaled_noise(p, raw.w, raw.v, jnp.int32(0), S * N, S)
    return Draws(w.reshape(S, N, p.noise_dim), v.reshape(S, p.output_dim), raw.uplink, raw.downlink, raw.init_key)


def _as_key_of(k, like):
    """``k`` (a :func:`jaxnc.prng.unrolled` key, or ``like``'s own when not re-labelled) as a key
    of ``like``'s kind: raw uint32 data, or a typed key of its implementation."""
    if k.dtype == like.dtype:
        return k
    data = jax.random.key_data(k)
    return jax.random.wrap_key_data(data, impl=jax.random.key_impl(like)) if jnp.issubdtype(
        like.dtype, jax.dtypes.prng_key) else data


class Trajectory(NamedTuple):
    """One run. Fast-rate signals have K = steps rows, slow-rate ones S = steps / N."""

    x: jax.Array          # float[K, n] true state at the start of each fast period
    u: jax.Array          # float[K, m] applied action
    z: jax.Array          # float[S, p] measurement
    xhat: jax.Array       # float[S, n] the estimate the controller used
    sent_sc: jax.Array    # float[S] sensor transmissions
    recv_sc: jax.Array    # float[S] the controller received something: a packet delivered at that instant
    #                       by the uplink's order (a time-stamped estimator also reads packets the order
    #                       did not deliver, Link's docstring: use order="all" to count them all)
    sent_ca: jax.Array    # float[S] controller transmissions
    recv_ca: jax.Array    # float[K] a packet reached the actuator
    failed: jax.Array     # bool
    fail_step: jax.Array  # int32: first failed fast instant (K if never; K too for a failure in the last
    #                       fast period: count failures with `failed`, not fail_step < K)
    fail_action: jax.Array   # bool: the run failed first by a non-finite action (NaN or inf from the controller,
    #                          the estimate it used or the actuator: numerics, not the plant leaving its bounds)
    done: jax.Array       # bool: the monitor found the run complete
    done_step: jax.Array  # int32: first fast instant after which it was complete (K if never; see fail_step)
    tx_sc: jax.Array      # float: sensor transmissions in the whole run (sum of sent_sc, after a failure too:
    #                       the held plant's; Metrics.rate_sc stops at the failure, live_periods)
    tx_ca: jax.Array      # float: controller transmissions in the whole run (sum of sent_ca; as tx_sc)
    parts: Any = ()       # dict role -> what Record's function of that role kept ("plant" [K, ...],
    #                       "estimator" [S, ...], "controller" [S, ...], "actuator" [K, ...], "monitor" [K, ...])
    final_plant: Any = ()   # the plant's state at the end of the run


def _wanted(record: Record, name: str) -> bool:
    return name in record.signals


class _Carry(NamedTuple):
    x: Any
    trig: Any
    up: Any
    est: Any
    ctrl: Any
    ctrig: Any
    down: Any
    act: Any
    bel: Any
    mon: Any
    failed: jax.Array
    fail_step: jax.Array
    done: jax.Array
    done_step: jax.Array
    fail_action: jax.Array


@jit_when_eager
def simulate(loop: Loop, key, draws: Draws | None = None) -> Trajectory:
    """One closed-loop run; a pure function of (loop, key), to vmap over keys.

    ``draws`` replaces :func:`draw`'s (e.g. a recorded realisation shared by loops). What
    is kept follows ``loop.record`` (a :class:`Record`). An estimator that takes the believed
    actions (``inputs="believed"``) is told those of the controller's copy of what it sent:
    its own (``controller.sent``) when it declares ``keeps_copy``, else the runner's, the
    actuator role fed the controller's packets at once.

    Called on concrete values (outside jit, vmap or grad) it runs one compiled program per
    loop structure, the loop an argument of it (as :func:`jaxnc.montecarlo.run_batched`
    passes it; :func:`jit_when_eager`): a second call, with the same loop or another of the
    same structure and new numbers, compiles nothing (it compiled the whole run again on every
    call). Under a trace it is traced as it is."""
    ctx = loop.ctx
    N, S = loop.N, loop.steps // loop.N
    # the noise of each slow period is sliced from the flat standard draws and scaled there: no
    # [S, N, q] array with a short minor axis (a slow scalar loop), and the scan carries no
    # cotangent of the whole noise when a gradient reaches the standard deviations
    d = _normals(loop, key) if draws is None else draws
    plant, act_role = loop.plant, loop.actuator
    x0 = plant.init(d.init_key)
    z0 = plant.measure(x0, jnp.zeros((ctx.output_dim,), jnp.float32))
    ctrl0 = loop.controller.init(ctx)
    est0 = loop.estimator.init(ctx)
    # the packet's shape, from the estimate the controller will be given (not the plant's state)
    _, pkt0, _ = jax.eval_shape(lambda: loop.controller.step(ctrl0, _first_estimate(loop, ctx), jnp.float32(1),
                                                              jnp.int32(0), ctx))
    pkt_zero = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), pkt0)
    act0 = act_role.init(ctx)
    ctrig0 = None
    believed_needed = loop.estimator.inputs == "believed"
    controller_copy = believed_needed and loop.controller.keeps_copy    # the controller keeps its own copy
    # through a downlink that neither loses nor delays into a one-packet actuator the actuator
    # receives exactly the copy's packets at the same instants: its actions are the copy's
    ideal_downlink = (isinstance(loop.downlink.loss, NoLoss) and isinstance(loop.downlink.delay, NoDelay)
                      and loop.downlink.tau_max is None and isinstance(act_role, PacketActuator)
                      and act_role.capacity == 1)
    runner_copy = believed_needed and not controller_copy and not ideal_downlink   # the runner keeps the copy
    if loop.controller_trigger is not None:
        ctrig0 = loop.controller_trigger.init(ctx._replace(signal_dim=int(np.shape(pkt_zero.data[0])[-1])))
    carry0 = _Carry(
        x=x0, trig=loop.trigger.init(ctx._replace(signal_dim=ctx.output_dim)),
        up=loop.uplink.init(z0), est=est0, ctrl=ctrl0, ctrig=ctrig0,
        down=loop.downlink.init(pkt_zero.data), act=act0, bel=act0 if runner_copy else (), mon=loop.monitor.init(ctx),
        failed=jnp.zeros((), bool), fail_step=jnp.asarray(loop.steps, jnp.int32),
        done=jnp.zeros((), bool), done_step=jnp.asarray(loop.steps, jnp.int32), fail_action=jnp.zeros((), bool))

    rec = loop.record
    want = lambda name: _wanted(rec, name)

    def slow(c: _Carry, inp):
        k, w_k, v_k, d_up, d_down = inp
        if draws is None:
            w_k, v_k = _scaled_noise(plant, jax.lax.dynamic_slice_in_dim(d.w, k * (N * plant.noise_dim), N * plant.noise_dim),
                                     jax.lax.dynamic_slice_in_dim(d.v, k * plant.output_dim, plant.output_dim), k * N, N, 1)
        t0 = k * N
        # 1-2. sensor and trigger
        z = plant.measure(c.x, v_k)
        trig, send_sc = loop.trigger.step(c.trig, z, k)
        # 3. uplink, read by the controller side at t0
        up = loop.uplink.send(c.up, z, t0, k, send_sc, d_up, t0)
        inbox, up = loop.uplink.inbox(up, t0)
        # 4. estimator
        est, xhat = loop.estimator.correct(c.est, inbox, k)
        # 5. controller (and its trigger)
        ctrl, pkt, send_ca = loop.controller.step(c.ctrl, xhat, inbox.fresh, k, ctx)
        ctrig = c.ctrig
        if loop.controller_trigger is not None:
            # evaluated only where the controller would send; otherwise its state stays
            ctrig_new, fire = loop.controller_trigger.step(c.ctrig, pkt.data[0], k)
            ctrig = jax.tree.map(lambda a, b: jnp.where(send_ca > 0.5, a, b), ctrig_new, c.ctrig)
            send_ca = send_ca * fire
        # 6. downlink; the controller's own copy as if delivered at once
        down = loop.downlink.send(c.down, pkt.data, pkt.stamp, k, send_ca, d_down, t0)
        bel = c.bel
        if runner_copy:
            own = Inbox(jax.tree.map(lambda a: a[None], pkt.data), pkt.stamp[None], send_ca[None],
                        jnp.ones((1,), bool), send_ca[None])
            bel = act_role.receive(bel, own)

        def fast(fc, inp_j):
            x, down, act, bel, mon, failed, fail_step, done, done_step, fail_action = fc
            j, w_t = inp_j
            t = t0 + j
            box, down = loop.downlink.inbox(down, t)
            act = act_role.receive(act, box)
            act, u = act_role.output(act, t)
            bel, ub = act_role.output(bel, t) if runner_copy else (bel, u)
            u_ok = jnp.all(jnp.isfinite(u))
            u = jnp.where(u_ok, u, jnp.zeros_like(u))        # a diverged controller counts as a failure
            x_new = plant.dynamics(x, u, w_t)
            mon_new, bad, complete = loop.monitor.step(mon, plant.state_vector(x_new), u, t)
            if loop.monitor.freeze:
                # once failed the plant is held, so x_new is a state it never has: the monitor
                # stops with it (its state held, no completion after the failure)
                mon = jax.tree.map(lambda a, b: jnp.where(failed, a, b), mon, mon_new)
                complete = complete & ~failed
            else:
                mon = mon_new
            bad = bad | ~u_ok
            fail_action = jnp.where(bad & ~failed, ~u_ok, fail_action)
            fail_step = jnp.where(bad & ~failed, t + 1, fail_step)
            failed = failed | bad
            done_step = jnp.where(complete & ~done, t + 1, done_step)
            done = done | complete
            if loop.monitor.freeze:
                x_new = jax.tree.map(lambda a, b: jnp.where(failed, a, b), x, x_new)
            out = (plant.state_vector(x) if want("x") else (), u, ub if runner_copy else (),
                   jnp.sum(box.new) if want("recv_ca") else (),
                   rec.actuator(act_role, act, t) if rec.actuator is not None else (),
                   rec.plant(plant, x_new) if rec.plant is not None else (),
                   rec.monitor(loop.monitor, mon) if rec.monitor is not None else ())
            return (x_new, down, act, bel, mon, failed, fail_step, done, done_step, fail_action), out

        fc0 = (c.x, down, c.act, bel, c.mon, c.failed, c.fail_step, c.done, c.done_step, c.fail_action)
        fc, (xs, us, ubs, rca, arec, prec, mrec) = jax.lax.scan(fast, fc0, (jnp.arange(N, dtype=jnp.int32), w_k))
        x, down, act, bel, mon, failed, fail_step, done, done_step, fail_action = fc
        # 7. estimator prediction over the period
        if controller_copy:
            ubs = loop.controller.sent(ctrl)
        elif believed_needed and not runner_copy:
            ubs = us
        est = loop.estimator.predict(est, us, ubs if believed_needed else us, k)
        c = _Carry(x, trig, up, est, ctrl, ctrig, down, act, bel, mon, failed, fail_step, done, done_step, fail_action)
        outs = dict(x=xs, u=us if want("u") else (), z=z if want("z") else (), xhat=xhat if want("xhat") else (),
                    sent_sc=send_sc, recv_sc=inbox.fresh if want("recv_sc") else (), sent_ca=send_ca,
                    recv_ca=rca, actuator=arec, plant=prec, monitor=mrec,
                    estimator=rec.estimator(loop.estimator, est) if rec.estimator is not None else (),
                    controller=rec.controller(loop.controller, ctrl) if rec.controller is not None else ())
        return c, outs

    noise = (jnp.zeros((S, 0), jnp.float32),) * 2 if draws is None else (d.w, d.v)
    xs_in = (jnp.arange(S, dtype=jnp.int32), *noise, d.uplink.delay, d.downlink.delay)
    body = jax.checkpoint(slow, policy=jax.checkpoint_policies.nothing_saveable) if loop.remat else slow
    final, o = jax.lax.scan(body, carry0, xs_in)
    K = loop.steps
    fast_rows = lambda tree: jax.tree.map(lambda a: a.reshape(K, *a.shape[2:]), tree)   # [S, N, ...] -> [K, ...]
    empty = jnp.zeros((0,), jnp.float32)

    def pick(name, fast=False):
        v = o[name]
        if not _wanted(loop.record, name) or (isinstance(v, tuple) and not v):
            return empty
        return fast_rows(v) if fast else v

    return Trajectory(
        x=pick("x", True), u=pick("u", True), z=pick("z"), xhat=pick("xhat"), sent_sc=o["sent_sc"],
        recv_sc=pick("recv_sc"), sent_ca=o["sent_ca"], recv_ca=pick("recv_ca", True),
        failed=final.failed, fail_step=final.fail_step, done=final.done, done_step=final.done_step,
        fail_action=final.fail_action,
        tx_sc=jnp.sum(o["sent_sc"]), tx_ca=jnp.sum(o["sent_ca"]),
        parts={r: fast_rows(o[r]) if r in ("plant", "actuator", "monitor") else o[r] for r in PARTS
               if getattr(rec, r) is not None},
        final_plant=final.x)


class Metrics(NamedTuple):
    """Per-run summaries."""

    cost: jax.Array       # Loop.cost of the run (inf when failed; nan when the loop has no cost)
    cost_raw: jax.Array   # the same without the failure mask (the plant frozen at failure: finite unless that
    #                       state's cost overflows float32, a divergence with no Monitor bounds)
    rate_sc: jax.Array    # sensor transmissions per slow period of the run (a failed run: in and per the periods
    #                       up to its failure, live_periods)
    rate_ca: jax.Array    # controller transmissions per slow period (as rate_sc)
    unstable: jax.Array   # bool: the run failed
    unstable_action: jax.Array   # bool: it failed first by a non-finite action (Trajectory.fail_action), not by the
    #                              plant's state (non-finite or outside Monitor.bounds)

    #: units of the fields the library knows (the cost's are the user's Q and R's), for
    #: :func:`jaxnc.results.save_per_seed` and the Dataset of :func:`jaxnc.load`
    UNITS = {"rate_sc": "transmissions per slow period", "rate_ca": "transmissions per slow period"}
    #: what a field that is nan in every run that did not fail means (:func:`jaxnc.montecarlo.describe`)
    NAN_MEANS = dict.fromkeys(("cost", "cost_raw"), "the loop has no cost (Loop(cost=...))")

    def __repr__(self) -> str:
        from jaxnc.montecarlo import describe
        return describe(self)


def live_periods(failed, fail_step, N: int, S: int):
    """int32: the slow periods a run lived, S if it did not fail, else those through the one
    it failed in, ``(fail_step - 1) // N + 1`` (``fail_step`` the first failed fast instant,
    :class:`Trajectory`). A failed run's transmission counts and rates stop there."""
    return jnp.where(failed, (jnp.asarray(fail_step, jnp.int32) - 1) // N + 1, S).astype(jnp.int32)


def evaluate(loop: Loop, traj: Trajectory) -> Metrics:
    """Metrics of one recorded run: the cost (inf when the run failed; ``cost_raw`` without
    that mask) and the transmissions per slow period: a failed run's rates count and divide
    by its slow periods up to and including the one it failed in (:func:`live_periods`; after
    it the plant is held and its sends are no part of the run, as the monitor stops there),
    not :class:`Trajectory`'s whole-run ``tx_sc`` / ``tx_ca``."""
    S = loop.steps // loop.N
    if loop.cost is not None and _wanted(loop.record, "x") and _wanted(loop.record, "u"):
        raw = loop.cost(traj.x, traj.u)
    else:
        raw = jnp.asarray(jnp.nan, jnp.float32)
    cost = jnp.where(traj.failed, jnp.inf, raw)
    lived = live_periods(traj.failed, traj.fail_step, loop.N, S)
    live = (jnp.arange(S, dtype=jnp.int32) < lived).astype(jnp.float32)
    lived = lived.astype(jnp.float32)
    return Metrics(cost, raw, jnp.sum(traj.sent_sc * live) / lived, jnp.sum(traj.sent_ca * live) / lived,
                   traj.failed, traj.failed & traj.fail_action)


def run(loop: Loop, key, *, metrics=evaluate, **context):
    """One seed's metrics, ``metrics(loop, simulate(loop, key), **context)``: the per-seed
    function the Monte-Carlo engine maps, ``montecarlo.run_batched(run_seed, keys, args=(loop,))``.

    Args:
      loop: the :class:`Loop`. key: the run's PRNG key (:func:`draw`).
      metrics: a function ``metrics(loop, traj, **context)`` of the loop and its
        :class:`Trajectory` (default :func:`evaluate`: the loop's cost and rates); a paper's
        scheme passes its own (``jaxnc.schemes.<paper>.run`` is this function with it).
      context: further keyword arguments of ``metrics`` (e.g. a reference run's output).

    Returns:
      what ``metrics`` returns (a pytree of arrays)."""
    return metrics(loop, simulate(loop, key), **context)


def run_seed(key, loop: Loop) -> Metrics:
    """:func:`run` with the key first, as :func:`jaxnc.montecarlo.run_batched` calls it:
    ``run_batched(run_seed, keys, args=(loop,))`` compiles once per loop structure."""
    return run(loop, key)
