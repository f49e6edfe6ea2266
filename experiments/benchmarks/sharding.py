"""Scale-out benchmark: one ``bilateral_adam`` step on a grid sharded over 1, 2, 4, 8 devices.

For every grid (a 2-D texture ``(N, N, C)`` and a 3-D volume ``(N, N, N, C)``), filter
mode (separable / full) and device mesh, it compiles one optimizer update
(``bilateral_adam``: postfilter of ``m, v`` guided by the parameters) two ways:

* ``shard_map``: parameters on an *explicit* mesh (``jax.make_mesh``'s default);
  the filter runs per device with explicit halo exchange
  (``optax_bilateral/_src/filter/sharded.py``);
* ``xla_auto``: parameters on an *auto* mesh; the single-device filter is split
  by XLA's SPMD partitioner.

and reports, per configuration:

* the largest difference from the unsharded step (updates and state);
* whether the updates and state keep the parameters' sharding;
* the time per step (median over interleaved rounds, compilation excluded);
* the bytes the compiled program moves between devices per step, read from its
  HLO: every ``collective-permute`` (operand bytes x source-target pairs),
  ``all-gather`` and ``all-reduce`` (result bytes), summed over devices, on the
  branch a step with all-finite gradients takes;
* the halo volumes it is compared with: ``halo_per_level``, the fields and the
  guide exchanged at every level ``i`` within its radius ``r_i = 2 * 2**i``
  (``2 r_i`` x face area per cut), and ``halo_minimum``, the fields per level plus
  the guide once at the widest radius (the guide never changes), which is what
  must cross devices (corners of 2-axis splits in full mode not counted).

Honest caveat, printed with the table: the devices are *virtual* CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=8``) sharing this machine's
2 cores, so more devices cannot run faster here; the timings show the overhead
of splitting, the byte counts show what a real multi-device run would move.

``python -m experiments.benchmarks.sharding [--quick] [--out DIR] [--only cases,channels]``
writes ``summary.json``, ``table.md`` and ``step_time.png`` to DIR (default
``results/bench_sharding``). ``channels``: the filter of a one-channel field against a
two-channel one on 2 devices (the one-channel fix, BENCHMARKS.md "Design decisions").
"""

from __future__ import annotations

import os
import sys

if "jax" not in sys.modules:
    # Must precede the first jax import: the device count is fixed at start-up.
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8"
    ).strip()

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from experiments import common
from experiments.benchmarks.collectives import collective_stats, halo_bytes

# ----------------------------------------------------------------------------------------
# The benchmark


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    shape: tuple  # spatial shape
    channels: int
    levels: int
    separable: bool
    paths: tuple  # ("shard_map", "xla_auto")


def default_cases(quick: bool) -> list[Case]:
    if quick:
        return [Case("texture 32^2x3, F=2, separable", (32, 32), 3, 2, True, ("shard_map",))]
    return [
        Case(
            "texture 1024^2x3, F=5, separable", (1024, 1024), 3, 5, True, ("shard_map", "xla_auto")
        ),
        Case("texture 512^2x3, F=5, full", (512, 512), 3, 5, False, ("shard_map", "xla_auto")),
        Case("volume 64^3x4, F=4, separable", (64, 64, 64), 4, 4, True, ("shard_map", "xla_auto")),
        # XLA's partitioner needs minutes to compile full 3-D (measured 92 s for 16^3, F=2).
        Case("volume 32^3x4, F=3, full", (32, 32, 32), 4, 3, False, ("shard_map",)),
    ]


MESH_SHAPES = ((1, 1), (2, 1), (4, 1), (8, 1), (4, 2))


def _device_mesh(shape, axis_type):
    devices = np.array(jax.devices()[: math.prod(shape)]).reshape(shape)
    return Mesh(devices, ("x", "y"), axis_types=(axis_type, axis_type))


def _problem(case: Case):
    key = jax.random.PRNGKey(0)
    full = case.shape + (case.channels,)
    params = {"grid": jax.random.uniform(key, full, jnp.float32, 0.05, 1.0)}
    grads = {"grid": jax.random.normal(jax.random.fold_in(key, 1), full, jnp.float32)}
    tx = common.filtered_adam(1e-2, sigma_d=0.1, levels=case.levels, separable=case.separable)
    state = tx.init(params)
    # One step first, so the state's moments are not all zero.
    _, state = jax.jit(tx.update)(grads, state, params)
    return tx, params, grads, state


def _put(tree, ndim, grid_sharding, replicated):
    """``tree`` on the devices: grid-shaped leaves split, the others replicated."""
    return jax.tree.map(
        lambda a: jax.device_put(a, grid_sharding if np.ndim(a) == ndim else replicated), tree
    )


def _max_diff(a, b) -> float:
    return max(
        float(jnp.max(jnp.abs(jnp.asarray(x, jnp.float32) - jnp.asarray(y, jnp.float32))))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))
        if np.size(x)
    )


def _keeps_sharding(tree, sharding_of_grid, ndim) -> bool:
    """Every grid-shaped leaf of ``tree`` has the parameters' sharding."""
    ok = True
    for leaf in jax.tree.leaves(tree):
        if np.ndim(leaf) == ndim:
            ok &= leaf.sharding.is_equivalent_to(sharding_of_grid, ndim)
    return bool(ok)


def run_case(case: Case, repeats: int, quick: bool = False, progress: bool = True) -> list[dict]:
    from tqdm.auto import tqdm

    tx, params, grads, state = _problem(case)
    step = jax.jit(tx.update)
    ref_out = step(grads, state, params)
    ndim = len(case.shape) + 1
    # name -> (compiled step, its arguments, its table row)
    configs = {
        "unsharded": (step.lower(grads, state, params).compile(), (grads, state, params), None)
    }
    rows = []
    mesh_shapes = MESH_SHAPES[:4] if quick else MESH_SHAPES
    todo = [(path, m) for path in case.paths for m in mesh_shapes]
    for path, mesh_shape in tqdm(todo, desc=case.name, disable=not progress, leave=False):
        device_mesh = _device_mesh(
            mesh_shape, AxisType.Explicit if path == "shard_map" else AxisType.Auto
        )
        sh = NamedSharding(device_mesh, P("x", "y"))
        replicated = NamedSharding(device_mesh, P())
        args = tuple(_put(t, ndim, sh, replicated) for t in (grads, state, params))
        t0 = time.perf_counter()
        compiled = jax.jit(tx.update).lower(*args).compile()
        compile_s = time.perf_counter() - t0
        out = compiled(*args)
        stats = collective_stats(compiled.as_text())
        blocks = tuple(mesh_shape) + (1,) * (len(case.shape) - 2)
        # postfilter: fields m and v (2C channels), guide theta (C channels)
        halo = halo_bytes(
            case.shape,
            blocks,
            case.levels,
            fields=2 * case.channels,
            guide=case.channels,
            separable=case.separable,
        )
        moved = sum(v["bytes"] for v in stats.values())
        grid_bytes = math.prod(case.shape) * case.channels * 4
        row = dict(
            case=case.name,
            path=path,
            devices=math.prod(mesh_shape),
            mesh="x".join(map(str, mesh_shape)),
            max_abs_diff=_max_diff(out, ref_out),
            sharding_kept=_keeps_sharding(out, sh, ndim),
            compile_s=compile_s,
            permute_bytes=stats["collective-permute"]["bytes"],
            permute_count=stats["collective-permute"]["count"],
            all_gather_bytes=stats["all-gather"]["bytes"],
            all_gather_count=stats["all-gather"]["count"],
            largest_all_gather_vs_grid=stats["all-gather"]["max_bytes"] / grid_bytes,
            all_reduce_bytes=stats["all-reduce"]["bytes"],
            bytes_moved=moved,
            halo_per_level=halo["per_level"],
            halo_minimum=halo["minimum"],
            moved_over_minimum=(moved / halo["minimum"])
            if halo["minimum"]
            else (0.0 if moved == 0 else math.inf),
        )
        rows.append(row)
        configs[(path, row["mesh"])] = (compiled, args, row)

    # Interleaved timing: every round runs every configuration once.
    times = {k: [] for k in configs}
    for c, a, _ in configs.values():
        jax.block_until_ready(c(*a))
    for _ in range(repeats):
        for k, (c, a, _) in configs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(c(*a))
            times[k].append(time.perf_counter() - t0)
    base = float(np.median(times["unsharded"]))
    for k, (_, _, row) in configs.items():
        if row is not None:
            row["step_ms"] = 1e3 * float(np.median(times[k]))
            row["vs_unsharded"] = row["step_ms"] / (1e3 * base)
    rows.insert(
        0,
        dict(
            case=case.name,
            path="unsharded",
            devices=1,
            mesh="-",
            step_ms=1e3 * base,
            vs_unsharded=1.0,
            max_abs_diff=0.0,
            sharding_kept=True,
            bytes_moved=0,
        ),
    )
    return rows


NOTE = (
    "Devices are virtual CPU devices (XLA_FLAGS=--xla_force_host_platform_device_count=8) "
    "sharing this machine's 2 cores with other jobs: splitting cannot speed a step up here, "
    "so step_ms shows the cost of splitting, not a speed-up. Bytes are read from the "
    "compiled HLO and are what a real multi-device run would move per step."
)

COLUMNS = (
    "case",
    "path",
    "mesh",
    "devices",
    "step_ms",
    "vs_unsharded",
    "compile_s",
    "max_abs_diff",
    "sharding_kept",
    "bytes_moved",
    "halo_per_level",
    "halo_minimum",
    "moved_over_minimum",
    "permute_count",
    "all_gather_count",
    "largest_all_gather_vs_grid",
)


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(r["case"] for r in rows))
    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 3.4), dpi=110, squeeze=False)
    for ax, case in zip(axes[0], cases):
        base = next(r for r in rows if r["case"] == case and r["path"] == "unsharded")["step_ms"]
        ax.axhline(base, color="k", lw=1, ls=":", label="unsharded")
        for p in ("shard_map", "xla_auto"):
            pts = [
                r for r in rows if r["case"] == case and r["path"] == p and r["mesh"].endswith("x1")
            ]
            if pts:
                ax.plot([r["devices"] for r in pts], [r["step_ms"] for r in pts], "o-", label=p)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("virtual CPU devices (row split)")
        ax.set_ylabel("ms per step")
        ax.set_title(case, fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle("2 shared CPU cores: splitting shows overhead, not speed-up", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


SECTIONS = ("cases", "channels")


def channel_rows(quick: bool) -> list[dict]:
    """The filter of one channel against two, each array split over 2 devices along its
    first axis (explicit mesh): the sharded kernel's side of benchmark.channel_rows."""
    from experiments.benchmarks import suite as bm

    mesh = _device_mesh((2, 1), AxisType.Explicit)
    split = NamedSharding(mesh, P("x"))
    with jax.set_mesh(mesh):
        return bm.channel_rows(quick, 2 if quick else 10, lambda a: jax.device_put(a, split))


def main(argv=None) -> dict:
    def extra(p):
        p.add_argument(
            "--only",
            default=",".join(SECTIONS),
            help=f"comma-separated sections to run, of {SECTIONS}",
        )

    args = common.parse_args(
        "sharded bilateral_adam step: time and bytes moved", "results/bench_sharding", argv, extra
    )
    only = [x.strip() for x in args.only.split(",") if x.strip()]
    if not only or any(x not in SECTIONS for x in only):
        raise ValueError(f"--only: choose from {SECTIONS}, got {args.only!r}")
    if jax.device_count() < 8:
        raise RuntimeError(
            "bench_sharding needs 8 devices: run it as its own process (it sets "
            "XLA_FLAGS=--xla_force_host_platform_device_count=8 before importing jax)"
        )
    repeats = 3 if args.quick else 7
    rows = []
    if "cases" in only:
        for case in default_cases(args.quick):
            rows += run_case(case, repeats, args.quick)
    channels = channel_rows(args.quick) if "channels" in only else []
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {
        "note": NOTE,
        "quick": args.quick,
        "rows": rows,
        "channels": channels,
        "jax": jax.__version__,
        "devices": jax.device_count(),
    }
    path = common.write_summary(args.out, {}, **summary)
    table = common.markdown_table(rows, COLUMNS)
    chan = common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in channels])
    head = "### The filter alone (F = 3), one channel against two, 2 devices"
    md = f"{NOTE}\n\n{table}\n\n{head}\n\n{chan}\n"
    (args.out / "table.md").write_text(md)
    if rows:
        _plot(rows, args.out / "step_time.png")
    print(md)
    print(f"wrote {path}")
    return summary


if __name__ == "__main__":
    main()
