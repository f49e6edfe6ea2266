"""Where one update's XLA compile goes: its phases and each kernel's compile, traced.

    python -m tools.compile_profile --shape 512x512x3
    python -m tools.compile_profile --shape 32x32x1 --wrapper MultiSteps

Lowers ``jax.jit(update)`` of ``optax.adam`` and of ``bilateral_adam``'s defaults (inside
``optax.MultiSteps`` or ``optax.apply_if_finite`` with ``--wrapper``: what an eager call of
the wrapper compiles every time) from cold caches, then compiles each under
``jax.profiler.trace`` and adds up XLA's own trace events: the backend's phases
(``FusionCompiler::Compile`` is one per XLA kernel, summed over the two compile threads;
``JitCompiler::Compile`` the machine code; ``ThunkEmitter`` the program's steps) and each
kernel's compile with its op count. The kernels' compile follows their number, not their
size (docs/research/compilation.md). Writes ``compile_profile.json`` and ``.md``.
"""

from __future__ import annotations

import collections
import time

import jax
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks import suite as bm
from tools.profile_update import traced_events

PHASES = (
    "CpuCompiler::RunBackend",
    "FusionCompiler::Compile",
    "JitCompiler::Compile",
    "ThunkEmitter::EmitEntryComputation",
)
WRAPPERS = {
    "bare": lambda opt: opt,
    "MultiSteps": lambda opt: optax.MultiSteps(opt, 4),
    "apply_if_finite": lambda opt: optax.apply_if_finite(opt, 3),
}


def traced_compile(lowered):
    """The compiled program, its seconds to compile and the XLA trace events it made."""
    out = {}

    def run():
        t0 = time.perf_counter()
        out["compiled"] = lowered.compile()
        out["seconds"] = time.perf_counter() - t0

    events = traced_events(run)
    return out["compiled"], out["seconds"], events


def profile(opt, shape) -> dict:
    """One cold lowering and traced compile of ``jax.jit(opt.update)`` on a leaf of ``shape``."""
    params, grad = bm.update_arrays(shape)
    state = opt.init(params)
    jax.clear_caches()
    t0 = time.perf_counter()
    lowered = jax.jit(opt.update).lower(grad, state, params)
    lower_s = time.perf_counter() - t0
    compiled, compile_s, events = traced_compile(lowered)
    ms = collections.Counter()
    for e in events:
        ms[e["name"]] += e["dur"] / 1e3
    kernels = [
        {"kernel": e["args"].get("module", "?"), "ops": int(e["args"].get("op_count", 0))}
        | {"ms": e["dur"] / 1e3}
        for e in events
        if e["name"] == "FusionCompiler::Compile"
    ]
    return {
        "trace + lower s": lower_s,
        "compile s": compile_s,
        "kernels": bm.kernel_count(compiled),
        **{f"{p} ms": ms[p] for p in PHASES},
        "per kernel": sorted(kernels, key=lambda k: -k["ms"]),
    }


def main(argv=None) -> dict:
    def extra(p):
        p.add_argument("--shape", default="64x64x1", help="the leaf, e.g. 512x512x3")
        p.add_argument("--wrapper", choices=sorted(WRAPPERS), default="bare")

    args = common.parse_args(
        "an update's XLA compile, traced", "results/compile_profile", argv, extra
    )
    shape = tuple(int(n) for n in args.shape.split("x") if n.isdigit())
    if len(shape) < 2 or "x".join(map(str, shape)) != args.shape or min(shape) < 1:
        raise ValueError(f"--shape must be HxW, HxWxC, DxHxWxC (sizes >= 1), got {args.shape!r}")
    shape = (16, 16, 1) if args.quick else shape
    bm.cold_compile_seconds(optax.sgd(0.1), (4, 4, 1))  # JAX's own start-up, paid once
    wrap = WRAPPERS[args.wrapper]
    result = {
        name: profile(wrap(make()), shape)
        for name, make in (
            ("adam", lambda: optax.adam(0.02)),
            ("ours", lambda: ob.bilateral_adam(0.02)),
        )
    }
    rows = [
        {"program": k} | {c: v for c, v in r.items() if c != "per kernel"}
        for k, r in result.items()
    ]
    kernels = [{"program": k} | row for k, r in result.items() for row in r["per kernel"]]
    intro = (
        f"One cold compile of the update on a {shape} leaf ({args.wrapper}); "
        f"`python -m tools.compile_profile --shape {'x'.join(map(str, shape))} "
        f"--wrapper {args.wrapper}`. Phases summed over XLA's compile threads."
    )
    md = common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in rows])
    md += "\n\n" + common.markdown_table(
        [{k: common.fmt(v) for k, v in r.items()} for r in kernels]
    )
    md = f"{intro}\n\n{md}"
    print(md)
    common.write_results(args.out, "compile_profile", {"programs": result, "quick": args.quick}, md)
    return result


if __name__ == "__main__":
    main()
