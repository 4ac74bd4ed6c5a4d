"""The tune-loops experiment (experiments/tune_loops.py) in a tiny size: the cart-pole loop's
checks at two points, one two-stage tune_loop call (its budget rule tested), the equal-budget search, files written and
reused by a re-run with the same settings.

Marked slow (about 2.5 minutes on two cores, mostly compiling the cart-pole's check and tuner
programs): what it shares with other studies is in the default suite, the orchestration by
test_montecarlo's stored_study tests and tune-study's tiny end-to-end test, tune_loop on
this cart-pole loop by the autotuning notebook's quick mode."""
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import montecarlo
from jaxnc.experiment import load_builtin

load_builtin()
from jaxnc.experiments import tune_loops as tl  # noqa: E402


@pytest.mark.slow
def test_tune_loops_cartpole_tiny_writes_and_resumes(tmp_path, capsys):
    settings = dict(loops="cartpole", steps=10, batch=4, estimator="score", check_seeds=4, study_check_seeds=4, w_drhe=30.0,
                    w_cartpole=2.0, seed=0, max_eval_seeds=16,
                    search_budget=36)     # 9 candidates x 4 rounds: the two-stage tuner, its budget rule tested at step 8
    res = tl.run(settings, seeds=8, out=tmp_path, progress=False)["cartpole"]
    assert len(res["checks"]) == 2 and {c["recommended"] for c in res["checks"]} <= {"straight_through", "score", "richardson", None}
    assert res["checks"][1]["at"] == {"trigger.delta": 1e-2} and res["checks"][0]["seeds"] == 4
    e = res["eval"]
    # the paired difference is the difference of the means (same seeds)
    assert abs(e["tuned_minus_search"][0] - (e["tuned"][0] - e["search"][0])) < 1e-9
    assert res["search"]["simulations"] <= res["tune"]["simulations"]            # equal budget, not more
    tn = res["tune"]
    assert tn["resolution"]["steps"] == 8 and len(tn["resolution"]["t"]) == 1 and tn["steps"] == 10
    stopped = max(tn["resolution"]["t"]) < tn["resolution"]["z"]
    assert tn["gradient_steps"] == (8 if stopped else 10) and (tn["pick"] == []) == stopped
    assert res["verdict"].split(" (doubtful")[0] in ("better than the search", "within the search's interval",
                                                     "worse than the search")
    need = e["normal_interval_seeds"]
    assert set(need) == {"tuned", "search", "tuned_minus_search"} and min(need.values()) >= 28
    # 8 seeds are below Cochran's floor of 28 whatever the skewness: unless the two points are one,
    # the evaluation doubles to its cap of 16 and is still doubtful there
    assert e["rounds"] == ([8] if e["same_point"] else [8, 16]) and e["start_seeds"] == 8
    assert ("doubtful" in res["verdict"]) != e["same_point"]
    for f in ("cartpole.json", "cartpole.tuning.json", "results.json", "tables.md", "tune_loops.png"):
        assert (tmp_path / f).exists(), f
    doc = montecarlo.load_results(tmp_path / "results.json")
    assert doc["config"]["loops"] == ["cartpole"] and doc["config"]["seeds"] == 8
    before = (tmp_path / "cartpole.json").read_bytes()
    capsys.readouterr()
    again = tl.run(settings, seeds=8, out=tmp_path, progress=True)["cartpole"]
    assert "reusing" in capsys.readouterr().out
    assert (tmp_path / "cartpole.json").read_bytes() == before
    assert json.dumps(again, sort_keys=True) == json.dumps(montecarlo.load_results(tmp_path / "cartpole.json")["results"],
                                                           sort_keys=True)
    assert np.isfinite(again["eval"]["tuned"][0])


def test_verdict_is_doubtful_when_cochrans_rule_asks_for_more_seeds():
    assert tl.verdict(-0.3, 0.15, 4000, 8192) == "better than the search"
    assert tl.verdict(0.1, 0.15, 100, 512) == "within the search's interval"
    assert tl.verdict(0.16, 0.02, 4019, 512) == ("worse than the search (doubtful: skewed costs, the normal interval "
                                                "needs about 4019 seeds)")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Gain:
    b: float = 1.0


def _lognormal_run(cfg, key):
    """A cost with a heavy right tail (lognormal, sigma 1.5): Cochran's rule asks for hundreds of
    seeds or more on any sample."""
    return cfg.b * jnp.exp(1.5 * jax.random.normal(key))


def _problem(name="toy"):
    from jaxnc.tune import Positive
    return tl.Problem(name, _Gain(1.0), {"b": Positive()}, lambda j: j, _lognormal_run, {"b": 2.0},
                      {"b": [0.5, 1.0]}, "a toy with a heavy tail")


def _res(tuned, search):
    return {"tune": {"start": {"b": 1.0}, "tuned": {"b": tuned}}, "search": {"best": {"b": search}}}


def test_evaluation_grows_the_seeds_cochrans_rule_asks_for_up_to_its_cap():
    """evaluate(): 64 seeds for each point, then the tuned point and the search's best on at least
    twice as many while Cochran's rule (seeds_for_paired_interval) asks for more, up to the cap;
    the extended sample is the same as one batch of that many seeds (a seed's value does not
    depend on the round it ran in); the start keeps its first 64."""
    from jaxnc import montecarlo
    p = _problem()
    ev = tl.evaluate(p, _res(0.5, 0.6), seeds=64, max_seeds=4096, progress=False)
    e = ev["eval"]
    r = e["rounds"]
    assert r[0] == 64 == e["start_seeds"] and len(r) >= 2 and r[-1] == e["seeds"] <= 4096
    assert all(b >= 2 * a or b == 4096 for a, b in zip(r, r[1:]))
    need = max(e["normal_interval_seeds"].values())
    assert need <= e["seeds"] or e["seeds"] == 4096
    assert ("doubtful" in ev["verdict"]) == (need > e["seeds"])
    keys = montecarlo.seed_keys(tl.EVAL_SEED, e["seeds"])
    for b, got in ((0.5, e["tuned"]), (0.6, e["search"])):
        v = np.asarray(jax.vmap(lambda k: _lognormal_run(_Gain(jnp.float32(b)), k))(keys), np.float64)
        assert got == pytest.approx(montecarlo.mean_ci(v), rel=1e-6)
    v0 = np.asarray(jax.vmap(lambda k: _lognormal_run(_Gain(jnp.float32(1.0)), k))(keys[:64]), np.float64)
    assert e["start"] == pytest.approx(montecarlo.mean_ci(v0), rel=1e-6)
    # a tuned point that is the search's needs no more seeds: their difference is zero on each
    same = tl.evaluate(p, _res(0.5, 0.5), seeds=64, max_seeds=4096, progress=False)
    assert same["eval"]["rounds"] == [64] and same["eval"]["same_point"]
    assert same["verdict"] == "within the search's interval" and tuple(same["eval"]["tuned_minus_search"]) == (0.0, 0.0)
