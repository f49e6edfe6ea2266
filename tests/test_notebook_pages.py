"""The docs site's notebook pages: each notebook with the outputs of one recorded run.

``notebooks/outputs/NAME.json`` (and the PNGs beside it) hold the outputs of one executed
run; ``build_notebooks.page`` merges them with the stripped notebook in git, and the mkdocs
hook (docs/notebook_pages.py) adds the pages to the site. These tests read files only.
"""

import base64
import importlib.util
import json
import pathlib
import re

import nbformat
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"


def _load(name: str, path: pathlib.Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


build_notebooks = _load("build_notebooks", NOTEBOOKS / "build_notebooks.py")
FIGURES = _load("test_notebooks_figures", ROOT / "tests" / "test_notebooks.py").FIGURES
# A PNG 1x1 pixel, for the recording test.
PIXEL = base64.b64encode(
    bytes.fromhex(
        "89504e470d0a1a0a0000000d4948445200000001000000010806000000"
        "1f15c4890000000d49444154789c6360f8cfc0f01f0005000201a5d1e1f20000000049454e44ae426082"
    )
).decode()


@pytest.mark.parametrize("name", build_notebooks.NAMES)
def test_recorded_outputs_belong_to_the_notebook_in_git(name):
    rec = build_notebooks.load_record(name)  # raises if the code cells changed since
    assert rec["notebook"] == name and rec["size"] in ("full", "quick")


@pytest.mark.parametrize("name", build_notebooks.NAMES)
def test_page_shows_every_cell_and_every_figure(name):
    text = build_notebooks.page(name)
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    for cell in nb.cells:
        assert cell.source in text, f"{name}: cell {cell.id} is missing from its page"
    shown = re.findall(rf"!\[[^\]]*\]\({name}/([\w.-]+\.png)\)", text)
    stored = sorted(p.name for p in (build_notebooks.OUTPUTS / name).glob("*.png"))
    assert sorted(shown) == stored, "every recorded figure shown once, and no stale PNG"
    assert len(shown) >= len(FIGURES[name]), f"{name}: fewer figures than the notebook saves"
    for png in stored:
        size = (build_notebooks.OUTPUTS / name / png).stat().st_size
        assert size <= build_notebooks.PNG_BUDGET, f"{png}: {size} bytes; figures must stay small"
    assert "Recorded outputs" in text and "/work/" not in text


def test_a_changed_notebook_refuses_its_old_record(monkeypatch, tmp_path):
    name = build_notebooks.NAMES[0]
    rec = json.loads((build_notebooks.OUTPUTS / f"{name}.json").read_text())
    rec["cells"][0]["source_sha256"] = "0" * 16
    (tmp_path / f"{name}.json").write_text(json.dumps(rec))
    monkeypatch.setattr(build_notebooks, "OUTPUTS", tmp_path)
    with pytest.raises(ValueError, match=rf"changed: \[0\].*--execute {name} --record {name}"):
        build_notebooks.page(name)


def test_record_keeps_stdout_markdown_and_figures(monkeypatch, tmp_path):
    nb = nbformat.v4.new_notebook()
    cell = nbformat.v4.new_code_cell("print('x')")
    cell.outputs = [
        nbformat.v4.new_output("stream", name="stdout", text=f"{ROOT}/results/a.png\n"),
        nbformat.v4.new_output("stream", name="stderr", text="progress 50%\r"),
        nbformat.v4.new_output("display_data", data={"text/markdown": "| a |\n|---|"}),
        nbformat.v4.new_output("display_data", data={"image/png": PIXEL, "text/plain": "<F>"}),
    ]
    nb.cells = [nbformat.v4.new_markdown_cell("# T"), cell]
    executed = tmp_path / "executed.ipynb"
    nbformat.write(nb, executed)
    monkeypatch.setattr(build_notebooks, "executed_path", lambda name, quick: executed)
    monkeypatch.setattr(build_notebooks, "OUTPUTS", tmp_path / "outputs")
    rec = json.loads(build_notebooks.record("t", quick=True).read_text())
    assert rec["size"] == "quick"
    assert rec["cells"] == [
        {
            "source_sha256": build_notebooks.source_hash("print('x')"),
            "outputs": [
                {"text": "results/a.png\n"},
                {"markdown": "| a |\n|---|"},
                {"image": "t-00-2.png"},
            ],
        }
    ]
    assert (tmp_path / "outputs" / "t" / "t-00-2.png").read_bytes().startswith(b"\x89PNG")
