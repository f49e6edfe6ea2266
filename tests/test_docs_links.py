"""No document cites a file that is not in the repository.

The rule, for README.md, BENCHMARKS.md, CHANGELOG.md, every Markdown page under docs/ and
the Markdown cells of every notebook (notebooks/*.ipynb, whose pages the docs site shows):

* every relative Markdown link or image (``[text](path)``, ``![alt](path)``) resolves, from
  the page's folder, to a file or folder of the repository (or to a notebook's page,
  ``docs/notebooks/<name>.md``, which the docs build generates from
  ``notebooks/<name>.ipynb``), and none points into ``results/``;
* every path written in the text (``dir/name.ext``, with at least one folder, as in
  ``experiments/benchmarks/suite.py`` or ``figures/x.png``) exists, read from the repository root,
  from the page's folder or from ``optax_bilateral/`` (docs name ``_src/optimizer/step.py``);
* a path of *another* repository is cited as such: its paragraph names the repository
  (``github owner/name``, as docs/method.md cites the authors' code);
* paths under ``results/`` are what the experiments write (git-ignored): they are generated
  outputs, so they appear only as code (in backticks or a code block, next to the command
  that writes them), never as a link or as plain text.
"""

import json
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCUMENTS = sorted(
    [
        ROOT / "README.md",
        ROOT / "BENCHMARKS.md",
        ROOT / "CHANGELOG.md",
        *(ROOT / "docs").rglob("*.md"),
    ]
)
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
GENERATED = "results/"
EXTENSIONS = "py|md|ipynb|json|png|toml|txt|npz|yml|yaml|sh|js|csv"
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
PATH = re.compile(rf"(?<![\w/.<>*{{}}-])((?:[\w.-]+/)+[\w.-]+\.(?:{EXTENSIONS}))(?![\w/])")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
OTHER_REPOSITORY = re.compile(r"github [\w.-]+/[\w.-]+")


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


def _is_file(path: pathlib.Path) -> bool:
    """Whether ``path`` is in the repository, or is a notebook page the docs build generates."""
    path = path.resolve()
    if path.exists():
        return True
    page_of = path.parent == ROOT / "docs" / "notebooks" and path.suffix == ".md"
    return page_of and (ROOT / "notebooks" / f"{path.stem}.ipynb").exists()


def _exists(ref: str, page: pathlib.Path) -> bool:
    return any(_is_file(base / ref) for base in (ROOT, page.parent, ROOT / "optax_bilateral"))


def _external(ref: str, text: str) -> bool:
    """Whether every paragraph citing ``ref`` names the other repository it belongs to."""
    paragraphs = [p for p in re.split(r"\n\s*\n", text) if ref in p]
    return bool(paragraphs) and all(OTHER_REPOSITORY.search(p) for p in paragraphs)


def _links(text: str) -> list[str]:
    """Relative link targets outside code, without their #anchor."""
    prose = CODE_SPAN.sub("", FENCE.sub("", text))
    out = []
    for target in LINK.findall(prose):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL or an anchor on the same page
        out.append(target.split("#", 1)[0])
    return out


def test_every_document_is_checked():
    names = _ids(DOCUMENTS + NOTEBOOKS)
    assert {"README.md", "BENCHMARKS.md", "CHANGELOG.md", "docs/method.md"} <= set(names)
    assert {"notebooks/memoryless.ipynb", "notebooks/ablation.ipynb"} <= set(names)
    memoryless = _text(ROOT / "notebooks" / "memoryless.ipynb")
    assert memoryless.startswith("# Memoryless") and "import optax_bilateral" not in memoryless


def _text(page: pathlib.Path) -> str:
    """A document's Markdown: the file, or a notebook's Markdown cells."""
    if page.suffix != ".ipynb":
        return page.read_text()
    cells = json.loads(page.read_text())["cells"]
    return "\n\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")


@pytest.mark.parametrize("page", DOCUMENTS + NOTEBOOKS, ids=_ids(DOCUMENTS + NOTEBOOKS))
def test_links_resolve_to_repository_files(page):
    text = _text(page)
    missing = [t for t in _links(text) if not _is_file(page.parent / t)]
    generated = [
        t for t in _links(text) if (page.parent / t).resolve().is_relative_to(ROOT / "results")
    ]
    assert not missing, f"{page.name}: links to files that are not in the repository: {missing}"
    assert not generated, f"{page.name}: links to generated outputs (results/): {generated}"


@pytest.mark.parametrize("page", DOCUMENTS + NOTEBOOKS, ids=_ids(DOCUMENTS + NOTEBOOKS))
def test_cited_paths_exist_and_generated_ones_are_code(page):
    text = _text(page)
    cited = PATH.findall(text)
    missing = sorted(
        {
            p
            for p in cited
            if not p.startswith(GENERATED) and not _exists(p, page) and not _external(p, text)
        }
    )
    assert not missing, f"{page.name}: cites files that are not in the repository: {missing}"
    prose = CODE_SPAN.sub("", FENCE.sub("", text))
    bare = sorted({p for p in PATH.findall(prose) if p.startswith(GENERATED)})
    assert not bare, (
        f"{page.name}: generated outputs {bare} written as plain text or links; "
        "write them as code, next to the command that writes them"
    )


def test_the_rule_catches_what_it_should():
    page = ROOT / "docs" / "example.md"
    assert _links("see [x](missing.md) and [y](https://a.b/c) and [z](#here)") == ["missing.md"]
    assert _links("`[x](in-code.md)`") == []
    assert PATH.findall("run `experiments/benchmarks/suite.py`, see docs/x.md.") == [
        "experiments/benchmarks/suite.py",
        "docs/x.md",
    ]
    assert PATH.findall("`OUT/cache/<scene>/<family>.json` and `processes/*/m.json`") == []
    assert not _exists("experiments/no_such_file.py", page)
    assert _exists("notebooks/ablation.md", page) and not _exists("notebooks/no_such.md", page)
    assert _exists("_src/optimizer/step.py", page) and _exists("figures", page)
    assert _external("a/b.py", "The authors' code (github owner/repo, `a/b.py`).\n\nMore.")
    assert not _external("a/b.py", "Our `a/b.py`.\n\nThe authors' (github owner/repo).")


@pytest.mark.parametrize(
    "module, page",
    [
        ("optax_bilateral", "optax_bilateral.md"),
        ("optax_bilateral.triangle_mesh", "triangle_mesh.md"),
        ("optax_bilateral.mitsuba", "mitsuba.md"),
    ],
)
def test_api_pages_document_every_public_name(module, page):
    import importlib

    text = (ROOT / "docs" / "api" / page).read_text()
    documented = set(re.findall(rf"^::: {re.escape(module)}\.(\w+)$", text, re.M))
    public = set(importlib.import_module(module).__all__) - {
        "mesh",
        "triangle_mesh",
    }  # submodules: their own page
    assert documented == public, (sorted(public - documented), sorted(documented - public))
