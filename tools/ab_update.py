"""A/B of ``bilateral_adam``'s update against another revision of the library, in one process.

    python -m tools.ab_update --rev HEAD --shape 512x512x1 --levels 5
    python -m tools.ab_update --rev HEAD~3 --shape 64x64x64x1 --full --repeats 4

The working tree's library (``new``) and the library at ``--rev`` (``old``, exported with
``git archive`` into a temporary folder as the package ``optax_bilateral_ab``) build the
same optimizer; their updates and ``optax.adam``'s are timed in alternation on the same
arrays (``benchmark.interleaved``: rotating rounds, medians). Every repeat prints the
milliseconds, the ratios to Adam and ``new/old``; the repeats go to ``--out`` as JSON and
Markdown. This is how a change to the filter is measured on a shared machine: two
processes can differ by 2-3x for the same program (BENCHMARKS.md, "two speeds"), one
process timing both sides cannot.

The optimizer is the texture experiment's by default (``optax.inject_hyperparams`` with
traced ``learning_rate`` and ``sigma_d``, ``b1 = 0.2``; ``--log-guide`` for its log guide);
``--shape`` follows the default leaf rule (``HxW``: 2-D; ``...xC``: all but the last axis
spatial).
"""

from __future__ import annotations

import importlib
import pathlib
import re
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


def export_revision(rev: str, dest: pathlib.Path, repo: pathlib.Path | None = None):
    """Imports the library as it is at git revision ``rev`` under the name ``optax_bilateral_ab``.

    The package is written to ``dest`` with every ``optax_bilateral`` import renamed, so
    that both versions live in one process.
    """
    repo = repo or pathlib.Path(ob.__file__).resolve().parents[1]
    try:
        tar = subprocess.run(
            ["git", "-C", str(repo), "archive", rev, "optax_bilateral"],
            check=True,
            capture_output=True,
        ).stdout
    except subprocess.CalledProcessError as e:
        raise ValueError(f"--rev {rev!r}: git archive failed: {e.stderr.decode().strip()}") from e
    subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    pkg = dest / AB_PACKAGE
    (dest / "optax_bilateral").rename(pkg)
    for f in pkg.rglob("*.py"):
        f.write_text(re.sub(r"\boptax_bilateral\b", AB_PACKAGE, f.read_text()))
    sys.path.insert(0, str(dest))
    for name in [m for m in sys.modules if m == AB_PACKAGE or m.startswith(AB_PACKAGE + ".")]:
        del sys.modules[name]
    return importlib.import_module(AB_PACKAGE)


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


def optimizer(lib, levels: int, separable: bool, log_guide: bool):
    """The texture experiment's postfilter from ``lib`` (either revision has ``postfilter``),
    its learning rate and sigma_d injectable."""

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
) -> list[dict]:
    """``repeats`` rows of side-by-side medians: adam, old and new updates (ms), ratios."""
    params, grad = arrays(shape)
    opts = {
        "adam": optax.adam(1e-2),
        "old": optimizer(old_lib, levels, separable, log_guide),
        "new": optimizer(ob, levels, separable, log_guide),
    }
    fns = {}
    for k, opt in opts.items():
        prog = bm.update_program(opt)
        fns[k] = (prog, (grad, bm.warm_state(opt, params, grad), params))
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
            old = export_revision(args.rev, pathlib.Path(tmp))
            rows = compare(
                old,
                shape,
                args.levels,
                not args.full,
                args.log_guide,
                args.repeats,
                args.rounds,
                args.inner,
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
        "rows": rows,
        "new / old (median)": float(np.median([r["new / old"] for r in rows])),
        "jax": jax.__version__,
    }
    md = (
        f"new (working tree) vs old ({args.rev}), shape {args.shape}, F={args.levels}, "
        f"{'full' if args.full else 'separable'}\n\n"
        + common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in rows])
    )
    common.write_results(args.out, "ab_update", summary, md)
    print(f"new / old, median over repeats: {summary['new / old (median)']:.3f}")
    return summary


if __name__ == "__main__":
    main()
