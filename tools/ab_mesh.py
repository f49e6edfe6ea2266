"""A/B of the mesh solves and updates against another revision of the library, in one process.

    python -m tools.ab_mesh --rev HEAD
    python -m tools.ab_mesh --rev HEAD~1 --frequencies 32 64 --rounds 45

The working tree's library (``new``) and the library at ``--rev`` (``old``, with its own
native extension: :func:`tools.ab_update.export_revision`) factorise ``I + lambda L`` of the
mesh experiment's rounded cube (an icosphere of ``10 f^2 + 2`` vertices, ``f`` from
``--frequencies``; lambda 19) and time, in alternation on the same arrays
(``benchmark.interleaved``: rotating rounds, medians): the host sweeps of 3 and 64 float32
columns (Large Steps' solve and the defaults' normal filter), and the jitted updates of
``bilateral_large_steps`` and ``large_steps`` (``solver="cholesky"``: the FFI solve). Each
row has both sides' milliseconds, ``new / old`` from the medians and paired by round, and
the largest difference between the two sides' results relative to the largest value (the
sums' order may change; the solves must agree to float32 rounding). Writes ``ab_mesh.json``
and ``.md`` to ``--out``. Two processes on this machine differ by more than most changes
to the sweeps; one process timing both sides does not.
"""

from __future__ import annotations

import importlib
import pathlib
import sys
import tempfile
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.benchmarks import suite as bm
from experiments.mitsuba.mesh import rounded_cube
from tools import ab_update

LAMBDA = 19.0  # the mesh experiment's
COLUMNS = (3, 64)  # Large Steps' solve; the defaults' normal filter (16 terms x 4)


def programs(lib, laplacian, vertices, faces) -> dict[str, tuple]:
    """``{part: (fn, args)}`` of one library: its host solves and its two jitted updates."""
    mesh = lib.mesh_laplacian(faces)
    host = laplacian._Cholesky(np.asarray(mesh.neighbors), np.asarray(mesh.degree))
    factor = host.factor(LAMBDA)
    rng = np.random.default_rng(0)
    out = {}
    for k in COLUMNS:
        b = rng.normal(size=(len(vertices), k)).astype(np.float32)
        out[f"sweeps {k}"] = (factor.solve, (b,))
    x = jnp.asarray(vertices, jnp.float32)
    g = jnp.asarray(rng.normal(size=x.shape), jnp.float32)
    for name in ("bilateral_large_steps", "large_steps"):
        opt = getattr(lib, name)(0.03, mesh, LAMBDA, solver="cholesky")
        out[name] = (jax.jit(opt.update), (g, opt.init(x), x))
    return out


def largest_difference(a, b) -> float:
    """max |a - b| over max |b|, over every leaf."""
    a, b = jax.tree.leaves(a), jax.tree.leaves(b)
    top = max(float(np.max(np.abs(np.asarray(y)))) for y in b) or 1.0
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(a, b)) / top


def compare(frequency: int, rounds: int) -> list[dict]:
    """One row per part at ``frequency``: both sides timed in alternation."""
    import optax_bilateral.triangle_mesh as new_mesh
    from optax_bilateral._src.mesh import laplacian as new_laplacian

    old_mesh = importlib.import_module(f"{ab_update.AB_PACKAGE}.triangle_mesh")
    old_laplacian = importlib.import_module(f"{ab_update.AB_PACKAGE}._src.mesh.laplacian")
    vertices, faces = rounded_cube(frequency, 0.6, 0.08)
    sides = {
        "new": programs(new_mesh, new_laplacian, vertices, faces),
        "old": programs(old_mesh, old_laplacian, vertices, faces),
    }
    rows = []
    for part in sides["new"]:
        fns = {side: sides[side][part] for side in sides}
        outs = {side: fn(*args) for side, (fn, args) in fns.items()}
        r = bm.interleaved(fns, rounds, desc=f"{len(vertices)} vertices, {part}")
        ms = {side: 1e3 * v["median"] for side, v in r.items()}
        rows.append(
            {
                "vertices": len(vertices),
                "part": part,
                "old ms": ms["old"],
                "new ms": ms["new"],
                "new / old": ms["new"] / ms["old"],
                "new / old (paired)": common.paired_ratio(
                    {k: v["samples"] for k, v in r.items()}, "new", "old"
                ),
                "largest difference": largest_difference(outs["new"], outs["old"]),
            }
        )
        print(" | ".join(f"{k} {common.fmt(v)}" for k, v in rows[-1].items()), flush=True)
    return rows


def main(argv: Sequence[str] | None = None) -> dict:
    def extra(p):
        p.add_argument("--rev", default="HEAD", help="git revision to compare against")
        p.add_argument(
            "--frequencies",
            type=int,
            nargs="+",
            default=[16, 32, 64],
            help="icosphere subdivisions: 10 f^2 + 2 vertices (default 16 32 64)",
        )
        p.add_argument("--rounds", type=int, default=31, help="rotating rounds per part")

    args = common.parse_args(
        "A/B of the mesh solves and updates against another revision",
        "results/ab_mesh",
        argv,
        extra,
    )
    if args.rounds < 1:
        raise ValueError(f"--rounds must be >= 1, got {args.rounds}")
    if any(f < 1 for f in args.frequencies):
        raise ValueError(f"--frequencies must be >= 1, got {args.frequencies}")
    if args.quick:
        args.frequencies, args.rounds = [3], 3
    with tempfile.TemporaryDirectory() as tmp:
        try:
            ab_update.export_revision(args.rev, pathlib.Path(tmp))
            rows = [r for f in args.frequencies for r in compare(f, args.rounds)]
        finally:  # the folder is deleted: forget it
            if tmp in sys.path:
                sys.path.remove(tmp)
    summary = {"rev": args.rev, "lambda": LAMBDA, "rows": rows, "jax": jax.__version__}
    md = (
        f"new (working tree) vs old ({args.rev}), rounded cube, lambda {LAMBDA:g}, "
        f"float32; `python -m tools.ab_mesh`\n\n"
        + common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in rows])
    )
    common.write_results(args.out, "ab_mesh", summary, md)
    return summary


if __name__ == "__main__":
    main()
