"""A heated chamber under PID over a bursty lossy sensor link with PETC.

A user's loop built only from jaxnc's parts (docs/build_your_own_loop.md): the chamber is
the first-order model 0.8 / (20 s + 1) (degrees C above ambient per percent of heater
power), its temperature is sent over a Gilbert-Elliott (bursty) link when PETC decides;
the PID (filtered derivative, setpoint weight b = 0.7, heater limited to 0..100 % with
back-calculation anti-windup) holds its output when no measurement arrives. The loop is
:func:`thermal_pid` and :data:`SETPOINT`; :data:`experiment` makes it a command-line
study, ``jaxnc run examples.thermal_pid:experiment --seeds 1000``.
"""
import control

from jaxnc import loop as nc
from jaxnc import references as refs

T, STEPS = 0.5, 240                                    # 2 Hz, 2 minutes
SETPOINT = refs.Step(30.0, time=5.0)                   # +30 degrees C after 5 s
TRACKING = nc.Tracking(SETPOINT, index=0, window=20)   # the chamber's temperature, x[0]


def thermal_pid(delta=0.25, p_gb=0.05):
    chamber = nc.LTI.from_control(control.tf([0.8], [20.0, 1.0]), T, realization="observable",
                                  w_std=0.02, v_std=0.1)             # x[0] = z: the temperature
    pid = nc.PID(Kp=5.0, Ki=0.3, Kd=1.0, Tf=1.0, b=0.7, c=0.0, u_min=0.0, u_max=100.0, Kb=0.5,
                 reference=SETPOINT, anti_windup="back_calculation")
    bursty = nc.Link(nc.GilbertElliott(p_gb=p_gb, p_bg=0.3, loss_good=0.01, loss_bad=0.8))
    return nc.Loop(plant=chamber, trigger=nc.Petc(delta=delta, max_silence=10), uplink=bursty,
                   estimator=nc.Passthrough(), controller=pid, downlink=nc.Link(), actuator=nc.HoldLast(),
                   T=T, steps=STEPS)


# ----------------------------------------------------------------------------- beyond the loop


def _run_experiment(settings, *, seeds, out, progress):
    from examples._study import run_study
    loop = thermal_pid(delta=settings["delta"], p_gb=settings["p_gb"])
    title = f"heated chamber, PID over a bursty link with PETC (delta={settings['delta']:g}, p_gb={settings['p_gb']:g})"
    return run_study("thermal_pid", title, loop, TRACKING, {"": 0}, settings, seeds=seeds, out=out, progress=progress)


def _experiment():
    from jaxnc.experiment import Experiment, Option
    return Experiment(
        name="thermal_pid", description="user example: heated chamber, PID over a bursty lossy link with PETC",
        options=(Option("delta", "float", 0.25, "PETC absolute threshold (degrees C squared)", low=0.0, high=100.0),
                 Option("p_gb", "float", 0.05, "link: good -> bad probability per packet", low=0.0, high=1.0),
                 Option("seed", "int", 0, "base seed", low=0, high=2**31 - 1)),
        run=_run_experiment)


experiment = _experiment()
