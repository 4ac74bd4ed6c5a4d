"""Bad inputs over the CLI and the Python API: each a clear error naming the parameter
(no traceback, nothing silently accepted), raised before anything is traced."""
import json

import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc.cli import run_cli
from jaxnc.network import Channel


@pytest.mark.parametrize("setting, fragment", [
    ("N=１", "N must be an integer"),                 # a full-width digit
    ("N=1_0", "N must be an integer"),
    ("N=+", "N must be an integer"),
    ("dp=1e-400", "underflows to 0"),
    ("dp=0x1", "dp must be a number"),
    ("dp=½", "dp must be a number"),
    ("dp=1_0", "dp must be a number"),
    ("dp=nan", "dp must be a number"),
])
def test_cli_numbers_are_plain_ascii_and_do_not_underflow(setting, fragment, tmp_path, capsys):
    code = run_cli(["run", "mecanum", "--seeds", "2", "--out", str(tmp_path / "o"), "--set", setting])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and fragment in err[0], err


def test_cli_repeated_key_and_seed_bound(tmp_path, capsys):
    assert run_cli(["run", "mecanum", "--seeds", "2", "--out", str(tmp_path), "--set", "N=2", "N=3"]) == 2
    assert "setting 'N' given twice" in capsys.readouterr().err
    assert run_cli(["run", "mecanum", "--seeds", "5000000000", "--set", "case=SR", "N=1"]) == 2
    assert "--seeds must be an integer in [1, 4294967295]" in capsys.readouterr().err


@pytest.mark.parametrize("call, fragment", [
    (lambda: montecarlo.seed_keys(2**32, 3), "seed must be in [0, 4294967295]"),
    (lambda: montecarlo.seed_keys(-1, 1), "seed must be in"),
    (lambda: montecarlo.seed_keys(0, 1.5), "n must be an integer"),
    (lambda: montecarlo.seed_keys(0, 2, start=0.5), "start must be an integer"),
    (lambda: montecarlo.seed_keys("0", 2), "seed must be an integer"),
    (lambda: montecarlo.seed_keys(0, -1), "n and start must be >= 0"),
    (lambda: montecarlo.run_batched(lambda k: k, montecarlo.seed_keys(0, 2), chunk_size=2.5), "chunk_size"),
    (lambda: montecarlo.run_batched(lambda k: k, montecarlo.seed_keys(0, 2), chunk_size=0), "chunk_size"),
    (lambda: montecarlo.run_batched(lambda k: k, np.zeros((4, 2), np.float32)), "keys must be raw uint32"),
    (lambda: montecarlo.run_batched(lambda k: k, jnp.arange(4)), "keys must be raw uint32"),
    (lambda: Channel(p_loss=[0.1, 1.2]), "Channel.p_loss must be in [0, 1)"),
    (lambda: Channel(p_loss="0.3"), "Channel.p_loss must be a number"),
    (lambda: Channel(eta=[0.1, "a"]), "Channel.eta must be a number"),
    (lambda: nc.Bernoulli(p=[0.2, 1.5]), "Bernoulli.p must be in [0, 1)"),
    (lambda: nc.ShiftedExponential(eta=-0.1), "ShiftedExponential.eta must be in [0, inf)"),
    (lambda: nc.TruncatedExponential(eta=0.2, phi=0.1, tau_max=0.1), "tau_max must be >= eta"),
    (lambda: nc.PmfDelay([[0.5, 0.5]]), "PmfDelay.pmf must be a non-empty 1-D array"),
    (lambda: nc.GilbertElliott(p_bg=0.0), "GilbertElliott.p_bg must be in (0, 1]"),
    (lambda: nc.Link(capacity=0), "Link.capacity must be an integer in [1"),
    (lambda: nc.Link(tau_max=-1.0), "Link.tau_max must be in [0, inf)"),
    (lambda: nc.Petc(delta=-1.0), "Petc.delta must be in [0, inf)"),
    (lambda: nc.Petc(reading="max"), "Petc.reading must be one of sum, each"),
    (lambda: nc.Petc(temperature=0.0, relaxed=True), "Petc.temperature must be > 0 when relaxed"),
    (lambda: nc.Periodic(every=0), "Periodic.every must be an integer in [1"),
    (lambda: nc.PacketActuator(horizon=0), "PacketActuator.horizon must be an integer in [1"),
    (lambda: nc.PacketActuator(on_exhausted="last"), "PacketActuator.on_exhausted must be one of hold, zero"),
    (lambda: nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0, 0.0]]), "LTI.C must have 2 columns"),
    (lambda: nc.LTI(A=np.ones((2, 3)), B=[[0.0], [1.0]], C=[[1.0, 0.0]]), "LTI.A must be square"),
    (lambda: nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]], x0=[1.0]), "LTI.x0 must have 2 entries"),
    (lambda: nc.LTI.from_continuous(np.eye(2), [[0.0], [1.0]], [[1.0, 0.0]], T=0.0), "T must be in (0, inf)"),
    (lambda: nc.Discrete(x0=[0.0, 0.0], w_std=0.0, v_std=0.0, f=lambda x, u, w: x[:1], h=lambda x, v: x[:1] + v),
     "f(x, u, w) must return the state's shape"),
    (lambda: nc.Discrete(x0=[0.0, 0.0], w_std=0.0, v_std=0.0, f=lambda x, u, w: x, h=lambda x, v: x + v[0]),
     "h(x, v) must return output_dim=1 values"),
    (lambda: nc.Discrete(x0=[0.0], w_std=[0.1, 0.2], v_std=0.0, f=lambda x, u, w: x, h=lambda x, v: x + v),
     "w_std must be a scalar or have 1 entries"),
    (lambda: nc.StateFeedback(K=[[np.nan, 1.0]]), "StateFeedback.K must be finite"),
    (lambda: nc.StateFeedback(K=[[1.0]], u_min=1.0, u_max=0.0), "StateFeedback.u_min must be <= u_max"),
    (lambda: nc.Monitor(bounds=["a"]), "Monitor.bounds must be a number"),
])
def test_python_api_errors_name_the_parameter(call, fragment):
    with pytest.raises(ValueError) as e:
        call()
    assert fragment in str(e.value), str(e.value)


def test_ekf_shapes_and_definiteness_are_checked():
    plant = nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]])
    good = dict(Q=np.eye(2), R=np.eye(1), mean0=[0.0, 0.0], cov0=np.eye(2))
    for bad, fragment in ((dict(Q=np.eye(3)), "EKF.Q must be 2x2"), (dict(R=np.eye(2)), "EKF.R must be 1x1"),
                          (dict(mean0=[0.0]), "EKF.mean0 must have 2 entries"),
                          (dict(cov0=np.eye(3)), "EKF.cov0 must be 2x2"),
                          (dict(cov0=np.array([[1.0, 2.0], [0.0, 1.0]])), "EKF.cov0 must be symmetric"),
                          (dict(R=-np.eye(1)), "EKF.R must be positive"), (dict(Q=[1.0, -1.0]), "EKF.Q"),
                          (dict(buffer=-1), "EKF.buffer must be an integer")):
        with pytest.raises(ValueError, match="") as e:
            nc.EKF(plant, **{**good, **bad})
        assert fragment in str(e.value), (fragment, str(e.value))


def test_results_file_errors_name_the_file(tmp_path):
    p = tmp_path / "results.json"
    montecarlo.save_results(p, experiment="x", config={}, results={"a": 1.0}, wall_time_s=0.0)
    text = p.read_text()
    p.write_text(text[: len(text) // 2])                      # truncated
    with pytest.raises(ValueError, match=r"results.json: not a jaxnc results file \(invalid JSON at line"):
        montecarlo.load_results(p)
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match="results.json: not a jaxnc results file .not UTF-8"):
        montecarlo.load_results(p)
    json.loads(text)                                          # the full file was fine
