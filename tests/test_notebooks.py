"""Every notebook in notebooks/ runs top to bottom in its quick mode (JAXNC_QUICK=1).

The code cells are executed in one namespace, parsed with the json module (no Jupyter
needed), with the Agg backend so figures are drawn but not shown. Notebooks whose quick
mode is not quick enough for the default suite are listed in SLOW and marked slow. (How
long a quick mode takes is measured, not asserted: `pytest --durations`.)
"""
import json
import pathlib

import matplotlib
import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parent.parent / "notebooks").glob("*.ipynb"))
SLOW: set[str] = set()


def run_notebook(path: pathlib.Path) -> dict:
    nb = json.loads(path.read_text())
    ns = {"__name__": "__main__"}
    for i, cell in enumerate(nb["cells"]):
        if cell["cell_type"] != "code":
            continue
        src = "".join(cell["source"])
        if src.lstrip().startswith(("%", "!")):
            continue
        exec(compile(src, f"{path.name}[cell {i}]", "exec"), ns)
    return ns


@pytest.mark.parametrize("path", [pytest.param(p, id=p.name, marks=[pytest.mark.slow] if p.name in SLOW else [])
                                  for p in NOTEBOOKS])
def test_notebook_runs_quick(path, monkeypatch):
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    monkeypatch.setenv("JAXNC_QUICK", "1")
    monkeypatch.setattr(plt, "show", lambda *a, **k: plt.close("all"))
    ns = run_notebook(path)
    assert ns, path
