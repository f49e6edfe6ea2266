"""Griffe extension for the docs site: the reST bits of the docstrings, as Markdown.

The docstrings are Google style with a little reST (``.. math::`` blocks, ``:math:``,
``:func:`` and ``:class:`` roles, ``Example::``) so that ``help()`` reads well; this
turns them into what mkdocstrings renders: ``$$`` blocks for MathJax, ``$...$``,
cross-references to the public names, and an ``Examples:`` section. The sources stay
as they are.
"""

from __future__ import annotations

import importlib
import re
import textwrap

import griffe

PUBLIC_MODULES = ("optax_bilateral", "optax_bilateral.triangle_mesh", "optax_bilateral.mitsuba")
ROLE = re.compile(r":(?:func|class|meth|data|mod|attr|obj):`~?([\w.]+)`")
MATH_ROLE = re.compile(r":math:`([^`]+)`")
MATH_BLOCK = re.compile(
    r"^(?P<indent>[ \t]*)\.\. math::[ \t]*\n(?P<body>(?:(?P=indent)[ \t]+.*\n|[ \t]*\n)+)", re.M
)


def _public_names() -> dict[str, str]:
    names = {}
    for module in PUBLIC_MODULES:
        for name in importlib.import_module(module).__all__:
            names.setdefault(name, f"{module}.{name}")
    return names


def _math_block(match: re.Match) -> str:
    indent = match.group("indent")
    body = textwrap.dedent(match.group("body")).strip("\n")
    blocks = [b.strip("\n") for b in re.split(r"\n[ \t]*\n", body) if b.strip()]
    out = "\n\n".join(f"{indent}$$\n{textwrap.indent(b, indent)}\n{indent}$$" for b in blocks)
    return out + "\n\n"


def to_markdown(text: str, public: dict[str, str]) -> str:
    """The docstring ``text`` with its reST constructs turned into Markdown."""

    def role(match: re.Match) -> str:
        name = match.group(1)
        target = public.get(name.rsplit(".", 1)[-1]) if not name.startswith("_") else None
        if target is not None and name in (target, target.rsplit(".", 1)[-1]):
            return f"[`{name}`][{target}]"
        return f"`{name}`"

    text = MATH_BLOCK.sub(_math_block, text + "\n").rstrip("\n")
    text = MATH_ROLE.sub(lambda m: f"${m.group(1)}$", text)
    text = ROLE.sub(role, text)
    return re.sub(r"^([ \t]*)Examples?::[ \t]*$", r"\1Examples:", text, flags=re.M)


class RstToMarkdown(griffe.Extension):
    """Rewrites every docstring of the loaded package (sources untouched)."""

    def __init__(self) -> None:
        self.public = _public_names()

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = to_markdown(obj.docstring.value, self.public)
