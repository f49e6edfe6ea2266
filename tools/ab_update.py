"""A/B of ``bilateral_adam``'s update against another revision of the library, in one process.

    python -m tools.ab_update --rev HEAD --shape 512x512x1 --levels 5
    python -m tools.ab_update --rev HEAD~3 --shape 64x64x64x1 --full --repeats 4
    python -m tools.ab_update --rev HEAD~1 --shape 512x512x3 --defaults

The working tree's library (``new``) and the library at ``--rev`` (``old``, exported with
``git archive`` into a temporary folder as the package ``optax_bilateral_ab``) build the
same optimizer; their updates and ``optax.adam``'s are timed in alternation on the same
arrays (``benchmark.interleaved``: rotating rounds, medians). Every repeat prints the
milliseconds, the ratios to Adam and ``new/old``, and whether the two updates are equal
bit for bit; the repeats go to ``--out`` as JSON and Markdown. This is how a change to the
filter is measured on a shared machine: two processes can differ by 2-3x for the same
program (BENCHMARKS.md, "two speeds"), one process timing both sides cannot.

The old revision runs its own native kernel: where its ``csrc/`` and ``setup.py`` equal the
working tree's, a copy of the working tree's build, else one built from its sources by its
``setup.py`` (a minute or two); its FFI targets registered under ``optax_bilateral_ab_*``
names, so that both builds live in one process. ``--no-native`` runs the old revision on its
pure-JAX kernels, as a revision from before the kernel does.

The optimizer is the texture experiment's by default (``optax.inject_hyperparams`` with
traced ``learning_rate`` and ``sigma_d``, ``b1 = 0.2``; ``--log-guide`` for its log guide);
``--defaults``: ``bilateral_adam(0.02)`` with every default (``sigma_d="auto"``, F = 3).
``--shape`` follows the default leaf rule (``HxW``: 2-D; ``...xC``: all but the last axis
spatial).
"""

from __future__ import annotations

import importlib
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence

import jax
import numpy as np
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks import suite as bm

AB_PACKAGE = "optax_bilateral_ab"


# The native extension's FFI targets: their prefix, and the old revision's in this process.
TARGET_PREFIX = "optax_bilateral_"
AB_TARGET_PREFIX = "optax_bilateral_ab_"

# The old revision's extension module: its build loaded from a folder of its own, its FFI
# targets renamed (registered by the old package's extension.py under the new names).
NATIVE_WRAPPER = f"""\"\"\"The revision's extension, its FFI targets renamed.\"\"\"

import importlib.util
import pathlib

_path = next((pathlib.Path(__file__).parent / "native_build").glob("_native*.so"))
_spec = importlib.util.spec_from_file_location("_native", _path)
_module = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_module)


def registrations():
    return {{{AB_TARGET_PREFIX!r} + k[len({TARGET_PREFIX!r}):]: v
            for k, v in _module.registrations().items()}}


def __getattr__(name):
    return getattr(_module, name)
"""


def export_revision(
    rev: str, dest: pathlib.Path, repo: pathlib.Path | None = None, native: bool = True
):
    """Imports the library as it is at git revision ``rev`` under the name ``optax_bilateral_ab``.

    The package is written to ``dest`` with every ``optax_bilateral`` import renamed, so
    that both versions live in one process; with ``native``, with its native extension
    (:func:`native_build`), where the revision has one.
    """
    repo = repo or pathlib.Path(ob.__file__).resolve().parents[1]
    paths = ["optax_bilateral"] + [p for p in ("csrc", "setup.py") if _exists(repo, rev, p)]
    try:
        tar = subprocess.run(
            ["git", "-C", str(repo), "archive", rev, *paths],
            check=True,
            capture_output=True,
        ).stdout
    except subprocess.CalledProcessError as e:
        raise ValueError(f"--rev {rev!r}: git archive failed: {e.stderr.decode().strip()}") from e
    subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    if native and len(paths) == 3:
        native_build(rev, dest, repo)
    pkg = dest / AB_PACKAGE
    (dest / "optax_bilateral").rename(pkg)
    for f in pkg.rglob("*.py"):
        text = f.read_text().replace(f'"{TARGET_PREFIX}', f'"{AB_TARGET_PREFIX}')
        f.write_text(re.sub(r"\boptax_bilateral\b", AB_PACKAGE, text))
    sys.path.insert(0, str(dest))
    for name in [m for m in sys.modules if m == AB_PACKAGE or m.startswith(AB_PACKAGE + ".")]:
        del sys.modules[name]
    return importlib.import_module(AB_PACKAGE)


def _exists(repo: pathlib.Path, rev: str, path: str) -> bool:
    out = subprocess.run(
        ["git", "-C", str(repo), "ls-tree", "--name-only", rev, "--", path],
        capture_output=True,
        text=True,
    )
    return out.returncode == 0 and bool(out.stdout.strip())


def native_build(rev: str, dest: pathlib.Path, repo: pathlib.Path) -> str:
    """The revision's extension in ``dest/optax_bilateral/native_build``, loaded by a wrapper
    module ``_native`` that renames its FFI targets: a copy of the working tree's build where
    ``csrc/`` and ``setup.py`` are the same at ``rev``, else built by the revision's
    ``setup.py``. Returns how it was made."""
    pkg = dest / "optax_bilateral"
    here = sorted(pathlib.Path(ob.__file__).resolve().parent.glob("_native*.so"))
    same = (
        subprocess.run(
            ["git", "-C", str(repo), "diff", "--quiet", rev, "--", "csrc", "setup.py"]
        ).returncode
        == 0
    )
    if same and here:
        so, how = here[0], "a copy of the working tree's build"
    else:
        subprocess.run(
            [sys.executable, "setup.py", "-q", "build_ext", "--inplace"],
            cwd=dest,
            check=True,
            capture_output=True,
        )
        built = sorted(pkg.glob("_native*.so"))
        if not built:
            raise RuntimeError(f"--rev {rev!r}: its setup.py built no native extension")
        so, how = built[0], f"built from {rev}'s csrc/"
    (pkg / "native_build").mkdir()
    shutil.copy(so, pkg / "native_build" / so.name)
    for stale in pkg.glob("_native*.so"):
        stale.unlink()
    (pkg / "_native.py").write_text(NATIVE_WRAPPER)
    print(f"old revision's native kernel: {how}", flush=True)
    return how


def parse_shape(text: str) -> tuple[int, ...]:
    try:
        shape = tuple(int(v) for v in text.lower().split("x"))
    except ValueError:
        shape = ()
    if len(shape) < 2 or min(shape) < 1:
        raise ValueError(
            f"--shape must be sizes joined by 'x' (at least 2), e.g. 512x512x1; got {text!r}"
        )
    return shape


def optimizer(lib, levels: int, separable: bool, log_guide: bool, defaults: bool = False):
    """The texture experiment's postfilter from ``lib`` (either revision has ``postfilter``),
    its learning rate and sigma_d injectable; ``defaults``: ``lib.bilateral_adam(0.02)``."""
    if defaults:
        return lib.bilateral_adam(0.02)

    def factory(learning_rate, sigma_d):
        post = lib.postfilter(
            0.2, sigma_d=sigma_d, levels=levels, separable=separable, log_guide=log_guide
        )
        return optax.chain(post, optax.scale_by_learning_rate(learning_rate))

    return optax.inject_hyperparams(factory)(learning_rate=0.02, sigma_d=0.1)


def arrays(shape):
    """(params, grad) of ``shape`` with positive params; ``HxW`` is one channel, ``(H, W, 1)``
    (a layout every revision's default leaf rule filters)."""
    params, grad = bm.update_arrays(shape if len(shape) > 2 else shape + (1,))
    return abs(params) + 0.05, grad  # positive: the log guide is defined


def compare(
    old_lib,
    shape,
    levels: int,
    separable: bool,
    log_guide: bool,
    repeats: int,
    rounds: int,
    inner: int,
    defaults: bool = False,
) -> list[dict]:
    """``repeats`` rows of side-by-side medians: adam, old and new updates (ms), ratios, and
    whether the two updates (and states) are equal bit for bit."""
    params, grad = arrays(shape)
    opts = {
        "adam": optax.adam(1e-2),
        "old": optimizer(old_lib, levels, separable, log_guide, defaults),
        "new": optimizer(ob, levels, separable, log_guide, defaults),
    }
    fns = {}
    for k, opt in opts.items():
        prog = bm.update_program(opt)
        fns[k] = (prog, (grad, bm.warm_state(opt, params, grad), params))
    old_out, new_out = (jax.tree.leaves(fns[k][0](*fns[k][1])) for k in ("old", "new"))
    same = len(old_out) == len(new_out) and all(
        np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
        for a, b in zip(old_out, new_out)
    )
    rows = []
    for rep in range(repeats):
        r = bm.interleaved(fns, rounds, inner, desc=f"repeat {rep + 1}/{repeats}")
        ms = {k: 1e3 * v["median"] for k, v in r.items()}
        rows.append(
            {
                "repeat": rep + 1,
                "adam ms": ms["adam"],
                "old ms": ms["old"],
                "new ms": ms["new"],
                "old x adam": ms["old"] / ms["adam"],
                "new x adam": ms["new"] / ms["adam"],
                "new / old": ms["new"] / ms["old"],
                "new / old (paired)": common.paired_ratio(
                    {k: v["samples"] for k, v in r.items()}, "new", "old"
                ),
                "bit-equal": same,
            }
        )
        print(" | ".join(f"{k} {common.fmt(v)}" for k, v in rows[-1].items()), flush=True)
    return rows


def main(argv: Sequence[str] | None = None) -> dict:
    def extra(p):
        p.add_argument("--rev", default="HEAD", help="git revision to compare against")
        p.add_argument("--shape", default="512x512x1", help="parameter shape, e.g. 64x64x64x1")
        p.add_argument("--levels", type=int, default=5)
        p.add_argument("--full", action="store_true", help="full instead of separable mode")
        p.add_argument("--log-guide", action="store_true")
        p.add_argument("--repeats", type=int, default=3)
        p.add_argument("--rounds", type=int, default=11)
        p.add_argument("--inner", type=int, default=3)
        p.add_argument(
            "--defaults", action="store_true", help="bilateral_adam(0.02) with every default"
        )
        p.add_argument(
            "--no-native",
            action="store_true",
            help="the old revision on its pure-JAX kernels (no build of its extension)",
        )

    args = common.parse_args(
        "A/B of the update against another revision", "results/ab", argv, extra
    )
    shape = parse_shape(args.shape)
    for name in ("levels", "repeats", "rounds", "inner"):
        v = getattr(args, name)
        if v < (0 if name == "levels" else 1):
            raise ValueError(f"--{name} must be >= {0 if name == 'levels' else 1}, got {v}")
    if args.quick:
        args.repeats, args.rounds, args.inner = 1, 1, 1
    with tempfile.TemporaryDirectory() as tmp:
        try:
            old = export_revision(args.rev, pathlib.Path(tmp), native=not args.no_native)
            rows = compare(
                old,
                shape,
                args.levels,
                not args.full,
                args.log_guide,
                args.repeats,
                args.rounds,
                args.inner,
                args.defaults,
            )
        finally:  # the folder is deleted: forget it
            if tmp in sys.path:
                sys.path.remove(tmp)
    summary = {
        "rev": args.rev,
        "shape": shape,
        "levels": args.levels,
        "separable": not args.full,
        "log_guide": args.log_guide,
        "defaults": args.defaults,
        "old kernel": old.native_status()._asdict() if hasattr(old, "native_status") else None,
        "rows": rows,
        "new / old (median)": float(np.median([r["new / old"] for r in rows])),
        "jax": jax.__version__,
    }
    md = (
        f"new (working tree) vs old ({args.rev}), shape {args.shape}, "
        + ("defaults" if args.defaults else f"F={args.levels}, ")
        + ("" if args.defaults else ("full" if args.full else "separable"))
        + f"; old kernel: {summary['old kernel']}\n\n"
        + common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in rows])
    )
    common.write_results(args.out, "ab_update", summary, md)
    print(f"new / old, median over repeats: {summary['new / old (median)']:.3f}")
    return summary


if __name__ == "__main__":
    main()
