"""Experiment definitions, installed as ``jaxnc.experiments``; importing registers them."""
from . import autotune, balancing, diffdrive, hdd, mecanum, mecanum_grid  # noqa: F401
