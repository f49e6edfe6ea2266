"""What ``ob.sparse_adam`` costs over ``ob.bilateral_adam``'s defaults (issue #54: at most
1.2x on 512x512x3), side by side in one process, with ``optax.adam`` for scale.

    python -m experiments.benchmarks.sparse [--quick] [--out DIR] [--rounds N]

Per grid and gradient (``dense``: every texel touched, as the benchmarks' other updates;
``sparse``: 4 texels in 144 touched, a far camera's 12 texels per pixel, which turns the
coarse path on): the update's median time over interleaved rounds, cold compile seconds,
and XLA's planned temporaries over the parameter's size, for Adam, the defaults,
``sparse_adam`` and ``sparse_adam`` as it was before 2026-12-01 (``sigma_d="sparse"``, whose
extra filter level runs on a sparse leaf, and a coarse share of 0.25).
Writes bench_sparse.json and bench_sparse.md.
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks.suite import (
    cold_compile_seconds,
    interleaved,
    machine,
    temp_mb,
    update_arrays,
)

LEARNING_RATE = 0.02
EVERY = 12  # a far camera: one bilinear lookup's texels in 12 x 12


def optimizers() -> dict[str, optax.GradientTransformation]:
    return {
        "adam": optax.adam(LEARNING_RATE),
        "defaults": ob.bilateral_adam(LEARNING_RATE),
        "sparse_adam": ob.sparse_adam(LEARNING_RATE),
        # Its defaults before 2026-12-01: the sparse rule's extra level on a sparse leaf.
        "sparse_adam, extra level": ob.sparse_adam(
            LEARNING_RATE, sigma_d="sparse", coarse_share=0.25
        ),
    }


def far_camera(grad: jax.Array) -> jax.Array:
    """``grad`` on 2 x 2 texels of every :data:`EVERY` x :data:`EVERY` block, 0 elsewhere."""
    keep = np.zeros(grad.shape[:-1], bool)
    keep[::EVERY, ::EVERY] = keep[1::EVERY, ::EVERY] = True
    keep[::EVERY, 1::EVERY] = keep[1::EVERY, 1::EVERY] = True
    return jnp.where(jnp.asarray(keep)[..., None], grad, 0)


def rows(shape: tuple[int, ...], rounds: int) -> list[dict]:
    params, dense = update_arrays(shape)
    moved = params - 1e-2 * dense
    # Compiling does not depend on the gradient's values: once per method.
    compile_s = {n: sum(cold_compile_seconds(o, shape)) for n, o in optimizers().items()}
    out = []
    for gradient, grad in (("dense", dense), ("sparse", far_camera(dense))):
        fns, extra = {}, {}
        for name, opt in optimizers().items():
            program = jax.jit(opt.update)
            state = opt.init(params)
            for _ in range(3):
                _, state = program(grad, state, params)
            fns[name] = (program, (grad, state, moved))
            compiled = program.lower(grad, state, moved).compile()
            extra[name] = {
                "temporaries / parameter": temp_mb(compiled) * 2**20 / params.nbytes,
                "compile s": compile_s[name],
            }
        timed = interleaved(fns, rounds, desc=f"{gradient} {shape}")
        samples = {k: v["samples"] for k, v in timed.items()}
        for name in fns:
            row = {"grid": "x".join(map(str, shape)), "gradient": gradient, "method": name}
            row["ms (median)"] = 1e3 * timed[name]["median"]
            row["x adam (paired)"] = common.paired_ratio(samples, name, "adam")
            row["x defaults (paired)"] = common.paired_ratio(samples, name, "defaults")
            out.append({**row, **extra[name]})
    return out


def markdown(table: Sequence[dict]) -> str:
    keys = list(table[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in table:
        cells = [f"{r[k]:.3g}" if isinstance(r[k], float) else str(r[k]) for k in keys]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> dict:
    def extra(p):
        p.add_argument("--rounds", type=int, default=None, help="timing rounds (default 30)")

    args = common.parse_args(__doc__.splitlines()[0], "results/bench_sparse", argv, extra=extra)
    shapes = [(64, 64, 3)] if args.quick else [(512, 512, 3), (128, 128, 3)]
    rounds = args.rounds or (3 if args.quick else 30)
    table = [r for s in shapes for r in rows(s, rounds)]
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"machine": machine(), "rows": table}
    (out / "bench_sparse.json").write_text(json.dumps(result, indent=1) + "\n")
    md = markdown(table)
    (out / "bench_sparse.md").write_text(md)
    print(md)
    return result


if __name__ == "__main__":
    main()
