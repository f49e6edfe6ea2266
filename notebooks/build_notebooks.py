"""Builds ``notebooks/*.ipynb`` (outputs stripped) from the sources in ``notebooks/src/``, or
runs them.

    python notebooks/build_notebooks.py                 # write every notebook from its source
    python notebooks/build_notebooks.py --check         # exit 1 if a notebook and its source
                                                        # differ
    python notebooks/build_notebooks.py --execute NAME  # run notebooks/NAME.ipynb; the executed
                                                        # copy goes to results/notebooks/NAME.ipynb
                                                        # (results/notebooks/quick/ when quick)

A source ``notebooks/src/NAME.py`` is plain Python split into cells by marker
lines: ``# %%`` starts a code cell, ``# %% [markdown]`` a markdown cell whose
lines all start with ``#`` (the ``# `` prefix is removed). The notebooks in git
therefore never hold outputs, and a diff of a notebook is a diff of its source.
Set ``OPTAX_BILATERAL_QUICK=1`` for the test-suite size.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

import nbformat

HERE = pathlib.Path(__file__).resolve().parent
SRC = HERE / "src"
NAMES = ("memoryless", "pre_vs_post", "ablation")
KERNEL = {"display_name": "Python 3 (ipykernel)", "language": "python", "name": "python3"}


def parse_source(text: str) -> list[tuple[str, str]]:
    """``[(kind, source)]`` with kind ``"code"`` or ``"markdown"``, in order."""
    cells: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped == "# %% [markdown]":
            cells.append(("markdown", []))
        elif stripped == "# %%":
            cells.append(("code", []))
        elif not cells:
            if stripped:
                raise ValueError(f"text before the first cell marker: {line!r}")
        else:
            kind, lines = cells[-1]
            if kind == "markdown":
                if stripped and not line.startswith("#"):
                    raise ValueError(f"markdown lines must start with '#', got {line!r}")
                line = line[2:] if line.startswith("# ") else line[1:]
            lines.append(line)
    out = []
    for kind, lines in cells:
        while lines and not lines[-1].strip():
            lines.pop()
        while lines and not lines[0].strip():
            lines.pop(0)
        if lines:
            out.append((kind, "\n".join(lines)))
    return out


def build(name: str) -> nbformat.NotebookNode:
    """The notebook ``name`` from ``src/name.py``, without outputs, with stable cell ids."""
    cells = []
    for i, (kind, source) in enumerate(parse_source((SRC / f"{name}.py").read_text())):
        make = nbformat.v4.new_markdown_cell if kind == "markdown" else nbformat.v4.new_code_cell
        cell = make(source)
        cell["id"] = f"{name}-{i:02d}"
        cells.append(cell)
    nb = nbformat.v4.new_notebook(cells=cells)
    nb.metadata["kernelspec"] = dict(KERNEL)
    nb.metadata["language_info"] = {"name": "python"}
    nbformat.validate(nb)
    return nb


def dumps(nb: nbformat.NotebookNode) -> str:
    return nbformat.writes(nb) + "\n"


def execute(name: str, timeout: int = 7200) -> pathlib.Path:
    """Runs ``notebooks/name.ipynb`` with its working directory ``notebooks/``; returns the
    executed copy."""
    from nbclient import NotebookClient

    nb = nbformat.read(HERE / f"{name}.ipynb", as_version=4)
    t0 = time.perf_counter()
    NotebookClient(
        nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}
    ).execute()
    quick = os.environ.get("OPTAX_BILATERAL_QUICK", "") not in ("", "0")
    out = HERE.parent / "results" / "notebooks" / ("quick" if quick else "") / f"{name}.ipynb"
    out.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, out)
    print(f"{name}: executed in {time.perf_counter() - t0:.1f} s -> {out}")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail if a notebook is out of date")
    parser.add_argument(
        "--execute",
        nargs="+",
        metavar="NAME",
        choices=NAMES,
        help="run these notebooks (executed copies go to results/notebooks/)",
    )
    args = parser.parse_args(argv)
    if args.execute:
        for name in args.execute:
            execute(name)
        return 0
    stale = []
    for name in NAMES:
        path = HERE / f"{name}.ipynb"
        text = dumps(build(name))
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            path.write_text(text)
    if stale:
        print(f"out of date (run python notebooks/build_notebooks.py): {', '.join(stale)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
