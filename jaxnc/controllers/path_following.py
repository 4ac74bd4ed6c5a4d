"""Remote path-following controller of seed 000 (sections 2.4, 3.1, 3.2).

Enhanced pure pursuit (eq. 8) gives world-frame reference velocities, which are
rotated into the body frame; the orientation reference is psi_ref = 0, turned into a
yaw-rate reference W_ref = -K_psi * psi_hat. Three PI loops act on the velocity errors
(V_ref - V_hat) and the inverse kinematics (eq. 9) turn (Vx_u, Vy_u, W_u) into wheel
speed references.

The paper does not give its gains; ours are chosen for the kinematic plant, where the
velocity measured at k+1 is the command applied at k: with Kp = 0.2 and Ki = 6 1/s the
velocity loop at T = 0.1 s has poles 0.56 and -0.36. The same gains run at NT in the
single-rate (SR) scheme, as a re-used design would (the paper does not re-tune SR);
the characteristic polynomial z^2 + (Kp + Ki NT - 1) z - Kp then loses stability when
Ki NT > 2 - 2 Kp, i.e. NT > 0.27 s.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import array_fields, check_int, check_nonneg, check_positive, concrete, scalar_fields
from jaxnc.controllers.pi import pi_step, wrap_angle
from jaxnc.controllers.pure_pursuit import pure_pursuit_velocity
from jaxnc.paths import Path
from jaxnc.plants.mecanum import inverse_kinematics


class FollowerState(NamedTuple):
    idx: jax.Array     # int32, monotone nearest path index (pure pursuit progress)
    integ: jax.Array   # float[3], PI integrators for (Vx, Vy, W)


# Pure-pursuit look-ahead (m); the paper gives none (how it was chosen: docs/design_notes.md).
LOOKAHEAD = 0.08


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PathFollower:
    """Pure pursuit + PI loops + inverse kinematics (seed 000 eq. 8-9).

    Kp, Ki: a number or float[3] (the Vx, Vy and W loops), >= 0; K_psi, V_ref, L_ref: single
    numbers (lists become arrays). Raises ValueError naming the field."""

    path: Path
    Kp: jax.Array = dataclasses.field(default_factory=lambda: np.full(3, 0.2, np.float32))
    Ki: jax.Array = dataclasses.field(default_factory=lambda: np.full(3, 6.0, np.float32))
    K_psi: jax.Array = 1.0
    V_ref: jax.Array = 0.2
    # look-ahead: the paper gives none; see LOOKAHEAD
    L_ref: jax.Array = LOOKAHEAD
    window: int = dataclasses.field(default=80, metadata=dict(static=True))   # path points searched ahead
    back: int = dataclasses.field(default=50, metadata=dict(static=True))     # ... and behind (see pure_pursuit_velocity)
    # along a noise-free prediction the robot moves at most omega_max * R * T = 0.1 m
    # (10 path points) per step: a narrow forward window suffices there
    window_step: int = dataclasses.field(default=16, metadata=dict(static=True))

    def __post_init__(self):
        array_fields(self, "Kp", "Ki", "K_psi", "V_ref", "L_ref")
        for n in ("Kp", "Ki"):
            v = getattr(self, n)
            if concrete(v) and np.shape(v) not in ((), (3,)):
                raise ValueError(f"PathFollower.{n} must be a number or 3 numbers (the Vx, Vy and W loops), "
                                 f"got shape {np.shape(v)}")
        scalar_fields(self, "K_psi", "V_ref", "L_ref")
        check_nonneg("PathFollower.Kp", self.Kp)
        check_nonneg("PathFollower.Ki", self.Ki)
        check_nonneg("PathFollower.K_psi", self.K_psi)
        check_positive("PathFollower.V_ref", self.V_ref)
        check_positive("PathFollower.L_ref", self.L_ref)
        check_int("PathFollower.window", self.window, 2)
        check_int("PathFollower.back", self.back, 0)
        check_int("PathFollower.window_step", self.window_step, 2)

    def init(self) -> FollowerState:
        return FollowerState(jnp.zeros((), jnp.int32), jnp.zeros((3,), jnp.float32))

    def __call__(self, model, mean, state: FollowerState, Ts, *, narrow: bool = False):
        """One controller evaluation from the estimate ``mean``: returns (u, state).

        ``narrow=True`` searches the path only ``window_step`` points ahead, for the
        steps of the prediction stage after the first."""
        window, back = (self.window_step, 0) if narrow else (self.window, self.back)
        v_w, idx = pure_pursuit_velocity(self.path, mean[3:5], state.idx,
                                L_ref=self.L_ref, V_ref=self.V_ref, window=window, back=back)
        c, s = jnp.cos(mean[5]), jnp.sin(mean[5])
        ref = jnp.stack([c * v_w[0] + s * v_w[1],
                         -s * v_w[0] + c * v_w[1],
                         -self.K_psi * wrap_angle(mean[5])])
        v_u, integ = pi_step(self.Kp, self.Ki, state.integ, ref - mean[:3], Ts)
        return inverse_kinematics(model, v_u), FollowerState(idx, integ)
