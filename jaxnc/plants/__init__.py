"""Plant models (discrete time, fast period T): ``dynamics(x, u, w)``, ``measure(x, v)``."""
from jaxnc.plants.mecanum import Mecanum, MecanumNoise

__all__ = ["Mecanum", "MecanumNoise"]
