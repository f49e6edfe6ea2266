"""The notebooks: stripped in git, in sync with their sources, and they run at the quick size.

Each notebook is executed with nbclient in a fresh kernel whose working directory
is ``notebooks/`` (as Jupyter would), with ``OPTAX_BILATERAL_QUICK=1``.
A notebook fails the test if any cell raises, including the checks written into
the notebooks themselves (the memoryless postfilter equals ``B g / sqrt(B g^2)``
and keeps no buffers; the jointly filtered steps respect the bound of supplement
§1.3), and if it does not save its figures.
"""

import importlib.util
import pathlib
import time

import nbformat
import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"


def _load_builder():
    """``notebooks/build_notebooks.py`` is a script, not a package module: load it by path."""
    spec = importlib.util.spec_from_file_location(
        "build_notebooks", NOTEBOOKS / "build_notebooks.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


build_notebooks = _load_builder()

# Figures each notebook must write (results/notebooks/ at full size, .../quick/ at the quick size).
FIGURES = {
    "memoryless": ["memoryless_curves", "memoryless_textures", "memoryless_eq24"],
    "pre_vs_post": ["pre_vs_post_curves", "pre_vs_post_textures", "pre_vs_post_bound"],
    "ablation": [
        "ablation_grid_camera",
        "ablation_noise_target",
        "ablation_low_noise_noise_target",
        "ablation_low_noise_camera_target",
        "ablation_schedule",
    ],
}


def test_every_notebook_has_a_source_and_a_figure_list():
    assert set(build_notebooks.NAMES) == set(FIGURES)
    assert {p.stem for p in NOTEBOOKS.glob("*.ipynb")} == set(build_notebooks.NAMES)


@pytest.mark.parametrize("name", build_notebooks.NAMES)
def test_notebook_in_git_is_stripped_and_matches_its_source(name):
    path = NOTEBOOKS / f"{name}.ipynb"
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None, (
                f"{name}: cell {cell.get('id')} has outputs; rebuild with "
                "python notebooks/build_notebooks.py"
            )
    assert path.read_text() == build_notebooks.dumps(build_notebooks.build(name)), (
        f"{name}.ipynb differs from notebooks/src/{name}.py; "
        "run python notebooks/build_notebooks.py"
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", build_notebooks.NAMES)
def test_notebook_runs_at_the_quick_size(name, monkeypatch):
    from nbclient import NotebookClient

    monkeypatch.setenv("OPTAX_BILATERAL_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    start = time.time()
    NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    ).execute()
    out = NOTEBOOKS.parent / "results" / "notebooks" / "quick"  # full-size figures stay untouched
    for fig in FIGURES[name]:
        png = out / f"{fig}.png"
        assert png.exists() and png.stat().st_mtime >= start - 1, f"{name} did not save {png}"
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "quick=True" in text, f"{name} did not run at the quick size"
