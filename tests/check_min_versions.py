"""``make test-min``'s first check: this interpreter runs the pinned minimum versions.

``python tests/check_min_versions.py constraints-min.txt`` prints the Python version and
each pinned distribution's installed version, and exits 1 unless every pin is what is
installed and the Python is the oldest that pyproject.toml's requires-python admits.
"""

import importlib.metadata
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def pins(path: pathlib.Path) -> dict[str, str]:
    """``name==version`` lines of a constraints file (comments and blanks skipped)."""
    out = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, version = line.split("==")
            out[name.strip()] = version.strip()
    return out


def oldest_python() -> tuple[int, int]:
    text = (ROOT / "pyproject.toml").read_text()
    major, minor = re.search(r'^requires-python = ">=(\d+)\.(\d+)"', text, re.M).groups()
    return int(major), int(minor)


def main(path: str) -> int:
    wrong = []
    python = sys.version_info[:2]
    print(f"Python {sys.version.split()[0]}")
    if python != oldest_python():
        wrong.append(f"Python {python} is not the oldest supported {oldest_python()}")
    for name, version in pins(pathlib.Path(path)).items():
        installed = importlib.metadata.version(name)
        print(f"{name} {installed}")
        if installed != version:
            wrong.append(f"{name} {installed} is installed, {version} is pinned")
    for line in wrong:
        print(f"error: {line}", file=sys.stderr)
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
