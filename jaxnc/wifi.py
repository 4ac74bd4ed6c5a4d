"""Wi-Fi-like channel: bursty, regular loss and a discrete delay law; CSV traces and replay.

Seed 001 (Branz et al., 2020), section 4 and Table 1.  Each direction of the link
(robot -> controller, controller -> robot) is a :class:`WifiChannel`, a
*Markov-modulated renewal* loss process plus i.i.d. discrete delays:

* a two-regime Gilbert-Elliott chain (good/bad), switching good -> bad with
  probability ``p_gb`` and bad -> good with ``p_bg`` per packet (bursts);
* in the **bad** regime each packet is lost with probability ``loss_bad``;
* in the **good** regime losses form a renewal process: after a loss the next
  ``gap_min`` packets get through, then each is lost with probability
  ``loss_good``, and the ``gap_max``-th is always lost.  ``gap_min = 0`` and a
  large ``gap_max`` give the classical Gilbert-Elliott (Bernoulli) good state.
  The bounded gap is what Table 1 asks for: its window-40 PER never drops below
  2.3 % and its spread (std 2.4 %) is half a binomial's, i.e. Wi-Fi losses at
  1 kHz are *more regular* than Bernoulli losses (contention and beacon
  collisions in a crowded band), with occasional bursts up to 42 %.
* every packet's delay (in whole 1 ms steps) is drawn i.i.d. from ``delay_pmf``
  (index = delay in steps).

The regime and the gap counter are the state of a Markov chain, so a trace is one
``lax.scan`` over packets.  A **trace** is an ``int32`` array of per-packet delays in
steps with ``LOST = -1`` for a lost packet; on disk it is a CSV file with header
``step,delay`` and one row per packet (send step, delay in steps, empty when lost).

The **loop-back** composition of section 4 (A -> B -> A): the packet sent by A at step
k reaches B at ``k + d_f[k]`` and is relayed on B's packet of that step, so its
loop-back delay is ``d_f[k] + d_b[k + d_f[k]]`` and it is lost if either leg is.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import os
import re
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_given, check_int, check_range, checked_pytree, concrete, scalar_fields

__all__ = [
    "LOST",
    "WifiChannel",
    "NOMINAL",
    "sample_trace",
    "gilbert_elliott_losses",
    "arrival_steps",
    "newest_arrival",
    "loopback",
    "LoopbackStats",
    "loopback_stats",
    "window_per",
    "write_trace",
    "read_trace",
    "stationary_loss",
    "delivery_probability",
    "interfered",
    "delay_cdf",
]

LOST = -1
_DTYPE = jnp.float32


@checked_pytree
@dataclasses.dataclass(frozen=True)
class WifiChannel:
    """One direction of the Wi-Fi link (see the module docstring).

    Attributes:
      p_gb, p_bg: per-packet regime switching probabilities good -> bad and bad -> good.
      loss_good: loss probability per packet in the good regime once ``gap_min`` packets
        have passed since the last loss.
      loss_bad: loss probability per packet in the bad regime.
      delay_pmf: probabilities of a delay of 0, 1, ..., D-1 steps (sums to 1).
      loss_extra: probability that a packet is lost independently of the regimes, on top
        of them (an interferer, :func:`interfered`; 0 for the fitted channels).
      gap_min, gap_max: static ints, the shortest and longest run of delivered packets
        between two losses in the good regime (``0 <= gap_min < gap_max``).
    """

    p_gb: float | jax.Array = 0.0
    p_bg: float | jax.Array = 1.0
    loss_good: float | jax.Array = 0.0
    loss_bad: float | jax.Array = 0.0
    delay_pmf: jax.Array = dataclasses.field(default_factory=lambda: np.asarray([0.0, 1.0], np.float32))
    loss_extra: float | jax.Array = 0.0
    gap_min: int = dataclasses.field(default=0, metadata=dict(static=True))
    gap_max: int = dataclasses.field(default=1_000_000, metadata=dict(static=True))

    def __post_init__(self):
        for n in ("p_gb", "p_bg", "loss_good", "loss_bad", "loss_extra"):
            check_given(f"WifiChannel.{n}", getattr(self, n), "a single number")
        scalar_fields(self, "p_gb", "p_bg", "loss_good", "loss_bad", "loss_extra")
        check_range("WifiChannel.p_gb", self.p_gb, 0.0, 1.0)
        check_range("WifiChannel.p_bg", self.p_bg, 0.0, 1.0, low_open=True)
        check_range("WifiChannel.loss_good", self.loss_good, 0.0, 1.0)
        check_range("WifiChannel.loss_bad", self.loss_bad, 0.0, 1.0)
        check_range("WifiChannel.loss_extra", self.loss_extra, 0.0, 1.0, high_open=True)
        check_int("WifiChannel.gap_min", self.gap_min, 0)
        check_int("WifiChannel.gap_max", self.gap_max, self.gap_min + 1)
        pmf = self.delay_pmf
        check_given("WifiChannel.delay_pmf", pmf, "a 1-D array of probabilities")
        if isinstance(pmf, (list, tuple)) or concrete(pmf):      # a jax array too (it was not checked)
            try:
                pmf = np.asarray(pmf, float)
            except (TypeError, ValueError):
                raise ValueError(f"WifiChannel.delay_pmf must be a 1-D array of probabilities, got {pmf!r}") from None
            if pmf.ndim != 1 or pmf.size < 1:
                raise ValueError(f"WifiChannel.delay_pmf must be a 1-D array of probabilities, got shape {pmf.shape}")
            check_range("WifiChannel.delay_pmf", pmf, 0.0, 1.0)
            if abs(pmf.sum() - 1.0) > 1e-4:
                raise ValueError(f"WifiChannel.delay_pmf must sum to 1, got {pmf.sum():.6f}")
            if isinstance(self.delay_pmf, (list, tuple)):          # one leaf, as the other fields
                object.__setattr__(self, "delay_pmf", pmf.astype(np.float32))

    @property
    def max_delay(self) -> int:
        """Largest delay (steps) the pmf can produce: ``len(delay_pmf) - 1``."""
        return int(np.shape(self.delay_pmf)[0]) - 1


def _pmf(delays: dict[int, float], size: int) -> np.ndarray:
    p = np.zeros(size, np.float32)
    for d, q in delays.items():
        p[d] = q
    return p / p.sum()


# Fitted to the loop-back statistics of Table 1 (docs/balancing.md, tests/test_wifi.py):
# both directions alike.  One-way delay 1 step (60 %), 2 (36 %), 3 (3 %), 4 (0.93 %) and a
# flat far tail of 0.07 % over 5..18 steps (the rare 20-step loop-back maxima).  In the
# good regime at least 15 packets pass between two losses, then each is lost with
# probability 0.3, never more than 39 in a row pass (about one loss in 18 packets);
# bursts (bad regime) last 40 packets on average at 23 % loss, about 6 a minute.
NOMINAL = WifiChannel(
    p_gb=1.0e-4,
    p_bg=1.0 / 40.0,
    loss_good=0.30,
    loss_bad=0.23,
    delay_pmf=_pmf({1: 0.60, 2: 0.36, 3: 0.03, 4: 0.0093, **{d: 0.0007 / 14 for d in range(5, 19)}}, 19),
    gap_min=15,
    gap_max=39,
)


def interfered(ch: WifiChannel, hit: float) -> WifiChannel:
    """``ch`` under a pulsed interferer that spoils each transmission attempt with
    probability ``hit`` (ours: section 4 injects noise at -21 and -19 dBm but gives no
    statistics for it, only "a small degradation").

    With the paper's one retry: a packet whose first attempt is spoilt and whose retry
    is not arrives one step later; one whose two attempts are both spoilt is lost. The
    delay law of the delivered packets becomes ``(pmf(d) + hit pmf(d - 1)) / (1 + hit)``
    (one entry longer) and ``loss_extra`` becomes ``1 - (1 - loss_extra)(1 - hit^2)``
    (independent of the regimes, so the loss is ``1 - (1 - stationary_loss(ch))(1 -
    hit^2)``). ``hit = 0`` returns the same channel with a delay law one (zero) entry
    longer.

    Raises:
      ValueError: ``hit`` outside [0, 1).
    """
    check_range("hit", hit, 0.0, 1.0, high_open=True)
    h = float(hit)
    pmf = np.asarray(ch.delay_pmf, np.float64)
    shifted = np.concatenate([pmf, [0.0]]) + h * np.concatenate([[0.0], pmf])
    return dataclasses.replace(ch, delay_pmf=(shifted / shifted.sum()).astype(np.float32),
                               loss_extra=1.0 - (1.0 - float(ch.loss_extra)) * (1.0 - h * h))


def stationary_loss(ch: WifiChannel) -> float:
    """Long-run packet loss probability of one direction (numpy, float64, for design and tests).

    Exact for the chain :func:`sample_trace` runs (:func:`gilbert_elliott_losses`), whatever
    the switching rates: the losses are a Markov renewal process. Between two losses the
    packet at gap counter c (packets delivered since the last loss) moves the regime with
    ``P = [[1 - p_gb, p_gb], [p_bg, 1 - p_bg]]`` and is then lost with ``l(r, c)``: ``loss_bad``
    in the bad regime; in the good one 0 for c < ``gap_min``, ``loss_good`` up to
    ``gap_max``, 1 from ``gap_max`` on. With ``S_c = P diag(1 - l(., c))`` and ``D_c = P
    diag(l(., c))`` (constant on those three ranges, so their products are matrix powers and
    geometric sums), the regime at successive losses is the chain ``E = sum_c S_0..S_{c-1}
    D_c`` and the mean number of packets from a loss to the next one is ``tau = sum_c S_0..
    S_{c-1} 1``; the loss rate is ``1 / (pi_E tau)``, ``pi_E`` the stationary law of E. With
    slow switching (``p_gb, p_bg << 1 / E[G]``, the fitted channels) this is the former
    formula, the regimes' stationary law weighing the bad regime's ``loss_bad`` and the good
    one's renewal rate ``1 / (E[G] + 1)``, ``G = gap_min + min(Geometric(loss_good), gap_max -
    gap_min)``; with fast switching that formula was off (0.3185 for 0.2997, tests/test_wifi.py).
    The independent ``loss_extra`` comes on top: ``1 - (1 - regimes) (1 - loss_extra)``.
    """
    q, qb = float(ch.loss_good), float(ch.loss_bad)
    p_gb, p_bg = float(ch.p_gb), float(ch.p_bg)
    gmin, m = int(ch.gap_min), int(ch.gap_max) - int(ch.gap_min)
    P = np.array([[1.0 - p_gb, p_gb], [p_bg, 1.0 - p_bg]])     # rows: previous regime (good, bad)

    def split(good):                 # (S, D) for a packet lost with ``good`` / qb in each regime
        D = P * np.array([good, qb])
        return P - D, D

    def powers(S, n):                # (S^n, sum_{j<n} S^j) by one block matrix power
        I, Z = np.eye(2), np.zeros((2, 2))
        M = np.linalg.matrix_power(np.block([[S, I], [Z, I]]), n)
        return M[:2, :2], M[:2, 2:]

    (SA, DA), (SB, DB), (SC, DC) = split(0.0), split(q), split(1.0)
    PA, GA = powers(SA, gmin)
    PB, GB = powers(SB, m)
    GC = np.linalg.inv(np.eye(2) - SC)           # p_bg > 0: from gap_max on the good regime always loses
    E = GA @ DA + PA @ GB @ DB + PA @ PB @ GC @ DC
    tau = (GA + PA @ GB + PA @ PB @ GC) @ np.ones(2)
    pi = np.array([E[1, 0], E[0, 1]]) / (E[1, 0] + E[0, 1])
    regimes = 1.0 / float(pi @ tau)
    return regimes + (1.0 - regimes) * float(ch.loss_extra)     # 1 - (1 - regimes)(1 - extra), no cancellation


def delivery_probability(ch: WifiChannel, within: int) -> float:
    """P(a packet arrives with delay <= ``within`` steps) = (1 - loss) P(d <= within).

    Raises:
      ValueError: ``within`` not an integer >= 0 (2.5 failed in a slice, -1 gave 0).
    """
    check_int("delivery_probability: within", within, 0)
    pmf = np.asarray(ch.delay_pmf, float)
    return (1.0 - stationary_loss(ch)) * float(pmf[: within + 1].sum())


def sample_trace(key, ch: WifiChannel, n: int) -> jax.Array:
    """Draw a trace of ``n`` packets (int32 delays in steps, ``LOST`` where lost).

    The chain starts in its stationary regime (good with probability p_bg/(p_gb+p_bg))
    and with a gap counter uniform on [0, gap_max). The regime is stationary from the first
    packet, the gap counter is not (its stationary law weighs age a by P(gap >= a), not
    uniformly): with ``gap_min > 0`` the first packets' loss differs from the stationary
    loss, e.g. :data:`NOMINAL`: 18.6 % at packet 0, 2.6-10 % over packets 1-40, 5.52 % from
    packet 200 on (stationary 5.52 %; 100 000 traces), a transient of about 100 packets.
    Delays use their own subkey (drawn for lost packets too), so changing a loss
    parameter leaves the delays of the surviving packets unchanged. The ``loss_extra``
    losses use ``fold_in(key, 4)``, independent of the four subkeys of ``split(key, 4)``,
    and leave the regimes' chain as it is (the trace with ``loss_extra = 0`` is the same
    whatever the rest).  ``n`` is static: a
    non-negative integer (ValueError otherwise, before tracing).
    """
    check_int("sample_trace: n", n, 0)
    n = int(n)
    k0, k_sw, k_loss, k_delay = jax.random.split(key, 4)
    p_gb = jnp.asarray(ch.p_gb, _DTYPE)
    p_bg = jnp.asarray(ch.p_bg, _DTYPE)
    q_good = jnp.asarray(ch.loss_good, _DTYPE)
    q_bad = jnp.asarray(ch.loss_bad, _DTYPE)
    ka, kb = jax.random.split(k0)
    bad0 = jax.random.uniform(ka, (), _DTYPE) < p_gb / (p_gb + p_bg)
    c0 = jax.random.randint(kb, (), 0, ch.gap_max)
    u_sw = jax.random.uniform(k_sw, (n,), _DTYPE)
    u_loss = jax.random.uniform(k_loss, (n,), _DTYPE)
    lost = gilbert_elliott_losses(bad0, u_sw, u_loss, p_gb, p_bg, q_good, q_bad, c0, ch.gap_min, ch.gap_max)
    # fold_in(key, i) is split(key, n)[i] for i < n (JAX's threefry keys): fold_in(key, 1) drew the
    # regime switches' own uniforms, so an extra loss hit exactly the packets with u_sw < loss_extra
    u_extra = jax.random.uniform(jax.random.fold_in(key, 4), (n,), _DTYPE)
    lost = lost | (u_extra < jnp.asarray(ch.loss_extra, _DTYPE))
    logits = jnp.log(jnp.asarray(ch.delay_pmf, _DTYPE))
    delay = jax.random.categorical(k_delay, logits, shape=(n,)).astype(jnp.int32)
    return jnp.where(lost, LOST, delay)


def gilbert_elliott_losses(bad0, u_switch, u_loss, p_gb, p_bg, loss_good, loss_bad, gap0=0, gap_min: int = 0,
                           gap_max: int | None = None) -> jax.Array:
    """bool[n]: the losses of the two-regime chain (module docstring) on given uniforms, one ``lax.scan``.

    Packet i first moves the regime (bad stays bad iff ``u_switch[i] >= p_bg``; good turns bad
    iff ``u_switch[i] < p_gb``), then is lost in the bad regime iff ``u_loss[i] < loss_bad``; in the good regime iff at least
    ``gap_min`` packets passed since the last loss and ``u_loss[i] < loss_good``, or
    ``gap_max`` passed (None: no bound). ``gap_min = 0``, ``gap_max = None`` is the classical
    Gilbert-Elliott channel (:class:`jaxnc.loop.GilbertElliott`).

    Args:
      bad0: bool[], the regime before packet 0. u_switch, u_loss: float32[n] uniforms on [0, 1).
      p_gb, p_bg, loss_good, loss_bad: float32 scalars. gap0: int32, packets passed since the
        last loss before packet 0. gap_min, gap_max: static ints.
    """
    def step(carry, u):
        bad, c = carry
        us, ul = u
        bad = jnp.where(bad, us >= p_bg, us < p_gb)
        good_loss = (c >= gap_min) & (ul < loss_good)
        if gap_max is not None:
            good_loss = (c >= gap_max) | good_loss
        lost = jnp.where(bad, ul < loss_bad, good_loss)
        return (bad, jnp.where(lost, 0, c + 1)), lost

    return jax.lax.scan(step, (jnp.asarray(bad0, bool), jnp.asarray(gap0, jnp.int32)), (u_switch, u_loss))[1]


def arrival_steps(trace: jax.Array, max_delay: int | None = None) -> jax.Array:
    """Step at which each packet becomes available (``send step + delay``), as int32.

    Lost packets, and packets later than ``max_delay`` steps when it is given (a receiver
    buffer of that length counts them as lost), get a large sentinel (``2**30``).
    """
    trace = jnp.asarray(trace, jnp.int32)
    k = jnp.arange(trace.shape[-1], dtype=jnp.int32)
    ok = trace >= 0
    if max_delay is not None:
        ok = ok & (trace <= max_delay)
    return jnp.where(ok, k + trace, jnp.int32(2**30))


def newest_arrival(trace: jax.Array, max_delay: int | None = None) -> jax.Array:
    """For each step j, the send step of the most recently *arrived* packet (``-1``: none yet).

    What a receiver without time stamps uses (the emulation design, eq. 5): the packet
    with the largest arrival step ``<= j``; of several arriving together, the newest.
    Replay helper, computed once per trace before the scan.
    """
    trace = jnp.asarray(trace, jnp.int32)
    n = trace.shape[-1]
    a = arrival_steps(trace, max_delay)
    t = jnp.arange(n, dtype=jnp.int32)
    best = jnp.full(n, -1, jnp.int32).at[jnp.where(a < n, a, n)].max(t, mode="drop")
    s_last = jax.lax.cummax(jnp.where(best >= 0, t, -1))
    return jnp.where(s_last >= 0, best[jnp.maximum(s_last, 0)], -1)


def loopback(forward: jax.Array, backward: jax.Array) -> jax.Array:
    """Loop-back trace A -> B -> A of two one-way traces (section 4, see module docstring).

    A packet whose relay instant ``k + d_f`` falls beyond the backward trace is lost.
    """
    forward = jnp.asarray(forward, jnp.int32)
    backward = jnp.asarray(backward, jnp.int32)
    n = forward.shape[-1]
    k = jnp.arange(n, dtype=jnp.int32)
    j = k + jnp.maximum(forward, 0)
    inside = j < backward.shape[-1]
    db = jnp.take(backward, jnp.minimum(j, backward.shape[-1] - 1), axis=-1)
    ok = (forward >= 0) & inside & (db >= 0)
    return jnp.where(ok, forward + db, LOST)


def window_per(trace, window: int = 40) -> np.ndarray:
    """Packet error rate over each sliding window of ``window`` packets (numpy), as in Fig. 4b:
    float64[n - window + 1] for a trace of n packets.

    Raises:
      ValueError: ``window`` not an integer in [1, n] (no full window).
    """
    n = int(np.size(trace))
    check_int("window_per: window", window, 1, max(n, 1))
    if n == 0:
        raise ValueError("window_per: the trace is empty")
    lost = (np.asarray(trace) < 0).astype(np.float64)
    c = np.concatenate([[0.0], np.cumsum(lost)])
    return (c[window:] - c[:-window]) / window


class LoopbackStats(NamedTuple):
    """Table 1 statistics of one trace (delays in steps, PER in %)."""

    delay_median: float
    delay_std: float
    delay_max: float
    delay_min: float
    per_median: float     # of the window-40 PER sequence, %
    per_std: float
    per_max: float
    per_min: float
    per_mean: float       # overall packet loss of the trace, %


def loopback_stats(trace, window: int = 40) -> LoopbackStats:
    """Delay and window-PER statistics of a (loop-back) trace, the rows of Table 1; the delay
    statistics are nan for a trace that delivered nothing (as :func:`delay_cdf`)."""
    t = np.asarray(trace)
    d = t[t >= 0].astype(np.float64)
    w = 100.0 * window_per(t, window)
    if d.size == 0:                 # numpy's max of nothing raised "zero-size array to reduction operation"
        d = np.full(1, np.nan)
    return LoopbackStats(
        delay_median=float(np.median(d)), delay_std=float(np.std(d)), delay_max=float(d.max()),
        delay_min=float(d.min()), per_median=float(np.median(w)), per_std=float(np.std(w)),
        per_max=float(w.max()), per_min=float(w.min()), per_mean=100.0 * float(np.mean(t < 0)))


def delay_cdf(trace, max_delay: int) -> np.ndarray:
    """Empirical CDF of the delays of the delivered packets of ``trace`` (numpy), at
    0, 1, ..., ``max_delay`` steps: float64[max_delay + 1] (Fig. 5 for a loop-back trace).
    Lost packets are left out (the CDF reaches 1); nan if none was delivered."""
    t = np.asarray(trace).ravel()
    d = t[t >= 0]
    if d.size == 0:
        return np.full(max_delay + 1, np.nan)
    return np.searchsorted(np.sort(d), np.arange(max_delay + 1), side="right") / d.size


# ----------------------------------------------------------------------------- CSV traces


def write_trace(path, trace) -> None:
    """Write a one-way trace as CSV: header ``step,delay``, one row per packet, empty delay = lost.

    Raises:
      ValueError: ``trace`` is not a 1-D array of integer delays (a batch of traces [B, n]
        was written as one trace of B n packets, a delay of 1.7 steps as 1), before the file
        is opened.
    """
    a = np.asarray(trace)
    if a.ndim != 1 or a.dtype.kind not in "iuf" or (a.dtype.kind == "f" and not np.all(a == np.round(a))):
        raise ValueError(f"write_trace: trace must be a 1-D array of integer delays in steps (negative = lost), "
                         f"got an array of {a.dtype} of shape {a.shape}"
                         + ("" if a.ndim != 1 or a.dtype.kind not in "f" else " with non-integer delays"))
    t = a.astype(np.int64)
    path = os.fspath(path)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["step", "delay"])
        for k, d in enumerate(t):
            w.writerow([k, "" if d < 0 else int(d)])


_DIGITS = re.compile(r"[0-9]+\Z")       # plain ASCII digits: int() also takes "１" and "1_0"
_INT32_MAX = 2**31 - 1


def read_trace(path) -> np.ndarray:
    """Read a CSV trace (see :func:`write_trace`) into an int32 array, ``LOST`` where empty.

    Rows may be in any order; steps must be 0..n-1, each exactly once, and a delay is
    empty (lost) or a non-negative integer below 2**31 in plain ASCII digits.

    Raises:
      OSError: the file cannot be opened (its message names the file).
      ValueError: the file is not UTF-8, has no ``step,delay`` header, or a row is
        malformed (a negative, huge or non-integer step/delay, a repeated step) -- the
        message starts with ``<path>:<line>:`` -- or the steps are not 0..n-1.
    """
    with open(os.fspath(path), "rb") as f:
        data = f.read()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise ValueError(f"{path}:{line}: not a UTF-8 text file (byte {data[e.start]:#04x} "
                         f"at offset {e.start})") from None
    rows = {}
    r = csv.reader(io.StringIO(text, newline=""))
    header = next(r, None)
    if header is None or [h.strip().lower() for h in header[:2]] != ["step", "delay"]:
        raise ValueError(f"{path}:1: expected the header 'step,delay', got {header!r}")
    for row in r:
        line = r.line_num
        if not row:
            continue
        step = row[0].strip()
        delay = row[1].strip() if len(row) > 1 else ""
        if delay.startswith("-") and _DIGITS.match(delay[1:]):
            raise ValueError(f"{path}:{line}: delay must be empty (a lost packet) or a non-negative "
                             f"integer, got {delay}")
        if len(row) > 2 or not _DIGITS.match(step) or not (delay == "" or _DIGITS.match(delay)):
            raise ValueError(f"{path}:{line}: expected 'step,delay' with a non-negative integer step and "
                             f"a non-negative integer delay (empty when lost), got {row!r}")
        k = int(step)
        d = LOST if delay == "" else int(delay)
        if d > _INT32_MAX:
            raise ValueError(f"{path}:{line}: delay must be in [0, {_INT32_MAX}] steps, got {d}")
        if k in rows:
            raise ValueError(f"{path}:{line}: step {k} repeated")
        rows[k] = d
    n = len(rows)
    if sorted(rows) != list(range(n)):
        raise ValueError(f"{path}: steps must be 0..{n - 1}, each once")
    return np.asarray([rows[k] for k in range(n)], np.int32)
