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


def pure_pursuit(path: Path, xy, idx_prev, *, L_ref, V_ref, window: int):
    """Returns ``(v_ref_world[2], idx)``; ``idx`` is the monotone nearest-point index."""
    idx, _ = closest_index(path, xy, idx_prev, window)
    target = point_at(path, path.s[idx] + L_ref)
    d = target - xy
    D = jnp.sqrt(jnp.sum(d * d) + 1e-12)
    return V_ref * d / jnp.maximum(D, L_ref), idx
