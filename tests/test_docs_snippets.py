"""Every Python block of README.md and docs/*.md runs, and prints what its page shows.

A page's blocks run in order in one namespace (a page reads as one session), in a fresh
Python process whose working directory is a temporary folder (files the blocks write stay
there) and which imports ``experiments`` from the checkout. tests/docs_blocks.py says how a
page marks a block that another test runs, one that cannot run here, hidden set-up code and
the output it checks.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pytest

import docs_blocks
from docs_blocks import ROOT

PAGES = [p.relative_to(ROOT).as_posix() for p in docs_blocks.pages()]
RUN = {
    page: [b for b in docs_blocks.blocks(ROOT / page) if b.kind == "run"]
    for page in PAGES
    if any(b.kind == "run" for b in docs_blocks.blocks(ROOT / page))
}
# Runs the blocks given as JSON [[name, before, code], ...] in one namespace; writes what
# each printed to the file named by argv[2].
DRIVER = """
import contextlib, io, json, sys
ns = {"__name__": "__main__"}
printed = []
for name, before, code in json.load(open(sys.argv[1])):
    exec(compile(before, name + " (set-up)", "exec"), ns)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, name, "exec"), ns)
    printed.append(out.getvalue())
    sys.stdout.write(out.getvalue())
json.dump(printed, open(sys.argv[2], "w"))
"""


def test_every_block_is_run_here_or_names_who_runs_it_or_why_not():
    seen = 0
    for page in PAGES:
        for block in docs_blocks.blocks(ROOT / page):
            seen += 1
            if block.kind == "by":
                test_file, name = block.note.split(maxsplit=1)
                source = (ROOT / test_file).read_text()
                assert f'"{name}"' in source, f"{block.where}: {test_file} does not run {name!r}"
            elif block.kind == "skip":
                # Only what the CI machine cannot do (several hosts or devices) is skipped.
                assert "multi-host" in block.note or "multi-GPU" in block.note, block.where
                compile(block.before + block.code, block.where, "exec")
    assert seen >= 15 and len(RUN) >= 8, (seen, sorted(RUN))  # the parser finds them


@pytest.mark.parametrize("page", sorted(RUN))
def test_page_blocks_run_and_print_what_the_page_shows(page, tmp_path):
    blocks = RUN[page]
    program = [[b.where, b.before, b.code] for b in blocks]
    (tmp_path / "blocks.json").write_text(json.dumps(program))
    (tmp_path / "driver.py").write_text(DRIVER)
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    # The pages run at XLA's default optimisation, not the suite's level 0 (tests/conftest.py),
    # under which docs/tuning.md's table runs 10x longer; the suite's other compile options
    # stay (they change rounding at most, and halve these pages' time).
    level = "--xla_backend_optimization_level="
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(level))
    proc = subprocess.run(
        [sys.executable, "driver.py", "blocks.json", "printed.json"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": path, "XLA_FLAGS": flags},
        capture_output=True,
        text=True,
        timeout=1800,  # docs/tuning.md's table: about 40 s on an idle 2-core machine
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    printed = json.loads((tmp_path / "printed.json").read_text())
    for block, out in zip(blocks, printed):
        if block.prints is not None:
            problems = docs_blocks.compare_prints(out, block.prints)
            assert problems == [], f"{block.where}: " + "; ".join(problems)


def test_prints_are_compared_by_words_and_by_the_last_printed_digit():
    assert docs_blocks.compare_prints("error 0.0071\n", "error 0.0068") == []
    assert docs_blocks.compare_prints("error 0.0074\n", "error 0.0068") != []
    assert docs_blocks.compare_prints("loss 0.0068\n", "error 0.0068") != []
    assert docs_blocks.compare_prints("a 1.5e-3 b\n", "a 1.2e-3 b") == []
    assert docs_blocks.compare_prints("x 2\ny 3\n", "x 2") != []
    assert docs_blocks.compare_prints("[0.02 0.1]", "[0.02 0.1]") == []


def test_markers_are_read_from_the_comment_before_a_fence(tmp_path, monkeypatch):
    page = tmp_path / "page.md"
    page.write_text(
        "<!-- docs-test: before\nx = 1\n-->\n```python\nprint(x)\n```\n\nIt prints:\n\n"
        "<!-- docs-test: prints -->\n```text\n1\n```\n\n"
        "<!-- docs-test: skip multi-host: needs a cluster -->\n```python\nf()\n```\n\n"
        "```sh\nmake\n```\n<!-- docs-test: by tests/test_x.py setup -->\n```python\ny = 2\n```\n"
    )
    monkeypatch.setattr(docs_blocks, "ROOT", tmp_path)
    first, second, third = docs_blocks.blocks(page)
    assert (first.kind, first.before, first.code, first.prints) == (
        "run",
        "x = 1\n",
        "print(x)\n",
        "1\n",
    )
    assert (second.kind, second.note, second.line) == ("skip", "multi-host: needs a cluster", 16)
    assert (third.kind, third.note) == ("by", "tests/test_x.py setup")
    assert pathlib.PurePath(third.page).name == "page.md"
