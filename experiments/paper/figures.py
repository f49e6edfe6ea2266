"""The small figures the README and the docs show (docs/figures/).

    python -m experiments.paper.figures texture [--quick] [--out DIR]
    python -m experiments.paper.figures speed_accuracy [--source BENCHMARKS.md|accuracy.json]
                                        [--out DIR]

``texture``: the texture experiment's problem (512² GGX roughness, 1/1 spp, 150 iterations;
``--quick``: 64², 30 iterations) solved by Adam and by ``bilateral_adam``, each with the
setting that was best in ``python -m experiments.paper.texture``; writes ``texture_recovery.png``
(target, Adam, ours) and prints the final errors.

``speed_accuracy``: final texture error against the filter's time per update for F = 1…6,
separable and full, float32 and bfloat16 first moments, from the accuracy section of the
benchmark: the tables of BENCHMARKS.md (the committed numbers, the default) or an
``accuracy.json`` written by ``python -m experiments.benchmarks --only accuracy``;
writes ``speed_accuracy.png``.

Figures go to ``results/figures`` unless ``--out`` says otherwise (``--out docs/figures``
refreshes the committed ones).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
from collections.abc import Sequence

import numpy as np
import optax

import optax_bilateral as ob
from experiments import common
from experiments.paper import texture as texp

ROOT = pathlib.Path(__file__).resolve().parents[2]
# The best settings of `python -m experiments.paper.texture --full` (docs/experiments.md).
ADAM = dict(learning_rate=0.01, b1=0.9)
OURS = dict(learning_rate=0.02, sigma_d=0.05, log_guide=True)
FILTER_TABLE = "Filter time and error vs the full float64 filter"
RUNS_TABLE = "Texture experiment, cross-bilateral"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def texture(out: pathlib.Path, quick: bool) -> dict:
    """Runs Adam and ``bilateral_adam`` on the texture problem; writes texture_recovery.png."""
    from matplotlib.colors import LogNorm

    from optax_bilateral.toy import texture as tex

    cfg = texp.default_config(quick)
    prob = texp.Problem(cfg)
    opts = {
        "Adam": optax.adam(**ADAM),
        "bilateral_adam": ob.bilateral_adam(b1=cfg.b1_filtered, levels=cfg.levels, **OURS),
    }
    target = np.asarray(prob.target)
    finals, errors = {}, {}
    for name, opt in opts.items():
        trace = common.run_method(
            name, prob.step_fn(opt), (prob.init, opt.init(prob.init)), cfg.iterations
        )
        finals[name] = np.asarray(trace.final[0])
        errors[name] = float(np.mean(np.abs(finals[name] - target)))
        print(f"{name}: mean |alpha - target| after {cfg.iterations} iterations {errors[name]:.4f}")
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(7.5, 2.7), dpi=72)
    norm = LogNorm(tex.ALPHA_MIN, tex.ALPHA_MAX)
    panels = [("target roughness", target)] + [
        (f"{name}: error {errors[name]:.4f}", finals[name]) for name in opts
    ]
    for ax, (title, img) in zip(axes, panels):
        ax.imshow(img, cmap="viridis", norm=norm, interpolation="lanczos")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(
        f"{cfg.size}² texture, {cfg.spp} spp, {cfg.iterations} iterations "
        f"(start error {float(np.mean(np.abs(np.asarray(prob.init) - target))):.4f})",
        fontsize=9,
    )
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "texture_recovery.png"
    fig.savefig(path)
    plt.close(fig)
    print(path)
    return {"errors": errors, "png": str(path)}


def markdown_tables(text: str) -> dict[str, list[dict[str, str]]]:
    """Every pipe table of a Markdown text under the heading just above it."""
    tables, heading, rows = {}, None, None
    for line in text.splitlines() + [""]:
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        elif line.startswith("|") and heading is not None:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if rows is None:
                rows = [cells]
            elif not all(re.fullmatch(r":?-+:?", c) for c in cells):
                rows.append(cells)
        elif rows is not None:
            tables[heading] = [dict(zip(rows[0], r)) for r in rows[1:]]
            rows = None
    return tables


def _table(tables: dict, prefix: str) -> list[dict[str, str]]:
    found = [rows for heading, rows in tables.items() if heading.startswith(prefix)]
    if not found:
        raise ValueError(f"no table under a heading starting with {prefix!r}")
    return found[0]


def accuracy_rows(source: pathlib.Path) -> tuple[list[dict], list[dict]]:
    """(filter rows, texture-run rows) of the benchmark's accuracy section."""
    if source.suffix == ".json":
        data = json.loads(source.read_text())
        data = data.get("data", data)
        return data["filter"], data["texture_runs"]
    tables = markdown_tables(source.read_text())
    return _table(tables, FILTER_TABLE), _table(tables, RUNS_TABLE)


def _final_error(row: dict) -> float:
    """The run's final mean absolute texel error (its column name varies: "final mean ...")."""
    return float(next(v for k, v in row.items() if k.startswith("final mean")))


def speed_accuracy(out: pathlib.Path, source: pathlib.Path) -> pathlib.Path:
    """Final texture error against filter time per update; writes speed_accuracy.png."""
    filters, runs = accuracy_rows(source)
    ms = {(int(r["F"]), r["mode"], r["dtype"]): float(r["filter ms"]) for r in filters}
    adam = [_final_error(r) for r in runs if r["run"] == "adam"]
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.4), dpi=90)
    styles = {
        ("separable", "float32"): ("C0", "o", "-"),
        ("full", "float32"): ("C1", "s", "-"),
        ("separable", "bfloat16 (m)"): ("C0", "x", ":"),
        ("full", "bfloat16 (m)"): ("C1", "+", ":"),
    }
    for (mode, dtype), (color, marker, line) in styles.items():
        sel = sorted(
            (int(r["F"]), _final_error(r))
            for r in runs
            if r["mode"] == mode and r["moment dtype"] == dtype
        )
        if not sel:
            continue
        xs = [ms[(f, mode, "float32")] for f, _ in sel]
        ax.plot(
            xs,
            [e for _, e in sel],
            color=color,
            marker=marker,
            linestyle=line,
            label=f"{mode}, {'bfloat16' if 'bfloat16' in dtype else 'float32'} m",
        )
        if dtype == "float32":
            for x, (f, e) in zip(xs, sel):
                ax.annotate(f"F={f}", (x, e), textcoords="offset points", xytext=(3, 3), fontsize=7)
    if adam:
        ax.axhline(adam[0], color="gray", linestyle="--", label=f"Adam ({adam[0]:.4f})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("filter time per update, 512² (m, v), ms")
    ax.set_ylabel("final mean |alpha - target|")
    ax.set_title("texture experiment, 150 iterations: error vs filter cost", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "speed_accuracy.png"
    fig.savefig(path)
    plt.close(fig)
    print(path)
    return path


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("figure", choices=("texture", "speed_accuracy"))
    parser.add_argument("--out", type=pathlib.Path, default=ROOT / "results" / "figures")
    parser.add_argument("--quick", action="store_true", help="texture: the 64² test size")
    parser.add_argument(
        "--source",
        type=pathlib.Path,
        default=ROOT / "BENCHMARKS.md",
        help="speed_accuracy: BENCHMARKS.md or an accuracy.json",
    )
    args = parser.parse_args(argv)
    if args.figure == "texture":
        texture(args.out, args.quick or common.quick_from_env())
    else:
        speed_accuracy(args.out, args.source)


if __name__ == "__main__":
    main()
