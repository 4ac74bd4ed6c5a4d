"""One closed loop for every networked system: roles, their implementations, one runner.

Build a :class:`Loop` from a plant, a link per direction, a trigger, an estimator, a
controller and an actuator; :func:`simulate` runs it (one ``lax.scan``), :func:`run`
returns its :class:`Metrics` (or a metrics function's of the trajectory), and ``jaxnc.montecarlo.run_batched(run_seed, keys,
args=(loop,))`` maps it over seeds. See docs/build_your_own_loop.md.
"""
from jaxnc.loop.actuators import ActuatorState, HoldLast, PacketActuator, ZeroOrder
from jaxnc.loop.cascade import Cascade, CascadeState
from jaxnc.loop.compensator import LinearController
from jaxnc.loop.numre import Numre, NumreState
from jaxnc.loop.unstamped import ArrivalHold, DirtyDerivative, DirtyDerivativeState
from jaxnc.loop.base import (AbstractActuator, AbstractController, AbstractDelay, AbstractEstimator, AbstractInitial,
                             AbstractLoss, AbstractMonitor, AbstractPlant, AbstractTrigger, AbstractWrappedPlant, Inbox,
                             Packet, blend, pytree_dataclass, static_field)
from jaxnc.loop.controllers import Function, IntegralFeedback, IntegralFeedbackState, Predictive, StateFeedback
from jaxnc.loop.estimators import EKF, EKFState, Passthrough, WeightedEstimate, period_means, period_means_finite
from jaxnc.loop.lead import LeadFeedback
from jaxnc.loop.links import (Bernoulli, GilbertElliott, Link, LinkDraws, NoDelay, NoLoss, PmfDelay,
                              ShiftedExponential, TraceDelay, TraceLoss, TruncatedExponential, WifiModel,
                              draw_link, link_delay_bounds, truncated_exponential)
from jaxnc.loop.costs import Tracking, TrackingMetrics, run_tracking
from jaxnc.loop.limits import (AbstractLimit, DeadZone, LimitedActuator, LimitedSensor, Quantizer, RateLimit,
                               RateLimitState, Saturation)
from jaxnc.loop.observers import (UKF, Luenberger, LuenbergerState, SteadyStateKF, SteadyStateKFState,
                                  slow_system, stationary_gain)
from jaxnc.loop.pid import PID, PIDState, pid_update
from jaxnc.loop.plants import LTI, Continuous, Discrete, rk4
from jaxnc.loop.roundtrip import RoundTrip
from jaxnc.loop.monitors import PathMonitor, PathMonitorState, path_distance
from jaxnc.loop.runner import (PARTS, SIGNALS, STREAMS, Context, Draws, FunctionCost, Loop, Metrics, Monitor, Quadratic,
                               Record, Trajectory, draw, evaluate, live_periods, run, run_seed, simulate)
from jaxnc.loop.triggers import Periodic, Petc, PetcState, petc_decide, petc_gap, petc_update
from jaxnc.loop.multirate import AbstractLiftedPlant, PeriodEKF
from jaxnc.loop.vehicles import DiffDrive, lifted_wheel_var
from jaxnc.loop.pursuit import PursuitPI, PursuitState
from jaxnc.loop.arrival import ArrivalActuator, ArrivalState
from jaxnc.loop.chains import ChainActuator, ChainActuatorState, ChainController, ChainCopy, ChainPacket

__all__ = [
    "Loop", "Record", "simulate", "run", "run_seed", "evaluate", "live_periods", "draw", "Draws", "Trajectory", "Metrics", "Monitor",
    "Quadratic", "FunctionCost", "Context", "STREAMS", "SIGNALS", "PARTS",
    "AbstractPlant", "AbstractInitial", "AbstractWrappedPlant", "AbstractTrigger", "AbstractEstimator", "AbstractController", "AbstractActuator",
    "AbstractMonitor", "AbstractLoss",
    "AbstractDelay", "Packet", "Inbox", "blend", "pytree_dataclass", "static_field",
    "Discrete", "Continuous", "LTI", "rk4",
    "Link", "LinkDraws", "NoLoss", "Bernoulli", "GilbertElliott", "TraceLoss", "NoDelay", "ShiftedExponential",
    "TruncatedExponential", "PmfDelay", "TraceDelay", "WifiModel", "truncated_exponential",
    "draw_link", "link_delay_bounds",
    "Periodic", "Petc", "PetcState", "petc_decide", "petc_gap", "petc_update",
    "EKF", "EKFState", "Passthrough", "WeightedEstimate", "period_means", "period_means_finite",
    "StateFeedback", "IntegralFeedback", "IntegralFeedbackState", "Function", "Predictive",
    "PID", "PIDState", "pid_update",
    "LinearController",
    "Tracking", "TrackingMetrics", "run_tracking",
    "AbstractLimit", "Saturation", "DeadZone", "Quantizer", "RateLimit", "RateLimitState", "LimitedActuator",
    "LimitedSensor",
    "Luenberger", "LuenbergerState", "SteadyStateKF", "SteadyStateKFState", "UKF",
    "slow_system", "stationary_gain",
    "PacketActuator", "ActuatorState", "HoldLast", "ZeroOrder",
    "Numre", "NumreState",
    "Cascade", "CascadeState",
    "AbstractLiftedPlant", "PeriodEKF",
    "DiffDrive", "lifted_wheel_var",
    "PursuitPI", "PursuitState",
    "ArrivalActuator", "ArrivalState",
    "ChainActuator", "ChainActuatorState", "ChainController", "ChainCopy", "ChainPacket",
    "DirtyDerivative", "DirtyDerivativeState",
    "ArrivalHold",
    "LeadFeedback",
    "RoundTrip",
    "PathMonitor", "PathMonitorState", "path_distance",
]
