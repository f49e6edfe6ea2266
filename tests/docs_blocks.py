"""The Python blocks of README.md and docs/*.md, with what the page says about running them.

A block is run as it is shown. An HTML comment on the line before its fence (invisible on
GitHub and on the site) may say more:

* ``<!-- docs-test: before`` ... ``-->``: code run before the block, in its namespace, for
  what the page leaves to the reader (a mesh's ``faces``, a gradient);
* ``<!-- docs-test: by tests/FILE.py NAME -->``: ``tests/FILE.py`` runs it (finding it by
  ``NAME``), with what only that test can give (Mitsuba, a quick configuration);
* ``<!-- docs-test: skip REASON -->``: it cannot run on the CI machine (several hosts);
  it must still compile.

A ``text`` block marked ``<!-- docs-test: prints -->`` after a Python block (before the
next one) is what that block prints: the same words, and every number within 5 units of
its last printed digit (XLA may round a float32 sum differently across versions and
machines; more than that would be another result).

Only the standard library here: ``make dist``'s check (tests/check_dist.py) imports it in
a venv that has nothing but the wheel.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
MARKER = re.compile(r"<!-- docs-test: (?P<kind>before|by|skip|prints)\b(?P<rest>.*?)-->\s*$", re.S)
FENCE = re.compile(r"^```(?P<lang>\w*)\n(?P<body>.*?)^```$", re.S | re.M)
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


@dataclasses.dataclass
class Block:
    page: str  # relative to the repository root
    line: int  # of the opening fence
    code: str
    kind: str = "run"  # "run", "by" or "skip"
    before: str = ""  # hidden set-up code
    note: str = ""  # "by": "tests/FILE.py NAME"; "skip": the reason
    prints: str | None = None  # the output the page shows, if it checks one

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def pages() -> list[pathlib.Path]:
    """README.md, every Markdown page of docs/ and of docs/research/ (the generated notebook
    pages aside)."""
    docs = ROOT / "docs"
    return [ROOT / "README.md", *sorted(docs.glob("*.md")), *sorted(docs.glob("research/*.md"))]


def _marker(text: str, start: int) -> re.Match | None:
    """The ``docs-test`` comment that ends on the line before ``start``, if any."""
    head = text[:start].rstrip("\n")
    opening = head.rfind("<!--")
    if opening < 0 or not head.endswith("-->"):
        return None
    return MARKER.fullmatch(head[opening:])


def blocks(path: pathlib.Path) -> list[Block]:
    text = path.read_text()
    page = path.relative_to(ROOT).as_posix()
    out: list[Block] = []
    for fence in FENCE.finditer(text):
        lang, body = fence.group("lang"), fence.group("body")
        marker = _marker(text, fence.start())
        kind = marker.group("kind") if marker else None
        rest = marker.group("rest").strip() if marker else ""
        if lang == "text" and kind == "prints":
            if not out or out[-1].prints is not None:
                raise ValueError(f"{page}: a 'prints' block follows no Python block")
            out[-1].prints = body
            continue
        if lang != "python":
            continue
        block = Block(page, text[: fence.start()].count("\n") + 1, body)
        if kind == "before":
            block.before = rest + "\n"
        elif kind in ("by", "skip"):
            if not rest:
                raise ValueError(f"{block.where}: '{kind}' needs a test file or a reason")
            block.kind, block.note = kind, rest
        elif kind == "prints":
            raise ValueError(f"{block.where}: 'prints' marks a text block, not code")
        out.append(block)
    return out


def by(page: str, name: str) -> Block:
    """The block of ``page`` marked ``by tests/FILE.py NAME``."""
    found = [
        b for b in blocks(ROOT / page) if b.kind == "by" and b.note.split()[1:] == name.split()
    ]
    if len(found) != 1:
        raise LookupError(f"{page} has {len(found)} blocks marked 'by ... {name}'")
    return found[0]


def compare_prints(printed: str, shown: str) -> list[str]:
    """What differs between ``printed`` and the ``shown`` output (empty: they agree)."""
    got, want = printed.strip().splitlines(), shown.strip().splitlines()
    if len(got) != len(want):
        return [f"printed {len(got)} lines, the page shows {len(want)}:\n{printed}"]
    problems = []
    for g, w in zip(got, want):
        if NUMBER.sub("#", g).split() != NUMBER.sub("#", w).split():
            problems.append(f"printed {g!r}, the page shows {w!r}")
            continue
        for a, b in zip(NUMBER.findall(g), NUMBER.findall(w)):
            decimals = len(b.split("e")[0].split("E")[0].partition(".")[2])
            exponent = int(b.lower().split("e")[1]) if "e" in b.lower() else 0
            if abs(float(a) - float(b)) > 5 * 10.0 ** (exponent - decimals):
                problems.append(f"printed {a} where the page shows {b} (in {w!r})")
    return problems
