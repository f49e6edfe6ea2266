"""The filter and the update on an accelerator, with both single-device kernels.

``python -m experiments.benchmarks.gpu [--quick] [--out DIR]`` times, side by side in one
process:

* ``filter``: :func:`optax_bilateral.atrous_bilateral` alone, ``kernel="xla_cpu"`` against
  ``kernel="plain"``, on the benchmark's grids (512^2 x 3 with a 3-channel guide, 64^3 x 1),
  F = 5, separable and full;
* ``update``: ``bilateral_adam(...).update`` against ``optax.adam(...).update`` on the same
  arrays, each kernel (chosen with ``$OPTAX_BILATERAL_KERNEL`` while the program is
  traced), sigma_d = 0.1 and ``"auto"``;
* ``texture``: one iteration of the texture experiment (render, gradient, update) with
  Adam and with the cross-bilateral update of each kernel, against supplement Table 1's
  +3.4%.

It runs on whatever JAX's default backend is (BENCHMARKS.md, "GPU", was measured on an
H100) and writes ``bench_gpu.json``, ``bench_gpu.md`` and ``bench_gpu.png`` to ``--out``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence

import jax
import matplotlib
import optax

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks import suite

matplotlib.use("Agg")
import matplotlib.pyplot as plt

KERNELS = ("xla_cpu", "plain")
KERNEL_ENV = "OPTAX_BILATERAL_KERNEL"


@contextlib.contextmanager
def kernel_env(kernel: str) -> Iterator[None]:
    """``$OPTAX_BILATERAL_KERNEL = kernel`` while programs are traced inside."""
    old = os.environ.get(KERNEL_ENV)
    os.environ[KERNEL_ENV] = kernel
    try:
        yield
    finally:
        if old is None:
            del os.environ[KERNEL_ENV]
        else:
            os.environ[KERNEL_ENV] = old


def _grids(quick: bool) -> dict[str, tuple[int, ...]]:
    if quick:
        return {"texture 16x16x3": (16, 16, 3)}
    return {"texture 512x512x3": (512, 512, 3), "volume 64^3x1": (64, 64, 64, 1)}


def _modes(quick: bool) -> tuple[bool, ...]:
    """``separable`` values: both, or (to keep --quick's compilations few) separable only."""
    return (True,) if quick else (True, False)


def filter_rows(quick: bool, levels: int, rounds: int, inner: int) -> list[dict]:
    """The filter alone, both kernels side by side."""
    rows = []
    for name, shape in _grids(quick).items():
        params, grad = suite.update_arrays(shape)
        axes = tuple(range(len(shape) - 1))
        fns = {}
        for separable in _modes(quick):
            for kernel in KERNELS:

                def f(x, g, separable=separable, kernel=kernel, axes=axes):
                    return ob.atrous_bilateral(
                        (x, x * x),
                        g,
                        sigma_d=0.1,
                        levels=levels,
                        spatial_axes=axes,
                        separable=separable,
                        kernel=kernel,
                    )

                fns[(kernel, separable)] = (jax.jit(f), (grad, params))
        res = common_interleaved(fns, rounds, inner, f"filter {name}")
        for (kernel, separable), r in res.items():
            rows.append(
                {
                    "grid": name,
                    "mode": "separable" if separable else "full",
                    "kernel": kernel,
                    "ms (median)": 1e3 * r["median"],
                    "x xla_cpu (paired)": common.paired_ratio(
                        {k: v["samples"] for k, v in res.items()},
                        (kernel, separable),
                        ("xla_cpu", separable),
                    ),
                }
            )
    return rows


def common_interleaved(fns, rounds, inner, desc):
    """suite.interleaved with any hashable names."""
    keys = list(fns)
    res = suite.interleaved({str(i): fns[k] for i, k in enumerate(keys)}, rounds, inner, desc=desc)
    return {k: res[str(i)] for i, k in enumerate(keys)}


def update_rows(quick: bool, levels: int, rounds: int, inner: int) -> list[dict]:
    """bilateral_adam's update against optax.adam's, each kernel and sigma_d side by side."""
    rows = []
    for name, shape in _grids(quick).items():
        params, grad = suite.update_arrays(shape)
        adam = optax.adam(1e-2, b1=suite.B1, b2=suite.B2)
        fns = {"adam": (suite.update_program(adam), (grad, adam.init(params), params))}
        for kernel in KERNELS:
            for separable in _modes(quick):
                for sigma_d in (0.1,) if quick else (0.1, "auto"):
                    opt = common.filtered_adam(
                        1e-2, sigma_d=sigma_d, levels=levels, separable=separable
                    )
                    prog = suite.update_program(opt)
                    with kernel_env(kernel):  # traced here, under this kernel
                        state = opt.init(params)
                        for _ in range(2):
                            _, state = prog(grad, state, params)
                        jax.block_until_ready(state)
                    fns[(kernel, separable, sigma_d)] = (prog, (grad, state, params))
        res = common_interleaved(fns, rounds, inner, f"update {name}")
        samples = {k: v["samples"] for k, v in res.items()}
        for key, r in res.items():
            if key == "adam":
                continue
            kernel, separable, sigma_d = key
            rows.append(
                {
                    "grid": name,
                    "mode": "separable" if separable else "full",
                    "kernel": kernel,
                    "sigma_d": sigma_d,
                    "ms (median)": 1e3 * r["median"],
                    "adam ms (median)": 1e3 * res["adam"]["median"],
                    "x adam (paired)": common.paired_ratio(samples, key, "adam"),
                }
            )
    return rows


def texture_rows(quick: bool, levels: int, rounds: int) -> list[dict]:
    """The texture experiment's iteration, Adam and ours, once per kernel."""
    rows = []
    # --quick: the plain kernel only (benchmark's own --quick test runs the CPU one).
    for kernel in KERNELS[1:] if quick else KERNELS:
        with kernel_env(kernel):
            for r in suite.texture_iterations(quick, rounds=rounds, levels=(levels,)):
                rows.append({"kernel": kernel, **r})
    return rows


def _plot(rows: Sequence[dict], path) -> None:
    fig, ax = plt.subplots(figsize=(6.4, 3.2))
    labels = [f"{r['grid'].split()[1]} {r['mode'][:3]} {r['kernel']} {r['sigma_d']}" for r in rows]
    ax.barh(range(len(rows)), [r["x adam (paired)"] for r in rows], color="tab:blue")
    ax.set_yticks(range(len(rows)), labels, fontsize=6)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_xlabel("update time / optax.adam's (paired median)")
    ax.set_xscale("log")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _markdown(data: dict) -> str:
    md = [f"Device: {data['machine']['device']}, jax {data['machine']['jax']}", ""]
    for section in ("filter", "update", "texture"):
        if section in data:
            rows = [{k: common.fmt(v) for k, v in r.items()} for r in data[section]]
            md += [f"### {section}", "", common.markdown_table(rows), ""]
    return "\n".join(md)


def main(argv: Sequence[str] | None = None) -> dict:
    args = common.parse_args(
        "The filter and the update on an accelerator, both kernels", "results/bench_gpu", argv
    )
    quick = args.quick
    levels = 1 if quick else 5
    rounds, inner = (2, 1) if quick else (21, 5)
    sections = {
        "filter": lambda: filter_rows(quick, levels, rounds, inner),
        "update": lambda: update_rows(quick, levels, rounds, inner),
        "texture": lambda: texture_rows(quick, levels, 2 if quick else 30),
    }
    data = {"machine": suite.machine()}
    for section, rows in sections.items():
        data[section] = rows()
        # Written after each section: a run cut short on a lent machine keeps what it has.
        common.write_results(args.out, "bench_gpu", data, _markdown(data))
    _plot(data["update"], args.out / "bench_gpu.png")
    print(_markdown(data))
    return data


if __name__ == "__main__":
    main()
