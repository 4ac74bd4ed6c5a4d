"""Controllers and the smart actuator."""
from jaxnc.controllers.path_following import FollowerState, PathFollower
from jaxnc.controllers.pi import pi_step, wrap_angle
from jaxnc.controllers.pure_pursuit import pure_pursuit_curvature, pure_pursuit_velocity

__all__ = ["FollowerState", "PathFollower",
           "pi_step", "wrap_angle", "pure_pursuit_velocity", "pure_pursuit_curvature"]
