"""A loop made only of a user's own parts, one per role of the protocol table
(docs/build_your_own_loop.md: plant, loss and delay models, trigger, estimator,
controller, actuator, monitor, and a controller-side trigger), against a float64 NumPy
recursion of the same arithmetic written from that page's order of a period: sense,
trigger, send, deliver (read at the slow instant), estimate, control, send, and at every
fast instant deliver, actuate, step the plant, watch it; then predict over the period."""
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc

T = 0.05


@nc.pytree_dataclass
class _Arm(nc.AbstractPlant):
    """3 states, 2 inputs, 3 noises, 2 outputs: a pendulum and a first-order lag."""

    a: Any = 2.0
    x0: Any = (0.4, 0.0, -0.3)
    w_std: Any = (0.0, 0.02, 0.01)
    v_std: Any = (0.01, 0.02)
    state_dim = 3
    input_dim = 2
    noise_dim = 3
    output_dim = 2

    def dynamics(self, x, u, w):
        return jnp.stack([x[0] + T * x[1] + w[0], x[1] + T * (-self.a * jnp.sin(x[0]) - 0.3 * x[1] + u[0]) + w[1],
                          0.9 * x[2] + T * u[1] + w[2]])

    def measure(self, x, v):
        return jnp.stack([x[0], x[2]]) + v


@nc.pytree_dataclass
class _Loss(nc.AbstractLoss):
    p: Any = 0.3

    def sample(self, key, n):
        return jax.random.uniform(key, (n,)) < self.p


@nc.pytree_dataclass
class _Cyclic(nc.AbstractDelay):
    """Delays in fast periods repeating a pattern: later packets overtake earlier ones."""

    pattern: tuple = nc.static_field((0,))
    in_steps = True

    def sample(self, key, n, T):
        d = jnp.asarray(np.resize(np.asarray(self.pattern, np.int32), n))
        return d, d.astype(jnp.float32) * T

    def bounds(self, T):
        return min(self.pattern), max(self.pattern)


class _SentLast(NamedTuple):
    last: jax.Array
    first: jax.Array


@nc.pytree_dataclass
class _Threshold(nc.AbstractTrigger):
    """Send the first signal, then when an entry moved more than delta from the last one sent."""

    delta: Any = 0.02

    def init(self, ctx):
        return _SentLast(jnp.zeros((ctx.signal_dim,), jnp.float32), jnp.ones((), jnp.float32))

    def step(self, state, s, k):
        send = jnp.maximum(state.first, (jnp.max(jnp.abs(s - state.last)) > self.delta).astype(jnp.float32))
        return _SentLast(jnp.where(send > 0.5, s, state.last), jnp.zeros((), jnp.float32)), send


@nc.pytree_dataclass
class _Observer(nc.AbstractEstimator):
    """x̂ += L (z - C x̂) with the newest measurement delivered now; predicted with the applied actions."""

    model: Any
    L: Any
    inputs = "applied"

    def init(self, ctx):
        return jnp.zeros((ctx.state_dim,), jnp.float32)

    def correct(self, xh, inbox, k):
        z, _, w = inbox.newest()
        xh = xh + w * (jnp.asarray(self.L) @ (z - jnp.stack([xh[0], xh[2]])))
        return xh, xh

    def predict(self, xh, u_applied, u_believed, k):
        for j in range(u_applied.shape[0]):
            xh = self.model.dynamics(xh, u_applied[j], jnp.zeros((3,), jnp.float32))
        return xh


@nc.pytree_dataclass
class _Controller(nc.AbstractController):
    """A state feedback with an integral of x̂_0, H decaying actions a packet, sent when something arrived or
    every third slow instant."""

    K: Any
    ki: Any = 0.5
    horizon: int = nc.static_field(3)

    def init(self, ctx):
        return jnp.zeros((), jnp.float32)

    def step(self, I, xhat, fresh, k, ctx):
        I = I + ctx.N * ctx.T * xhat[0]
        base = -(jnp.asarray(self.K) @ xhat) - jnp.stack([self.ki * I, 0.0 * I])
        acts = (0.8 ** jnp.arange(self.horizon, dtype=jnp.float32))[:, None] * base[None, :]
        send = jnp.maximum(fresh, (k % 3 == 0).astype(jnp.float32))
        return I, nc.Packet(acts, (k * ctx.N).astype(jnp.int32)), send


class _Held(NamedTuple):
    u: jax.Array
    stamp: jax.Array
    last: jax.Array


@nc.pytree_dataclass
class _Actuator(nc.AbstractActuator):
    """The newest packet by stamp: its action t - stamp while due, else the last one applied."""

    horizon: int = nc.static_field(3)

    def init(self, ctx):
        return _Held(jnp.zeros((self.horizon, ctx.input_dim), jnp.float32), jnp.asarray(-(2**30), jnp.int32),
                     jnp.zeros((ctx.input_dim,), jnp.float32))

    def receive(self, st, inbox):
        data, stamp, w = inbox.newest()
        take = (w > 0.5) & (stamp > st.stamp)
        return _Held(jnp.where(take, data, st.u), jnp.where(take, stamp, st.stamp), st.last)

    def output(self, st, t):
        i = t - st.stamp
        u = jnp.where((i >= 0) & (i < self.horizon), st.u[jnp.clip(i, 0, self.horizon - 1)], st.last)
        return st._replace(last=u), u


@nc.pytree_dataclass
class _Counter(nc.AbstractMonitor):
    """Counts the fast periods after which |x_0| > 0.2; fails beyond 3."""

    def init(self, ctx):
        return jnp.zeros((), jnp.int32)

    def step(self, c, x, u, t):
        c = c + (jnp.abs(x[0]) > 0.2).astype(jnp.int32)
        return c, jnp.abs(x[0]) > 3.0, jnp.zeros((), bool)


def _count(monitor, c):
    return c


_K = np.array([[3.0, 1.5, 0.0], [0.0, 0.0, 1.2]], np.float32)
_L = np.array([[0.5, 0.0], [0.8, 0.0], [0.0, 0.6]], np.float32)


def _loop(N, up, down, orders, ctrig):
    return nc.Loop(plant=_Arm(), trigger=_Threshold(0.02), uplink=nc.Link(_Loss(0.3), _Cyclic(up), order=orders[0]),
                   estimator=_Observer(_Arm(), _L), controller=_Controller(_K), controller_trigger=ctrig,
                   downlink=nc.Link(_Loss(0.2), _Cyclic(down), order=orders[1]), actuator=_Actuator(),
                   monitor=_Counter(), cost=nc.Quadratic(Q=[1.0, 0.1, 1.0], R=[0.01, 0.01]), N=N, steps=30 * N, T=T,
                   record=nc.Record(monitor=_count))


def _reference(loop, d, ct_delta):
    """float64: the loop above from the docs' order of a period (module docstring)."""
    def f(x, u, w):
        return np.array([x[0] + T * x[1] + w[0], x[1] + T * (-2.0 * np.sin(x[0]) - 0.3 * x[1] + u[0]) + w[1],
                         0.9 * x[2] + T * u[1] + w[2]])
    N, S, H = loop.N, loop.steps // loop.N, 3
    w, v = np.asarray(d.w, float), np.asarray(d.v, float)
    dup, ddn = np.asarray(d.uplink.delay), np.asarray(d.downlink.delay)
    K, L = _K.astype(float), _L.astype(float)
    x, xh, I, count = np.array([0.4, 0.0, -0.3]), np.zeros(3), 0.0, 0
    sent_z, first, sent_a, cfirst = np.zeros(2), True, np.zeros(2), True
    up, up_newest, down = [], -(2**30), []
    held_u, held_stamp, last_u = np.zeros((H, 2)), -(2**30), np.zeros(2)
    out = {n: [] for n in ("x", "u", "xhat", "sent_sc", "recv_sc", "sent_ca", "count")}
    for k in range(S):
        t0 = k * N
        z = np.array([x[0], x[2]]) + v[k]                                  # 1. sense
        send = first or np.max(np.abs(z - sent_z)) > 0.02                  # trigger
        sent_z, first = (z if send else sent_z), False
        if send and dup[k] >= 0:                                           # 2. send
            up.append(dict(stamp=t0, arrival=t0 + dup[k], data=z))
        now = [p for p in up if p["arrival"] <= t0]                        # deliver at the slow instant
        up = [p for p in up if p["arrival"] > t0]
        new = max(now, key=lambda p: p["stamp"]) if now else None
        if new is not None and loop.uplink.order == "newest" and new["stamp"] <= up_newest:
            new = None                                                     # older than one delivered before
        if new is not None:
            up_newest = max(up_newest, new["stamp"])
            xh = xh + L @ (new["data"] - xh[[0, 2]])                       # 3. estimate
        out["xhat"].append(xh.copy())
        I += N * T * xh[0]                                                 # 4. control
        acts = (0.8 ** np.arange(H))[:, None] * (-(K @ xh) - np.array([0.5 * I, 0.0]))[None, :]
        send_ca = new is not None or k % 3 == 0
        if ct_delta is not None and send_ca:                               # the controller's trigger
            send_ca = cfirst or np.max(np.abs(acts[0] - sent_a)) > ct_delta
            sent_a, cfirst = (acts[0] if send_ca else sent_a), False
        if send_ca and ddn[k] >= 0:
            down.append(dict(stamp=t0, arrival=t0 + ddn[k], data=acts))
        us = []
        for j in range(N):                                                 # 5. actuate, every fast instant
            t = t0 + j
            now = [p for p in down if p["arrival"] <= t]
            down = [p for p in down if p["arrival"] > t]
            if now and max(p["stamp"] for p in now) > held_stamp:
                best = max(now, key=lambda p: p["stamp"])
                held_u, held_stamp = best["data"], best["stamp"]
            u = held_u[t - held_stamp] if 0 <= t - held_stamp < H else last_u
            last_u = u
            out["x"].append(x)
            out["u"].append(u)
            x = f(x, u, w[k, j])
            count += abs(x[0]) > 0.2
            out["count"].append(count)
            us.append(u)
        for u in us:                                                       # 6. predict with the applied actions
            xh = f(xh, u, np.zeros(3))
        out["sent_sc"].append(float(send))
        out["recv_sc"].append(float(new is not None))
        out["sent_ca"].append(float(send_ca))
    out = {n: np.array(a, float) for n, a in out.items()}
    out["cost"] = np.mean(out["x"] ** 2 @ np.array([1.0, 0.1, 1.0]) + out["u"] ** 2 @ np.array([0.01, 0.01]))
    return out


@pytest.mark.parametrize("N, up, down, orders, ct_delta", [
    (2, (0, 5, 0, 1), (2, 0, 0, 4), ("newest", "all"), None),       # packets overtake in both directions
    (3, (0, 7, 1), (1, 5, 0, 0), ("all", "newest"), 0.05),
])
def test_a_loop_of_the_users_own_parts_equals_a_float64_recursion_of_the_order_of_a_period(N, up, down, orders,
                                                                                           ct_delta):
    loop = _loop(N, up, down, orders, None if ct_delta is None else _Threshold(ct_delta))
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    trs = jax.jit(jax.vmap(nc.simulate, in_axes=(None, 0)))(loop, keys)
    for i, key in enumerate(keys):
        tr = jax.tree.map(lambda a: a[i], trs)
        ref = _reference(loop, nc.draw(loop, key), ct_delta)
        assert 0 < ref["recv_sc"].sum() < ref["sent_sc"].sum() and 0 < ref["sent_ca"].sum() < len(ref["sent_ca"])
        for name in ("sent_sc", "recv_sc", "sent_ca"):
            np.testing.assert_array_equal(np.asarray(getattr(tr, name)), ref[name], err_msg=name)
        np.testing.assert_array_equal(np.asarray(tr.parts["monitor"]), ref["count"])
        for name in ("x", "u", "xhat"):           # float32 rounding carried along 30 slow periods
            np.testing.assert_allclose(np.asarray(getattr(tr, name)), ref[name], rtol=0, atol=2e-6, err_msg=name)
        np.testing.assert_allclose(float(nc.evaluate(loop, tr).cost), ref["cost"], rtol=2e-6)
