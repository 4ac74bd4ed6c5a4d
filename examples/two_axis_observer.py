"""A two-axis positioning stage: LQR from a steady-state Kalman filter, saturated forces.

A user's loop built only from jaxnc's parts (docs/build_your_own_loop.md): each axis is a
1 kg carriage with viscous friction (x = (p_x, p_y, v_x, v_y), forces u in newtons); only
the positions are measured (1 mm noise) and sent over a link that loses 20 % of the
packets; a steady-state Kalman filter (gain from the Riccati equation, predicting when a
measurement is lost) estimates the state; the LQR's forces are limited to +-1 N by the
actuator. The loop is :func:`two_axis` and :data:`TARGET`; :data:`experiment` makes it a
command-line study, ``jaxnc run examples.two_axis_observer:experiment --seeds 1000``.
"""
import numpy as np

from jaxnc import loop as nc
from jaxnc import references as refs
from jaxnc.controllers.hold_lq import dlqr

T, STEPS = 0.02, 250                                   # 50 Hz, 5 s
TARGET = [0.5, 0.3]                                    # metres, from the origin at t = 0
TRACKING = nc.Tracking(refs.Step(TARGET), index=(0, 1), window=25)


def two_axis(p_loss=0.2, force=1.0):
    A = np.block([[np.zeros((2, 2)), np.eye(2)], [np.zeros((2, 2)), -0.5 * np.eye(2)]])   # friction 0.5 N s/m
    B, C = np.vstack([np.zeros((2, 2)), np.eye(2)]), np.eye(2, 4)
    stage = nc.LTI.from_continuous(A, B, C, T, w_std=[0.0, 0.0, 2e-3, 2e-3], v_std=[1e-3, 1e-3])
    kf = nc.SteadyStateKF(stage, Q=np.asarray(stage.w_std) ** 2, R=np.diag(np.asarray(stage.v_std) ** 2))
    K = dlqr(stage.A, stage.B, np.diag([40.0, 40.0, 10.0, 10.0]), np.eye(2))[0]
    return nc.Loop(plant=stage, trigger=nc.Periodic(), uplink=nc.Link(nc.Bernoulli(p_loss)), estimator=kf,
                   controller=nc.StateFeedback(K, x_ref=TARGET + [0.0, 0.0]), downlink=nc.Link(),
                   actuator=nc.LimitedActuator(nc.HoldLast(), nc.Saturation(-force, force)), T=T, steps=STEPS)


# ----------------------------------------------------------------------------- beyond the loop


def _run_experiment(settings, *, seeds, out, progress):
    from examples._study import run_study
    loop = two_axis(p_loss=settings["p_loss"], force=settings["force"])
    title = (f"two-axis stage, LQR from a steady-state KF, forces within +-{settings['force']:g} N, "
             f"p_loss={settings['p_loss']:g}")
    return run_study("two_axis_observer", title, loop, TRACKING, {"_x": 0, "_y": 1}, settings, seeds=seeds, out=out,
                     progress=progress)


def _experiment():
    from jaxnc.experiment import Experiment, Option
    return Experiment(
        name="two_axis_observer",
        description="user example: two-axis stage, LQR from a steady-state Kalman filter, saturated forces",
        options=(Option("p_loss", "float", 0.2, "sensor packet loss probability", low=0.0, high=0.99),
                 Option("force", "float", 1.0, "actuator force limit (N)", low=0.01, high=1000.0),
                 Option("seed", "int", 0, "base seed", low=0, high=2**31 - 1)),
        run=_run_experiment)


experiment = _experiment()
