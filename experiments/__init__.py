"""Experiment definitions, installed as ``jaxnc.experiments``."""
