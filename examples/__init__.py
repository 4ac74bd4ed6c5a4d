"""Example loops built from jaxnc's parts (run from the repository root)."""
