"""Snapshots of what a refactoring must not change, and the script that records them.

    .venv/bin/python tests/snapshots.py          # re-record both files below
    .venv/bin/python tests/snapshots.py --check  # compare the lowered programs (opt-in)

* ``tests/api_snapshot.txt``: ``__all__`` of ``optax_bilateral`` and
  ``optax_bilateral.triangle_mesh``, one line per name with its signature (functions), its fields
  (NamedTuples) or its value (constants). ``tests/test_snapshots.py`` compares it on every run.
* ``tests/hlo_hashes.json``: a SHA-256 of the *lowered* (not compiled) program of the
  postfilter's update on the benchmark's grids (512x512x3 and 64^3x1, F = 5, separable and
  full), normalised so that only the computation counts: locations, result names and the
  names of private functions (renamed in order of first use) are dropped. An opt-in check
  (``--check``) for a change meant to leave the programs alone (a refactoring, a docstring):
  the suite does not pin it, since every restructuring and every JAX upgrade changes it while
  the goldens (tests/test_goldens.py) pin the numbers.

An intentional change re-records the file in the same commit and says why there.
The HLO of one program differs between jax versions; the file records the version.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import pathlib
import re

HERE = pathlib.Path(__file__).resolve().parent
HLO_PATH = HERE / "hlo_hashes.json"
API_PATH = HERE / "api_snapshot.txt"

HLO_CASES = {
    "512x512x3 F=5 separable": ((512, 512, 3), True),
    "512x512x3 F=5 full": ((512, 512, 3), False),
    "64x64x64x1 F=5 separable": ((64, 64, 64, 1), True),
    "64x64x64x1 F=5 full": ((64, 64, 64, 1), False),
}


def normalise_hlo(text: str) -> str:
    """The lowered module's text without what a refactoring may change but XLA ignores."""
    text = re.sub(r"\s*loc\((?:[^()]|\([^()]*\))*\)", "", text)  # source locations
    text = re.sub(r"#loc\d*\s*=.*\n", "", text)
    text = re.sub(r"jax\.(?:result|arg)_info = \"[^\"]*\",?\s*", "", text)  # pytree paths
    text = re.sub(r"\s*\{\s*\}", "", text)
    text = re.sub(r"^module @\S+", "module", text, flags=re.M)
    names: dict[str, str] = {}

    def rename(m):
        name = m.group(1)
        if name == "main":
            return "@main"
        return "@" + names.setdefault(name, f"f{len(names)}")

    return re.sub(r"@([\w.$\-]+)", rename, text)


def hlo_hash(shape, separable: bool) -> str:
    import jax
    import jax.numpy as jnp
    import optax

    import optax_bilateral as ob

    post = ob.postfilter(sigma_d=0.1, levels=5, separable=separable)
    opt = optax.chain(post, optax.scale_by_learning_rate(1e-2))
    p = jax.ShapeDtypeStruct(shape, jnp.float32)
    state = jax.eval_shape(opt.init, p)
    text = jax.jit(opt.update).lower(p, state, p).as_text()
    return hashlib.sha256(normalise_hlo(text).encode()).hexdigest()


def toolchain() -> str:
    import jax
    import jaxlib

    return f"jax {jax.__version__}, jaxlib {jaxlib.__version__}"


def hlo_hashes() -> dict[str, str]:
    return {name: hlo_hash(*case) for name, case in HLO_CASES.items()}


def describe(module) -> list[str]:
    """One line per public name of ``module``."""
    lines = []
    for name in module.__all__:
        obj = getattr(module, name)
        full = f"{module.__name__}.{name}"
        if inspect.ismodule(obj):
            lines.append(f"{full}: module")
        elif isinstance(obj, type) and hasattr(obj, "_fields"):
            lines.append(f"{full}: NamedTuple({', '.join(obj._fields)})")
        elif isinstance(obj, type) and issubclass(obj, Warning):
            lines.append(f"{full}: {', '.join(b.__name__ for b in obj.__bases__)} subclass")
        elif isinstance(obj, type):
            lines.append(f"{full}: class{inspect.signature(obj)}")
        elif callable(obj):
            lines.append(f"{full}{inspect.signature(obj)}")
        else:
            lines.append(f"{full} = {obj!r}")
    return lines


def api_lines() -> list[str]:
    import optax_bilateral
    import optax_bilateral.triangle_mesh

    return describe(optax_bilateral) + describe(optax_bilateral.triangle_mesh)


def check_hlo() -> int:
    """Compares the lowered programs with the recorded hashes; the number that differ."""
    recorded = json.loads(HLO_PATH.read_text())
    if recorded["toolchain"] != toolchain():
        print(f"recorded with {recorded['toolchain']}, running {toolchain()}: not comparable")
        return len(HLO_CASES)
    bad = 0
    for name, case in HLO_CASES.items():
        same = hlo_hash(*case) == recorded["hashes"][name]
        bad += not same
        print(f"{name}: {'unchanged' if same else 'CHANGED'}")
    return bad


if __name__ == "__main__":
    import sys

    if "--check" in sys.argv[1:]:
        sys.exit(1 if check_hlo() else 0)
    API_PATH.write_text("\n".join(api_lines()) + "\n")
    HLO_PATH.write_text(
        json.dumps({"toolchain": toolchain(), "hashes": hlo_hashes()}, indent=1) + "\n"
    )
    print(API_PATH.read_text())
    print(HLO_PATH.read_text())
