"""What ``sigma_d="auto"`` and ``"sure"`` cost per update: the same update with a fixed
``sigma_d``.

    python -m experiments.auto_cost [--quick] [--out DIR]

Times one jitted ``bilateral_adam`` update (postfilter, F = 3, separable) with
``sigma_d="auto"``, ``"sure"`` (F chosen among 2-3) and ``0.1``, ``"sure"`` with
``levels=5`` (F chosen among 2-5, its default ``SURE_LEVELS``), and ``optax.adam``'s, on a
512x512x3 texture
and a 64^3x1 volume, interleaved in one process; prints and writes the paired ratios
(median over rounds of the per-round ratio, :func:`experiments.common.paired_ratio`).
Target (issue #17): auto / fixed <= 1.2 ("sure" is an opt-in that buys accuracy with time;
it has no target).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments import common

GRIDS = {"texture 512^2x3": (512, 512, 3), "volume 64^3x1": (64, 64, 64, 1)}
QUICK_GRIDS = {"texture 64^2x3": (64, 64, 3), "volume 16^3x1": (16, 16, 16, 1)}
TARGET = 1.2


def _step(opt, params, grads):
    update = jax.jit(opt.update)

    def step(carry, i):
        del i
        state, p = carry
        u, state = update(grads, state, p)
        return (state, optax.apply_updates(p, u)), u

    return step, (opt.init(params), params)


def measure(shape, rounds: int, inner: int) -> dict:
    key = jax.random.PRNGKey(0)
    params = jax.random.uniform(key, shape, jnp.float32, 0.05, 1.0)
    grads = jax.random.normal(jax.random.fold_in(key, 1), shape, jnp.float32)
    axes = tuple(range(len(shape) - 1))
    opts = {
        "auto": ob.bilateral_adam(1e-2, sigma_d="auto", levels=3, spatial_axes=axes),
        "sure": ob.bilateral_adam(1e-2, sigma_d="sure", levels=3, spatial_axes=axes),
        "sure5": ob.bilateral_adam(1e-2, sigma_d="sure", levels=5, spatial_axes=axes),
        "fixed": ob.bilateral_adam(1e-2, sigma_d=0.1, levels=3, spatial_axes=axes),
        "adam": optax.adam(1e-2),
    }
    steps = {k: _step(o, params, grads) for k, o in opts.items()}
    common.time_steps_samples(steps, rounds=1, inner=1)  # compile
    samples = common.time_steps_samples(steps, rounds=rounds, inner=inner)
    ms = {k: 1e3 * float(np.median(v)) for k, v in samples.items()}
    return {
        "ms": ms,
        "auto_vs_fixed": common.paired_ratio(samples, "auto", "fixed"),
        "fixed_vs_adam": common.paired_ratio(samples, "fixed", "adam"),
        "auto_vs_adam": common.paired_ratio(samples, "auto", "adam"),
        "sure_vs_fixed": common.paired_ratio(samples, "sure", "fixed"),
        "sure_vs_auto": common.paired_ratio(samples, "sure", "auto"),
        "sure5_vs_fixed": common.paired_ratio(samples, "sure5", "fixed"),
        "sure5_vs_auto": common.paired_ratio(samples, "sure5", "auto"),
    }


def main(argv=None) -> dict:
    args = common.parse_args(
        "cost of sigma_d='auto' and 'sure' per update", "results/auto_cost", argv
    )
    grids, rounds, inner = (QUICK_GRIDS, 3, 2) if args.quick else (GRIDS, 15, 5)
    rows = {name: measure(shape, rounds, inner) for name, shape in grids.items()}
    lines = [
        "| grid | auto ms | sure ms | sure F<=5 ms | fixed sigma_d ms | optax.adam ms "
        "| auto / fixed (paired) | sure / fixed | sure / auto | sure F<=5 / fixed "
        f"| sure F<=5 / auto | fixed / Adam | target auto / fixed <= {TARGET} |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        met = "met" if r["auto_vs_fixed"] <= TARGET else "not met"
        lines.append(
            f"| {name} | {r['ms']['auto']:.3g} | {r['ms']['sure']:.3g} | {r['ms']['sure5']:.3g} "
            f"| {r['ms']['fixed']:.3g} | {r['ms']['adam']:.3g} | {r['auto_vs_fixed']:.3f} "
            f"| {r['sure_vs_fixed']:.2f} | {r['sure_vs_auto']:.2f} | {r['sure5_vs_fixed']:.2f} "
            f"| {r['sure5_vs_auto']:.2f} | {r['fixed_vs_adam']:.2f} | {met} |"
        )
    md = (
        "bilateral_adam update (postfilter, F = 3 unless named, separable), jitted, medians of "
        f"{rounds} interleaved rounds of {inner} steps; `python -m experiments.auto_cost`.\n\n"
        + "\n".join(lines)
    )
    print(md)
    common.write_results(args.out, "auto_cost", {"rows": rows, "quick": args.quick}, md)
    return rows


if __name__ == "__main__":
    main()
