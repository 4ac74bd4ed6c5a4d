"""A multibody Mecanum platform simulated by MuJoCo MJX: the "true plant" for seed 000.

Seed 000 (Carbonell et al., ISA Trans. 2024) section 4 validates its controllers on a
Simscape Multibody model with dead zone, saturation, encoder resolution and wheel
slip, while the estimator keeps the kinematic model of eq. (1). This module is
jaxnc's counterpart: a rigid-body robot with four motor-driven wheels, integrated by
MJX (MuJoCo's JAX backend), so it vmaps over seeds and runs inside the closed-loop
``lax.scan`` like :class:`jaxnc.plants.mecanum.Mecanum`.

How the wheels are modelled (one capsule per wheel, anisotropic friction)
------------------------------------------------------------------------
A Mecanum wheel grips the floor along the axis of its contacting roller, which lies at
45 degrees to the wheel's axle, and rolls freely across it. Each wheel is one capsule
of radius R whose axis lies *along the free direction* (perpendicular to the roller
axis, in the floor plane), on a hinge about that same axis, so the capsule keeps its
orientation in the chassis frame while it spins. MJX aligns the plane-capsule
contact frame with the capsule axis (tangent 1 = the axis, tangent 2 = the grip
direction), so a contact pair with friction ``(mu_free, mu_grip)`` makes the wheel
grip along the roller axis and slide freely across it. A capsule spinning at rate
omega_c about the free direction moves its contact point along the roller axis at
R*omega_c, while a Mecanum wheel spinning at omega moves it at R*omega/sqrt(2)
(the projection of its rolling speed on the roller axis): the motor drives the hinge
through a transmission of ratio sqrt(2) (``gear``), so the actuator's velocity *is*
the wheel speed of eq. (1) and the no-slip kinematics are exactly eq. (1). Passive
roller bodies (the other known option) would cost 4 x 10+ extra bodies and contacts;
the measured cost and accuracy of this choice are in docs/mjx.md.

What the plant adds to the kinematic model
------------------------------------------
* chassis and wheel inertia, contact compliance and wheel slip (finite grip friction);
* velocity-controlled motors: a proportional wheel-speed loop at the physics rate,
  torque ``tau = clip(kv (omega_ref - omega), +-tau_max)``, integrated implicitly, with
  a dead zone (dry friction: a torque below ``dead_zone`` does not turn the wheel) and
  the gearmotor's rotor inertia (``armature``);
* encoders with ``cpr`` counts per revolution: the wheel speed at the sampling instant
  rounded to the resolution of a count difference over one period T, 2 pi / (cpr T) (not
  the mean speed over the period that a count difference measures);
* the gyro/yaw and beacon-distance noise of :class:`MecanumNoise` on the measurements;
* domain randomisation per seed: the grip friction uniform in ``friction_range`` and
  the chassis mass (with its inertia) scaled uniformly in ``mass_range``.

Process noise: the first four entries of n1 (wheel-speed errors) are added to the
wheel-speed references, scaled with the motion as in the kinematic plant; the pose
slip entries are not used (slip comes from the physics).

Needs the optional extra ``pip install jaxnc[mjx]``; the rest of jaxnc imports without it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int, check_nonneg, check_positive, check_range
from jaxnc.loop.base import AbstractInitial, AbstractPlant, pytree_dataclass
from jaxnc.plants.mecanum import (INPUT_DIM, OUTPUT_DIM, POSITION_INDEX, PROCESS_NOISE_DIM, STATE_DIM, Mecanum,
                                   commanded, distances)

try:   # optional extra
    import mujoco
    # MJX prints "Failed to import warp" when NVIDIA Warp (its GPU backend) is absent:
    # irrelevant here, and noise in every run's output
    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
except ImportError as _err:   # pragma: no cover - exercised when the extra is missing
    mujoco = mjx = None
    _IMPORT_ERROR = _err
else:
    _IMPORT_ERROR = None

SQRT2 = math.sqrt(2.0)
# Wheel i: (sign of x, sign of y, free direction in the chassis frame). Wheel 1 front
# left, 2 front right, 3 rear left, 4 rear right, as eq. (1) and (9) number them; the
# free direction b_i is chosen so that (b_i x z) points along the grip direction and a
# positive hinge rate moves the robot as a positive wheel speed of eq. (1) does.
_WHEELS = ((1, 1, (1.0, 1.0)), (1, -1, (-1.0, 1.0)), (-1, 1, (-1.0, 1.0)), (-1, -1, (1.0, 1.0)))
WHEEL_DOFS = (6, 7, 8, 9)      # after the chassis free joint's 6 velocities
SETTLE_STEPS = 40              # physics steps at start-up to settle onto the floor


def require_mjx():
    """Raise a clear error when the optional MJX extra is not installed."""
    if mjx is None:
        raise ImportError("the MJX plant needs MuJoCo's JAX backend: pip install 'jaxnc[mjx]' "
                          f"(import failed: {_IMPORT_ERROR})")


def mecanum_mjcf(R: float = 0.05, Lx: float = 0.15, Ly: float = 0.15, *, chassis_mass: float = 4.0,
                 wheel_mass: float = 0.25, timestep: float = 0.005, mu_grip: float = 0.8,
                 mu_free: float = 0.005, kv: float = 0.1, tau_max: float = 0.5, dead_zone: float = 0.005,
                 armature: float = 0.002, iterations: int = 10, ls_iterations: int = 20,
                 cone: str = "elliptic", half_width: float = 0.005, tolerance: float = 1e-4) -> str:
    """MJCF text of the platform: a chassis on a free joint and four capsule wheels.

    The chassis box (0.4 m x 0.34 m x 0.08 m) and the wheels do not collide with
    anything but the floor, through four explicit contact pairs with anisotropic
    friction (``mu_free`` along the capsule axis, ``mu_grip`` across it). Each wheel's
    motor is a velocity servo ``tau = kv (omega_ref - omega)`` (a MuJoCo ``velocity``
    actuator, integrated implicitly: an explicit servo on a light, unloaded wheel is
    unstable at this time step) saturated at ``tau_max``; the dead zone is the dry
    friction it stands for (``frictionloss``: a torque below ``dead_zone`` does not turn
    the wheel), and ``armature`` the gearmotor's rotor inertia seen at the wheel.
    Torques are wheel-side (N m); the capsule hinge sees them through the sqrt(2)
    transmission.
    """
    s = 1.0 / SQRT2
    bodies, pairs, acts = [], [], []
    for i, (sx, sy, (bx, by)) in enumerate(_WHEELS, start=1):
        ax = f"{bx * s:.9f} {by * s:.9f} 0"
        bodies.append(
            f'      <body name="wheel{i}" pos="{sx * Lx} {sy * Ly} 0">\n'
            f'        <joint name="wheel{i}" type="hinge" axis="{ax}" damping="0.0005" '
            f'armature="{2 * armature}" frictionloss="{SQRT2 * dead_zone}"/>\n'
            f'        <geom name="wheel{i}" type="capsule" size="{R} {half_width}" zaxis="{ax}" mass="{wheel_mass}" '
            f'contype="0" conaffinity="0"/>\n'
            f'      </body>')
        pairs.append(f'    <pair geom1="floor" geom2="wheel{i}" condim="3" '
                     f'friction="{mu_free} {mu_grip} 0.005 0.0001 0.0001"/>')
        acts.append(f'    <velocity name="wheel{i}" joint="wheel{i}" gear="{SQRT2:.9f}" kv="{kv}" '
                    f'forcelimited="true" forcerange="{-tau_max} {tau_max}"/>')
    nl = "\n"
    return f"""<mujoco model="mecanum">
  <option timestep="{timestep}" integrator="implicitfast" iterations="{iterations}" ls_iterations="{ls_iterations}" cone="{cone}" tolerance="{tolerance}"/>
  <worldbody>
    <geom name="floor" type="plane" size="10 10 0.1" contype="0" conaffinity="0"/>
    <body name="chassis" pos="0 0 {R}">
      <freejoint name="chassis"/>
      <geom name="chassis" type="box" size="0.2 0.17 0.04" mass="{chassis_mass}" contype="0" conaffinity="0"/>
{nl.join(bodies)}
    </body>
  </worldbody>
  <contact>
{nl.join(pairs)}
  </contact>
  <actuator>
{nl.join(acts)}
  </actuator>
</mujoco>
"""


class MjxState(NamedTuple):
    """Per-seed state of the multibody plant."""

    data: "mjx.Data"
    psi: jax.Array          # unwrapped yaw (the kinematic state's psi is not wrapped)
    friction: jax.Array     # this seed's grip friction
    mass_scale: jax.Array   # this seed's chassis mass factor


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MjxMecanum(AbstractPlant):
    """The multibody platform as a loop plant (:class:`jaxnc.loop.AbstractPlant`).

    Build it with :func:`mjx_mecanum`. ``kin`` is the kinematic model it is built from
    (geometry, beacons, sampling period T, start pose ``kin.x0`` and noise ``kin.noise``);
    the loop's estimator keeps using the kinematic model. Its state is an
    :class:`MjxState`, drawn per seed from its declared ``x0`` (an :class:`MjxStart`,
    :class:`jaxnc.loop.AbstractInitial`); :meth:`state_vector` is the kinematic state of
    eq. (1). Methods: ``dynamics``, ``measure``, ``state_vector``.
    """

    state_dim = STATE_DIM
    input_dim = INPUT_DIM
    noise_dim = PROCESS_NOISE_DIM
    output_dim = OUTPUT_DIM
    position_index = POSITION_INDEX     # state_vector()[3:5] = (X, Y), the kinematic state's

    model: "mjx.Model"                 # motors (kv, tau_max, dead zone) live in the model
    kin: Mecanum
    cpr: jax.Array = 1024.0            # encoder counts per wheel revolution
    friction_range: jax.Array = (0.6, 1.0)   # grip friction, uniform per seed
    mass_range: jax.Array = (0.8, 1.2)       # chassis mass factor, uniform per seed
    substeps: int = dataclasses.field(default=20, metadata=dict(static=True))

    @property
    def T(self) -> float:
        return self.kin.T

    @property
    def step_period(self) -> float:
        return self.kin.T

    @property
    def w_std(self):
        """float[7]: the true process noise n1 (``kin.noise``)."""
        return self.kin.noise.process_std()

    @property
    def v_std(self):
        """float[9]: the true measurement noise n2 (``kin.noise``)."""
        return self.kin.noise.measurement_std()

    @property
    def x0(self) -> "MjxStart":
        """The random start (declared data): a robot at rest at pose ``kin.x0[3:6]`` on a
        model with this seed's friction and mass (:class:`MjxStart`)."""
        return MjxStart(self)

    def dynamics(self, s: MjxState, u, w) -> MjxState:
        """One fast period T: ``substeps`` physics steps with the wheel-speed loop."""
        u, motion = commanded(self.kin, u)                # saturation and noise scale of eq. (1)'s plant
        ref = u + motion * w[:4]
        data = s.data.replace(ctrl=ref.astype(s.data.ctrl.dtype))   # the motors' speed references
        data = _physics(seed_model(self, s.friction, s.mass_scale), data, self.substeps)
        yaw = _yaw(data.qpos[3:7])
        psi = s.psi + _wrap(yaw - s.psi)
        return MjxState(data, psi, s.friction, s.mass_scale)

    def state_vector(self, s: MjxState):
        """The kinematic state (Vx, Vy, W in the body frame, X, Y, psi) of eq. (1)."""
        q = s.data.qvel
        c, sn = jnp.cos(s.psi), jnp.sin(s.psi)
        vx = c * q[0] + sn * q[1]
        vy = -sn * q[0] + c * q[1]
        return jnp.stack([vx, vy, q[5], s.data.qpos[0], s.data.qpos[1], s.psi])

    def measure(self, s: MjxState, v):
        """Encoders (the wheel speeds at this instant rounded to 2 pi / (cpr T), the
        resolution of a count difference over T), yaw and beacon distances, plus noise n2."""
        res = 2.0 * jnp.pi / (self.cpr * self.kin.T)
        enc = jnp.round(wheel_speeds(s) / res) * res
        xy = s.data.qpos[0:2]
        return jnp.concatenate([enc, s.psi[None], distances(self.kin, xy)]) + v


@pytree_dataclass
class MjxStart(AbstractInitial):
    """The initial state of an :class:`MjxMecanum` (its declared ``x0``): per seed, the grip
    friction uniform in ``plant.friction_range`` and the chassis mass factor uniform in
    ``plant.mass_range``; the robot settles onto its wheels on that seed's model for
    ``SETTLE_STEPS`` physics steps and is put back at rest exactly at pose
    ``plant.kin.x0[3:6]`` (no bounce from the contact at t = 0)."""

    plant: MjxMecanum

    def sample(self, key) -> MjxState:
        """An :class:`MjxState` drawn from ``key`` (split into friction and mass draws)."""
        plant = self.plant
        x0 = jnp.asarray(plant.kin.x0, jnp.float32)
        kf, km = jax.random.split(key)
        fr = jnp.asarray(plant.friction_range, jnp.float32)
        mr = jnp.asarray(plant.mass_range, jnp.float32)
        mu = jax.random.uniform(kf, (), jnp.float32, fr[0], fr[1])
        ms = jax.random.uniform(km, (), jnp.float32, mr[0], mr[1])
        m = seed_model(plant, mu, ms)
        psi = x0[5]
        qpos = jnp.zeros(m.nq, jnp.float32)
        qpos = qpos.at[0:3].set(jnp.stack([x0[3], x0[4], jnp.asarray(plant.kin.R, jnp.float32)]))
        qpos = qpos.at[3:7].set(jnp.stack([jnp.cos(psi / 2), 0.0 * psi, 0.0 * psi, jnp.sin(psi / 2)]))
        data = _physics(m, mjx.make_data(m).replace(qpos=qpos), SETTLE_STEPS)
        qpos = data.qpos.at[0:2].set(qpos[0:2]).at[3:7].set(qpos[3:7]).at[7:].set(0.0)
        with jax.numpy_rank_promotion("allow"):     # MJX relies on implicit rank promotion
            data = mjx.forward(m, data.replace(qpos=qpos, qvel=jnp.zeros_like(data.qvel),
                                               time=jnp.zeros_like(data.time)))
        return MjxState(data, psi, mu, ms)


def wheel_speeds(s: MjxState):
    """float[4]: the wheel speeds of an :class:`MjxMecanum` state (rad/s)."""
    return SQRT2 * s.data.qvel[jnp.asarray(WHEEL_DOFS)]


def seed_model(plant: MjxMecanum, mu, mass_scale):
    """The MJX model of one seed: grip friction ``mu`` and chassis mass factor ``mass_scale``."""
    m = plant.model
    friction = m.pair_friction.at[:, 1].set(mu)
    mass = m.body_mass.at[1].multiply(mass_scale)
    inertia = m.body_inertia.at[1].multiply(mass_scale)
    return m.replace(pair_friction=friction, body_mass=mass, body_inertia=inertia)


def describe(plant: MjxMecanum) -> dict:
    """JSON-friendly parameters of an :class:`MjxMecanum` (the MJCF is regenerated from them)."""
    return {"plant": "mjx", "R": float(plant.kin.R), "Lx": float(plant.kin.Lx), "Ly": float(plant.kin.Ly),
            "T": plant.kin.T, "timestep": float(plant.model.opt.timestep), "substeps": plant.substeps,
            "kv": float(plant.model.actuator_gainprm[0, 0]), "tau_max": float(plant.model.actuator_forcerange[0, 1]),
            "dead_zone": float(plant.model.dof_frictionloss[WHEEL_DOFS[0]]) / SQRT2,
            "armature": float(plant.model.dof_armature[WHEEL_DOFS[0]]) / 2,
            "cpr": float(plant.cpr), "friction_range": [float(a) for a in np.asarray(plant.friction_range)],
            "mass_range": [float(a) for a in np.asarray(plant.mass_range)],
            "chassis_mass": float(plant.model.body_mass[1])}


def _physics(m, data, n: int):
    """``n`` MJX physics steps of model ``m``."""
    with jax.numpy_rank_promotion("allow"):     # MJX relies on implicit rank promotion
        return jax.lax.scan(lambda d, _: (mjx.step(m, d), None), data, None, length=n)[0]


def _yaw(quat):
    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    return jnp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _wrap(a):
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def mjx_mecanum(kin: Mecanum | None = None, *, timestep: float = 0.005, chassis_mass: float = 4.0,
                wheel_mass: float = 0.25, kv: float = 0.1, tau_max: float = 0.5, dead_zone: float = 0.005,
                armature: float = 0.002,
                cpr: float = 1024.0, friction_range=(0.6, 1.0), mass_range=(0.8, 1.2), mu_free: float = 0.005,
                iterations: int = 10, ls_iterations: int = 20, cone: str = "elliptic",
                tolerance: float = 1e-4) -> MjxMecanum:
    """Build a validated MJX Mecanum plant matching the kinematic model ``kin``."""
    require_mjx()
    kin = kin or Mecanum()
    check_positive("timestep", timestep)
    substeps = kin.T / timestep
    if abs(substeps - round(substeps)) > 1e-6:
        raise ValueError(f"timestep must divide the plant period T={kin.T}, got {timestep}")
    substeps = int(round(substeps))
    check_int("substeps (T / timestep)", substeps, 1, 10_000)
    check_range("timestep", timestep, 0.0, 0.01, low_open=True)   # contact time constant 0.02 s needs <= 0.01
    for name, v in (("chassis_mass", chassis_mass), ("wheel_mass", wheel_mass), ("kv", kv), ("tau_max", tau_max),
                    ("cpr", cpr)):
        check_positive(name, v)
    check_nonneg("dead_zone", dead_zone)
    check_nonneg("armature", armature)
    check_range("mu_free", mu_free, 1e-5, 1.0)
    for name, rng, lo in (("friction_range", friction_range, 1e-5), ("mass_range", mass_range, 1e-3)):
        rng = tuple(float(a) for a in rng)
        if len(rng) != 2 or not (lo <= rng[0] <= rng[1]):
            raise ValueError(f"{name} must be (low, high) with {lo} <= low <= high, got {rng}")
    if cone not in ("elliptic", "pyramidal"):
        raise ValueError(f"cone must be 'elliptic' or 'pyramidal', got {cone!r}")
    check_int("iterations", iterations, 1, 1000)
    check_int("ls_iterations", ls_iterations, 1, 1000)
    xml = mecanum_mjcf(float(kin.R), float(kin.Lx), float(kin.Ly), chassis_mass=chassis_mass,
                       wheel_mass=wheel_mass, timestep=timestep, mu_grip=float(np.mean(friction_range)),
                       mu_free=mu_free, kv=kv, tau_max=tau_max, dead_zone=dead_zone, armature=armature,
                       iterations=iterations, ls_iterations=ls_iterations, cone=cone,
                       tolerance=tolerance)
    model = mjx.put_model(mujoco.MjModel.from_xml_string(xml))
    return MjxMecanum(model=model, kin=kin, cpr=np.float32(cpr),
                      friction_range=np.asarray(friction_range, np.float32),
                      mass_range=np.asarray(mass_range, np.float32), substeps=substeps)
