"""mkdocs hook: MathJax's files from the installed Python package, served with the site.

The site typesets its formulas with MathJax 3 (``docs/javascripts/mathjax.js`` configures
it for pymdownx.arithmatex). Its files come from the ``django-static-mathjax`` package of
the ``docs`` extra (MathJax 3.2.2's ``es5`` folder, unchanged), not from a CDN, so the site
renders its math without a network (docs/design.md, "The docs site"). This hook adds that
folder to the site as ``assets/mathjax/``; ``mkdocs.yml`` loads
``assets/mathjax/tex-mml-chtml.js``, which finds its fonts and extensions beside it.
"""

from __future__ import annotations

import importlib.metadata
import pathlib

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

DISTRIBUTION = "django-static-mathjax"
ES5 = "mathjax/static/mathjax/es5"  # inside the distribution
SITE_DIR = "assets/mathjax"
ENTRY = "tex-mml-chtml.js"


def es5_folder() -> pathlib.Path:
    """The installed MathJax ``es5`` folder; a clear error when the package is missing."""
    try:
        dist = importlib.metadata.distribution(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError as err:
        raise PluginError(
            f"the docs need MathJax from the Python package {DISTRIBUTION!r}: "
            "pip install -e '.[docs]' (make docs installs it)"
        ) from err
    folder = pathlib.Path(str(dist.locate_file(ES5)))
    if not (folder / ENTRY).is_file():
        raise PluginError(f"{DISTRIBUTION} has no {ES5}/{ENTRY}; reinstall it")
    return folder


def on_files(files: Files, config) -> Files:
    folder = es5_folder()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        uri = f"{SITE_DIR}/{path.relative_to(folder).as_posix()}"
        files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files
