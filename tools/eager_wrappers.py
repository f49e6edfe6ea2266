"""Seconds and compilations per eager call of optax's wrappers around an optimizer.

    python -m tools.eager_wrappers [--quick] [--out DIR]

``optax.adam`` and ``bilateral_adam`` on a 32x32x1 leaf, bare and inside ``optax.chain``,
``optax.MultiSteps`` and ``optax.apply_if_finite``, each called without ``jax.jit``: the first
call's seconds, then every later call's, and how many XLA compilations each call started
(docs/jit.md, "Eager updates"). Writes ``eager_wrappers.json`` and ``.md``.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks.compiles import CompileCounter

WRAPPERS = {
    "bare": lambda opt: opt,
    "chain": lambda opt: optax.chain(optax.clip(1.0), opt),
    "MultiSteps": lambda opt: optax.MultiSteps(opt, 4),
    "apply_if_finite": lambda opt: optax.apply_if_finite(opt, 3),
}
INNER = {"optax.adam": lambda: optax.adam(0.02), "bilateral_adam": lambda: ob.bilateral_adam(0.02)}


def calls(opt, params, grads, n: int) -> list[tuple[float, int]]:
    """``(seconds, compilations)`` of ``n`` eager calls of ``opt.update``."""
    state, out = opt.init(params), []
    for _ in range(n):
        with CompileCounter() as counter:
            t = time.perf_counter()
            updates, state = opt.update(grads, state, params)
            jax.block_until_ready(updates)
        out.append((time.perf_counter() - t, counter.count))
    return out


def main(argv=None) -> list[dict]:
    args = common.parse_args("eager calls of optax's wrappers", "results/eager_wrappers", argv)
    shape, n = ((16, 16, 1), 2) if args.quick else ((32, 32, 1), 4)
    params = jnp.full(shape, 0.5, jnp.float32)
    grads = jax.random.normal(jax.random.PRNGKey(0), shape)
    rows = []
    for inner, make in INNER.items():
        for wrapper, wrap in WRAPPERS.items():
            measured = calls(wrap(make()), params, grads, n)
            rows.append(
                {
                    "optimizer": inner,
                    "wrapper": wrapper,
                    "first call s": measured[0][0],
                    "later calls s": [round(s, 4) for s, _ in measured[1:]],
                    "compilations per call": [c for _, c in measured],
                }
            )
    intro = f"Eager calls on a {shape} leaf; `python -m tools.eager_wrappers`."
    common.write_rows(args.out, "eager_wrappers", rows, intro, args.quick)
    return rows


if __name__ == "__main__":
    main()
