"""The four papers' closed loops as configurations of the one runner :mod:`jaxnc.loop` (no scan of their own):
mecanum (seed 000: SR, DR, DRH, DRHE), balancing (001), hdd (003), diffdrive (004)."""
