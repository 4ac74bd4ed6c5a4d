"""Controller design at configuration time (numpy / python-control), with JAX runtime forms.

* ``dualrate``: model-based dual-rate control (Salt & Albertos; seed 004 eq. 21-31).
* ``mrci``: multi-rate controller implementation by interlacing (seed 003 eq. 19-20, 34).
"""
from jaxnc.design.dualrate import (DiscreteSS, DualRateController, DualRateDesign, DualRateState, c2d_zoh,
                                   closed_loop, dualrate_design, pi_controller, single_rate_pi)
from jaxnc.design.mrci import (Mode, Mrci, MrciDesign, MrciState, computation_saving, decompose, mrci_init,
                               mrci_step, partial_fractions)

__all__ = ["DiscreteSS", "DualRateController", "DualRateDesign", "DualRateState", "c2d_zoh", "closed_loop",
           "dualrate_design", "pi_controller", "single_rate_pi",
           "Mode", "Mrci", "MrciDesign", "MrciState", "computation_saving", "decompose", "mrci_init",
           "mrci_step", "partial_fractions"]
