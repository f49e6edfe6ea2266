"""The native kernel against the pure-JAX ``xla_cpu`` kernel, inside one ``bilateral_adam``
update, each as a ratio to ``optax.adam`` measured side by side in this process.

    python -m experiments.benchmarks.native [--quick] [--out DIR] [--rounds N]

Per grid and kernel: cold compile seconds of one update (defaults and a fixed sigma_d), the
update's median time (interleaved rounds), and XLA's planned temporaries over the
parameter's size. The kernel is chosen as a user would, with ``$OPTAX_BILATERAL_KERNEL``
(read when the update is traced). And, one fresh process each, the peak resident memory
gained over 5 updates of a 2048x2048x3 leaf (the first compiles) in parameter sizes, against
Adam's. And the filter alone on each single-device kernel of the CPU, ``plain`` included.
Writes bench_native.json and bench_native.md.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import textwrap
import time
from collections.abc import Sequence

import jax
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks.suite import (
    FIXED_SIGMA_D,
    cold_compile_seconds,
    interleaved,
    temp_mb,
    update_arrays,
)
from optax_bilateral._src.filter import native
from optax_bilateral._src.filter.front import KERNEL_ENV

KERNELS = ("xla_cpu", "native")


def optimizers(full: bool) -> dict[str, optax.GradientTransformation]:
    """Adam, the defaults, a fixed sigma_d at F = 5 and (2-D grids: a full 3-D pass compiles
    for minutes on the xla_cpu kernel) the same in full mode."""
    opts = {
        "adam": optax.adam(0.02),
        "defaults": ob.bilateral_adam(0.02),
        "fixed sigma_d F=5": common.filtered_adam(0.02, sigma_d=FIXED_SIGMA_D, levels=5),
    }
    if full:
        opts["fixed sigma_d F=5 full"] = common.filtered_adam(
            0.02, sigma_d=FIXED_SIGMA_D, levels=5, separable=False
        )
    return opts


def _with_kernel(kernel: str, fn):
    """``fn()`` with every filter traced on ``kernel``: the variable is read when a program is
    traced, so traces cached before (the library's jitted per-leaf steps) are dropped, and so
    are this kernel's after."""
    old = os.environ.get(KERNEL_ENV)
    os.environ[KERNEL_ENV] = kernel
    jax.clear_caches()
    try:
        return fn()
    finally:
        if old is None:
            os.environ.pop(KERNEL_ENV)
        else:
            os.environ[KERNEL_ENV] = old
        jax.clear_caches()


def measure(shape: tuple[int, ...], rounds: int) -> list[dict]:
    params, grad = update_arrays(shape)
    moved = params - 1e-2 * grad
    opts = optimizers(full=len(shape) == 3)
    rows, fns, plans = [], {}, {}
    compile_s = {("adam", ""): sum(cold_compile_seconds(opts["adam"], shape))}
    for kernel in KERNELS:
        for name, opt in opts.items():
            if name == "adam":
                continue

            def build(opt=opt):
                state = opt.init(params)
                up = jax.jit(opt.update)
                for _ in range(2):
                    _, state = up(grad, state, params)
                return up, state, up.lower(grad, state, moved).compile()

            compile_s[(name, kernel)] = _with_kernel(
                kernel, lambda opt=opt: sum(cold_compile_seconds(opt, shape))
            )
            _, state, compiled = _with_kernel(kernel, build)
            fns[f"{name} {kernel}"] = (compiled, (grad, state, moved))
            plans[f"{name} {kernel}"] = temp_mb(compiled)
    adam_state = opts["adam"].init(params)
    fns["adam"] = (jax.jit(opts["adam"].update), (grad, adam_state, moved))
    res = interleaved(fns, rounds, desc=f"update {shape}")
    param_mb = params.size * params.dtype.itemsize / 2**20
    for kernel in KERNELS:
        for name in opts:
            if name == "adam":
                continue
            label = f"{name} {kernel}"
            rows.append(
                {
                    "grid": "x".join(map(str, shape)),
                    "update": name,
                    "kernel": kernel,
                    "compile x adam": compile_s[(name, kernel)] / compile_s[("adam", "")],
                    "update ms": 1e3 * res[label]["median"],
                    "update x adam": res[label]["median"] / res["adam"]["median"],
                    "temporaries / parameter": plans[label] / param_mb,
                }
            )
    return rows


# One process per optimizer: its peak resident memory over `updates` updates of a leaf (the
# first compiles), above what the process held before it made the parameter and its gradient.
_RSS_CHILD = textwrap.dedent(
    """
    import json, resource, sys
    import jax, optax
    import optax_bilateral as ob
    from experiments import common
    from experiments.benchmarks.suite import FIXED_SIGMA_D, update_arrays

    def peak_kib():
        # Linux's VmHWM: this program's own peak (ru_maxrss keeps the parent's across exec).
        try:
            with open("/proc/self/status") as fh:
                return next(int(l.split()[1]) for l in fh if l.startswith("VmHWM:"))
        except (OSError, StopIteration):
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    name, shape, updates = sys.argv[1], tuple(json.loads(sys.argv[2])), int(sys.argv[3])
    jax.block_until_ready(jax.numpy.zeros(3) + 1)  # the runtime started: not the update's
    before = peak_kib()
    params, grad = update_arrays(shape)
    opt = {
        "adam": lambda: optax.adam(0.02),
        "defaults": lambda: ob.bilateral_adam(0.02),
        "fixed sigma_d F=5": lambda: common.filtered_adam(0.02, sigma_d=FIXED_SIGMA_D, levels=5),
    }[name]()
    update = jax.jit(opt.update)
    state = opt.init(params)
    for _ in range(updates):
        u, state = update(grad, state, params)
        params = optax.apply_updates(params, u)
    jax.block_until_ready((params, state))
    after = peak_kib()
    print(json.dumps({"growth_kib": after - before, "param_kib": params.nbytes / 1024}))
    """
)


RSS_RUNS = [("adam", "")] + [(n, k) for k in KERNELS for n in ("defaults", "fixed sigma_d F=5")]


def rss_rows(shape: tuple[int, ...], updates: int, runs=RSS_RUNS) -> list[dict]:
    """Peak RSS growth over ``updates`` updates of one leaf, in parameter sizes, per
    ``(optimizer, kernel)`` of ``runs``, each in a fresh process (the first update's
    compilation included)."""
    rows = []
    for name, kernel in runs:
        env = dict(os.environ, **({KERNEL_ENV: kernel} if kernel else {}))
        proc = subprocess.run(
            [sys.executable, "-c", _RSS_CHILD, name, json.dumps(shape), str(updates)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(
            {
                "grid": "x".join(map(str, shape)),
                "update": name,
                "kernel": kernel or "-",
                "peak RSS growth / parameter": r["growth_kib"] / r["param_kib"],
            }
        )
    return rows


def filter_rows(grids: Sequence[tuple[int, ...]], rounds: int) -> list[dict]:
    """The filter alone (jitted; ``(g, g*g)``, F = 5, sigma_d 0.1) on every single-device kernel
    of the CPU, ``plain`` included: what the CPU would fall back to without ``xla_cpu``."""
    rows = []
    for shape in grids:
        params, grad = update_arrays(shape)
        axes = tuple(range(len(shape) - 1))
        for separable in (True, False) if len(shape) == 3 else (True,):
            fns, extra = {}, {}
            for kernel in (*KERNELS, "plain"):

                def f(g, p, kernel=kernel, separable=separable, axes=axes):
                    return ob.atrous_bilateral(
                        (g, g * g),
                        p,
                        sigma_d=0.1,
                        levels=5,
                        spatial_axes=axes,
                        separable=separable,
                        kernel=kernel,
                    )

                t0 = time.perf_counter()
                compiled = jax.jit(f).lower(grad, params).compile()
                extra[kernel] = (time.perf_counter() - t0, temp_mb(compiled))
                fns[kernel] = (compiled, (grad, params))
            res = interleaved(fns, rounds, desc=f"filter {shape}")
            fields_mb = 2 * params.size * params.dtype.itemsize / 2**20
            for kernel, r in res.items():
                rows.append(
                    {
                        "grid": "x".join(map(str, shape)),
                        "mode": "separable" if separable else "full",
                        "kernel": kernel,
                        "compile s": extra[kernel][0],
                        "filter ms": 1e3 * r["median"],
                        "x native": r["median"] / res["native"]["median"],
                        "temporaries / fields": extra[kernel][1] / fields_mb,
                    }
                )
    return rows


def table(rows: Sequence[dict]) -> str:
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        cells = [f"{v:.3g}" if isinstance(v, float) else str(v) for v in r.values()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="one small grid, few rounds (tests)")
    p.add_argument("--out", default="results/bench_native")
    p.add_argument("--rounds", type=int, default=None)
    args = p.parse_args(argv)
    if not native.available():
        raise SystemExit(f"the native kernel cannot run here: {native.status().reason}")
    grids = (
        [(16, 16, 1)]
        if args.quick
        else [(64, 64, 1), (512, 512, 3), (64, 64, 64, 1), (128, 128, 128, 1)]
    )
    rounds = args.rounds or (3 if args.quick else 15)
    rows = [r for shape in grids for r in measure(shape, rounds)]
    if args.quick:  # a process each: Adam's and one of ours
        rss = rss_rows((32, 32, 3), 2, [("adam", ""), ("fixed sigma_d F=5", "native")])
    else:
        rss = rss_rows((2048, 2048, 3), 5)
    # Beside the update's grids: one channel on a line, and short innermost rows.
    short = [(262144, 1), (128, 128, 16, 1)]
    filters = filter_rows(grids[:1] if args.quick else grids[1:] + short, rounds)
    status = native.status()
    data = {
        "rows": rows,
        "rss": rss,
        "filter": filters,
        "instruction set": status.reason,
        "threads": status.threads,
    }
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_native.json").write_text(json.dumps(data, indent=1))
    md = table(rows) + "\n" + table(rss) + "\n" + table(filters)
    (out / "bench_native.md").write_text(md)
    print(md)
    print(f"instruction set {status.reason}, {status.threads} threads; temporaries: XLA's plan")
    return data


if __name__ == "__main__":
    main()
