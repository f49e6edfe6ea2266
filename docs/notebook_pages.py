"""mkdocs hook: a page per notebook, with the outputs of its recorded run (docs/design.md).

``notebooks/build_notebooks.py`` writes each page (:func:`page`) from the stripped notebook
in git and its recorded outputs (``notebooks/outputs/``); this hook adds the pages and their
figures to the site as generated files, so nothing is written into docs/ and nothing runs.
After the build it checks that every figure a page shows is in the site.
"""

from __future__ import annotations

import importlib.util
import pathlib
import re

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _builder():
    """``notebooks/build_notebooks.py`` is a script, not a package module: load it by path."""
    path = ROOT / "notebooks" / "build_notebooks.py"
    spec = importlib.util.spec_from_file_location("build_notebooks", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def on_files(files: Files, config) -> Files:
    builder = _builder()
    for name in builder.NAMES:
        try:
            text = builder.page(name)
        except (FileNotFoundError, ValueError) as err:
            raise PluginError(f"the {name} notebook page: {err}") from err
        files.append(File.generated(config, f"notebooks/{name}.md", content=text))
        for png in sorted((builder.OUTPUTS / name).glob("*.png")):
            files.append(
                File.generated(config, f"notebooks/{name}/{png.name}", abs_src_path=str(png))
            )
    return files


def on_post_build(config) -> None:
    site = pathlib.Path(config["site_dir"])
    for name in _builder().NAMES:
        html = (site / "notebooks" / name / "index.html").read_text()
        images = re.findall(r'<img[^>]+src="([^"]+\.png)"', html)
        missing = [
            src for src in images if not (site / "notebooks" / name / src).resolve().is_file()
        ]
        if not images or missing:
            raise PluginError(f"the {name} notebook page shows no figure or misses {missing}")
