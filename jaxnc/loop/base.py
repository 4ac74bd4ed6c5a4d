"""The roles of a networked loop and the data that passes between them.

A closed loop (:class:`jaxnc.loop.Loop`) is made of six roles, each a frozen-dataclass
pytree of *parameters* with pure methods; its *state* is a NamedTuple returned by
``init(ctx)`` and threaded through the runner's scan (optax's ``init/update``, MJX's
``step(m, d)``). Every role has the same shape: ``init(ctx) -> state`` and methods
``(state, inputs...) -> (state, outputs...)`` (the plant, whose state is the physical
state, has ``dynamics`` and ``measure``). The runner (:mod:`jaxnc.loop.runner`) calls
them in a fixed order every slow period k (fast instants t = kN .. kN + N - 1, fast
period T):

1. ``plant.measure(x, v)`` -> z_k (the sensor samples at t = kN);
2. ``trigger.step(state, z_k, k)`` -> (state, send 0/1): PETC, periodic, ...;
3. the sensor-to-controller :class:`~jaxnc.loop.links.Link` stores the packet
   (z_k, stamp k) with its arrival time drawn up front; the controller side reads its
   :class:`Inbox` at t = kN (packets that arrive between slow instants wait for the next);
4. ``estimator.correct(state, inbox, k)`` -> (state, xhat), the estimate the controller uses;
5. ``controller.step(state, xhat, fresh, k, ctx)`` -> (state, :class:`Packet` of actions,
   send), optionally gated by a controller-side trigger on the first action;
6. the controller-to-actuator link stores the packet; then for each fast instant t the
   actuator receives what arrives at t (``actuator.receive(state, inbox)`` -> state),
   ``actuator.output(state, t)`` -> (state, u_t), and the plant moves,
   ``plant.dynamics(x, u_t, w_t)``;
7. ``estimator.predict(state, u_applied[N, m], u_believed[N, m], k)`` -> state: the actions
   the actuator applied, and those the controller believes applied (its own packets, as
   if delivered at once), over the period.

Optional behaviour is declared, never discovered: by class attributes (``inputs``,
``horizon``, ``stamps_ahead``, ``period_steps``, ``keeps_copy``, ``in_steps``, ``freeze``,
``position_index``, ``position_field``). A controller that declares
``keeps_copy`` keeps the sender's copy of what it sent in its own state and says, with
``sent(state)``, which actions that copy applies over the period (seed 000's prediction
chains); otherwise the runner keeps that copy for it (the actuator role fed the
controller's packets at once) when the estimator needs the believed actions. What a run
records is the loop's :class:`~jaxnc.loop.Record`.

Everything a component needs that does not depend on the loop's signals (noise, packet
losses and delays) is drawn up front from the run's key, so loops can be compared on the
same realisation (common random numbers).

Flags that a gradient may pass through (send decisions with a straight-through
relaxation, link weights) are 0/1 floats; selections on them use blends
``w * new + (1 - w) * old``, which are exact selects in the forward pass.
"""
from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import checked_pytree

__all__ = ["Packet", "Inbox", "blend", "static_field", "pytree_dataclass", "AbstractPlant", "AbstractInitial",
           "AbstractWrappedPlant", "AbstractLiftedPlant", "AbstractTrigger", "AbstractEstimator", "AbstractController", "AbstractActuator",
           "AbstractMonitor", "AbstractLoss", "AbstractDelay"]


def static_field(default=dataclasses.MISSING):
    """A dataclass field that is static in the pytree (an integer that shapes arrays, a
    string or function that selects code): part of the compiled program, not a leaf."""
    return dataclasses.field(default=default, metadata=dict(static=True))



def pytree_dataclass(cls):
    """``cls`` as a frozen dataclass registered as a pytree (fields made with
    :func:`static_field` are static, the others leaves). jax rebuilds it without calling
    ``__init__`` (:func:`jaxnc._validate.checked_pytree`), so ``__post_init__`` validates
    only what a person builds."""
    return checked_pytree(dataclasses.dataclass(frozen=True)(cls))


class Packet(NamedTuple):
    """What a link carries.

    Attributes:
      data: pytree payload, e.g. a measurement ``float[p]`` or actions ``float[H, m]``.
      stamp: int32 scalar, the fast instant the payload refers to (the sampling instant of
        a measurement, the instant of ``data[0]`` for actions).
    """

    data: Any
    stamp: jax.Array


class Inbox(NamedTuple):
    """A receiver's view of a link's ring of the last ``C`` transmissions (leading axis C).

    Attributes:
      data: the payloads, pytree with leading axis C.
      stamp: int32[C], the packets' time stamps (-1 for a slot never used).
      weight: float[C], 1 for a packet that was sent and not lost or discarded (a 0/1
        float that carries a send decision's gradient), 0 otherwise.
      arrived: bool[C], the packet has reached the receiver by now.
      new: float[C], ``weight`` where the packet is delivered now (first arrival, and kept
        by the link's ordering policy), 0 elsewhere.
    """

    data: Any
    stamp: jax.Array
    weight: jax.Array
    arrived: jax.Array
    new: jax.Array

    @property
    def fresh(self):
        """1.0 when anything was delivered now (a 0/1 float)."""
        return jnp.minimum(jnp.sum(self.new), 1.0)

    def packet(self, k, stamp):
        """(data, weight) of the packet the sender sent at slow instant k (the link keeps it
        in slot k mod C) if it is stamped ``stamp`` and has arrived; weight 0 otherwise (the
        data is then the slot's, to be blended away)."""
        slot = jnp.mod(k, self.stamp.shape[0])
        ok = (self.stamp[slot] == stamp) & self.arrived[slot] & (stamp >= 0)
        return jax.tree.map(lambda a: a[slot], self.data), jnp.where(ok, self.weight[slot], 0.0)

    def slot(self, k):
        """(data, weight) of slot k mod C, where the sender put its packet of slot instant k:
        the slot's weight (a silent instant's is 0 but carries the send decision's gradient,
        a relaxed trigger's β unsent), 0 for a packet sent and not arrived yet. Equal to
        :meth:`packet` ``(k, kN)`` in value whenever the slot holds instant k's packet and the
        decision is hard."""
        i = jnp.mod(k, self.stamp.shape[0])
        late = (self.stamp[i] >= 0) & ~self.arrived[i]
        return jax.tree.map(lambda a: a[i], self.data), jnp.where(late, 0.0, self.weight[i])

    def measurement(self, k, stamp, weight: str):
        """An estimator's read of slow instant k: :meth:`packet` ``(k, stamp)`` for ``weight``
        ``"stamp"``, :meth:`slot` ``(k)`` for ``"slot"`` (the estimators' ``weight`` option,
        :func:`check_weight`)."""
        return self.slot(k) if weight == "slot" else self.packet(k, stamp)

    def newest(self):
        """(data, stamp, weight) of the newest delivered packet by time stamp; weight 0 when
        nothing was delivered."""
        key = jnp.where(self.new > 0, self.stamp, -(2**30))
        i = jnp.argmax(key)
        return jax.tree.map(lambda a: a[i], self.data), self.stamp[i], self.new[i]


def check_weight(owner: str, weight) -> None:
    """ValueError unless an estimator's ``weight`` option is ``"stamp"`` or ``"slot"``
    (:meth:`Inbox.measurement`)."""
    if weight not in ("stamp", "slot"):
        raise ValueError(f"{owner}.weight must be one of stamp, slot, got {weight!r}")


def blend(w, new, old):
    """``new`` where the 0/1 float ``w`` is 1, else ``old``, leaf by leaf: a float blend
    (exact in the forward pass, lets a straight-through gradient pass) or, for integer and
    boolean leaves, a select."""
    def leaf(a, b):
        a, b = jnp.asarray(a), jnp.asarray(b)
        if jnp.issubdtype(a.dtype, jnp.floating):
            ww = jnp.asarray(w, a.dtype)
            return ww * a + (1.0 - ww) * b
        return jnp.where(jnp.asarray(w) > 0.5, a, b)
    return jax.tree.map(leaf, new, old)


class AbstractPlant(abc.ABC):
    """A plant in discrete time at the fast period T.

    Subclasses are frozen dataclasses (registered pytrees) and define ``dynamics`` and
    ``measure`` (the protocol's two required methods), the dimensions and the noise
    scales ``w_std`` / ``v_std`` (declared data: fields or properties); the runner draws
    standard normal noises and multiplies them by those scales. ``init`` (or the
    declared ``x0`` and ``x0_std``) and ``state_vector`` are optional (defaults below). The same object serves as the model
    of an estimator (``jax.jacfwd(plant.dynamics)``).
    """

    #: {field: allowed shapes}, each a tuple of dimension names among "state", "input",
    #: "output", "signal" (a trigger's signal), "estimate" (a controller's input): checked
    #: against the loop's sizes when a Loop is built (declared, e.g. ``{"K": (("input",
    #: "estimate"),)}``; ``()`` is a scalar)
    field_shapes: ClassVar[dict] = {}

    #: seconds of one ``dynamics`` step, when the plant has its own (a Loop checks that its
    #: fast period T equals it; e.g. a sampled LTI's T); None: the plant takes the loop's
    step_period = None

    #: int or None (declared): the index in the state vector (:meth:`state_vector`) of the
    #: first of the two entries that are the plant's planar position (x, y), in m, e.g. a
    #: vehicle's (``DiffDrive``: 2, ``Mecanum`` and ``MjxMecanum``: 3); None: the plant
    #: declares none. A monitor that watches a position (``AbstractMonitor.position_field``,
    #: ``PathMonitor``) reads it there unless told otherwise
    position_index: ClassVar[int | None] = None

    #: int: the process noise enters every ``noise_period`` fast periods (at fast instants
    #: t = 0, P, 2P, ...; zero in between), e.g. a disturbance once per actuation period of a
    #: plant simulated on a finer grid (static; a field or property may override it)
    noise_period = 1

    #: int: state, input, process-noise and output/measurement-noise dimensions
    state_dim: int
    input_dim: int
    noise_dim: int
    output_dim: int

    #: float[noise_dim]: std of the process noise w (the runner multiplies standard normals
    #: by it); float[output_dim]: std of the measurement noise v. Declared data: a field or
    #: a property of every plant.
    w_std: Any
    v_std: Any

    @abc.abstractmethod
    def dynamics(self, x, u, w):
        """x_{t+1} = f(x_t, u_t, w_t): one fast period of the plant; x its state (float[n], or
        the plant's own state pytree), u float[m], w float[noise_dim]."""

    @abc.abstractmethod
    def measure(self, x, v):
        """z = h(x, v); v float[output_dim] -> float[output_dim]."""

    #: float[n] or None: the std of a random initial state, x_0 = x0 + x0_std * N(0, I) drawn
    #: from the run's key (declared data; None: x_0 = x0 exactly)
    x0_std = None

    def init(self, key):
        """Initial state x_0: ``x0``, plus ``x0_std`` times standard normals drawn from ``key``
        when the plant declares ``x0_std``; ``x0.sample(key)`` when the declared ``x0`` is
        an :class:`AbstractInitial` (a distribution of a state of any pytree)."""
        if isinstance(self.x0, AbstractInitial):
            return self.x0.sample(key)
        x0 = jnp.asarray(self.x0, jnp.float32)
        if self.x0_std is None:
            return x0
        return x0 + jnp.asarray(self.x0_std, jnp.float32) * jax.random.normal(key, x0.shape, jnp.float32)

    def state_vector(self, x):
        """The state as float[n] for recording and failure checks (default: x itself; a
        plant whose state is not a vector, e.g. a multibody simulator's, overrides it)."""
        return x


class AbstractInitial(abc.ABC):
    """The distribution of a plant's initial state, declared as the plant's ``x0`` where
    ``x0 + x0_std * N(0, I)`` cannot say it: a state that is not a vector, or a start that
    draws more than Gaussian offsets (e.g. a multibody robot settled on a model whose
    friction and mass are drawn per seed, :class:`jaxnc.plants.mecanum_mjx.MjxStart`).
    :meth:`AbstractPlant.init` samples it; the plant then declares no ``x0_std``."""

    @abc.abstractmethod
    def sample(self, key):
        """x_0 drawn from the PRNG ``key``: any pytree the plant's ``dynamics`` takes."""


class AbstractWrappedPlant(AbstractPlant):
    """A plant that wraps another, ``plant`` (a field of the subclass), as diffrax's
    ``AbstractWrappedSolver`` wraps a solver: everything the wrapper does not override is
    the inner plant's, its methods (``dynamics``, ``measure``, ``init``, ``state_vector``)
    and its declared data (dimensions, ``w_std``, ``v_std``, ``x0``, ``x0_std``,
    ``step_period``, ``noise_period``, ``position_index``). A wrapper overrides only what it changes, e.g.
    :class:`jaxnc.loop.LimitedSensor` the measurement."""

    plant: AbstractPlant

    state_dim = property(lambda self: self.plant.state_dim)
    input_dim = property(lambda self: self.plant.input_dim)
    noise_dim = property(lambda self: self.plant.noise_dim)
    output_dim = property(lambda self: self.plant.output_dim)
    w_std = property(lambda self: self.plant.w_std)
    v_std = property(lambda self: self.plant.v_std)
    x0 = property(lambda self: self.plant.x0)
    x0_std = property(lambda self: self.plant.x0_std)
    step_period = property(lambda self: self.plant.step_period)
    noise_period = property(lambda self: self.plant.noise_period)
    position_index = property(lambda self: self.plant.position_index)

    def dynamics(self, x, u, w):
        """The inner plant's ``dynamics``."""
        return self.plant.dynamics(x, u, w)

    def measure(self, x, v):
        """The inner plant's ``measure``."""
        return self.plant.measure(x, v)

    def init(self, key):
        """The inner plant's ``init``."""
        return self.plant.init(key)

    def state_vector(self, x):
        """The inner plant's ``state_vector``."""
        return self.plant.state_vector(x)


class AbstractLiftedPlant(AbstractPlant):
    """A plant that also declares its slow-period (lifted) model (seed 004 eq. 8), for an
    estimator that predicts once per slow period (``EKF(rate="slow")``)."""

    @abc.abstractmethod
    def period(self, x, us, w):
        """The state float[n] one slow period after x float[n], with the fast actions
        ``us`` float[M, m] applied in order and the additive noise w float[n]."""


class AbstractTrigger(abc.ABC):
    """Decides at each slow instant whether a signal is sent (sensor side: z; controller
    side: the first action of a packet)."""

    #: {field: allowed shapes}, each a tuple of dimension names among "state", "input",
    #: "output", "signal" (a trigger's signal), "estimate" (a controller's input): checked
    #: against the loop's sizes when a Loop is built (declared, e.g. ``{"K": (("input",
    #: "estimate"),)}``; ``()`` is a scalar)
    field_shapes: ClassVar[dict] = {}

    @abc.abstractmethod
    def init(self, ctx):
        """State before the first instant, for a signal of ``ctx.signal_dim`` entries (the
        runner sets it: the measurement's size for the sensor's trigger, an action's for
        the controller's)."""

    @abc.abstractmethod
    def step(self, state, s, k):
        """(state, send) for signal s float[signal_dim] at slow instant k: send is a 0/1
        float (straight-through gradient where relaxed)."""


class AbstractEstimator(abc.ABC):
    """The controller side's belief of the plant state.

    ``inputs`` (a declared class attribute) says which actions :meth:`predict` uses:
    ``"believed"`` (the controller's own packets as if delivered at once: what a remote
    filter knows; the runner then keeps that copy of the actuator) or ``"applied"`` (the
    actions the actuator applied: a filter collocated with it)."""

    #: {field: allowed shapes}, each a tuple of dimension names among "state", "input",
    #: "output", "signal" (a trigger's signal), "estimate" (a controller's input): checked
    #: against the loop's sizes when a Loop is built (declared, e.g. ``{"K": (("input",
    #: "estimate"),)}``; ``()`` is a scalar)
    field_shapes: ClassVar[dict] = {}

    inputs: ClassVar[str] = "believed"

    #: slow periods of delivered packets the estimator looks back on (declared; e.g. the
    #: ``EKF``'s ``buffer``): a ``Loop`` sizing its uplink (``Link(capacity=None)``) keeps at
    #: least ``lookback + 1`` packets in the ring
    lookback: ClassVar[int] = 0

    #: True for an estimator that uses a measurement only by its time stamp and at most
    #: ``lookback`` slow periods late (:meth:`Inbox.packet`; declared: the ``EKF``, ``UKF``,
    #: ``Luenberger``, ``SteadyStateKF``): a ``Loop`` whose uplink delays every packet longer
    #: than that (it would never correct) raises when it is built. False: it uses whatever
    #: arrives (``Inbox.newest``)
    by_stamp: ClassVar[bool] = False

    #: True for an estimator that takes the newest delivered measurement as the one of the
    #: instant it arrives (declared: :class:`~jaxnc.loop.Numre`, built for links without
    #: delay): a ``Loop`` whose uplink can delay a packet raises when it is built
    undelayed_uplink: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, ctx):
        """State before the first instant; ``ctx`` (:class:`jaxnc.loop.runner.Context`)
        gives the dimensions, N, T and the uplink's ring capacity."""

    @abc.abstractmethod
    def correct(self, state, inbox: Inbox, k):
        """Use what the uplink delivered (``inbox``) at slow instant k: (state, xhat), xhat
        the estimate the controller uses now (e.g. float[n])."""

    @abc.abstractmethod
    def predict(self, state, u_applied, u_believed, k):
        """Propagate over the period k (actions float[N, m]); returns the state."""


class AbstractController(abc.ABC):
    """Computes a packet of actions from the estimate at a slow instant."""

    #: {field: allowed shapes}, each a tuple of dimension names among "state", "input",
    #: "output", "signal" (a trigger's signal), "estimate" (a controller's input): checked
    #: against the loop's sizes when a Loop is built (declared, e.g. ``{"K": (("input",
    #: "estimate"),)}``; ``()`` is a scalar)
    field_shapes: ClassVar[dict] = {}

    #: int: number of fast actions per packet (static; a dataclass field or property may
    #: override it)
    horizon = 1

    #: int (declared): fast periods by which its packets' stamps lead the instant they are
    #: computed at (a static int; a field or property may override it, e.g. ``LeadFeedback``'s
    #: ``lead``). A Loop checks that a :class:`~jaxnc.loop.PacketActuator` keeps enough
    #: packets to hold one until its stamp is due.
    stamps_ahead = 0

    #: int or None (declared): the fast periods per slow period the controller is built for
    #: (a static int; a field or property may override it, e.g. ``PursuitPI``'s ``ns *
    #: model.sub``, whose PI and packets assume that period). A Loop checks that its N equals
    #: it. None: any N.
    period_steps = None

    #: str or None (declared): the name of the field holding the model the controller
    #: predicts its estimate with (``Predictive``, ``LeadFeedback``: ``"model"``); a Loop
    #: checks that its state size is the estimate's.
    prediction_model: ClassVar[str | None] = None

    #: bool (declared): the controller keeps the sender's copy of what it sent (the
    #: actuator its packets drive, fed them at once) in its own state, and :meth:`sent`
    #: gives the actions that copy applies over the period; an estimator with
    #: ``inputs="believed"`` is told them. False: the runner keeps that copy for it.
    keeps_copy: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, ctx):
        """Controller state before the first instant."""

    @abc.abstractmethod
    def step(self, state, xhat, fresh, k, ctx):
        """(state, Packet(actions float[horizon, m], stamp), send 0/1 float).

        ``fresh`` is 1.0 when the estimator received something at this instant."""

    def sent(self, state):
        """float[N, m]: the actions the sender's copy applies over the period of the last
        :meth:`step` (``state`` its result), as if the packets were delivered at once. Only
        for a controller that declares ``keeps_copy``."""
        raise NotImplementedError(f"{type(self).__name__} does not keep a copy of what it sent (keeps_copy)")


class AbstractActuator(abc.ABC):
    """Applies, every fast period, an action from the packets it has received.

    ``horizon`` (declared): the actions per packet it plays, a static int that a Loop checks
    against its controller's ``horizon``; None (the default): it takes packets of any length."""

    #: {field: allowed shapes}, each a tuple of dimension names among "state", "input",
    #: "output", "signal" (a trigger's signal), "estimate" (a controller's input): checked
    #: against the loop's sizes when a Loop is built (declared, e.g. ``{"K": (("input",
    #: "estimate"),)}``; ``()`` is a scalar)
    field_shapes: ClassVar[dict] = {}
    horizon = None

    @abc.abstractmethod
    def init(self, ctx):
        """State before the first packet."""

    @abc.abstractmethod
    def receive(self, state, inbox: Inbox):
        """Install what the downlink delivers now (``inbox.new``); returns the state."""

    @abc.abstractmethod
    def output(self, state, t):
        """(state, u_t float[m]) for fast instant t."""


class AbstractMonitor(abc.ABC):
    """Watches the true plant after every fast period: whether the run has failed (the
    plant left its safe set, or diverged) and whether it is complete (e.g. a path's end
    reached). Failure and completion are each recorded once, at their first instant
    (``Trajectory.fail_step``, ``done_step``); a monitor may keep state (e.g. progress
    along a path) and have it recorded with ``Record(monitor=fn)``.

    ``freeze`` (declared): once failed, the runner holds the plant at its last good state,
    so divergence stays data (finite numbers and a flag) rather than NaN, and stops the
    monitor with it: its state is held and the run is not marked complete after its failure
    (without ``freeze`` the plant runs on and the monitor keeps watching it)."""

    field_shapes: ClassVar[dict] = {}
    freeze = True

    #: str or None (declared): the name of the monitor's static field holding the index of
    #: the plant's planar position in its state vector (``PathMonitor``: ``"xy"``). Where
    #: that field is None, a Loop sets it, when it is built, to its plant's declared
    #: ``AbstractPlant.position_index``, and refuses a plant that declares none. None: the
    #: monitor reads no position.
    position_field: ClassVar[str | None] = None

    @abc.abstractmethod
    def init(self, ctx):
        """State before the first fast period."""

    @abc.abstractmethod
    def step(self, state, x, u, t):
        """(state, failed bool, done bool) after the fast period t, for the plant's state
        vector x float[n] (``plant.state_vector``) reached with the action u float[m]."""


class _LinkModel(abc.ABC):
    """What the two models a :class:`~jaxnc.loop.links.Link` draws before the run, its loss
    and its delay, share: :meth:`packets`."""

    def packets(self):
        """The most packets the model can draw (a recorded trace's length; a
        :class:`~jaxnc.loop.Loop` refuses a run with more slow instants when it is built), or
        None: any number (the default)."""
        return None


class AbstractLoss(_LinkModel):
    """A packet-loss model of a :class:`~jaxnc.loop.links.Link` (drawn before the run)."""

    @abc.abstractmethod
    def sample(self, key, n: int):
        """bool[n]: whether the packet of each of ``n`` slow instants is lost (n static)."""


class AbstractDelay(_LinkModel):
    """A delay model of a :class:`~jaxnc.loop.links.Link` (drawn before the run).

    ``in_steps`` (declared): the model draws whole fast periods (the link then compares
    them with ``tau_max`` in periods, not in float seconds)."""

    in_steps: ClassVar[bool] = False

    @abc.abstractmethod
    def sample(self, key, n: int, T):
        """(steps int32[n], seconds float32[n]): each packet's delay in whole fast periods
        (quantised up, negative = lost) and in seconds."""

    def bounds(self, T: float):
        """(lo, hi): the delay's smallest and largest value in whole fast periods (ints,
        0 <= lo <= hi; a Loop refuses others) when concrete and known (hi None: unbounded or
        unknown). Default (0, None)."""
        return 0, None
