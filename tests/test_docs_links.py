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
  that writes them), never as a link or as plain text;
* every module of ``experiments`` or ``tools`` they name (``python -m experiments.tuning``,
  ``experiments.tuning.scenes.RENDERED``, ``experiments.tuning:sure_factory``), and the
  Makefile's, is in the repository: ``python -m`` names a module or a package with a
  ``__main__``, and a name after the module is defined in it. A finished study's command
  stays only where its table row or paragraph says its script left the repository.
  CHANGELOG.md keeps the names of its time.
"""

import ast
import functools
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


MODULE = re.compile(r"(?<![\w./(-])(python -m )?((?:experiments|tools)(?:\.\w+)+)(?::(\w+))?")
FINISHED = re.compile(r"left the repository|git keeps it|kept at commit")


@functools.cache
def _defined(path: pathlib.Path) -> frozenset[str]:
    """The names a module defines or imports at its top level."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
    return frozenset(names)


def _module_problem(dotted: str, attr: str | None, run: bool) -> str | None:
    """Why ``dotted`` (``python -m`` if ``run``; ``:attr`` if given) names nothing of the
    repository, or None."""
    parts, path = dotted.split("."), ROOT / dotted.split(".")[0]
    i = 1
    while i < len(parts) and (
        (path / parts[i]).with_suffix(".py").is_file()
        or (path / parts[i] / "__init__.py").is_file()
    ):
        path, i = path / parts[i], i + 1
    if i == 1:
        return "no such module"
    file = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    rest = parts[i:] + ([attr] if attr else [])
    if run and (rest or (path.is_dir() and not (path / "__main__.py").is_file())):
        return "not a module python -m can run"
    if rest and rest[0] not in _defined(file):
        return f"{'.'.join(parts[:i])} defines no {rest[0]}"
    return None


def _scope(text: str, start: int) -> str:
    """The table row (a line starting with ``|``) or the paragraph holding ``text[start]``."""
    line_start = text.rfind("\n", 0, start) + 1
    line = text[line_start : text.find("\n", start) % (len(text) + 1)]
    if line.lstrip().startswith("|"):
        return line
    begin = text.rfind("\n\n", 0, start) + 1
    end = text.find("\n\n", start)
    return text[begin : end if end >= 0 else len(text)]


def _unknown_modules(text: str) -> list[str]:
    out = []
    for m in MODULE.finditer(text):
        run, dotted, attr = m.groups()
        if re.search(rf"\.(?:{EXTENSIONS})$", dotted):  # a file name, such as experiments.md
            continue
        problem = _module_problem(dotted, attr, bool(run))
        if problem and not FINISHED.search(_scope(text, m.start())):
            out.append(f"{m.group(0)}: {problem}")
    return out


@pytest.mark.parametrize(
    "page",
    [p for p in DOCUMENTS if p.name != "CHANGELOG.md"] + NOTEBOOKS + [ROOT / "Makefile"],
    ids=_ids([p for p in DOCUMENTS if p.name != "CHANGELOG.md"] + NOTEBOOKS + [ROOT / "Makefile"]),
)
def test_cited_experiments_and_tools_exist(page):
    unknown = _unknown_modules(_text(page))
    assert not unknown, f"{page.name}: names modules that are not in the repository: {unknown}"


def test_the_module_rule_catches_what_it_should():
    assert (
        _unknown_modules("`python -m experiments.tuning --quick`, `python -m tools.ab_update`")
        == []
    )
    assert (
        _unknown_modules("`experiments.tuning.scenes.RENDERED`, `experiments.tuning:sure_factory`")
        == []
    )
    assert _unknown_modules("[page](experiments.md), `experiments.benchmarks.suite.main`") == []
    assert _unknown_modules("`python -m experiments.paper`") == [
        "python -m experiments.paper: not a module python -m can run"
    ]
    assert _unknown_modules("`experiments.tuning:no_such`") == [
        "experiments.tuning:no_such: experiments.tuning defines no no_such"
    ]
    gone = "`python -m experiments.gone` (a study; its script left the repository)"
    assert _unknown_modules(gone) == []
    assert _unknown_modules("`python -m experiments.gone`") == [
        "python -m experiments.gone: no such module"
    ]
    row = "| a | `python -m experiments.gone`, left the repository |\n| b | `experiments.gone` |"
    assert _unknown_modules(row) == ["experiments.gone: no such module"]
