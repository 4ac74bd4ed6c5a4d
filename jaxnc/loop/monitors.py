"""Monitors beyond the runner's :class:`~jaxnc.loop.Monitor`: path following.

A monitor (:class:`~jaxnc.loop.AbstractMonitor`) watches the true plant's state vector
after every fast period and says whether the run has failed and whether it is complete;
the runner records the first instant of each (``Trajectory.fail_step``, ``done_step``).
"""
from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import array_fields, check_bool, check_instance, check_int, check_range, scalar_fields
from jaxnc.loop.base import AbstractMonitor, pytree_dataclass, static_field
from jaxnc.metrics import local_distance
from jaxnc.paths import Path, track_index

__all__ = ["PathMonitor", "PathMonitorState", "path_distance"]


class PathMonitorState(NamedTuple):
    idx: jax.Array       # int32: the plant's progress, the index of its nearest path point
    dist: jax.Array      # float32: distance to the path (the polyline on the plant's own branch)
    done: jax.Array      # bool: the path's end was reached


@pytree_dataclass
class PathMonitor(AbstractMonitor):
    """Progress, distance, completion and failure of a plant following a planar path
    (the path tube of seed 000 section 4.1 and seed 004 section 4).

    After every ``every``-th fast period (those after which t + 1 is a multiple of ``every``:
    the instants kT of a plant sampled at T = ``every`` fast periods, seed 004's check every
    T), with the position p = (x[xy], x[xy + 1]) of the state vector:

    * progress: the nearest path point searched monotonically in a window of ``window``
      points ahead (:func:`jaxnc.paths.closest_index`), so the search stays on the plant's
      own branch where the path crosses itself; while the nearest point is the window's
      last (not the path's end) the search goes on from it (:func:`jaxnc.paths.track_index`),
      so the progress keeps up with a plant that moves more than the window between two
      checks instead of falling behind it with a distance that grows with its lead;
    * distance: to the two segments meeting at that point (:func:`jaxnc.metrics.local_distance`);
    * complete: once the progress is in the path's last tenth and p within ``end_tol`` of
      its end (stays complete);
    * failed: the distance exceeds ``max_dev`` before completion (afterwards the plant may
      coast off the end);

    and after every fast period: failed when the state is not finite. Between two checks the
    progress, distance and completion are held.

    Record the distance with ``Record(monitor=path_distance)``.

    Attributes:
      path: the :class:`~jaxnc.paths.Path`; max_dev, end_tol: m, > 0, single numbers.
      xy: static, the index of the position's first coordinate in the state vector; None
        (the default): the plant's declared ``position_index`` (``DiffDrive``: 2,
        ``Mecanum``: 3), set by the :class:`~jaxnc.loop.Loop` when it is built, which
        refuses a plant that declares none (give ``xy`` then).
      window: static, >= 2, path points searched per check (a plant that moves farther
        between two checks costs repeated searches, see progress above).
      every: static, fast periods per check (>= 1; default 1, every fast period).
      freeze: static; hold the plant, and this monitor's progress, distance and completion,
        at their last good values once failed (default False: both run on).

    Raises:
      ValueError: naming the field, for a value outside its range; from :meth:`init`, ``xy``
        None (not set by a Loop) or beyond the state vector.
    """

    position_field: ClassVar[str] = "xy"    # declared: a Loop fills xy=None from its plant's position_index

    path: Any
    max_dev: Any = 0.5
    end_tol: Any = 0.1
    xy: int | None = static_field(None)
    window: int = static_field(32)
    every: int = static_field(1)
    freeze: bool = static_field(False)

    def __post_init__(self):
        check_instance("PathMonitor.path", self.path, Path, "a jaxnc.paths.Path")
        array_fields(self, "max_dev", "end_tol")
        scalar_fields(self, "max_dev", "end_tol")
        check_range("PathMonitor.max_dev", self.max_dev, 0.0, None, low_open=True)
        check_range("PathMonitor.end_tol", self.end_tol, 0.0, None, low_open=True)
        if self.xy is not None:
            check_int("PathMonitor.xy", self.xy, 0, None)
        check_int("PathMonitor.window", self.window, 2, None)
        check_int("PathMonitor.every", self.every, 1, None)
        check_bool("PathMonitor.freeze", self.freeze)

    def init(self, ctx) -> PathMonitorState:
        if self.xy is None:
            raise ValueError("PathMonitor.xy must be given (the index of the position's first coordinate in the "
                             "state vector) outside a Loop, which sets it from its plant's position_index")
        if self.xy + 2 > ctx.state_dim:
            raise ValueError(f"PathMonitor.xy must be at most {ctx.state_dim - 2} for a state of "
                             f"{ctx.state_dim} entries, got {self.xy}")
        return PathMonitorState(jnp.zeros((), jnp.int32), jnp.zeros((), jnp.float32), jnp.zeros((), bool))

    def step(self, state: PathMonitorState, x, u, t):
        p, path = x[self.xy:self.xy + 2], self.path

        def check(s):
            idx = track_index(path, p, s.idx, self.window)
            dist = local_distance(path, p, idx)
            at_end = (idx >= (9 * path.M) // 10) & (jnp.sum((p - path.points[-1]) ** 2) < self.end_tol ** 2)
            done = s.done | at_end
            return PathMonitorState(idx, dist, done), (dist > self.max_dev) & ~done

        if self.every == 1:
            state, off_tube = check(state)
        else:       # t is the scan's instant, the same in every lane of a batch: a real branch
            state, off_tube = jax.lax.cond((t + 1) % self.every == 0, check,
                                           lambda s: (s, jnp.zeros((), bool)), state)
        return state, off_tube | ~jnp.all(jnp.isfinite(x)), state.done


def path_distance(monitor: PathMonitor, state: PathMonitorState):
    """The distance to the path after each fast period (a :class:`jaxnc.loop.Record` function)."""
    return state.dist
