"""Experiment definitions, installed as ``jaxnc.experiments``; importing registers them."""
from . import autotune, balancing, diffdrive, hdd, mecanum, mecanum_grid, tune_loops  # noqa: F401
