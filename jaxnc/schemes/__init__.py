"""Closed loops, one ``lax.scan`` each (``schemes.mecanum``: SR, DR, DRH, DRHE of seed 000)."""
