"""``jaxnc run MODULE:ATTR``: an experiment defined in the user's own module (not registered).

The user modules are written into ``tmp_path``, which becomes the working directory; the
current directory is taken off ``sys.path`` first, so the import only works because
:func:`jaxnc.experiment.resolve_experiment` puts it there.  The user experiment is trivial (no
jax compilation): its run writes ``results.json`` with :func:`jaxnc.montecarlo.save_results`.
"""
import json
import os
import pathlib
import subprocess
import sys

import pytest

from jaxnc import cli
from jaxnc import experiment as ex
from jaxnc.experiment import ConfigError, Experiment
from tests.test_cli import assert_one_line_error

USER_MODULE = '''
import types

from jaxnc.experiment import ConfigError, Experiment, Option

OPTIONS = (
    Option("gain", "float", 1.0, "a gain", low=0.0, high=10.0),
    Option("mode", "choice", "a", "a mode", choices=("a", "b")),
)


def _runner(name):
    def run(settings, *, seeds, out, progress):
        from jaxnc import montecarlo
        results = {"total": settings["gain"] * seeds, "mode": settings["mode"], "progress": progress}
        montecarlo.save_results(out / "results.json", experiment=name, config=dict(settings, seeds=seeds),
                                results=results, wall_time_s=0.0)
        print(f"{name} ran")
        return results
    return run


experiment = Experiment("user-study", "an experiment in a user module", OPTIONS, _runner("user-study"))
studies = types.SimpleNamespace(main=experiment)
NOT_AN_EXPERIMENT = 42


def make():
    return Experiment("user-made", "built by a factory", OPTIONS, _runner("user-made"))


def make_nothing():
    return None


def make_with(n):
    return experiment


def strict():
    raise ConfigError("strict needs mode=b")


def quits():
    import sys
    sys.exit(0)
'''

NESTED_MODULE = '''
from jaxnc.experiment import Experiment
from mymod import OPTIONS, _runner

CODES = []


def run(settings, *, seeds, out, progress):
    from jaxnc import cli
    if settings["mode"] == "a":       # while this run runs, a second one into the same folder
        CODES.append(cli.run_cli(["run", "nested:experiment", "--seeds", str(seeds), "--out", str(out),
                                  "--set", "mode=b", "--no-progress"]))
    return _runner("nested")(settings, seeds=seeds, out=out, progress=progress)


experiment = Experiment("nested", "starts a second run into its own folder", OPTIONS, run)
'''

MODULES = {
    "mymod": USER_MODULE,
    "nested": NESTED_MODULE,
    "noexp": "X = 1\n",
    "brokendep": "import no_such_dependency_xyz\n",
    "badname": "from json import no_such_name\n",
    "userpkg/__init__.py": "",
    "userpkg/study.py": "from mymod import experiment\n",
}
NAMES = {"mymod", "nested", "noexp", "brokendep", "badname", "userpkg", "no_such_dependency_xyz"}


@pytest.fixture(autouse=True)
def user_dir(tmp_path, monkeypatch):
    """tmp_path holds the user modules and is the cwd, but not on sys.path; empty registry."""
    for rel, text in MODULES.items():
        path = tmp_path / (rel if rel.endswith(".py") else rel + ".py")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    monkeypatch.chdir(tmp_path)
    cwd_aliases = {"", ".", str(tmp_path), os.getcwd()}
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in cwd_aliases])
    monkeypatch.setattr(ex, "REGISTRY", {})
    monkeypatch.setattr(ex, "load_builtin", lambda: None)
    yield tmp_path
    for name in list(sys.modules):
        if name.split(".")[0] in NAMES:
            del sys.modules[name]


def load(path):
    doc = json.loads(pathlib.Path(path).read_text())
    return doc["experiment"], doc["config"], doc["results"]


# ----------------------------------------------------------------------------- runs


def test_runs_user_experiment(user_dir, capsys):
    out = user_dir / "o"
    assert str(user_dir) not in sys.path
    code = cli.run_cli(["run", "mymod:experiment", "--seeds", "3", "--out", str(out),
                        "--set", "gain=2.5", "mode=b", "--no-progress"])
    assert code == 0
    assert "user-study ran" in capsys.readouterr().out
    name, config, results = load(out / "results.json")
    assert name == "user-study"
    assert config == {"gain": 2.5, "mode": "b", "seeds": 3}
    assert results == {"total": 7.5, "mode": "b", "progress": False}
    assert sys.path[0] == str(user_dir)                  # the cwd was put in front
    assert "user-study" not in ex.REGISTRY               # nothing is registered


def test_a_second_run_into_a_folder_being_written_is_refused(user_dir, capsys):
    # both used to pass the folder's claim (no results.json yet) and the later one's files
    # replaced, or mixed with, the other's, both exiting 0
    out = user_dir / "o"
    assert cli.run_cli(["run", "nested:experiment", "--seeds", "3", "--out", str(out), "--no-progress"]) == 0
    import nested
    assert nested.CODES == [2]
    err = capsys.readouterr().err
    assert "--out" in err and "is being written by another jaxnc run" in err, err
    _, config, _ = load(out / "results.json")
    assert config == {"gain": 1.0, "mode": "a", "seeds": 3}
    # the lock ends with the run: the same command again runs
    assert cli.run_cli(["run", "mymod:experiment", "--seeds", "3", "--out", str(user_dir / "p"), "--no-progress"]) == 0
    assert cli.run_cli(["run", "mymod:experiment", "--seeds", "3", "--out", str(user_dir / "p"), "--no-progress"]) == 0


def test_default_out_and_settings(user_dir):
    assert cli.run_cli(["run", "mymod:experiment", "--seeds", "2"]) == 0
    _, config, results = load(user_dir / "results" / "user-study" / "results.json")
    assert config == {"gain": 1.0, "mode": "a", "seeds": 2}
    assert results["progress"] is True


def test_factory_and_dotted_attribute(user_dir):
    assert cli.run_cli(["run", "mymod:make", "--seeds", "4", "--no-progress", "--set", "MODE=B"]) == 0
    name, config, _ = load(user_dir / "results" / "user-made" / "results.json")
    assert name == "user-made" and config["mode"] == "b" and config["seeds"] == 4
    assert cli.run_cli(["run", "mymod:studies.main", "--out", "d", "--seeds", "1", "--no-progress"]) == 0
    assert load(user_dir / "d" / "results.json")[0] == "user-study"
    assert cli.run_cli(["run", "userpkg.study:experiment", "--out", "p", "--seeds", "1",
                        "--no-progress"]) == 0
    assert (user_dir / "p" / "results.json").is_file()


def test_resolve_experiment_api(user_dir):
    exp = ex.resolve_experiment("mymod:experiment")
    assert isinstance(exp, Experiment) and exp.name == "user-study"
    assert ex.get_experiment("mymod:make").name == "user-made"
    assert ex.resolve_experiment(" mymod : studies.main ") is exp
    with pytest.raises(ConfigError, match="unknown experiment 'nope'; available: \\(none\\)"):
        ex.resolve_experiment("nope")


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("pairs, fragments", [
    (["gain=11"], ["gain must be a number in [0, 10], got '11'"]),
    (["mode=c"], ["mode must be one of a, b, got 'c'"]),
    (["foo=1"], ["unknown setting 'foo' for experiment 'user-study'", "valid keys: gain, mode"]),
])
def test_set_validation_applies(user_dir, capsys, pairs, fragments):
    assert cli.run_cli(["run", "mymod:experiment", "--out", "o", "--set", *pairs]) == 2
    assert_one_line_error(capsys, *fragments)
    assert not (user_dir / "o").exists()


@pytest.mark.parametrize("spec, fragments", [
    (":experiment", ["experiment ':experiment' has an empty module name; expected MODULE:ATTR"]),
    ("mymod:", ["experiment 'mymod:' has an empty attribute name; expected MODULE:ATTR"]),
    (":", ["empty module name"]),
    ("nosuchmod:experiment", ["no module named 'nosuchmod'", "experiment 'nosuchmod:experiment'"]),
    ("nopkg.sub:experiment", ["no module named 'nopkg'"]),
    ("userpkg.missing:experiment", ["no module named 'userpkg.missing'"]),
    ("mymod.py:experiment", ["no module named 'mymod.py'", "not a file name"]),
    (".mymod:experiment", ["module '.mymod' is relative"]),
    ("brokendep:experiment", ["module 'brokendep' failed to import: ModuleNotFoundError: "
                              "No module named 'no_such_dependency_xyz'"]),
    ("badname:experiment", ["module 'badname' failed to import: ImportError: cannot import name "
                            "'no_such_name'"]),
    ("mymod:experimnt", ["module 'mymod' has no attribute 'experimnt'",
                         "Experiment objects in it: experiment"]),
    ("mymod:studies.other", ["module 'mymod' has no attribute 'studies.other'"]),
    ("noexp:experiment", ["module 'noexp' has no attribute 'experiment'; it has no Experiment objects"]),
    ("mymod:NOT_AN_EXPERIMENT", ["'mymod:NOT_AN_EXPERIMENT' is of type int, not an Experiment"]),
    ("mymod:OPTIONS", ["'mymod:OPTIONS' is of type tuple, not an Experiment"]),
    ("mymod:make_nothing", ["'mymod:make_nothing' returned NoneType, not an Experiment"]),
    ("mymod:make_with", ["'mymod:make_with' is a callable that needs arguments (n)"]),
    ("mymod:Experiment", ["'mymod:Experiment' is a callable that needs arguments (name,"]),
    ("mymod:strict", ["strict needs mode=b"]),                 # a ConfigError from the factory
    ("mymod:quits", ["'mymod:quits' exited (SystemExit(0)) when called, instead of returning an Experiment"]),
    ("sys:exit", ["'sys:exit' is a built-in function, not an Experiment"]),     # exited 0, silently
])
def test_bad_specs_exit_2_one_line(user_dir, capsys, spec, fragments):
    assert cli.run_cli(["run", spec, "--out", "o"]) == 2
    assert_one_line_error(capsys, *fragments)
    assert not (user_dir / "o").exists()


def test_unknown_registered_name_mentions_module_form(capsys):
    assert cli.run_cli(["run", "nope"]) == 2
    assert_one_line_error(capsys, "unknown experiment 'nope'", "MODULE:ATTR")


def test_help_mentions_module_attr(capsys):
    with pytest.raises(SystemExit) as e:
        cli.run_cli(["run", "--help"])
    assert e.value.code == 0
    assert "MODULE:ATTR" in " ".join(capsys.readouterr().out.split())
    assert "MODULE:ATTR" in cli.__doc__


# ----------------------------------------------------------------------------- console script


def test_console_script_finds_module_in_cwd(user_dir):
    jaxnc = pathlib.Path(sys.executable).parent / "jaxnc"
    if not jaxnc.exists():
        pytest.skip(f"console script not installed next to {sys.executable}")
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("PYTHONPATH", None)
    proc = subprocess.run([str(jaxnc), "run", "mymod:experiment", "--seeds", "5", "--out", "cs",
                           "--set", "gain=0.5", "--no-progress"],
                          cwd=user_dir, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "user-study ran" in proc.stdout
    _, config, results = load(user_dir / "cs" / "results.json")
    assert config == {"gain": 0.5, "mode": "a", "seeds": 5} and results["total"] == 2.5
    proc = subprocess.run([str(jaxnc), "run", "mymod:nothing", "--out", "cs2"],
                          cwd=user_dir, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "jaxnc: error: module 'mymod' has no attribute 'nothing'; Experiment objects in it: experiment"]
