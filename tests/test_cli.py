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
