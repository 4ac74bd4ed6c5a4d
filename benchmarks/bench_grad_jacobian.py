"""The cart-pole's exact gradient: ways to differentiate the EKF's linearisation, in ONE process (ABBA).

Run:  JAXNC_NO_CACHE=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_grad_jacobian.py [--seeds 256] [--rounds 2]
      [--variants main held hessian hvp closed closed_bwd const]

bench_grad.py's cart-pole objective (the mean cost over ``--seeds`` seeds as a function of the
LQR gain K, examples/cartpole.py) with the ``EKF``'s prediction (``jaxnc.loop.estimators``'s
``ekf_predict``) replaced, in this process only, by one variant at a time; for each variant
``jit(objective)`` and ``jit(value_and_grad(objective))`` are compiled (compile CPU seconds,
instructions of the compiled HLO) and the programs then timed in the order A B ... B A
(best process CPU time of ``--rounds`` rounds). Variants (issue 32, "exact gradient <= 2.5x the
forward"):

* ``main``: the library's ``ekf_predict`` (A = d[f(x, u, w)]/d(x, w) by one forward-mode
  product per column, reverse mode over those products: the second-order path);
* ``held``: ``ekf_predict(jacobian_grad=False)``, the model's Jacobians held constant in
  reverse mode: an *approximate* gradient, the cost without the second-order path;
* ``const``: the Jacobian replaced by the constant linearisation at x = 0, u = 0 (the filter's
  values change): the forward pass's cost without computing the Jacobian at all;
* ``hessian``: the Jacobian under ``jax.custom_vjp``; its backward contracts the cotangent with
  the model's Hessian d2 F / d(x, w) d(x, u), computed by forward over forward (jacfwd of the
  forward-mode Jacobian), so no reverse mode runs over the forward-mode products;
* ``hvp``: the same ``custom_vjp``, its backward by forward over reverse: for each column j,
  the Hessian-vector product of <J_bar[:, j], F> along e_j;
* ``closed``: the cart-pole's continuous Jacobian in closed form (:func:`cartpole_jacobian`) and
  the discrete one as RK4 of the variational system (x, Phi), dPhi/dt = df/dx Phi + df/dw
  [0, I], in the forward pass and in reverse mode (what a plant's declared Jacobian would do;
  the forward changes at float32 rounding);
* ``closed_bwd``: the library's forward pass, and the closed form's reverse mode as the
  ``custom_vjp`` backward (the same derivative in exact arithmetic).

The table gives, per variant and program, compile CPU s, HLO instructions, best run CPU s, the
gradient's cost against the same variant's forward and against ``main``'s forward, whether the
forward's value equals ``main``'s bit for bit, and the gradient's largest difference from
``main``'s relative to its largest entry. Not recorded automatically (paste into RESULTS.md).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnc.loop.estimators as est  # noqa: E402
from bench_grad import _objectives  # noqa: E402
from examples.cartpole import cartpole  # noqa: E402
from examples.cartpole import f as cartpole_f  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.estimators import ekf as E  # noqa: E402
from jaxnc.estimators.sparsity import jacobian_columns  # noqa: E402

LOOP = "cart-pole (examples/cartpole.py), d/dK"
MAIN = est.ekf_predict


def cartpole_jacobian(x, u, w):
    """(df/dx float[4, 4], df/dw float[4, 2]) of examples/cartpole.py's ``f``, in closed form."""
    M, m, l, g = 1.0, 0.1, 0.5, 9.81
    mt = M + m
    s, c = jnp.sin(x[1]), jnp.cos(x[1])
    a = (u[0] + m * l * x[3] ** 2 * s) / mt
    a_th, a_om = m * l * x[3] ** 2 * c / mt, 2 * m * l * x[3] * s / mt
    den = l * (4 / 3 - m * c * c / mt)
    num = g * s - c * a
    th = num / den
    th_th = ((g * c + s * a - c * a_th) * den - num * l * 2 * m * c * s / mt) / den ** 2
    th_om = -c * a_om / den
    p_th = a_th - m * l * (th_th * c - th * s) / mt
    p_om = a_om - m * l * th_om * c / mt
    z, o = jnp.zeros_like(s), jnp.ones_like(s)
    fx = jnp.stack([jnp.stack([z, z, o, z]), jnp.stack([z, z, z, o]),
                    jnp.stack([z, p_th, z, p_om]), jnp.stack([z, th_th, z, th_om])])
    fw = jnp.asarray([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], x.dtype)
    return fx, fw


def _check_closed_form():
    """The closed form against jax.jacfwd in float64 at random points (raises if it differs)."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        for _ in range(20):
            x, u, w = (jnp.asarray(rng.normal(size=k) * 2) for k in (4, 1, 2))
            fx, fw = cartpole_jacobian(x, u, w)
            np.testing.assert_allclose(fx, jax.jacfwd(cartpole_f, 0)(x, u, w), rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(fw, jax.jacfwd(cartpole_f, 2)(x, u, w), rtol=1e-12, atol=1e-12)


def _columns(f, x, u, q):
    """The library's Jacobian [df/dx, df/dw] at (x, u, 0): one forward-mode product per column."""
    n = x.shape[0]
    w0 = jnp.zeros((q,), x.dtype)
    return jacobian_columns(lambda xw: f(xw[:n], u, xw[n:]), jnp.concatenate([x, w0]), tuple(range(n + q)))


def _variational(plant, x, u, q):
    """[dF/dx, dF/dw] of the plant's RK4 step F, as RK4 of the variational system with the
    closed-form continuous Jacobian (equal to the forward-mode one in exact arithmetic)."""
    n, steps = x.shape[0], plant.substeps
    h = jnp.asarray(plant.T, x.dtype) / steps
    w0 = jnp.zeros((q,), x.dtype)

    def rhs(x, P):
        fx, fw = cartpole_jacobian(x, u, w0)
        return cartpole_f(x, u, w0), E._mm(fx, P) + jnp.concatenate([jnp.zeros((n, n), x.dtype), fw], axis=1)

    def body(c, _):
        x, P = c
        k1, K1 = rhs(x, P)
        k2, K2 = rhs(x + 0.5 * h * k1, P + 0.5 * h * K1)
        k3, K3 = rhs(x + 0.5 * h * k2, P + 0.5 * h * K2)
        k4, K4 = rhs(x + h * k3, P + h * K3)
        return (x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4), P + (h / 6.0) * (K1 + 2 * K2 + 2 * K3 + K4)), None

    P0 = jnp.concatenate([jnp.eye(n, dtype=x.dtype), jnp.zeros((n, q), x.dtype)], axis=1)
    (_, P), _ = jax.lax.scan(body, (x, P0), None, length=steps)
    return P


def _custom(primal, bwd):
    """J(x, u) = primal(x, u) under jax.custom_vjp with backward bwd(x, u, J_bar) -> (x_bar, u_bar)."""
    J = jax.custom_vjp(primal)
    J.defvjp(lambda x, u: (primal(x, u), (x, u)), lambda res, Jb: bwd(*res, Jb))
    return J


def _jacobian(kind, f, q, plant):
    cols = lambda x, u: _columns(f, x, u, q)                                    # noqa: E731
    if kind == "hessian":
        def bwd(x, u, Jb):
            hx, hu = jax.jacfwd(cols, argnums=(0, 1))(x, u)
            return jnp.einsum("ijk,ij->k", hx, Jb), jnp.einsum("ijk,ij->k", hu, Jb)
        return _custom(cols, bwd)
    if kind == "hvp":
        def bwd(x, u, Jb):
            n = x.shape[0]
            z = jnp.concatenate([x, jnp.zeros((q,), x.dtype)])

            def one(e, c):
                grad = jax.grad(lambda z, u: jnp.dot(c, f(z[:n], u, z[n:])), argnums=(0, 1))
                return jax.jvp(lambda z: grad(z, u), (z,), (e,))[1]
            gz, gu = jax.vmap(one, in_axes=(0, 1))(jnp.eye(n + q, dtype=x.dtype), Jb)
            return gz.sum(0)[:n], gu.sum(0)
        return _custom(cols, bwd)
    if kind == "closed":
        return lambda x, u: _variational(plant, x, u, q)
    if kind == "closed_bwd":
        def bwd(x, u, Jb):
            return jax.vjp(lambda x, u: _variational(plant, x, u, q), x, u)[1](Jb)
        return _custom(cols, bwd)
    if kind == "const":
        zero = _columns(f, jnp.zeros((plant.state_dim,), jnp.float32), jnp.zeros((plant.input_dim,), jnp.float32), q)
        return lambda x, u: zero
    raise ValueError(kind)


def predict_variant(kind, plant):
    """An ``ekf_predict`` (dense, Joseph form) whose Jacobian comes from variant ``kind``."""
    if kind == "main":
        return MAIN
    if kind == "held":
        return lambda *a, **k: MAIN(*a, jacobian_grad=False, **k)

    def ekf_predict(f, belief, u, Q, noise_dim, *, jacobian_grad=True, structure=None):
        assert structure is None and jacobian_grad
        n = belief.mean.shape[0]
        mean = f(belief.mean, u, jnp.zeros((noise_dim,), belief.mean.dtype))
        J = _jacobian(kind, f, noise_dim, plant)(belief.mean, u)
        A, L = J[:, :n], J[:, n:]
        Q = jnp.asarray(Q, belief.cov.dtype)
        LQL = E._mm(L * Q[None, :], L.T) if Q.ndim == 1 else E._mm(E._mm(L, Q), L.T)
        return E.Gaussian(mean, E._symmetrize(E._mm(E._mm(A, belief.cov), A.T) + LQL))
    return ekf_predict


def build(kind, keys):
    """{program: (compiled, compile CPU s, HLO instructions, outputs)} of variant ``kind``."""
    est.ekf_predict = predict_variant(kind, cartpole().plant)
    try:
        obj, theta = _objectives()[LOOP]
        out = {}
        for name, fn in (("forward", obj), ("value_and_grad", jax.value_and_grad(obj))):
            c0 = time.process_time()
            comp = jax.jit(fn).lower(theta, keys).compile()
            res = jax.block_until_ready(comp(theta, keys))
            ninstr = sum(1 for line in comp.as_text().splitlines() if " = " in line and not line.lstrip().startswith("//"))
            out[name] = (comp, time.process_time() - c0, ninstr, [np.asarray(v) for v in jax.tree.leaves(res)])
            print(f"  {kind} {name}: compiled in {out[name][1]:.1f} CPU s", flush=True)
        return out, theta
    finally:
        est.ekf_predict = MAIN


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--variants", nargs="+", default=["main", "held", "hessian", "hvp", "closed", "closed_bwd", "const"])
    a = ap.parse_args()
    if a.variants[0] != "main":
        a.variants.insert(0, "main")
    _check_closed_form()
    keys = montecarlo.seed_keys(0, a.seeds)
    load0 = os.getloadavg()[0]
    built = {k: build(k, keys) for k in a.variants}
    best = {(k, p): np.inf for k in a.variants for p in ("forward", "value_and_grad")}
    for _ in range(a.rounds):
        for k in a.variants + a.variants[::-1]:
            (progs, theta) = built[k]
            for p in ("forward", "value_and_grad"):
                c0 = time.process_time()
                jax.block_until_ready(progs[p][0](theta, keys))
                best[(k, p)] = min(best[(k, p)], time.process_time() - c0)
    print(f"\n{a.seeds} seeds, {a.rounds} rounds of A B ... B A; 1-min load average {load0:.1f} at the start, "
          f"{os.getloadavg()[0]:.1f} at the end\n")
    print("| variant | program | compile CPU s | HLO instructions | best run CPU s | / own forward (run) "
          "| / main's forward (run) | / own forward (compile) | value bit-identical to main | gradient: max rel. difference to main |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    ref = built["main"][0]
    for k in a.variants:
        progs = built[k][0]
        for p in ("forward", "value_and_grad"):
            _, comp, ninstr, outs = progs[p]
            same = np.array_equal(outs[0], ref[p][3][0])
            extra = ["", "", ""]
            diff = ""
            if p == "value_and_grad":
                extra = [f"x{best[(k, p)] / best[(k, 'forward')]:.2f}", f"x{best[(k, p)] / best[('main', 'forward')]:.2f}",
                         f"x{comp / progs['forward'][1]:.2f}"]
                g, g0 = outs[1], ref[p][3][1]
                diff = f"{np.max(np.abs(g - g0)) / np.max(np.abs(g0)):.1e}"
            print(f"| {k} | {p} | {comp:.1f} | {ninstr} | {best[(k, p)]:.3f} | {' | '.join(extra)} "
                  f"| {'yes' if same else 'no'} | {diff} |")


if __name__ == "__main__":
    main()
