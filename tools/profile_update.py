"""Where an update's time goes: its compiled kernels, timed by JAX's profiler.

    python -m tools.profile_update --shape 512x512 --log-guide
    python -m tools.profile_update --shape 512x512x3 --full --calls 20
    python -m tools.profile_update --shape 512x512x3 --defaults

Compiles ``bilateral_adam``'s update (the optimizer of ``tools.ab_update``: the
texture experiment's, with ``--log-guide`` its log guide) and ``optax.adam``'s on the same
arrays, times both untraced (``benchmark.interleaved``), then runs each ``--calls`` times
under ``jax.profiler.trace`` and adds up, per call, the time of every compiled kernel
(XLA fusion or custom call), grouped by family: a fusion's name without its ``.N``
suffix, a custom call's target. The native filter kernel (``kernel="auto"`` on the CPU) is
one custom call per cascade (``optax_bilateral_atrous_fields`` when it filters Adam's
moments), each native statistic another; with ``OPTAX_BILATERAL_KERNEL=xla_cpu``,
``select_exponential_fusion`` kernels compute the weights (one exp per pair of taps),
``multiply_divide_fusion`` kernels are the passes, and ``wrapped_pad`` /
``*_pad_fusion`` kernels pad the fields for the next pass. Writes ``profile.json`` and
``profile.md`` to ``--out``.

The profiler slows every kernel (here by ~1.5-3x, unevenly), so compare the families of
one run with each other, not with untraced timings; the untraced medians are printed
beside them for scale. Run it under ``taskset -c 0`` to see what one core does.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import re
import tempfile
from collections.abc import Sequence

import jax
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks import suite as bm
from tools import ab_update

_KERNEL = re.compile(r"%([\w.\-]+) = [^=]*? (fusion|custom-call)\((.*)")
_TARGET = re.compile(r'custom_call_target="([^"]+)"')


def kernel_names(compiled) -> dict[str, str]:
    """The kernels (XLA fusions, and custom calls: the native kernels) of a compiled program,
    in every branch, each with its family: a fusion's name without its ``.N`` suffix
    (``select_exponential_fusion.12`` -> ``select_exponential_fusion``), a custom call's
    target (``optax_bilateral_atrous``), so that each native call is told apart."""
    names = {}
    for name, kind, rest in _KERNEL.findall(compiled.as_text()):
        target = _TARGET.search(rest) if kind == "custom-call" else None
        names[name] = target.group(1) if target else re.sub(r"\.\d+$", "", name)
    return names


def traced_events(run) -> list[dict]:
    """The complete events (``"ph": "X"``) of ``jax.profiler.trace`` around ``run()``."""
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            run()
        paths = glob.glob(f"{tmp}/**/*.trace.json.gz", recursive=True)
        if not paths:
            raise RuntimeError("jax.profiler.trace wrote no perfetto trace")
        with gzip.open(paths[0]) as fh:
            events = json.load(fh)["traceEvents"]
    return [e for e in events if e.get("ph") == "X"]


def traced_kernels(fn, args, names: dict[str, str], calls: int) -> dict[str, dict]:
    """{family: {"kernels per call", "us per call"}} over ``calls`` traced calls of ``fn``."""
    jax.block_until_ready(fn(*args))

    def run():
        for _ in range(calls):
            jax.block_until_ready(fn(*args))

    count, dur = collections.Counter(), collections.Counter()
    for e in traced_events(run):
        if e.get("name") in names:
            count[names[e["name"]]] += 1
            dur[names[e["name"]]] += e["dur"]
    return {k: {"kernels per call": count[k] / calls, "us per call": dur[k] / calls} for k in count}


def profile(
    shape,
    levels: int,
    separable: bool,
    log_guide: bool,
    calls: int,
    rounds: int,
    defaults: bool = False,
) -> dict:
    params, grad = ab_update.arrays(shape)
    ours = ab_update.optimizer(ob, levels, separable, log_guide, defaults)
    opts = {"adam": optax.adam(1e-2), "ours": ours}
    # The guide moved since the state's last step, as in an optimisation (at rest,
    # sigma_d="auto" measures the guide's contrast again: a step it does not take then).
    moved = params - 1e-2 * grad
    progs = {}
    for k, opt in opts.items():
        prog = bm.update_program(opt)
        state = bm.warm_state(opt, params, grad)
        progs[k] = (prog, (grad, state, moved))
    wall = bm.interleaved(progs, rounds, 3, desc="untraced")
    out = {
        "shape": list(shape),
        "levels": levels,
        "separable": separable,
        "log_guide": log_guide,
        "defaults": defaults,
        "calls": calls,
        "programs": {},
    }
    for k, (prog, args) in progs.items():
        compiled = prog.lower(*args).compile()
        names = kernel_names(compiled)
        fams = traced_kernels(prog, args, names, calls)
        total = sum(v["us per call"] for v in fams.values())
        out["programs"][k] = {
            "untraced ms (median)": 1e3 * wall[k]["median"],
            "traced kernel ms per call": 1e-3 * total,
            "kernels compiled": len(names),
            "kernels run per call": sum(v["kernels per call"] for v in fams.values()),
            "temp MB": bm.temp_mb(compiled),
            "families": {
                f: dict(v, share=v["us per call"] / total if total else float("nan"))
                for f, v in sorted(fams.items(), key=lambda kv: -kv[1]["us per call"])
            },
        }
    return out


def markdown(result: dict) -> str:
    setting = (
        "bilateral_adam(0.02) defaults"
        if result.get("defaults")
        else f"F={result['levels']}, {'separable' if result['separable'] else 'full'}"
        f"{', log guide' if result['log_guide'] else ''}"
    )
    head = (
        f"update kernels, shape {'x'.join(map(str, result['shape']))}, {setting}, "
        f"{result['calls']} traced calls\n\n"
    )
    summary = [
        {
            "program": k,
            **{
                c: common.fmt(v[c])
                for c in (
                    "untraced ms (median)",
                    "traced kernel ms per call",
                    "kernels run per call",
                    "temp MB",
                )
            },
        }
        for k, v in result["programs"].items()
    ]
    rows = [
        {
            "program": k,
            "kernel family": f,
            "kernels per call": common.fmt(v["kernels per call"]),
            "us per call (traced)": common.fmt(v["us per call"]),
            "share": f"{100 * v['share']:.0f}%",
        }
        for k, p in result["programs"].items()
        for f, v in p["families"].items()
    ]
    return head + common.markdown_table(summary) + "\n\n" + common.markdown_table(rows)


def main(argv: Sequence[str] | None = None) -> dict:
    def extra(p):
        p.add_argument("--shape", default="512x512", help="parameter shape, e.g. 64x64x64x1")
        p.add_argument("--levels", type=int, default=5)
        p.add_argument("--full", action="store_true", help="full instead of separable mode")
        p.add_argument("--log-guide", action="store_true")
        p.add_argument(
            "--defaults",
            action="store_true",
            help="bilateral_adam(0.02) with every default (ignores --levels, --full, --log-guide)",
        )
        p.add_argument("--calls", type=int, default=20, help="traced calls per program")
        p.add_argument("--rounds", type=int, default=11, help="untraced timing rounds")

    args = common.parse_args("Per-kernel profile of the update", "results/profile", argv, extra)
    shape = ab_update.parse_shape(args.shape)
    for name in ("levels", "calls", "rounds"):
        v = getattr(args, name)
        if v < (0 if name == "levels" else 1):
            raise ValueError(f"--{name} must be >= {0 if name == 'levels' else 1}, got {v}")
    if args.quick:
        args.calls, args.rounds = 2, 1
    result = profile(
        shape, args.levels, not args.full, args.log_guide, args.calls, args.rounds, args.defaults
    )
    result["jax"] = jax.__version__
    md = markdown(result)
    common.write_results(args.out, "profile", result, md)
    print(md)
    return result


if __name__ == "__main__":
    main()
