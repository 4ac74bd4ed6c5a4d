"""jaxnc: JAX-differentiable networked control systems."""
__version__ = "0.1.0"
