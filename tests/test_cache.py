"""The persistent compilation cache switch of the command line (jaxnc.cache)."""
import jax

from jaxnc import cache
from jaxnc.cli import run_cli


def test_cache_dir_option_turns_the_cache_on_there_and_bad_dirs_are_one_line_errors(tmp_path, capsys, monkeypatch):
    before = jax.config.jax_compilation_cache_dir
    try:
        d = tmp_path / "xla"
        monkeypatch.chdir(tmp_path)          # a trivial user experiment: the cache is set up before it runs
        (tmp_path / "tinyexp.py").write_text(
            "from jaxnc.experiment import Experiment\n"
            "experiment = Experiment(name='tiny', description='t', options=(), run=lambda s, **k: {})\n")
        assert run_cli(["run", "tinyexp:experiment", "--seeds", "1", "--out", str(tmp_path / "o"),
                        "--cache-dir", str(d)]) == 0
        assert d.is_dir() and jax.config.jax_compilation_cache_dir == str(d)
        blocker = tmp_path / "file"
        blocker.write_text("x")
        assert run_cli(["run", "tinyexp:experiment", "--seeds", "1", "--out", str(tmp_path / "o"),
                        "--cache-dir", str(blocker / "sub")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("jaxnc: error: --cache-dir: cannot create directory")
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def test_default_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXNC_CACHE_DIR", str(tmp_path / "c"))
    assert cache.default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("JAXNC_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert cache.default_cache_dir() == tmp_path / "x" / "jaxnc" / "xla"


def test_compile_clock_counts_a_fresh_program_once():
    import jax.numpy as jnp
    x, y = jnp.ones(3), jnp.zeros(3)
    c0 = cache.compile_clock()
    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + x)
    f(x).block_until_ready()
    c1 = cache.compile_clock()
    f(y).block_until_ready()                          # the same shapes: no new compilation
    c2 = cache.compile_clock()
    assert (c1 - c0).compilations >= 1 and (c1 - c0).seconds > 0
    assert (c2 - c1).compilations == 0
