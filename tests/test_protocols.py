"""Every part implements at most three methods of its own (issue 30, docs/build_your_own_loop.md).

A *part* is a concrete class of the package that fills a role: a subclass of one of the role
bases of :mod:`jaxnc.loop.base` (``AbstractPlant``, ``AbstractTrigger``, ``AbstractEstimator``,
``AbstractController``, ``AbstractActuator``, ``AbstractMonitor``, ``AbstractLoss``,
``AbstractDelay``, ``AbstractInitial``, and the declared capabilities there such as
``AbstractWrappedPlant``), a limit (:class:`jaxnc.loop.AbstractLimit`) or a link
(:class:`jaxnc.loop.Link`).

A part *implements* a method when a public plain function (not a property, classmethod,
staticmethod, dunder or ``__post_init__``) is defined in the ``__dict__`` of the class or
of one of its bases outside :mod:`jaxnc.loop.base` (what the role bases give, defaults
included, is not the part's). Every module of the package is imported first, so parts
that a scheme or a tuning module defines are walked too.
"""
import importlib
import inspect
import pathlib
import pkgutil

import pytest

import jaxnc
from jaxnc.loop import AbstractLimit, Link
from jaxnc.loop import base

MAX_METHODS = 3
ROLE_BASES = tuple(c for c in vars(base).values()
                   if inspect.isclass(c) and c.__module__ == base.__name__ and c.__name__.startswith("Abstract"))


def _import_all():
    for info in pkgutil.walk_packages(jaxnc.__path__, "jaxnc."):
        try:
            importlib.import_module(info.name)
        except ImportError:        # an optional extra (MuJoCo) is missing: its parts are not walked
            continue


def _subclasses(cls):
    for sub in cls.__subclasses__():
        yield sub
        yield from _subclasses(sub)


def _parts():
    _import_all()
    found = {Link}
    for root in (*ROLE_BASES, AbstractLimit):
        found.update(c for c in _subclasses(root) if c.__module__.startswith("jaxnc.") and not inspect.isabstract(c))
    return sorted(found, key=lambda c: f"{c.__module__}.{c.__qualname__}")


def implemented(cls) -> set[str]:
    """The public methods ``cls`` or a base outside :mod:`jaxnc.loop.base` defines."""
    names = set()
    for k in cls.__mro__:
        if k is object or k.__module__ in (base.__name__, "abc") or k in ROLE_BASES:
            continue
        for name, v in vars(k).items():
            if name.startswith("_") or isinstance(v, (property, classmethod, staticmethod)):
                continue
            if inspect.isfunction(v):
                names.add(name)
    return names


PARTS = _parts()


def test_the_walk_finds_the_parts():
    """The walk reaches parts of every role, the wrappers and the package's own schemes'."""
    names = {c.__name__ for c in PARTS}
    assert {"LTI", "LimitedSensor", "Petc", "EKF", "StateFeedback", "PacketActuator", "Monitor", "Bernoulli",
            "ShiftedExponential", "Quantizer", "Link", "Balancing", "DiffDrive", "ChainController"} <= names
    assert len(PARTS) >= 50


def test_the_definition_counts_what_a_class_writes():
    """``implemented`` counts a part's own methods and an intermediate base's, not the role
    base's defaults, nor properties, static methods or dunders."""
    @base.pytree_dataclass
    class Mid(base.AbstractTrigger):
        def init(self, ctx):
            return ()

    @base.pytree_dataclass
    class Part(Mid):
        def step(self, state, s, k):
            return state, 1.0

        def extra(self):
            return 0

        @property
        def prop(self):
            return 0

        @staticmethod
        def helper():
            return 0

        def __post_init__(self):
            pass

    assert implemented(Part) == {"init", "step", "extra"}
    wrapped = implemented(jaxnc.loop.LimitedSensor)
    assert wrapped == {"measure"}, wrapped        # dynamics, init, state_vector and data: the wrapper base's


@pytest.mark.parametrize("part", PARTS, ids=lambda c: f"{c.__module__}.{c.__qualname__}")
def test_a_part_implements_at_most_three_methods(part):
    methods = implemented(part)
    assert len(methods) <= MAX_METHODS, f"{part.__qualname__} implements {sorted(methods)}"


def test_a_wrapped_plant_is_its_inner_plant_except_where_it_overrides():
    """LimitedSensor writes only ``measure``: its dynamics, random start, state vector and
    declared data are the inner plant's (AbstractWrappedPlant), its measurement is limited."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jaxnc import loop as nc

    inner = nc.LTI(A=[[0.9, 0.1], [0.0, 0.8]], B=[[0.0], [1.0]], C=[[1.0, 0.0]], x0=[1.0, -1.0],
                   x0_std=[0.3, 0.2], w_std=[0.1, 0.2], v_std=[0.05])
    wrapped = nc.LimitedSensor(inner, nc.Quantizer(0.25))
    key = jax.random.PRNGKey(7)
    x0 = wrapped.init(key)
    np.testing.assert_array_equal(x0, inner.init(key))
    assert not np.allclose(x0, inner.x0)                       # x0_std is the inner plant's: a random start
    x, u, w = jnp.asarray([0.3, -0.2]), jnp.asarray([0.5]), jnp.asarray([0.1, -0.1])
    np.testing.assert_array_equal(wrapped.dynamics(x, u, w), inner.dynamics(x, u, w))
    np.testing.assert_array_equal(wrapped.state_vector(x), inner.state_vector(x))
    for name in ("state_dim", "input_dim", "noise_dim", "output_dim", "w_std", "v_std", "x0", "x0_std",
                 "step_period", "noise_period"):
        np.testing.assert_array_equal(np.asarray(getattr(wrapped, name)), np.asarray(getattr(inner, name)), name)
    z = wrapped.measure(jnp.asarray([0.37, 0.0]), jnp.zeros(1))
    assert float(z[0]) == 0.25 and float(inner.measure(jnp.asarray([0.37, 0.0]), jnp.zeros(1))[0]) != 0.25


def test_a_declared_initial_distribution_is_sampled_by_the_default_init():
    """A plant whose declared ``x0`` is an AbstractInitial starts from ``x0.sample(key)``
    (any pytree), through the plant protocol's default ``init``."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from typing import NamedTuple

    class Start(NamedTuple):
        pos: jax.Array
        mass: jax.Array

    @base.pytree_dataclass
    class Uniform(base.AbstractInitial):
        low: float = 1.0
        high: float = 2.0

        def sample(self, key):
            return Start(jnp.zeros(2), jax.random.uniform(key, (), jnp.float32, self.low, self.high))

    @base.pytree_dataclass
    class Cart(base.AbstractPlant):
        state_dim, input_dim, noise_dim, output_dim = 2, 1, 1, 1
        w_std, v_std = np.zeros(1, np.float32), np.zeros(1, np.float32)

        @property
        def x0(self):
            return Uniform()

        def dynamics(self, x, u, w):
            return x._replace(pos=x.pos + u / x.mass)

        def measure(self, x, v):
            return x.pos[:1] + v

        def state_vector(self, x):
            return x.pos

    keys = jax.random.split(jax.random.PRNGKey(0), 32)
    s = jax.vmap(Cart().init)(keys)
    m = np.asarray(s.mass)
    assert isinstance(s, Start) and m.min() >= 1.0 and m.max() <= 2.0 and m.std() > 0.1
    np.testing.assert_array_equal(np.asarray(s.pos), 0.0)


def test_each_scheme_module_is_a_builder_of_at_most_250_lines_and_simulate_is_defined_once():
    """Issue 30's shape: a paper's module builds its loop from library parts (250 lines at most), and
    the package has one runner (``def simulate`` once, in jaxnc/loop/runner.py)."""
    root = pathlib.Path(jaxnc.__file__).parent
    long = {p.name: n for p in (root / "schemes").glob("*.py") if (n := len(p.read_text().splitlines())) > 250}
    assert not long, f"scheme modules over 250 lines: {long}"
    defs = [str(p.relative_to(root)) for p in root.rglob("*.py") if "def simulate(" in p.read_text()]
    assert defs == [str(pathlib.Path("loop") / "runner.py")], defs
