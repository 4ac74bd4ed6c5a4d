"""run_batched after jax.distributed.initialize(): two local CPU processes (loopback
coordinator, gloo collectives) through `jaxnc run ... --distributed`, each getting the
full result, equal seed by seed to one process's run of the same command."""
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxnc
from jaxnc.cli import main
from jaxnc.montecarlo import load_results

ROOT = Path(__file__).resolve().parent.parent
TIME_LIMIT_S = 240      # both processes are killed if they have not finished by then (a hung coordinator)

# A user's study (as in tests/test_cli_user.py): the failing call, run_batched on a
# loop passed as a runtime argument (a pytree with Python floats in it). The loop was
# seed 000's DRH Mecanum loop; here a two-state servo (LTI plant, EKF, PETC over a lossy,
# delayed link) has the same kind of pytree at a fraction of the compile time, which each
# process pays again (test_builtin_experiment_on_two_processes, marked slow, runs the
# Mecanum experiment on two processes).
STUDY = '''
"""A two-state servo over a lossy, delayed link: per-seed metrics."""
import time
import jax
import numpy as np
from jaxnc import loop as nc, montecarlo, results
from jaxnc.experiment import Experiment, Option

def servo(p_loss):
    plant = nc.LTI(A=[[1.0, 0.1], [0.0, 0.95]], B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0],
                   w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05 ** 2, mean0=[0.0, 0.0], cov0=np.eye(2))
    up = nc.Link(nc.Bernoulli(p_loss), nc.PmfDelay([0.5, 0.5]), order="all", capacity=5)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=1e-3), uplink=up, estimator=ekf,
                   controller=nc.StateFeedback([[3.0, 1.5]]), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=40, T=0.1)

def one_run(key, loop):
    return nc.run(loop, key)

def run(settings, *, seeds, out, progress=True):
    t0 = time.perf_counter()
    loop = servo(settings["p_loss"])
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    m = montecarlo.run_batched(one_run, keys, args=(loop,), chunk_size=8, progress=progress)
    first = montecarlo.run_batched(one_run, keys[:1], args=(loop,), chunk_size=8, progress=False)   # < 1 per process
    results.save_per_seed(out, {"servo": m})
    cost = montecarlo.summarize(m.cost, m.unstable)
    montecarlo.save_results(out / "results.json", experiment="servo", config={"settings": settings, "seeds": seeds},
                            results={"cost": cost, "seed0": first._asdict(), "processes": jax.process_count()},
                            wall_time_s=time.perf_counter() - t0)
    print(f"servo: cost = {cost.mean:.4f} over {cost.n_stable} of {seeds} seeds")
    return {"cost": cost}

experiment = Experiment("servo", "two-state servo", (Option("p_loss", "float", 0.2, "loss probability", low=0.0,
                                                            high=0.95),
                                                     Option("seed", "int", 0, "base seed", low=0)), run)
'''
# the README's multi-host paragraph shows these commands
ARGV = ["run", "mp_servo:experiment", "--seeds", "7", "--no-progress"]     # blocks of 4 and 3 seeds


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_two_processes(tmp_path, argv=ARGV, cwd=None):
    port = _free_port()
    cache = ["--no-cache"] if os.environ.get("JAXNC_NO_CACHE") else []
    procs = []
    for i in (0, 1):
        cmd = [sys.executable, "-m", "jaxnc.cli", *argv, *cache, "--out", str(tmp_path / f"process{i}"),
               "--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)]
        procs.append(subprocess.Popen(cmd, cwd=cwd or tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      start_new_session=True))
    outputs = []
    try:
        for p in procs:
            outputs.append(p.communicate(timeout=TIME_LIMIT_S)[0].decode(errors="replace"))
    except subprocess.TimeoutExpired:
        pytest.fail(f"the two processes did not finish in {TIME_LIMIT_S} s (coordinator hung?); both killed")
    finally:
        for p in procs:                         # never leave a process behind
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=30)
    for i, (p, text) in enumerate(zip(procs, outputs)):
        assert p.returncode == 0, f"process {i} exited with {p.returncode}:\n{text[-3000:]}"
    return outputs


def test_two_processes_give_the_single_process_result_to_every_process(tmp_path, monkeypatch):
    (tmp_path / "mp_servo.py").write_text(STUDY)
    outputs = _run_two_processes(tmp_path)
    assert "servo: cost" in outputs[0] and "servo: cost" not in outputs[1]        # the table is process 0's
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:                                   # one process, the same command
        main([*ARGV, "--out", str(tmp_path / "single")])
    assert e.value.code == 0
    single = jaxnc.load(tmp_path / "single")
    assert single.sizes["seed"] == 7 and not bool(single["unstable"].all())
    for i in (0, 1):
        ds = jaxnc.load(tmp_path / f"process{i}")
        assert ds.sizes == single.sizes
        for name in single.data_vars:
            # bit for bit: each process ran its 4 seeds through the same 16-lane program
            np.testing.assert_array_equal(ds[name].values, single[name].values, err_msg=f"process {i}: {name}")
        doc = load_results(tmp_path / f"process{i}" / "results.json")["results"]
        assert doc["processes"] == 2
        seed0 = doc["seed0"]
        for name, v in seed0.items():                 # one seed: process 1's block was empty
            assert np.asarray(v, single[name].dtype).tolist() == single[name].values[0, :1].tolist(), name


@pytest.mark.slow
def test_builtin_experiment_on_two_processes(tmp_path):
    """`jaxnc run mecanum ... --distributed` (nominal SR and DRH, the figure): every
    process writes the single-process run's per-seed metrics (about 2 min on 2 busy cores)."""
    argv = ["run", "mecanum", "--seeds", "8", "--no-progress",
            "--set", "case=DRH", "--set", "N=2", "--set", "dp=0.05", "--set", "path=turn180"]
    _run_two_processes(tmp_path, argv, cwd=ROOT)
    with pytest.raises(SystemExit) as e:
        main([*argv, "--out", str(tmp_path / "single")])
    assert e.value.code == 0
    single = jaxnc.load(tmp_path / "single")
    for i in (0, 1):
        ds = jaxnc.load(tmp_path / f"process{i}")
        assert list(ds["case"].values) == ["SR nominal", "DRH"]
        for name in single.data_vars:
            np.testing.assert_array_equal(ds[name].values, single[name].values, err_msg=f"process {i}: {name}")


@pytest.mark.parametrize("flags, message", [
    (["--coordinator", "127.0.0.1:1234"], "--coordinator, --num-processes and --process-id need --distributed"),
    (["--distributed", "--coordinator", "localhost"], "--coordinator must be HOST:PORT, got 'localhost'"),
    (["--distributed", "--num-processes", "0"], "--num-processes must be an integer in [1, 65536], got '0'"),
    (["--distributed", "--num-processes", "2", "--process-id", "2"], "--process-id must be an integer in [0, 1], got '2'"),
])
def test_bad_distributed_flags_are_one_line_errors(tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as e:                 # refused before jax.distributed is touched
        main(["run", "mecanum", "--out", str(tmp_path), *flags])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and message in err
