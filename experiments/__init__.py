"""Experiment definitions, installed as ``jaxnc.experiments``; importing registers them."""
from . import mecanum  # noqa: F401
