"""The largest texture and volume one process can optimise with ``bilateral_adam``'s defaults.

    python -m experiments.largest_grid [--memory-gib 24] [--run-gib G] [--steps 3] [--quick]

For textures n x n x 3 and volumes n^3 x 1 (float32) it compiles, from shapes alone, the
jitted step of a training loop, ``(params, state, grads) -> (params, state)`` with the
parameters and the state donated (updated in place), and reads XLA's plan of its memory:
arguments + outputs - aliased + temporaries. That plan is affine in the number of grid
points, so two sizes give the line and the largest n on a grid of ``--multiple`` whose plan
fits ``--memory-gib`` less ``--reserve-gib`` (the interpreter, JAX's runtime, the
gradient's own program) is then checked by compiling it. The largest n that fits
``--run-gib`` (default: the same memory; less on a machine shared with other jobs) is run
for ``--steps`` steps from fresh parameters with a noisy gradient: seconds per step and
the process's peak resident memory (``resource.getrusage``) against the plan.

Writes ``largest_grid.json`` and ``largest_grid.md`` to ``--out`` (default
``results/largest_grid``).
"""

from __future__ import annotations

import resource
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

import optax_bilateral as ob
from experiments import common

GIB = 2**30
KINDS = {"texture": lambda n: (n, n, 3), "volume": lambda n: (n, n, n, 1)}


def make_step(opt: optax.GradientTransformation):
    """A training loop's step: parameters and state donated, updated in place."""

    def step(params, state, grads):
        updates, state = opt.update(grads, state, params)
        return optax.apply_updates(params, updates), state

    return jax.jit(step, donate_argnums=(0, 1))


def planned_bytes(opt: optax.GradientTransformation, shape: tuple[int, ...]) -> int:
    """XLA's plan for one step on a float32 grid ``shape`` (nothing is allocated)."""
    p = jax.ShapeDtypeStruct(shape, jnp.float32)
    state = jax.eval_shape(opt.init, p)
    ma = make_step(opt).lower(p, state, p).compile().memory_analysis()
    return int(
        ma.argument_size_in_bytes
        + ma.output_size_in_bytes
        - ma.alias_size_in_bytes
        + ma.temp_size_in_bytes
    )


def largest_n(opt, kind: str, budget: int, multiple: int, probes: Sequence[int]) -> dict:
    """The largest n (a multiple of ``multiple``) whose planned step fits ``budget``."""
    shape_of = KINDS[kind]
    sizes = {n: int(np.prod(shape_of(n))) for n in probes}
    plans = {n: planned_bytes(opt, shape_of(n)) for n in probes}
    slope, intercept = np.polyfit(list(sizes.values()), list(plans.values()), 1)
    dim = len(shape_of(1)) - 1
    n = int(((budget - intercept) / slope / shape_of(1)[-1]) ** (1 / dim)) // multiple * multiple
    while n > multiple and planned_bytes(opt, shape_of(n)) > budget:  # the fit is checked
        n -= multiple
    plan = planned_bytes(opt, shape_of(n))
    return {
        "kind": kind,
        "n": n,
        "shape": "x".join(map(str, shape_of(n))),
        "elements": int(np.prod(shape_of(n))),
        "planned GiB": plan / GIB,
        "planned bytes per element": float(slope),
        "params GiB": 4 * np.prod(shape_of(n)) / GIB,
        "fits": plan <= budget,
    }


def peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def run_steps(opt, shape: tuple[int, ...], steps: int) -> dict:
    """``steps`` jitted steps of a noisy quadratic on a fresh grid; the first compiles."""
    key = jax.random.key(0)
    params = jax.jit(lambda k: jax.random.uniform(k, shape, minval=0.2, maxval=0.8))(key)
    state = jax.jit(opt.init)(params)
    grad_of = jax.jit(lambda p, k: (p - 0.5) + 0.3 * jax.random.normal(k, shape))
    step, seconds = make_step(opt), []
    for i in tqdm(range(steps + 1), desc=f"steps {shape}", leave=False):
        t0 = time.perf_counter()
        grads = grad_of(params, jax.random.fold_in(key, i))
        params, state = step(params, state, grads)
        jax.block_until_ready(params)
        seconds.append(time.perf_counter() - t0)
        del grads
    error = float(jnp.mean(jnp.abs(params - 0.5)))
    return {
        "first step s (compiles)": seconds[0],
        "s per step (median)": float(np.median(seconds[1:])),
        "peak RSS GiB": peak_rss_bytes() / GIB,
        "mean |params - 0.5| after": error,
        "finite": bool(jnp.all(jnp.isfinite(params))),
    }


def main(argv: Sequence[str] | None = None) -> dict:
    def extra(p):
        p.add_argument("--memory-gib", type=float, default=24.0, help="the machine's memory")
        p.add_argument("--reserve-gib", type=float, default=2.0, help="kept for the rest")
        p.add_argument(
            "--run-gib",
            type=float,
            default=None,
            help="memory the demonstration may use (default: --memory-gib less the reserve)",
        )
        p.add_argument("--steps", type=int, default=3)
        p.add_argument("--multiple", type=int, default=None, help="n is a multiple of this")

    args = common.parse_args("largest grid under the defaults", "results/largest_grid", argv, extra)
    quick = args.quick or common.quick_from_env()
    opt = ob.bilateral_adam(0.02)  # the defaults
    budget = int((args.memory_gib - args.reserve_gib) * GIB)
    run_budget = budget if args.run_gib is None else int(args.run_gib * GIB)
    probes = {"texture": (64, 128), "volume": (16, 32)} if quick else None
    rows = []
    for kind in tqdm(KINDS, desc="largest grid"):
        multiple = args.multiple or (16 if quick else {"texture": 256, "volume": 16}[kind])
        pr = probes[kind] if probes else {"texture": (1024, 2048), "volume": (64, 128)}[kind]
        best = largest_n(opt, kind, budget, multiple, pr)
        best["budget"] = f"{args.memory_gib:g} GiB less {args.reserve_gib:g}"
        rows.append(best)
        run = best if run_budget == budget else largest_n(opt, kind, run_budget, multiple, pr)
        ran = {**run, "budget": f"run here: {run_budget / GIB:g} GiB"}
        ran.update(run_steps(opt, KINDS[kind](run["n"]), args.steps))
        ran["peak RSS / plan"] = ran["peak RSS GiB"] / ran["planned GiB"]
        rows.append(ran)
    data = {"rows": rows, "optimizer": "bilateral_adam(0.02)", "steps": args.steps}
    columns = [
        "kind",
        "budget",
        "shape",
        "params GiB",
        "planned GiB",
        "planned bytes per element",
        "s per step (median)",
        "peak RSS GiB",
        "peak RSS / plan",
        "finite",
    ]
    table = [{c: common.fmt(r.get(c, "")) for c in columns} for r in rows]
    md = "\n".join(
        [
            "### The largest grids under bilateral_adam(0.02) (the defaults)",
            "",
            "planned: XLA's plan of one donated step (arguments + outputs - aliased + "
            "temporaries); run: a few jitted steps, median seconds after the first (which "
            "compiles), the process's peak resident memory.",
            "",
            common.markdown_table(table, columns),
        ]
    )
    common.write_results(args.out, "largest_grid", data, md)
    print(md)
    return data


if __name__ == "__main__":
    main()
