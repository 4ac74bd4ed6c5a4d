"""Enhanced pure pursuit (seed 000, section 3.1, eq. 8).

The target is the path point a look-ahead distance L_ref ahead (in arc length) of the
robot's nearest path point. With D the distance to the target, K_V = min(D/L_ref, 1)
and the reference velocity in the world frame is

    (Vx_ref, Vy_ref) = V_ref K_V (cos a, sin a),  a = atan2(d_y, d_x)     (eq. 8)

which equals V_ref * d / max(D, L_ref): written so, it is smooth and has no atan2
singularity when the robot sits on the target (at the end of the path).
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxnc.paths import Path, closest_index, point_at


def pure_pursuit(path: Path, xy, idx_prev, *, L_ref, V_ref, window: int, back: int = 0):
    """Returns ``(v_ref_world[2], idx)``; ``idx`` is the nearest path index, searched in
    ``idx_prev - back .. idx_prev + window - 1``.

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
