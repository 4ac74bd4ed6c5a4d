"""Command line and experiment registry, with a dummy experiment (no built-ins needed)."""
import pytest

from jaxnc import cli
from jaxnc import experiment as ex
from jaxnc.experiment import ConfigError, Experiment, Option

CALLS = []


def _dummy_run(settings, *, seeds, out, progress):
    CALLS.append(dict(settings=settings, seeds=seeds, out=out, progress=progress))
    print("dummy ran")
    return {"ok": True}


DUMMY = Experiment(
    name="dummy",
    description="a test experiment",
    options=(
        Option("case", "choice", "all", "scheme", choices=("SR", "DR", "DRH", "DRHE", "all")),
        Option("N", "int", 10, "multiplicity", low=1, high=12),
        Option("dp", "float", 0.5, "dropout probability", low=0.0, high=0.95),
        Option("sigma", "floats", (0.1, 0.2), "thresholds", low=0.0, high=10.0),
        Option("plot", "bool", True, "make figures"),
    ),
    run=_dummy_run,
)


@pytest.fixture(autouse=True)
def registry(monkeypatch):
    """A private registry holding only the dummy; built-ins are not imported."""
    monkeypatch.setattr(ex, "REGISTRY", {})
    monkeypatch.setattr(ex, "load_builtin", lambda: None)
    ex.register(DUMMY)
    CALLS.clear()
    yield ex.REGISTRY


def run(argv):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    return e.value.code


def assert_one_line_error(capsys, *fragments):
    err = capsys.readouterr().err
    lines = err.strip("\n").splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("jaxnc: error: "), err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], (f, err)
    return lines[0]


# ----------------------------------------------------------------------------- option parsing


def test_option_parse_values():
    assert DUMMY.parse_settings([]) == {"case": "all", "N": 10, "dp": 0.5, "sigma": (0.1, 0.2), "plot": True}
    s = DUMMY.parse_settings(["dp=0", "case=DRH", "sigma=1, 2,3", "plot=no", "N=3"])
    assert s == {"case": "DRH", "N": 3, "dp": 0.0, "sigma": (1.0, 2.0, 3.0), "plot": False}
    with pytest.raises(ConfigError, match=r"setting 'N' given twice \('N=12' and 'N=3'\)"):
        DUMMY.parse_settings(["N=12", "N=3"])
    assert DUMMY.parse_settings(["case=drhe"])["case"] == "DRHE"      # unique case-insensitive


@pytest.mark.parametrize("pair, message", [
    ("N=13", "N must be an integer in [1, 12], got '13'"),
    ("N=0", "N must be an integer in [1, 12], got '0'"),
    ("N=2.5", "N must be an integer in [1, 12], got '2.5'"),
    ("dp=abc", "dp must be a number in [0, 0.95], got 'abc'"),
    ("dp=nan", "dp must be a number in [0, 0.95], got 'nan'"),
    ("dp=0.99", "dp must be a number in [0, 0.95], got '0.99'"),
    ("case=XX", "case must be one of SR, DR, DRH, DRHE, all, got 'XX'"),
    ("sigma=1,,2", "sigma must be a comma-separated list of numbers in [0, 10], got '1,,2'"),
    ("sigma=1,11", "sigma must be a comma-separated list of numbers in [0, 10], got '1,11'"),
    ("plot=maybe", "plot must be true or false, got 'maybe'"),
])
def test_option_errors(pair, message):
    with pytest.raises(ConfigError) as e:
        DUMMY.parse_settings([pair])
    assert str(e.value) == message


def test_unknown_and_malformed_settings():
    with pytest.raises(ConfigError, match="unknown setting 'foo'.*valid keys: case, N, dp, sigma, plot"):
        DUMMY.parse_settings(["foo=1"])
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        DUMMY.parse_settings(["N"])
    with pytest.raises(ConfigError, match="unknown experiment 'nope'; available: dummy"):
        ex.get_experiment("nope")
    with pytest.raises(ValueError):
        Option("x", "complex", 0, "bad kind")


def test_load_builtin_never_raises(monkeypatch):
    monkeypatch.undo()                       # the real load_builtin, real registry
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")      # a half-written built-in may warn; it must not raise
        ex.load_builtin()


# ----------------------------------------------------------------------------- CLI


def test_version(capsys):
    assert run(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxnc {__import__('jaxnc').__version__}"


def test_the_command_sets_the_collectors_thresholds_for_a_tracing_process(monkeypatch, capsys):
    """At Python's default thresholds (700, 10, 10) full collections took a fifth to two
    fifths of each loop's trace; ``jaxnc`` (the console script) raises them for its own
    process (the library leaves them alone)."""
    import gc
    before = gc.get_threshold()
    try:
        gc.set_threshold(700, 10, 10)
        with pytest.raises(SystemExit) as stop:
            cli.main(["--version"])
        assert stop.value.code == 0 and gc.get_threshold() == (100_000, 50, 100)
    finally:
        gc.set_threshold(*before)
    capsys.readouterr()


def test_list(capsys):
    assert run(["list"]) == 0
    out = capsys.readouterr().out
    assert "dummy" in out and "a test experiment" in out
    assert "an integer in [1, 12]" in out and "default 10" in out
    assert "one of SR, DR, DRH, DRHE, all" in out and "default 0.1,0.2" in out


def test_run_passes_parsed_settings(tmp_path, capsys):
    out = tmp_path / "o" / "p"
    code = run(["run", "dummy", "--seeds", "7", "--out", str(out), "--set", "N=3", "dp=0.25",
                "--set", "case=DR", "--no-progress"])
    assert code == 0
    assert "dummy ran" in capsys.readouterr().out
    (call,) = CALLS
    assert call["settings"] == {"case": "DR", "N": 3, "dp": 0.25, "sigma": (0.1, 0.2), "plot": True}
    assert call["seeds"] == 7 and call["out"] == out
    assert call["progress"] is False and out.is_dir()


def test_run_defaults(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run(["run", "dummy"]) == 0
    (call,) = CALLS
    assert call["seeds"] == 1000 and call["progress"] is True
    assert str(call["out"]) == "results/dummy" and (tmp_path / "results" / "dummy").is_dir()
    assert call["settings"] == DUMMY.parse_settings([])


@pytest.mark.parametrize("argv, fragments", [
    (["run", "nope"], ["unknown experiment 'nope'", "available: dummy"]),
    (["run", "dummy", "--set", "foo=1"], ["unknown setting 'foo'", "valid keys: case, N, dp, sigma, plot"]),
    (["run", "dummy", "--set", "N=13"], ["N must be an integer in [1, 12], got '13'"]),
    (["run", "dummy", "--set", "dp=abc"], ["dp must be a number in [0, 0.95], got 'abc'"]),
    (["run", "dummy", "--set", "case=XX"], ["case must be one of SR, DR, DRH, DRHE, all"]),
    (["run", "dummy", "--set", "N"], ["malformed setting 'N'"]),
    (["run", "dummy", "--seeds", "0"], ["--seeds must be an integer in [1, 4294967295], got '0'"]),
    (["run", "dummy", "--seeds", "many"], ["--seeds must be an integer in [1, 4294967295], got 'many'"]),
    (["run", "dummy", "--bogus"], ["unrecognized arguments: --bogus"]),
    (["frobnicate"], ["invalid choice"]),
])
def test_errors_exit_2_one_line(argv, fragments, capsys, tmp_path):
    argv = argv + ["--out", str(tmp_path / "o")] if argv[0] == "run" and len(argv) > 1 else argv
    assert run(argv) == 2
    assert_one_line_error(capsys, *fragments)
    assert CALLS == []
    assert not (tmp_path / "o").exists()      # nothing created before the settings are valid


def test_config_error_inside_experiment(tmp_path, capsys):
    def bad_run(settings, *, seeds, out, progress):
        raise ConfigError("sigma must have 1 or 9 values, got 2")

    ex.register(Experiment("bad", "raises", (), bad_run))
    assert run(["run", "bad", "--out", str(tmp_path)]) == 2
    assert_one_line_error(capsys, "sigma must have 1 or 9 values")


def test_keyboard_interrupt(tmp_path, capsys):
    def slow_run(settings, *, seeds, out, progress):
        raise KeyboardInterrupt

    ex.register(Experiment("slow", "interrupted", (), slow_run))
    assert run(["run", "slow", "--out", str(tmp_path)]) == 130
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["jaxnc: interrupted"]


def test_run_cli_returns_code(tmp_path):
    assert cli.run_cli(["run", "dummy", "--out", str(tmp_path), "--seeds", "3"]) == 0
    assert cli.run_cli(["run", "dummy", "--set", "N=99"]) == 2


def test_ints_option():
    o = Option("N", "ints", (1, 2), "multiplicities", low=1, high=12)
    assert o.parse("1, 6,12") == (1, 6, 12)
    assert o.format_value((1, 6)) == "1,6"
    for bad in ("1,13", "1.5", "", "1,,2"):
        with pytest.raises(ConfigError, match=r"N must be a comma-separated list of integers in \[1, 12\]"):
            o.parse(bad)


# ----------------------------------------------------------------------------- the output folder, exit codes


def _writer(settings, *, seeds, out, progress):
    """An experiment that writes a finished results.json, as the built-in single runs do."""
    from jaxnc import montecarlo
    CALLS.append(dict(settings=settings, seeds=seeds))
    montecarlo.save_results(out / "results.json", experiment="writer", config={"settings": settings, "seeds": seeds},
                            results={}, wall_time_s=0.0)
    return {}


WRITER = Experiment("writer", "writes results.json", (Option("N", "int", 2, "n", low=1, high=9),), _writer)


def test_a_folder_of_other_settings_or_another_experiment_is_refused_before_running(tmp_path, capsys):
    ex.register(WRITER)
    out = str(tmp_path / "o")
    assert run(["run", "writer", "--seeds", "3", "--out", out, "--set", "N=4"]) == 0
    assert run(["run", "writer", "--seeds", "3", "--out", out, "--set", "N=4"]) == 0     # the same: it resumes
    capsys.readouterr()
    CALLS.clear()
    assert run(["run", "writer", "--seeds", "5", "--out", out, "--set", "N=5"]) == 2
    assert_one_line_error(capsys, "--out:", "holds the results of writer with other settings",
                          "N: 4 there, 5 here", "seeds: 3 there, 5 here", "choose another folder")
    assert run(["run", "dummy", "--seeds", "3", "--out", out]) == 2
    assert_one_line_error(capsys, "holds the results of experiment 'writer', not 'dummy'")
    assert CALLS == []                                   # refused before the experiment ran
    # a run that never finished (no results.json) overwrites nothing: another setting is fine
    fresh = tmp_path / "fresh"
    assert run(["run", "dummy", "--seeds", "3", "--out", str(fresh), "--set", "N=3"]) == 0
    assert run(["run", "dummy", "--seeds", "4", "--out", str(fresh), "--set", "N=4"]) == 0


def test_run_help_of_an_experiment_lists_its_settings(capsys):
    assert run(["run", "dummy", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jaxnc run") and "--seeds N" in out
    assert "settings of dummy: a test experiment" in out
    assert "    N      default 10; an integer in [1, 12]. multiplicity" in out
    assert run(["run", "-h"]) == 0 and "settings of" not in capsys.readouterr().out
    assert run(["run", "nosuch", "-h"]) == 2
    assert_one_line_error(capsys, "unknown experiment 'nosuch'")
    assert CALLS == []


def test_a_run_removes_the_temporary_file_a_killed_write_left(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    from jaxnc import montecarlo
    (tmp_path / "results.json").write_text("{}")
    script = ("import os, signal, sys\n"
              "from jaxnc import montecarlo\n"
              "def write(f):\n"
              "    f.write(b'{\"half'); f.flush(); os.kill(os.getpid(), signal.SIGKILL)\n"
              "montecarlo.atomic_write(sys.argv[1], write)\n")
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path / "results.json")], capture_output=True,
                          env=dict(os.environ, JAX_PLATFORMS="cpu"), timeout=120)
    assert done.returncode == -signal.SIGKILL, done.stderr.decode()
    left = montecarlo.stale_temporaries(tmp_path)
    assert [f.name[:14] for f in left] == [".results.json."] and left[0].read_bytes() == b'{"half'
    assert (tmp_path / "results.json").read_text() == "{}"          # the old file untouched
    (tmp_path / ".notes.tmp").write_text("mine")                     # not atomic_write's: kept
    assert run(["run", "dummy", "--seeds", "3", "--out", str(tmp_path)]) == 0
    assert montecarlo.stale_temporaries(tmp_path) == [] and (tmp_path / ".notes.tmp").exists()


def test_a_sweep_keeps_the_cells_of_other_settings_apart(tmp_path, capsys):
    ex.register(Experiment("writer", "", WRITER.options, _writer, keeps_cells=True))
    out = str(tmp_path)
    assert run(["run", "writer", "--seeds", "3", "--out", out, "--set", "N=4"]) == 0
    assert capsys.readouterr().err == ""
    assert run(["run", "writer", "--seeds", "3", "--out", out, "--set", "N=5"]) == 0
    err = capsys.readouterr().err                      # allowed, and said once
    assert err == (f"jaxnc: note: {out} holds writer cells of other settings (N: 4 there, 5 here); they are kept "
                   f"beside this run's, and the summary files will describe this run\n")
    import json
    assert json.loads((tmp_path / "run.json").read_text())["settings"] == {"N": 5}


@pytest.mark.parametrize("make, fragment", [
    (lambda p: "", "--out must be a folder path, got ''"),
    (lambda p: "  ", "--out must be a folder path, got '"),       # (spaces: the line's are collapsed)
    (lambda p: (p.joinpath("f").write_text("x"), str(p / "f" / "sub"))[1], "--out: cannot create directory"),
    (lambda p: (p.joinpath("f").write_text("x"), str(p / "f"))[1], "--out: cannot create directory"),
])
def test_bad_out_is_refused_before_running(tmp_path, capsys, make, fragment):
    assert run(["run", "dummy", "--seeds", "2", "--out", make(tmp_path)]) == 2
    assert_one_line_error(capsys, fragment)
    assert CALLS == [] and not (tmp_path / "run.json").exists()


def _unwritable(tmp_path):
    """A folder that exists and cannot be written in, whoever runs the tests."""
    import os
    import pathlib
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        return d
    proc = pathlib.Path("/proc/self")                # root writes anywhere but in /proc
    if not proc.is_dir():
        pytest.skip("no unwritable folder for root here")
    return proc


def test_unwritable_out_fails_in_under_a_second_before_running(tmp_path, capsys):
    import time
    d = _unwritable(tmp_path)
    try:
        t0 = time.perf_counter()
        assert run(["run", "dummy", "--seeds", "2", "--out", str(d)]) == 2
        assert time.perf_counter() - t0 < 1.0
        assert_one_line_error(capsys, f"--out: cannot write in directory '{d}'")
        assert CALLS == []
    finally:
        if d.is_relative_to(tmp_path):
            d.chmod(0o755)


def test_an_incomplete_unsharded_sweep_exits_3(tmp_path, capsys):
    def sweep_run(settings, *, seeds, out, progress, shard=None):
        CALLS.append(shard)
        print("1 of 4 cells are missing")
        return {"complete": False, "missing": 1}

    ex.register(Experiment("gappy", "a sweep that ends with a cell missing", (), sweep_run, keeps_cells=True))
    assert run(["run", "gappy", "--out", str(tmp_path)]) == cli.INCOMPLETE == 3
    cap = capsys.readouterr()
    assert "1 of 4 cells are missing" in cap.out
    assert cap.err.strip().startswith("jaxnc: error: gappy ended with cells missing") and cap.err.count("\n") == 1
    # a shard that has done its share while others owe cells ends normally
    assert run(["run", "gappy", "--out", str(tmp_path), "--shard", "0/2"]) == 0
    # a complete sweep, or a run that returns no "complete", exits 0
    ex.register(Experiment("full", "", (), lambda s, *, seeds, out, progress, shard=None: {"complete": True}))
    assert run(["run", "full", "--out", str(tmp_path / "f")]) == 0


def test_no_cache_keeps_no_compiled_programs_beside_the_results(tmp_path, monkeypatch):
    import jax

    from jaxnc.cache import cache_beside

    def study(settings, *, seeds, out, progress):
        cache_beside(out)                     # as mecanum-grid and mecanum-validation do
        CALLS.append(jax.config.jax_compilation_cache_dir)
        return {}

    ex.register(Experiment("study", "", (), study))
    before = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", None)        # as in a fresh process
        assert run(["run", "study", "--no-cache", "--out", str(tmp_path / "a")]) == 0
        assert CALLS == [None] and jax.config.jax_compilation_cache_dir is None
        monkeypatch.setenv("JAXNC_CACHE_DIR", str(tmp_path / "xla"))
        assert run(["run", "study", "--out", str(tmp_path / "b")]) == 0      # the cache, in its own folder
        assert CALLS[-1] == str(tmp_path / "xla")
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
        from jaxnc.cache import allow_cache_beside
        allow_cache_beside(True)


@pytest.mark.parametrize("spec, fragment", [
    ("sys:exit", "'sys:exit' is a built-in function, not an Experiment"),
    ("os:getpid", "'os:getpid' is a built-in function, not an Experiment"),
])
def test_a_builtin_function_is_not_an_experiment(spec, fragment, tmp_path, capsys):
    assert run(["run", spec, "--out", str(tmp_path)]) == 2
    assert_one_line_error(capsys, fragment)


def test_startup_imports_no_design_or_plotting_library():
    """``import jaxnc`` and the built-in experiments' registry (what every ``jaxnc`` command
    and every worker process pays) import neither python-control, scipy.signal nor
    matplotlib: the design functions and figures import them when they are called."""
    import subprocess
    import sys
    code = ("import sys, jaxnc, jaxnc.schemes.diffdrive, jaxnc.schemes.hdd\n"
            "from jaxnc.experiment import load_builtin; load_builtin()\n"
            "print(sorted(m for m in ('control', 'scipy.signal', 'matplotlib') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout
