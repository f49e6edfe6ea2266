"""What a run shows: the sensitivity curves and plots of the grid, and ``table.md``."""

from __future__ import annotations

import functools
import json
import math
import pathlib
from collections.abc import Mapping
from typing import Any

from experiments.tuning.sweep import jsonable

#: The issue's targets.
TARGET_BEST = 1.10
TARGET_ADAM = 1.05


def sensitivity(entry: dict, log_guide: bool) -> dict[int, list[tuple[float, float]]]:
    """``{levels: [(sigma_d, best-over-lr median error), ...]}`` of the bilateral grid."""
    best: dict[tuple[int, float], float] = {}
    for r in entry["grid"]["bilateral"]:
        if bool(r["static"]["log_guide"]) != log_guide:
            continue
        key = (int(r["static"]["levels"]), float(r["hyper"]["sigma_d"]))
        best[key] = min(best.get(key, math.inf), float(r["median"]))
    out: dict[int, list] = {}
    for (lev, sig), err in sorted(best.items()):
        out.setdefault(lev, []).append((sig, err))
    for lev, same in entry.get("levels_same_as", {}).items():
        if same in out:
            out[int(lev)] = list(out[same])
    return dict(sorted(out.items()))


def _xpos(sig: float, lo: float, hi: float) -> float:
    """Where a sigma_d is drawn on a log axis: 0 at ``lo``, inf at ``hi``."""
    return lo if sig == 0 else hi if sig == math.inf else sig


def plot_scene(entry: dict, path: pathlib.Path) -> pathlib.Path:
    """Final error against ``sigma_d`` (one curve per ``levels``), reference methods as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [False, True] if entry["log_guide_grid"] else [False]
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 4.4), dpi=110, squeeze=False)
    lines = {
        "adam": ("Adam (best lr, b1, b2)", "k", "-"),
        "auto": ("auto", "tab:red", "-"),
        "defaults": ("defaults", "tab:gray", ":"),
        "pyramid": ("pyramid + Adam", "tab:green", "--"),
    }
    for name in entry["methods"]:
        if name not in lines and name != "best_tuned":
            lines[name] = (name, "tab:purple", "-.")
    for ax, lg in zip(axes[0], panels):
        curves = sensitivity(entry, lg)
        finite = sorted({s for c in curves.values() for s, _ in c if 0 < s < math.inf})
        if not finite:
            continue
        lo, hi = finite[0] / 10, finite[-1] * 10  # where 0 and inf are drawn

        for lev, pts in curves.items():
            ax.plot(
                [_xpos(s, lo, hi) for s, _ in pts],
                [e for _, e in pts],
                marker="o",
                ms=3,
                lw=1.3,
                label=f"levels={lev}",
            )
        for name, (label, color, style) in lines.items():
            err = entry["methods"].get(name, {}).get("error")
            if err is not None and math.isfinite(err):
                ax.axhline(err, color=color, ls=style, lw=1.2, label=f"{label}: {err:.4g}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ticks = [lo] + [t for t in ax.get_xticks() if lo < t < hi] + [hi]
        ax.set_xticks(ticks)
        ax.set_xticklabels(["0"] + [f"{t:g}" for t in ticks[1:-1]] + ["inf"])
        ax.set_xlim(lo / 1.5, hi * 1.5)
        ax.set_xlabel("sigma_d" + (" (log guide)" if lg else " (linear guide)"))
        ax.set_ylabel(f"final error: {entry['error_name']}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    if entry["methods"]["auto"].get("error") is None:
        axes[0, 0].text(
            0.02,
            0.02,
            'auto: not available (sigma_d="auto" not accepted)',
            transform=axes[0, 0].transAxes,
            fontsize=7,
            color="tab:red",
        )
    import textwrap

    title = textwrap.fill(f"{entry['scene']}: {entry['description']}", 100 * len(panels))
    fig.suptitle(
        f"{title}\nmedian of {len(entry['seeds'])} seeds, best learning rate per point", fontsize=9
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def format_hyperparameters(h: Mapping[str, Any], keys=None) -> str:
    short = {"learning_rate": "lr", "sigma_d": "σ_d", "log_guide": "log"}
    out = []
    for k, v in h.items():
        if keys is not None and k not in keys:
            continue
        if isinstance(v, bool):
            if v:
                out.append(short.get(k, k))
            continue
        out.append(
            f"{short.get(k, k)}={v:g}" if isinstance(v, (int, float)) else f"{short.get(k, k)}={v}"
        )
    return ", ".join(out)


def _cell(methods: dict, k: str, keys=None) -> str:
    """Method ``k``'s error for the table, with the hyperparameters ``keys``."""
    x = methods[k]
    if x.get("error") is None:
        return "not available"
    return (
        f"{x['error']:.4g} ({format_hyperparameters(x['hyperparameters'], keys)})"
        if keys
        else f"{x['error']:.4g}"
    )


def _reference_note(summary: dict) -> str:
    if not summary.get("reference"):
        return ""
    libraries = sorted({e["reference_library"] for e in summary["scenes"].values()})
    return (
        f"Best-tuned, Adam and pyramid: from `{summary['reference']}` (library "
        f"{', '.join(libraries)}; each setting at its best learning rate), not rerun.\n\n"
    )


def markdown(summary: dict) -> str:
    """``table.md``: scenes x methods, ratios and the issue's targets."""
    scenes = summary["scenes"]
    cand = summary["candidates"]
    has_auto = summary["auto_available"]
    head = [
        "scene",
        "initial",
        "best-tuned (σ_d, levels, lr)",
        "auto",
        "defaults",
        "Adam (lr, b1, b2)",
        "pyramid (levels, lr)",
    ] + cand
    rows = []
    for name, e in scenes.items():
        cell = functools.partial(_cell, e["methods"])
        rows.append(
            [
                name,
                f"{e['initial_error']:.4g}",
                cell("best_tuned", ("sigma_d", "levels", "log_guide", "learning_rate")),
                cell("auto"),
                cell("defaults", ("learning_rate",)),
                cell("adam", ("learning_rate", "b1", "b2")),
                cell("pyramid", ("levels", "learning_rate")),
            ]
            + [cell(c) for c in cand]
        )
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    auto_text = (
        '= bilateral_adam(sigma_d="auto")' if has_auto else "not available in the installed library"
    )
    text = (
        f"# Tuning benchmark ({'quick' if summary['quick'] else 'full'})\n\n"
        f"Final parameter error, median over seeds {summary['settings']['seeds']}; every method "
        f"at its best learning rate. `auto` {auto_text}; "
        f"defaults = bilateral_adam {json.dumps(jsonable(summary['defaults']))}.\n\n"
        + _reference_note(summary)
        + "\n".join(lines)
        + "\n"
    )
    compared = (["auto"] if has_auto else []) + cand
    targets = [f"auto/best-tuned <= {TARGET_BEST}", f"auto/Adam <= {TARGET_ADAM} where Adam wins"]
    if compared:
        head2 = ["scene", "Adam wins"] + [
            c
            for name in compared
            for c in (
                f"{name}/best-tuned",
                f"{name}/Adam",
                f"{name}: ≤{TARGET_BEST}× best",
                f"{name}: ≤{TARGET_ADAM}× Adam",
            )
        ]
        lines2 = ["| " + " | ".join(head2) + " |", "|" + "|".join("---" for _ in head2) + "|"]
        for name, e in scenes.items():
            row = [name, "yes" if e["adam_wins"] else "no"]
            for c in compared:
                cmp_ = e["comparisons"][c]
                t1 = cmp_[f"<= {TARGET_BEST} x best-tuned"]
                t2 = cmp_[f"<= {TARGET_ADAM} x adam (where Adam wins)"]
                row += [
                    f"{cmp_['ratio_to_best_tuned']:.3g}",
                    f"{cmp_['ratio_to_adam']:.3g}",
                    "met" if t1 else "not met",
                    "—" if t2 is None else ("met" if t2 else "not met"),
                ]
            lines2.append("| " + " | ".join(row) + " |")
        text += "\n## Targets (issue #17)\n\n" + "\n".join(lines2) + "\n"
    else:
        text += (
            f"\n## Targets (issue #17)\n\n{'; '.join(targets)}: not measurable until "
            f'the library accepts sigma_d="auto" (or a --candidates method is given).\n'
        )
    refs = [
        "| scene | Adam wins | defaults / best-tuned | Adam / best-tuned | pyramid / best-tuned "
        "| defaults / Adam | s this run | s computing |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, e in scenes.items():
        m = e["methods"]
        b = m["best_tuned"]["error"]
        sec = e["seconds"]
        computing = sum(v for k, v in sec.items() if k != "total")
        refs.append(
            f"| {name} | {'yes' if e['adam_wins'] else 'no'} | {m['defaults']['error'] / b:.3g} "
            f"| {m['adam']['error'] / b:.3g} | {m['pyramid']['error'] / b:.3g} "
            f"| {m['defaults']['error'] / m['adam']['error']:.3g} "
            f"| {sec['total']:.0f} | {computing:.0f} |"
        )
    text += (
        "\n## Without tuning\n\n" + "\n".join(refs) + '\n\n"s computing": the seconds '
        "each family took when it was computed (cached grids keep theirs), with the "
        "scene's setup; run in parallel with other scenes.\n"
    )
    edges = [
        f"- {name}/{fam}: {format_hyperparameters({**x['static'], **x['hyper']})}"
        for name, e in scenes.items()
        for fam, lst in e["lr_at_grid_edge"].items()
        for x in lst
        if fam != "bilateral"
    ]
    n_bil = sum(len(e["lr_at_grid_edge"].get("bilateral", [])) for e in scenes.values())
    text += (
        f"\nLearning rate still at a grid edge after {summary['settings']['max_extend']} "
        f"extensions: {n_bil} bilateral grid points"
        + (", and:\n" + "\n".join(edges) if edges else "")
        + "\n"
    )
    return text
