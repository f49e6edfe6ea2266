"""``make dist``'s check of the built wheel, run by a clean venv that installed it.

``python tests/check_dist.py base``: the wheel alone (``pip install optax_bilateral``)
imports from the venv, not from the checkout, and runs the README's quick start (printing
the numbers the README shows) and its three compositions.

``python tests/check_dist.py wheel dist/*.whl``: the wheel holds the library, its metadata
and the built native kernel, nothing else (no tests, no C++ sources), as a platform wheel.

``python tests/check_dist.py extras``: after ``pip install 'optax_bilateral[dev]'`` (every
extra), each extra the wheel declares gives what it promises (:data:`EXTRAS`); an extra
without a check here fails.

Run from outside the checkout (``make dist`` runs it from the venv's folder), so that
``import optax_bilateral`` cannot find the sources.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile

import docs_blocks


def check_wheel(path: str) -> None:
    wheel = pathlib.Path(path)
    project = tomllib.loads((docs_blocks.ROOT / "pyproject.toml").read_text())["project"]
    names = zipfile.ZipFile(wheel).namelist()
    dist_info = f"optax_bilateral-{project['version']}.dist-info"
    assert {n.split("/")[0] for n in names} == {"optax_bilateral", dist_info}, names
    expected = {
        "optax_bilateral/py.typed",
        "optax_bilateral/_src/filter/front.py",
        "optax_bilateral/toy/texture.py",
    }
    assert expected <= set(names), names
    assert any(n.startswith(dist_info) and n.endswith("LICENSE") for n in names)
    # The native kernel: a platform wheel with the built extension, not its C++ sources.
    assert any(re.fullmatch(r"optax_bilateral/_native\..*\.so", n) for n in names), names
    assert not any(n.endswith((".cc", ".h")) for n in names)
    assert not wheel.name.endswith("-none-any.whl"), wheel.name
    metadata = zipfile.ZipFile(wheel).read(f"{dist_info}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in metadata
    requires = re.findall(r"^Requires-Dist: ([\w\-]+)[^;\n]*$", metadata, re.M)
    assert sorted(requires) == ["jax", "numpy", "optax"], requires  # extras aside
    print(f"{wheel.name}: the library, its metadata and the native kernel only")


def check_base() -> None:
    import optax_bilateral as ob

    where = pathlib.Path(ob.__file__).resolve()
    assert pathlib.Path(sys.prefix).resolve() in where.parents, f"imported from {where}"
    source = docs_blocks.ROOT / "optax_bilateral"
    assert source not in where.parents, f"imported from the sources: {where}"
    assert ob.__version__ == importlib.metadata.version("optax_bilateral")
    quickstart = docs_blocks.by("README.md", "quickstart")
    with tempfile.TemporaryDirectory() as tmp:
        run = subprocess.run(
            [sys.executable, "-c", quickstart.code],
            cwd=tmp,
            capture_output=True,
            text=True,
            timeout=900,
            check=True,
        )
    print(run.stdout, end="")
    problems = docs_blocks.compare_prints(run.stdout, quickstart.prints)
    assert problems == [], problems
    namespace: dict = {}
    exec(docs_blocks.by("README.md", "compositions").code, namespace)
    assert {"pre", "post", "both", "opt"} <= set(namespace)
    # The wheel carries the native kernel, built for any CPU of its platform.
    from optax_bilateral._src.filter import native

    status = native.status()
    assert status.available, status.reason
    print(
        f"optax_bilateral {ob.__version__} from {where.parent}: the quick start runs; "
        f"native kernel: {status.reason}"
    )


def _experiments() -> None:
    for name in ("skimage", "scipy", "tqdm"):
        importlib.import_module(name)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from optax_bilateral.toy import texture

    alpha = texture.target_roughness("camera", 32)  # scikit-image's camera image
    fig, ax = plt.subplots()
    ax.imshow(alpha)
    with tempfile.TemporaryDirectory() as tmp:
        fig.savefig(pathlib.Path(tmp) / "alpha.png")


def _cholesky() -> None:
    import jax.numpy as jnp
    import numpy as np

    import optax_bilateral.triangle_mesh as obm

    vertices = jnp.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], jnp.float32
    )
    faces = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    )
    opt = obm.large_steps(1e-2, faces, solver="cholesky")  # CHOLMOD through cholespy
    updates, _ = opt.update(0.1 * vertices, opt.init(vertices), vertices)
    assert bool(jnp.all(jnp.isfinite(updates))) and float(jnp.abs(updates).max()) > 0


def _mitsuba() -> None:
    import mitsuba as mi

    from optax_bilateral.mitsuba import SceneOptimizer, check_variant

    mi.set_variant("llvm_ad_rgb")
    assert check_variant() == "llvm_ad_rgb" and callable(SceneOptimizer)


def _docs() -> None:
    for name in (
        "mkdocs",
        "material",
        "mkdocstrings",
        "mkdocstrings_handlers.python",
        "pymdownx.arithmatex",
        "nbformat",
    ):
        importlib.import_module(name)
    files = importlib.metadata.files("django-static-mathjax") or []
    assert any(str(f).endswith("es5/tex-mml-chtml.js") for f in files), "no MathJax"


def _dev() -> None:
    for name in (
        "pytest",
        "xdist",
        "hypothesis",
        "optimistix",
        "nbclient",
        "ipykernel",
        "jaxtyping",
        "selenium",
        "build",
        "twine",
    ):
        importlib.import_module(name)
    for tool in ("ruff", "pyright"):
        assert (pathlib.Path(sys.prefix) / "bin" / tool).exists() or shutil.which(tool), tool


EXTRAS = {
    "experiments": _experiments,
    "cholesky": _cholesky,
    "mitsuba": _mitsuba,
    "docs": _docs,
    "dev": _dev,
}


def check_extras() -> None:
    declared = set(importlib.metadata.metadata("optax_bilateral").get_all("Provides-Extra"))
    assert declared == set(EXTRAS), f"extras without a check: {declared ^ set(EXTRAS)}"
    for name, check in EXTRAS.items():
        check()
        print(f"optax_bilateral[{name}]: ok")


if __name__ == "__main__":
    {"base": check_base, "extras": check_extras, "wheel": check_wheel}[sys.argv[1]](*sys.argv[2:])
