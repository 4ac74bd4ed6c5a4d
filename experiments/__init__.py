"""Experiment definitions, installed as ``jaxnc.experiments``; importing registers them."""
from . import autotune, balancing, diffdrive, hdd, mecanum, mecanum_grid, mecanum_validation, tune_loops, tune_study  # noqa: F401
