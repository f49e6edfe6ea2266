"""The library's shape, as docs/design.md promises it: small functions, typed settings, one way
for imports to run, and no tunable changed behind the code's back."""

from __future__ import annotations

import ast
import inspect
import pathlib
import re
import sys
from collections.abc import Mapping

import optax_bilateral as ob
import optax_bilateral.triangle_mesh as obm

ROOT = pathlib.Path(__file__).resolve().parents[1]
SRC = ROOT / "optax_bilateral" / "_src"
MAX_LINES, MAX_PRIVATE_PARAMS, MAX_MODULE_LINES = 60, 8, 800

# Tests of the experiments, the notebooks, the docs and the benchmarks may import experiments;
# the library's own tests may not (they must survive any change of the experiments).
EXPERIMENT_TESTS = re.compile(
    r"(test_(experiment_\w+|benchmarks|mitsuba\w*|notebook\w*|docs_\w+|recipes_\w+|readme)|mitsuba_env)\.py$"
)
#: The measuring instruments under experiments/ that the library's tests use too: they import
#: JAX, NumPy and the standard library only (checked below), so no experiment reaches those tests.
INSTRUMENTS = ("experiments.benchmarks.compiles", "experiments.benchmarks.collectives")


def _functions():
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield path.relative_to(ROOT), node


def _body_lines(node) -> int:
    """Lines of a function's body, its docstring left out."""
    body = node.body
    docstring = (
        isinstance(body[0], ast.Expr)
        and isinstance(body[0].value, ast.Constant)
        and isinstance(body[0].value.value, str)
    )
    start = (body[1].lineno if len(body) > 1 else node.end_lineno) if docstring else body[0].lineno
    return node.end_lineno - start + 1


def _arity(node) -> int:
    a = node.args
    n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
    return n - (1 if a.args and a.args[0].arg in ("self", "cls") else 0)


def test_no_library_function_is_longer_than_60_lines():
    long = [
        f"{path}:{node.lineno} {node.name} ({_body_lines(node)} lines)"
        for path, node in _functions()
        if _body_lines(node) > MAX_LINES
    ]
    assert not long, long


def test_no_private_library_function_takes_more_than_8_parameters():
    wide = [
        f"{path}:{node.lineno} {node.name} ({_arity(node)} parameters)"
        for path, node in _functions()
        if node.name.startswith("_") and not node.name.startswith("__")
        if _arity(node) > MAX_PRIVATE_PARAMS
    ]
    assert not wide, wide


def test_bilateral_adam_takes_at_most_ten_parameters_with_precise_types():
    sig = inspect.signature(ob.bilateral_adam)
    named = [p for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD]
    assert len(named) <= 10, [p.name for p in named]
    for fn in (ob.bilateral_adam, ob.postfilter, ob.prefilter):
        params = inspect.signature(fn).parameters
        for name in ("sigma_d", "levels"):
            annotation = str(params[name].annotation)
            assert annotation in ("SigmaSetting", "LevelsSetting"), (fn.__name__, annotation)


def test_mesh_functions_take_at_most_ten_named_parameters():
    """More settings than that are objects (``NormalFilter``, ``CG``); 0.1.0's keywords pass
    through ``**deprecated``."""
    wide = {}
    for name in obm.__all__:
        if inspect.isfunction(fn := getattr(obm, name)):
            params = inspect.signature(fn).parameters.values()
            wide[name] = len([p for p in params if p.kind is not p.VAR_KEYWORD])
    assert "bilateral_large_steps" in wide and "mesh_postfilter" in wide
    assert {name: n for name, n in wide.items() if n > 10} == {}


def test_no_mesh_module_is_longer_than_800_lines():
    long = {
        path.name: n
        for path in sorted((SRC / "mesh").glob("*.py"))
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not long, long


def test_no_test_or_experiment_changes_a_library_constant():
    """Tunables are fields of rule objects (``ob.auto_sigma(check_period=4)``); assigning a
    module attribute of the library (``auto.CHECK_PERIOD = 1``) would change every optimizer
    built afterwards, and a compiled program would not see it."""
    assignment = re.compile(r"^\s*(auto|sure|step|transforms|leaves|numerics)\.\w+\s*=[^=]", re.M)
    setter = re.compile(r"(monkeypatch\.setattr|setattr)\((auto|sure|step|optax_bilateral\._src)")
    found = []
    for folder in ("tests", "experiments", "tools", "notebooks"):
        for path in (ROOT / folder).rglob("*.py"):
            text = path.read_text()
            if assignment.search(text) or setter.search(text):
                found.append(str(path.relative_to(ROOT)))
    assert not found, found


def _modules(*folders: str) -> dict[str, pathlib.Path]:
    """Dotted name -> file of every module under ``folders`` (a package's is its ``__init__``)."""
    out = {}
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(path: pathlib.Path, modules: Mapping[str, pathlib.Path]) -> set[str]:
    """The modules ``path`` imports anywhere (inside functions too), as dotted names:
    ``from a.b import c`` names ``a.b.c`` where that is one of ``modules``, else ``a.b``."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    package = parts if parts[-1] == "__init__" else parts[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else ()
            module = ".".join([*base, *([node.module] if node.module else [])])
            for a in node.names:
                found.add(f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module)
    return found


def test_library_tests_import_no_experiment_but_its_instruments():
    """The library's tests must survive any change of the experiments; the instruments they
    share with the benchmarks (compile counting, HLO collectives) are the one exception."""
    modules = _modules("experiments")
    found = {
        path.name: sorted(bad)
        for path in sorted((ROOT / "tests").glob("*.py"))
        if not EXPERIMENT_TESTS.search(path.name)
        if (bad := {m for m in _imports(path, modules) if m.split(".")[0] == "experiments"})
        - set(INSTRUMENTS)
    }
    assert not found, found


def test_the_instruments_import_only_jax_numpy_and_the_standard_library():
    allowed = {"jax", "numpy", *sys.stdlib_module_names}
    modules = _modules("experiments")
    found = {
        name: sorted(bad)
        for name in INSTRUMENTS
        if (bad := {m for m in _imports(modules[name], modules) if m.split(".")[0] not in allowed})
    }
    assert not found, found


def test_no_experiment_imports_tools():
    """``tools/`` may import the experiments; the experiments never import ``tools/``."""
    modules = _modules("experiments")
    found = {
        name: sorted(m for m in _imports(path, modules) if m.split(".")[0] == "tools")
        for name, path in modules.items()
    }
    found = {k: v for k, v in found.items() if v}
    assert not found, found


def _cycle(graph: Mapping[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (module -> the modules it imports), or None."""
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> list[str] | None:
        if node in path:
            return path[path.index(node) :] + [node]
        if node in done:
            return None
        for nxt in sorted(graph[node]):
            if cycle := visit(nxt, [*path, node]):
                return cycle
        done.add(node)
        return None

    return next((c for node in sorted(graph) if (c := visit(node, []))), None)


def test_no_import_cycle_among_the_experiments_and_tools():
    """Read from every ``import`` (a function's too): a module imported lazily to dodge a
    cycle is still a cycle. Importing a package's module does not count as importing the
    package's ``__init__``."""
    modules = _modules("experiments", "tools")
    graph = {
        name: (_imports(path, modules) & set(modules)) - {name} for name, path in modules.items()
    }
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_the_cycle_check_finds_a_cycle_and_passes_a_chain():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_library_imports_neither_experiments_nor_tools():
    imports = re.compile(r"^\s*(from|import) (experiments|tools|tests)\b", re.M)
    found = [
        str(p) for p in (ROOT / "optax_bilateral").rglob("*.py") if imports.search(p.read_text())
    ]
    assert not found, found


# The layers of ``_src``, lowest first (docs/design.md, "Each module's one job"): a module
# imports its own group and the groups of lower layers, never one above or beside it.
LAYERS = {
    "validation": 0,
    "extension": 0,
    "numerics": 1,
    "filter": 2,
    "rules": 3,
    "optimizer": 4,
    "mesh": 5,
    "mitsuba": 5,
}
# The filter's kernels are its own: the layers above reach them through these modules.
FILTER_FACE = {"front", "operators", "layout", "bilateral", "local"}


def _is_module(dotted: str) -> bool:
    path = ROOT.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _library_imports(path: pathlib.Path):
    """The modules of ``optax_bilateral`` that ``path`` imports, as dotted names (``from a
    import b`` names ``a.b`` where that is a module, else ``a``)."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("optax_bilateral"):
            for alias in node.names:
                name = f"{node.module}.{alias.name}"
                yield name if _is_module(name) else node.module
        elif isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.startswith("optax_bilateral"))


def _place(module: str) -> tuple[str | None, str | None]:
    """``(group, module in the group)`` of a module of ``_src``, e.g. ``("rules", "auto")``;
    ``(None, None)`` outside ``_src`` (the package face)."""
    parts = module.split(".")
    if len(parts) < 3 or parts[1] != "_src":
        return None, None
    return parts[2], (parts[3] if len(parts) > 3 else None)


def test_imports_run_down_the_layers_of_src():
    wrong = []
    for path in sorted(SRC.rglob("*.py")):
        here, _ = _place(".".join(path.relative_to(ROOT).with_suffix("").parts))
        for name in sorted(set(_library_imports(path))):
            there, module = _place(name)
            where = f"{path.relative_to(ROOT)} imports {name}"
            if there is None:
                wrong.append(f"{where}: the package face")
            elif there != here and LAYERS[there] >= LAYERS[here]:
                wrong.append(f"{where}: layer {there} is not below {here}")
            elif there == "filter" != here and module not in FILTER_FACE:
                wrong.append(f"{where}: a kernel of the filter, past its face")
    assert not wrong, wrong


# The rules and the one module that maps shorthands to them; elsewhere a rule is a SigmaRule.
RULE_MODULES = {
    "rules/fixed.py",
    "rules/auto.py",
    "rules/sure.py",
    "rules/sparse.py",
    "rules/registry.py",
}
RULE_NAMES = {
    "Fixed",
    "Auto",
    "Sure",
    "Sparse",
    "AutoState",
    "SureState",
    "SparseState",
    "SURE_LEVELS",
    "auto",
    "sure",
}


def _docstrings(tree) -> set[int]:
    """The ids of the docstring nodes of a module and its classes and functions."""
    kinds = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    return {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, kinds) and node.body and isinstance(node.body[0], ast.Expr)
    }


def test_no_module_outside_the_rules_names_a_particular_rule():
    """Whatever a rule needs (its default levels, the transforms it can run in, its state)
    is declared on the rule (``SigmaRule.default_levels``, ``SigmaRule.check``), so a new
    rule needs no change elsewhere."""
    found = []
    for path in sorted(SRC.rglob("*.py")):
        if path.relative_to(SRC).as_posix() in RULE_MODULES:
            continue
        tree = ast.parse(path.read_text())
        docs = _docstrings(tree)
        for node in ast.walk(tree):
            named = (
                (isinstance(node, ast.Name) and node.id in RULE_NAMES)
                or (isinstance(node, ast.Attribute) and node.attr in RULE_NAMES)
                or (isinstance(node, ast.alias) and node.name.split(".")[-1] in RULE_NAMES)
                # (the filter's "auto" is its kernel's; the filter cannot import a rule)
                or (
                    (isinstance(node, ast.Constant) and node.value in ("auto", "sure", "sparse"))
                    and path.parent.name != "filter"
                )
            )
            if named and id(node) not in docs:
                found.append(f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', '?')}")
    assert not found, found
