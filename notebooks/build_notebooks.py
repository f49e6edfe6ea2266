"""Builds ``notebooks/*.ipynb`` (outputs stripped) from the sources in ``notebooks/src/``, or
runs them.

    python notebooks/build_notebooks.py                 # write every notebook from its source
    python notebooks/build_notebooks.py --check         # exit 1 if a notebook and its source
                                                        # differ
    python notebooks/build_notebooks.py --execute NAME  # run notebooks/NAME.ipynb; the executed
                                                        # copy goes to results/notebooks/NAME.ipynb
                                                        # (results/notebooks/quick/ when quick)
    python notebooks/build_notebooks.py --record NAME   # keep the executed copy's outputs for the
                                                        # docs site: notebooks/outputs/NAME.json and
                                                        # notebooks/outputs/NAME/*.png

A source ``notebooks/src/NAME.py`` is plain Python split into cells by marker
lines: ``# %%`` starts a code cell, ``# %% [markdown]`` a markdown cell whose
lines all start with ``#`` (the ``# `` prefix is removed). The notebooks in git
therefore never hold outputs, and a diff of a notebook is a diff of its source.
Set ``OPTAX_BILATERAL_QUICK=1`` for the test-suite size.

The docs site shows each notebook with the outputs of one recorded run
(:func:`record`, :func:`page`; docs/design.md, "The docs site"): its standard output,
its Markdown tables and its figures, checked against the notebook's code cells, so
that a page never shows the outputs of code that has since changed.
"""

from __future__ import annotations

import argparse
import ast
import datetime
import hashlib
import io
import json
import os
import pathlib
import sys
import time

import nbformat

HERE = pathlib.Path(__file__).resolve().parent
SRC = HERE / "src"
# The recorded outputs the docs site shows (committed: small JSON and PNGs).
OUTPUTS = HERE / "outputs"
PNG_BUDGET = 300_000  # bytes per recorded figure
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


def quick_from_env() -> bool:
    """Whether ``OPTAX_BILATERAL_QUICK`` asks for the test-suite size."""
    return os.environ.get("OPTAX_BILATERAL_QUICK", "") not in ("", "0")


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
    out = executed_path(name, quick_from_env())
    out.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, out)
    print(f"{name}: executed in {time.perf_counter() - t0:.1f} s -> {out}")
    return out


def executed_path(name: str, quick: bool) -> pathlib.Path:
    """Where :func:`execute` writes the executed copy of ``name``."""
    return HERE.parent / "results" / "notebooks" / ("quick" if quick else "") / f"{name}.ipynb"


def source_hash(source: str) -> str:
    """The fingerprint a recorded cell keeps of the code that produced its outputs.

    Taken of the code's syntax tree, so that reformatting or editing comments does not
    invalidate a record; any change to what the code does does."""
    try:
        text = ast.dump(ast.parse(source))
    except SyntaxError:  # e.g. IPython magics: the text itself
        text = source
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _small_png(data: bytes) -> bytes:
    """``data`` re-encoded with a 256-colour palette (plots and colour maps lose nothing visible),
    scaled down by steps of 0.8 while it exceeds ``PNG_BUDGET`` (noise textures compress badly);
    ``data`` itself when that is smaller."""
    from PIL import Image

    image = Image.open(io.BytesIO(data)).convert("RGB")
    while True:
        out = io.BytesIO()
        image.quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            out, "PNG", optimize=True
        )
        if out.tell() <= PNG_BUDGET or image.width < 600:
            break
        image = image.resize(
            (round(image.width * 0.8), round(image.height * 0.8)), Image.Resampling.LANCZOS
        )
    return out.getvalue() if out.tell() < len(data) else data


def record(name: str, quick: bool) -> pathlib.Path:
    """Keeps the outputs of the executed copy of ``name`` for the docs site.

    Writes ``notebooks/outputs/NAME.json``: per code cell, in order, the fingerprint of its
    source and its outputs (standard output as text, Markdown displays, figures as PNG files
    in ``notebooks/outputs/NAME/``). Standard error (progress bars, warnings) is left out.
    Absolute paths under the repository are written relative to it. A copy with an error
    output is refused.
    """
    import base64

    executed = executed_path(name, quick)
    if not executed.exists():
        raise FileNotFoundError(
            f"{executed} does not exist; run "
            f"python notebooks/build_notebooks.py --execute {name} first"
        )
    nb = nbformat.read(executed, as_version=4)
    root = str(HERE.parent) + os.sep
    figures = OUTPUTS / name
    figures.mkdir(parents=True, exist_ok=True)
    for old in figures.glob("*.png"):
        old.unlink()
    cells = []
    for index, cell in enumerate(c for c in nb.cells if c.cell_type == "code"):
        outputs: list[dict[str, str]] = []
        for out in cell.outputs:
            kind = out.output_type
            if kind == "error":
                raise ValueError(f"{executed}: code cell {index} raised {out.ename}; not recorded")
            if kind == "stream" and out.name == "stdout":
                text = out.text.replace(root, "")
                if outputs and "text" in outputs[-1]:
                    outputs[-1]["text"] += text
                else:
                    outputs.append({"text": text})
            elif kind in ("display_data", "execute_result"):
                data = out.data
                if "image/png" in data:
                    png = f"{name}-{index:02d}-{len(outputs)}.png"
                    (figures / png).write_bytes(_small_png(base64.b64decode(data["image/png"])))
                    outputs.append({"image": png})
                elif "text/markdown" in data:
                    outputs.append({"markdown": data["text/markdown"].replace(root, "")})
                elif "text/plain" in data:
                    outputs.append({"text": data["text/plain"].replace(root, "") + "\n"})
        cells.append({"source_sha256": source_hash(cell.source), "outputs": outputs})
    executed_on = datetime.date.fromtimestamp(executed.stat().st_mtime).isoformat()
    rec = {
        "notebook": name,
        "size": "quick" if quick else "full",
        "executed": executed_on,
        "cells": cells,
    }
    path = OUTPUTS / f"{name}.json"
    path.write_text(json.dumps(rec, indent=1, ensure_ascii=False) + "\n")
    print(
        f"{name}: recorded {len(cells)} code cells, "
        f"{len(list(figures.glob('*.png')))} figures -> {path}"
    )
    return path


def rekey(name: str, why: str) -> None:
    """Points ``name``'s record at the notebook's current code cells without re-running it,
    for a change that leaves every output as it was; ``why`` says so, on the page."""
    rec = json.loads((OUTPUTS / f"{name}.json").read_text())
    nb = nbformat.read(HERE / f"{name}.ipynb", as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    if len(code) != len(rec["cells"]):
        raise ValueError(f"{name}: cells were added or removed; re-run and re-record it")
    for cell, recorded in zip(code, rec["cells"]):
        recorded["source_sha256"] = source_hash(cell.source)
    rec["rekeyed"] = why
    (OUTPUTS / f"{name}.json").write_text(json.dumps(rec, indent=1, ensure_ascii=False) + "\n")


def load_record(name: str) -> dict:
    """The recorded outputs of ``name``, checked against the code cells of ``notebooks/NAME.ipynb``.

    Raises:
      ValueError: naming the cells, if the record was made from other code (the notebook has
        changed since): re-run and re-record it.
    """
    rec = json.loads((OUTPUTS / f"{name}.json").read_text())
    nb = nbformat.read(HERE / f"{name}.ipynb", as_version=4)
    code = [source_hash(c.source) for c in nb.cells if c.cell_type == "code"]
    recorded = [c["source_sha256"] for c in rec["cells"]]
    changed = [i for i, (a, b) in enumerate(zip(code, recorded)) if a != b]
    if len(code) != len(recorded) or changed:
        raise ValueError(
            f"notebooks/outputs/{name}.json was recorded from other code than "
            f"notebooks/{name}.ipynb ({len(recorded)} code cells recorded, {len(code)} now; "
            f"changed: {changed}); re-run it: "
            f"python notebooks/build_notebooks.py --execute {name} --record {name}"
        )
    return rec


def _fence(text: str, language: str) -> str:
    return f"```{language}\n{text.rstrip()}\n```"


def page(name: str) -> str:
    """The docs page of ``name`` (Markdown): its cells, each code cell followed by its recorded
    outputs, with a note after the title saying which run they come from."""
    rec = load_record(name)
    size = (
        "the full size (no `OPTAX_BILATERAL_QUICK`)"
        if rec["size"] == "full"
        else "the quick size (`OPTAX_BILATERAL_QUICK=1`, the test suite's: small textures and few "
        "iterations, so its numbers are not the paper-like results of the last section)"
    )
    note = (
        '!!! note "Recorded outputs"\n'
        f"    The outputs below are those of one run of this notebook at {size}, executed on "
        f"{rec['executed']} with `python notebooks/build_notebooks.py --execute {name}`; "
        "standard error (progress bars, warnings) is not shown. The notebook in the "
        f"repository, `notebooks/{name}.ipynb`, is stored without outputs: run it with that "
        "command, or open it in Jupyter from the repository root after `make install-dev`."
    )
    if "rekeyed" in rec:  # the code changed since the run in a way stated not to change it
        note += f"\n\n    {rec['rekeyed']}"
    nb = nbformat.read(HERE / f"{name}.ipynb", as_version=4)
    cells = iter(rec["cells"])
    parts = []
    for cell in nb.cells:
        if cell.cell_type == "markdown":
            parts.append(cell.source)
            if len(parts) == 1:
                parts.append(note)
            continue
        parts.append(_fence(cell.source, "python"))
        for out in next(cells)["outputs"]:
            if "text" in out:
                parts.append(_fence(out["text"], "text"))
            elif "markdown" in out:
                parts.append(out["markdown"].strip())
            else:
                parts.append(f"![A figure of the {name} notebook]({name}/{out['image']})")
    return "\n\n".join(parts) + "\n"


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
    parser.add_argument(
        "--record",
        nargs="+",
        metavar="NAME",
        choices=NAMES,
        help="after --execute, if given: keep the executed copies' outputs for "
        "the docs site (notebooks/outputs/)",
    )
    args = parser.parse_args(argv)
    if args.execute or args.record:
        for name in args.execute or ():
            execute(name)
        for name in args.record or ():
            record(name, quick_from_env())
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
