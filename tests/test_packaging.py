"""What is installed: only the library, typed, with its license and one version."""

import datetime
import importlib.metadata
import pathlib
import re
import tomllib
import zipfile

import pytest

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


def test_the_wheel_check_refuses_sources_tests_and_a_pure_wheel(tmp_path):
    """``make dist`` checks the wheel's contents (tests/check_dist.py wheel); that check
    passes a wheel laid out as the build lays it out and refuses each departure."""
    import check_dist

    version = _pyproject_version()
    info = f"optax_bilateral-{version}.dist-info"
    metadata = "License-Expression: Apache-2.0\n" + "".join(
        f"Requires-Dist: {name}>=1\n" for name in ("jax", "numpy", "optax")
    )
    good = {
        "optax_bilateral/py.typed": "",
        "optax_bilateral/_src/filter/front.py": "",
        "optax_bilateral/toy/texture.py": "",
        "optax_bilateral/_native.cpython-311-x86_64-linux-gnu.so": "",
        f"{info}/licenses/LICENSE": "",
        f"{info}/METADATA": metadata,
    }

    def wheel(files, tag="cp311-cp311-linux_x86_64"):
        folder = tmp_path / str(len(list(tmp_path.iterdir())))
        folder.mkdir()
        path = folder / f"optax_bilateral-{version}-{tag}.whl"
        with zipfile.ZipFile(path, "w") as z:
            for name, text in files.items():
                z.writestr(name, text)
        return str(path)

    check_dist.check_wheel(wheel(good))
    native = "optax_bilateral/_native.cpython-311-x86_64-linux-gnu.so"
    for bad in (
        wheel({**good, "csrc/atrous.cc": ""}),
        wheel({**good, "tests/test_atrous.py": ""}),
        wheel({k: v for k, v in good.items() if k != native}),
        wheel(good, tag="py3-none-any"),
        wheel({**good, f"{info}/METADATA": metadata + "Requires-Dist: scipy\n"}),
    ):
        with pytest.raises(AssertionError):
            check_dist.check_wheel(bad)
