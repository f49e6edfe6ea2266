"""What is installed: only the library, typed, with its license and one version."""

import datetime
import importlib.metadata
import os
import pathlib
import re
import subprocess
import sys
import tomllib
import zipfile

import check_min_versions
import optax_bilateral as ob

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _pyproject_version() -> str:
    text = (ROOT / "pyproject.toml").read_text()
    return re.search(r'^version = "([^"]+)"', text, re.M).group(1)


def test_version_is_written_once_and_read_from_the_metadata():
    assert ob.__version__ == importlib.metadata.version("optax_bilateral") == _pyproject_version()
    written = [
        p
        for p in (ROOT / "optax_bilateral").rglob("*.py")
        if re.search(r"__version__\s*=\s*['\"]\d", p.read_text())
    ]
    assert written == []


def test_wheel_holds_only_the_library(tmp_path):
    # The extension built for the baseline ISA only (setup.py): the wheel's layout is the
    # same, in ~3/4 of the build time; `make dist` builds and runs the full wheel.
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
        env=dict(os.environ, OPTAX_BILATERAL_BASELINE_ONLY="1"),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    (wheel,) = tmp_path.glob("optax_bilateral-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    dist_info = f"optax_bilateral-{_pyproject_version()}.dist-info"
    assert {n.split("/")[0] for n in names} == {"optax_bilateral", dist_info}
    assert {
        "optax_bilateral/py.typed",
        "optax_bilateral/_src/filter/front.py",
        "optax_bilateral/toy/texture.py",
    } <= set(names)
    assert any(n.startswith(dist_info) and n.endswith("LICENSE") for n in names)
    # The native kernel: a platform wheel with the built extension, not its C++ sources.
    assert any(re.fullmatch(r"optax_bilateral/_native\..*\.so", n) for n in names), names
    assert not any(n.endswith((".cc", ".h")) for n in names)
    assert not wheel.name.endswith("-none-any.whl"), wheel.name
    metadata = zipfile.ZipFile(wheel).read(f"{dist_info}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in metadata
    requires = re.findall(r"^Requires-Dist: ([\w\-]+)[^;\n]*$", metadata, re.M)
    assert sorted(requires) == ["jax", "numpy", "optax"]  # extras aside


def test_license_is_the_apache_2_text():
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "END OF TERMS AND CONDITIONS" in text


def test_the_declared_lower_bounds_are_the_pinned_minimum_versions():
    # make test-min runs the core tests with constraints-min.txt's pins: they must be the
    # lower bounds pyproject.toml declares (jaxlib: jax's own, which jax requires exactly).
    pinned = check_min_versions.pins(ROOT / "constraints-min.txt")
    text = (ROOT / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)\]", text, re.M | re.S).group(1)
    bounds = dict(re.findall(r'"([\w\-]+)>=([\d.]+)"', block))
    assert set(bounds) == {"jax", "optax", "numpy"}
    for name, bound in bounds.items():
        assert pinned[name].split(".")[: len(bound.split("."))] == bound.split("."), name
    assert pinned["jaxlib"] == pinned["jax"]
    assert check_min_versions.oldest_python() == (3, 11)


def test_the_release_is_dated_in_the_changelog_and_names_no_unpublished_url():
    version = _pyproject_version()
    releases = re.findall(
        r"^## (\d+\.\d+\.\d+) — (\d{4}-\d{2}-\d{2})$", (ROOT / "CHANGELOG.md").read_text(), re.M
    )
    assert releases and releases[0][0] == version, releases
    datetime.date.fromisoformat(releases[0][1])
    # No public repository or docs site exists yet, so the metadata names none: a project URL
    # is added with the place it points at (RELEASING.md, step 1).
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert "urls" not in project, project["urls"]
    meta = importlib.metadata.metadata("optax_bilateral")
    classifiers = meta.get_all("Classifier")
    assert "Programming Language :: Python :: 3.11" in classifiers
    assert meta["Requires-Python"] == ">=3.11"
