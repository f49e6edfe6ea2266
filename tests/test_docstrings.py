"""Every public callable documents each of its arguments and has an example that runs.

Public: the names in ``__all__`` of ``optax_bilateral``, ``optax_bilateral.triangle_mesh``
and ``optax_bilateral.mitsuba``, and every name of the toy renderers
(``optax_bilateral.toy.texture``, ``.volume``, ``.triangle_mesh``) that is defined there and
does not start with an underscore. For each callable (function or class):

* its docstring has an ``Example::`` section with at least one ``>>>`` line;
* every parameter of its signature is described in an ``Args:`` (or, for a state or a
  dataclass, ``Attributes:``) section;
* its examples run and print what they show (doctest): all of them in one child process,
  so that they share JAX's compilation caches, with XLA's backend optimisations off as in the
  whole suite (conftest.py; the examples use tiny shapes, so compiling is most of their cost).

The Mitsuba examples (those that import ``mitsuba`` or ``drjit``, or ask for the libLLVM)
need Mitsuba 3 and a libLLVM >= 16: where Mitsuba cannot be imported, or ``check_variant``
refuses the libLLVM (it renders nothing: an old libLLVM aborts the process that renders),
they are skipped with the reason; under CI they fail instead, as the other Mitsuba tests do.
"""

import doctest
import functools
import importlib
import inspect
import json
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
GROUPS = {
    "optax_bilateral": "__all__",
    "optax_bilateral.triangle_mesh": "__all__",
    "optax_bilateral.mitsuba": "__all__",
    "optax_bilateral.toy.texture": "defined",
    "optax_bilateral.toy.volume": "defined",
    "optax_bilateral.toy.triangle_mesh": "defined",
}
EXAMPLE = re.compile(r"^\s*Examples?::?\s*$", re.M)
SECTION = re.compile(r"^(Args|Attributes):\s*$", re.M)
NEEDS_MITSUBA = re.compile(r"\b(mitsuba|drjit) as\b|\bimport (mitsuba|drjit)\b|llvm_version\(")


def _public(module_name: str) -> list[tuple[str, object]]:
    module = importlib.import_module(module_name)
    if GROUPS[module_name] == "__all__":
        names = module.__all__
    else:
        names = [
            n
            for n, obj in vars(module).items()
            if not n.startswith("_") and getattr(obj, "__module__", None) == module_name
        ]
    out = []
    for name in names:
        obj = getattr(module, name)
        if callable(obj) and not inspect.ismodule(obj):
            out.append((f"{module_name}.{name}", obj))
    return out


PUBLIC = [item for module_name in GROUPS for item in _public(module_name)]
IDS = [name for name, _ in PUBLIC]


def _documented_args(doc: str) -> set[str]:
    """The names an ``Args:``/``Attributes:`` section describes (``a, b: ...`` gives both)."""
    names: set[str] = set()
    for match in SECTION.finditer(doc):
        for line in doc[match.end() :].splitlines()[1:]:
            if line and not line.startswith(" "):
                break  # the next section
            entry = re.match(r"^  (\*{0,2}\w+(?:, \*{0,2}\w+)*):", line)
            if entry:
                names.update(n.strip().lstrip("*") for n in entry.group(1).split(","))
    return names


def _parameters(obj) -> list[str]:
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return []
    return [n for n in sig.parameters if n not in ("self", "cls")]


@functools.lru_cache(maxsize=1)
def _mitsuba_unusable() -> str | None:
    """Why the Mitsuba examples cannot run here, or None. Renders nothing."""
    try:
        import mitsuba as mi

        from optax_bilateral.mitsuba import check_variant

        mi.set_variant("llvm_ad_rgb")
        check_variant()
    except (ImportError, RuntimeError, ValueError, AttributeError) as e:
        return f"{type(e).__name__}: {e}"
    return None


def test_every_group_has_public_callables():
    assert {name.rsplit(".", 1)[0] for name in IDS} == set(GROUPS)


@pytest.mark.parametrize("name, obj", PUBLIC, ids=IDS)
def test_docstring_documents_every_argument_and_has_an_example(name, obj):
    doc = inspect.getdoc(obj) or ""
    assert EXAMPLE.search(doc) and ">>>" in doc, f"{name}: no Example:: section with >>> lines"
    undocumented = [p for p in _parameters(obj) if p not in _documented_args(doc)]
    assert not undocumented, f"{name}: arguments missing from Args/Attributes: {undocumented}"


def test_the_argument_parser_reads_google_sections():
    doc = "Text.\n\nArgs:\n  a: one.\n    more.\n  b, c: two.\n  **kw: rest.\n\nReturns:\n  x: no."
    assert _documented_args(doc) == {"a", "b", "c", "kw"}


def run_examples() -> dict[str, str]:
    """Runs every public callable's examples in this process; ``{name: outcome}`` with outcome
    ``"ok"``, ``"skip: <reason>"`` (a Mitsuba example where Mitsuba is unusable) or the
    doctest report of the failure."""
    runner = doctest.DocTestRunner(
        optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False
    )
    finder = doctest.DocTestFinder(recurse=False, exclude_empty=False)
    outcomes = {}
    for name, obj in PUBLIC:
        module = importlib.import_module(name.rsplit(".", 1)[0])
        tests = [t for t in finder.find(obj, name, module=module, globs={}) if t.examples]
        if not tests:
            outcomes[name] = "no examples found"
            continue
        if any(NEEDS_MITSUBA.search(e.source) for t in tests for e in t.examples):
            reason = _mitsuba_unusable()
            if reason is not None:
                outcomes[name] = f"skip: {reason}"
                continue
        out: list[str] = []
        failed = sum(runner.run(t, out=out.append, clear_globs=True).failed for t in tests)
        outcomes[name] = "ok" if failed == 0 else "".join(out)
    return outcomes


@pytest.fixture(scope="module")
def example_outcomes() -> dict[str, str]:
    """All examples, run once in one child process (shared compilations; the XLA flags of
    conftest.py)."""
    run = subprocess.run(
        [sys.executable, __file__], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, f"the examples' process failed:\n{run.stderr[-3000:]}"
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("name", IDS)
def test_examples_run(name, example_outcomes):
    outcome = example_outcomes[name]
    if outcome.startswith("skip: "):
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the Mitsuba examples: {outcome[6:]}", pytrace=False)
        pytest.skip(f"this example needs a usable Mitsuba 3: {outcome[6:]}")
    assert outcome == "ok", f"{name}: example failed:\n{outcome}"


if __name__ == "__main__":
    print(json.dumps(run_examples()))
