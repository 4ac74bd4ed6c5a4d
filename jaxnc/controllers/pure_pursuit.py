"""Pure-pursuit path-tracking laws: the target is the path point a look-ahead distance
(in arc length) beyond the robot's nearest path point, found by a monotone windowed
search (:func:`jaxnc.paths.closest_index`).

* :func:`pure_pursuit_velocity` (seed 000, section 3.1, eq. 8, for an omnidirectional
  robot): a world-frame velocity towards the target. With D the distance to the target,
  K_V = min(D/L_ref, 1) and

      (Vx_ref, Vy_ref) = V_ref K_V (cos a, sin a),  a = atan2(d_y, d_x)     (eq. 8)

  which equals V_ref * d / max(D, L_ref): written so, it is smooth and has no atan2
  singularity when the robot sits on the target (at the end of the path).
* :func:`pure_pursuit_curvature` (seed 004, eq. 15-19, for a robot that steers): the
  curvature of the arc through the target tangent to the heading, and the turn rate
  omega = v_ref k.
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxnc.paths import Path, closest_index, point_at

__all__ = ["pure_pursuit_velocity", "pure_pursuit_curvature"]


def pure_pursuit_velocity(path: Path, xy, idx_prev, *, L_ref, V_ref, window: int, back: int = 0):
    """Seed 000 eq. (8): returns ``(v_ref_world float[2], idx)``; ``idx`` is the nearest path
    index, searched in ``idx_prev - back .. idx_prev + window - 1``.

    ``back > 0`` lets the progress step backwards: the remote side predicts progress
    along actions that may never have reached the actuator, and a correction must be
    able to pull the progress back, or the robot would cut across to a point far
    ahead. It stays local, so the search never jumps to the other branch where the
    Lissajous curve crosses itself.
    """
    start = jnp.maximum(jnp.asarray(idx_prev, jnp.int32) - back, 0)
    idx, _ = closest_index(path, xy, start, window + back)
    target = point_at(path, path.s[idx] + L_ref)
    d = target - xy
    D = jnp.sqrt(jnp.sum(d * d) + 1e-12)
    return V_ref * d / jnp.maximum(D, L_ref), idx


def pure_pursuit_curvature(path: Path, xy, psi, idx_prev, *, lad, v_ref, window: int):
    """Seed 004 eq. (15)-(19): returns ``((v_ref, omega_ref), idx)``.

    Args:
      path: the path; xy: float[2] position, psi: heading (rad); idx_prev: int32, the
        progress (nearest index) at the last call; lad: the look-ahead distance (arc
        length); v_ref: the speed; window: static, indices searched from ``idx_prev``.

    Returns:
      ``((v_ref, omega_ref), idx)`` with the curvature of eq. (18), for the target
      (x_t, y_t) an arc length ``lad`` beyond the nearest point,

          k = 2 ((y_t - y) cos psi - (x_t - x) sin psi) / ((x_t - x)^2 + (y_t - y)^2),

      i.e. 2 sin(theta) / L for a target at distance L and bearing theta, and
      omega_ref = v_ref k (eq. 19).
    """
    idx, _ = closest_index(path, xy, idx_prev, window)
    target = point_at(path, path.s[idx] + lad)
    dx, dy = target[0] - xy[0], target[1] - xy[1]
    c, s = jnp.cos(psi), jnp.sin(psi)
    kappa = 2.0 * (dy * c - dx * s) / (dx * dx + dy * dy + 1e-9)
    return (v_ref, v_ref * kappa), idx
