"""The new-user example (examples/cartpole.py): short, runs 1000 seeds, checked gradient."""
import ast
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnc

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from examples import cartpole as cp  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.cli import run_cli  # noqa: E402
from jaxnc.tune.check import gradient_check  # noqa: E402


def _assigned(node) -> set:
    """Names a top-level assignment binds (``T, STEPS = ...`` binds both)."""
    names = set()
    for t in node.targets:
        names |= {e.id for e in (t.elts if isinstance(t, ast.Tuple) else [t]) if isinstance(e, ast.Name)}
    return names


def _code_lines(src: str, names) -> int:
    """Lines of code (no blank lines, comments or docstrings) of the named top-level
    functions and assignments, plus the imports."""
    tree = ast.parse(src)
    lines = src.splitlines()
    count = 0
    for node in tree.body:
        keep = isinstance(node, (ast.Import, ast.ImportFrom)) or \
            (isinstance(node, ast.FunctionDef) and node.name in names) or \
            (isinstance(node, ast.Assign) and bool(_assigned(node) & set(names)))
        if not keep:
            continue
        skip = set()
        if isinstance(node, ast.FunctionDef) and ast.get_docstring(node) is not None:
            skip = set(range(node.body[0].lineno - 1, node.body[0].end_lineno))
        count += sum(1 for i in range(node.lineno - 1, node.end_lineno)
                     if i not in skip and lines[i].strip() and not lines[i].strip().startswith("#"))
    return count


def test_the_user_code_is_at_most_40_lines():
    n = _code_lines(pathlib.Path(cp.__file__).read_text(), {"f", "h", "cartpole", "T", "STEPS"})
    assert 20 < n <= 40, n


def test_runs_1000_seeds_and_stays_up():
    loop = cp.cartpole()
    # chunks of 16 seeds: the program test_cli_runs_the_example... compiles for its 16 seeds (a seed's
    # statistics do not depend on the chunk), so a fresh suite compiles the example's batched run once
    m = montecarlo.run_batched(nc.run_seed, montecarlo.seed_keys(0, 1000), args=(loop,), chunk_size=16,
                               progress=False)
    assert m.cost.shape == (1000,)
    assert np.mean(m.unstable) < 0.02
    # PETC at delta = 1e-3 sends on a minority of periods; the link loses 30 % of those
    assert 0.05 < np.mean(m.rate_sc) < 0.5
    assert np.all(np.isfinite(m.cost_raw))


def test_delta_gradient_agrees_with_finite_differences_and_straight_through_is_flagged():
    """The score-function estimate of d mean cost / d log delta agrees with central finite
    differences on the same 96 seeds (paired 95 % interval); the straight-through estimate
    at a sharp temperature does not (issue: 6e5 ... 3e10 measured), and is not recommended. (The
    extrapolated score, richardson, is tested on closed forms in test_tune_smoothing.)"""
    loop = cp.cartpole()
    chk = gradient_check(cp.cost_of_log_delta(loop), [np.log(1e-3)], montecarlo.seed_keys(1, 96),
                         fd_step=0.1, temperature=1e-4, score_scale=0.1, estimators=("straight_through", "score"))
    assert chk.consistent["score"], chk.table()
    assert chk.recommended == "score"
    assert not chk.consistent["straight_through"], chk.table()
    # unresolved: its standard error (2e6) is larger than any gradient it could be tested on (since the
    # check's "too noisy" rule is off by default, 2026-12-05; it still reads so with max_noise=10)
    assert chk.reason["straight_through"].startswith(("inconclusive", "differs")), chk.table()


def test_cli_runs_the_example_and_rejects_a_bad_module(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)
    out = tmp_path / "cp"
    assert run_cli(["run", "examples.cartpole:experiment", "--seeds", "16", "--out", str(out), "--no-progress",
                    "--set", "delta=0.0001"]) == 0
    doc = montecarlo.load_results(out / "results.json")
    assert doc["config"]["delta"] == pytest.approx(1e-4) and doc["config"]["seeds"] == 16
    loop = doc["config"]["loop"]                  # the configuration that made the results, whole
    assert loop["type"] == "Loop" and loop["trigger"]["delta"] == pytest.approx(1e-4)
    assert loop["uplink"]["loss"] == {"type": "Bernoulli", "p": pytest.approx(0.3)} and loop["steps"] == cp.STEPS
    # the folder loads as a run's per-seed metrics (it held only results.json: jaxnc.load refused it)
    df = jaxnc.load(out).jaxnc.to_pandas()
    assert df.loc["cartpole", "cost"] == pytest.approx(doc["results"]["cost"]["mean"], rel=1e-12)
    assert df.loc["cartpole", "n"] == 16
    capsys.readouterr()
    assert run_cli(["run", "examples.nope:experiment", "--seeds", "4", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "examples.nope" in err[0]


def test_the_filter_stays_positive_definite_through_a_long_silence():
    """The example's EKF sees nothing for 3.5 s (175 periods; the pole's unstable mode grows
    its covariance to ~1e9), then three measurements. In float32 the Joseph form (EKF's
    default) lost definiteness there: a negative eigenvalue larger than R, then a NaN
    estimate, which the runner counted as a failed run (0.2 % of the cart-pole's seeds at
    delta = 1e-2) and which made the straight-through gradient NaN (docs/tuning_loops.md).
    The example's square-root form keeps the covariance positive semi-definite."""
    ekf = cp.cartpole().estimator
    C, silent = 6, 175
    ctx = nc.Context(N=1, steps=silent + 3, T=cp.T, state_dim=4, input_dim=1, output_dim=2, uplink_capacity=C)
    z = jnp.asarray([0.0, 0.1], jnp.float32)

    def step(st, k):
        here = jnp.arange(C) == k % C                 # slot k mod C holds instant k's packet
        w = (here & (k >= silent)).astype(jnp.float32)
        box = nc.Inbox(jnp.broadcast_to(z, (C, 2)), jnp.where(here, k, -1).astype(jnp.int32), w, here, w)
        st, xhat = ekf.correct(st, box, k)
        return ekf.predict(st, jnp.zeros((1, 1)), jnp.zeros((1, 1)), k), xhat

    @jax.jit
    def run():
        st, xhat = jax.lax.scan(step, ekf.init(ctx), jnp.arange(silent + 3))
        return xhat, st.post.cov
    xhat, P = run()
    assert np.all(np.isfinite(np.asarray(xhat)))
    P = np.asarray(P, float)
    assert np.all(np.isfinite(P)) and np.linalg.eigvalsh(P).min() > -1e-9, np.linalg.eigvalsh(P)
