"""The one runner of the Mitsuba 3 experiments: run every entry, time the best interleaved,
write ``summary.json``, ``table.md`` and the curves.

An experiment (``texture``, ``volume``, ``tutorials``, ``mesh`` beside this module)
supplies

* a *problem*: its scene and ``mi.SceneParameters``, with ``param_errors(values) ->
  {metric: float}`` (cheap enough to call every ``record_every`` iterations) and
  ``evaluate(values, run_name) -> {metric: float}`` (an untimed, low-noise final
  evaluation, e.g. the image loss of a high-spp render);
* per method a list of :class:`Entry` (a sweep), each able to ``start()`` a :class:`Run`:
  one optimisation from the problem's initial values, written as the experiment's loop
  (``SceneOptimizer``, Mitsuba's tutorial loop with ``mi.ad.Adam`` or ``BilateralAdam``,
  Large Steps...).

:func:`run_entries` runs every entry for ``iterations`` steps (render seeds ``0, 1, ...``,
the same for every method), recording ``param_errors`` every ``record_every`` steps
(untimed), then times one fresh run of each method's best entry interleaved
(:func:`time_interleaved`): those medians set every entry's seconds per iteration and time
axis, so that load from other processes hits all methods alike. :func:`write_report`
writes the outputs and :func:`main` is every experiment's command line.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from experiments import common


class Run(Protocol):
    """One optimisation in progress on the problem's scene."""

    def activate(self) -> None:
        """Writes this run's current values into the scene (untimed; the scene is shared)."""
        ...

    def step(self, i: int) -> tuple[float, dict[str, float]]:
        """One iteration with render seed ``i``; returns the training loss and the seconds of
        the iteration's parts (e.g. ``{"render": ..., "update": ...}``), evaluated
        (``dr.sync_thread``) before each clock read."""
        ...

    def values(self) -> Mapping[str, Any]:
        """The current parameter values ``{key: array}``."""
        ...


@dataclasses.dataclass(frozen=True)
class Entry:
    """One sweep entry: its name, hyperparameters (for the summary) and a fresh run."""

    name: str
    hyperparameters: dict
    start: Callable[[], Run]


@dataclasses.dataclass(frozen=True)
class Metric:
    """The metric that picks a sweep's best entry and heads the table."""

    key: str = "param_error"
    label: str = "param error"


def run_entries(
    problem,
    entries: Mapping[str, Sequence[Entry]],
    *,
    iterations: int,
    record_every: int,
    timing_rounds: int,
    metric: Metric = Metric(),
    progress: bool = True,
) -> tuple[dict[str, list[common.Trace]], dict[str, dict[str, list[float]]]]:
    """Every entry's run, then the best entries timed interleaved.

    Returns ``(traces, samples)``: ``{method: [Trace]}`` (``trace.final`` holds the final
    values as NumPy arrays) and :func:`time_interleaved`'s samples per method.
    """
    traces: dict[str, list[common.Trace]] = {}
    by_name = {}
    for method, sweep in entries.items():
        traces[method] = []
        for entry in sweep:
            by_name[entry.name] = entry
            traces[method].append(
                _run_one(problem, entry, iterations, record_every, progress=progress)
            )
    best_runs = {m: by_name[best(traces[m], metric).name].start() for m in traces}
    samples = time_interleaved(best_runs, rounds=timing_rounds, warmup=1)
    for m in traces:
        for tr in traces[m]:
            tr.timed_seconds_per_iteration = float(np.median(samples[m]["total"]))
    return traces, samples


def run_interleaved(
    problem,
    entries: Mapping[str, Sequence[Entry]],
    *,
    iterations: int,
    record_every: int,
    metric: Metric = Metric(),
    progress: bool = True,
) -> tuple[dict[str, list[common.Trace]], dict[str, dict[str, list[float]]]]:
    """Every entry's run at once, one iteration of each in turn (the order rotated every
    iteration), each iteration timed: whole runs side by side, so that load from other
    processes hits all alike and every iteration's cost is measured (for runs whose cost
    changes along the way, e.g. a volume upsampled halfway). Records as
    :func:`run_entries`; the traces' time axis is their own cumulative step time (the first
    step's compilation removed). Returns ``(traces, samples)``: ``samples[method]`` holds
    the best entry's step parts and ``total`` over every step but the first.
    """
    import drjit as dr
    from tqdm.auto import tqdm

    runs = [(m, e, e.start()) for m, sweep in entries.items() for e in sweep]
    seconds: dict[str, list[dict[str, float]]] = {e.name: [] for _, e, _ in runs}
    records: dict[str, list[dict[str, float]]] = {e.name: [] for _, e, _ in runs}
    for i in tqdm(range(iterations), desc="interleaved runs", disable=not progress, leave=False):
        for _, e, run in runs[i % len(runs) :] + runs[: i % len(runs)]:
            run.activate()
            dr.sync_thread()
            t0 = time.perf_counter()
            loss, parts = run.step(i)
            dr.sync_thread()
            seconds[e.name].append({**parts, "total": time.perf_counter() - t0})
            last = i == iterations - 1
            if (i + 1) % record_every == 0 or last:
                values = run.values()
                metrics = {"iteration": i + 1, "loss": loss, **problem.param_errors(values)}
                if last:
                    metrics.update(problem.evaluate(values, e.name))
                records[e.name].append(metrics)
    traces: dict[str, list[common.Trace]] = {m: [] for m in entries}
    for m, e, run in runs:
        steps = np.array([s["total"] for s in seconds[e.name]])
        recs = records[e.name]
        iters = np.array([r["iteration"] for r in recs])
        names = {k for r in recs for k in r} - {"iteration"}
        traces[m].append(
            common.Trace(
                name=e.name,
                hyperparameters=dict(e.hyperparameters),
                iterations=iters,
                wall_time=np.cumsum(steps)[iters - 1],
                metrics={k: np.array([r.get(k, math.nan) for r in recs], float) for k in names},
                step_seconds=steps,
                final={k: np.array(v) for k, v in run.values().items()},
            )
        )
    samples = {}
    for m in traces:
        name = best(traces[m], metric).name
        samples[m] = {part: [s[part] for s in seconds[name][1:]] for part in seconds[name][0]}
    return traces, samples


def _run_one(problem, entry: Entry, iterations: int, record_every: int, progress: bool):
    import drjit as dr

    run = entry.start()
    done = [0]

    def step(carry, i):
        loss, _ = run.step(i)
        dr.sync_thread()
        done[0] += 1
        return carry, {"loss": loss}

    def evaluate(_):
        values = run.values()
        out = dict(problem.param_errors(values))
        if done[0] == iterations:
            out.update(problem.evaluate(values, entry.name))
        return out

    trace = common.run_method(
        entry.name,
        step,
        None,
        iterations,
        record_every=record_every,
        evaluate=evaluate,
        hyperparameters=entry.hyperparameters,
        progress=progress,
    )
    trace.final = {k: np.array(v) for k, v in run.values().items()}
    return trace


def time_interleaved(
    runs: Mapping[str, Run], rounds: int, warmup: int = 2, first_seed: int = 500_000
) -> dict[str, dict[str, list[float]]]:
    """Seconds per iteration of each run's parts and their ``total``.

    A round runs one iteration of each run, in an order rotated every round, so load from
    other processes hits all alike; before its iteration each run's own values are written
    into the shared scene (untimed), so every render sees that run's parameters. One
    scene, because renders got slower with more scenes alive in the process.
    ``warmup`` untimed rounds first (compilation). Returns ``{name: {part: [seconds per
    round]}}`` with the parts of :meth:`Run.step` and ``total``.
    """
    import drjit as dr

    samples: dict[str, dict[str, list[float]]] = {name: {} for name in runs}
    names = list(runs)
    seed = first_seed
    for r in range(warmup + rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            run = runs[name]
            run.activate()
            dr.sync_thread()
            t0 = time.perf_counter()
            _, parts = run.step(seed)
            dr.sync_thread()
            total = time.perf_counter() - t0
            if r >= warmup:
                for part, dt in {**parts, "total": total}.items():
                    samples[name].setdefault(part, []).append(dt)
        seed += 1
    return samples


def timing_rows(
    samples: Mapping[str, Mapping[str, list[float]]],
    baseline: str,
    parts: Sequence[tuple[str, str]] = (
        ("render", "render + backward ms"),
        ("update", "update ms"),
    ),
) -> list[dict]:
    """Medians (ms) of ``parts`` (``(part, column)``) and of the total, the update's share
    of it, and the total's change against ``baseline``: the median over rounds of the
    per-round ratio (:func:`experiments.common.paired_ratio`)."""
    totals = {k: v["total"] for k, v in samples.items()}
    rows = []
    for name, s in samples.items():
        row: dict[str, Any] = {"method": name}
        row.update({col: 1e3 * float(np.median(s[p])) for p, col in parts if p in s})
        row["total ms"] = 1e3 * float(np.median(s["total"]))
        if "update" in s:
            share = np.asarray(s["update"]) / np.asarray(s["total"])
            row["update share %"] = 100.0 * float(np.median(share))
        row[f"total vs {baseline} %"] = 100.0 * (common.paired_ratio(totals, name, baseline) - 1)
        row["rounds"] = len(s["total"])
        rows.append(row)
    return rows


def load_average() -> list[float]:
    """The 1, 5 and 15 minute load averages (the machine's conditions during a timing)."""
    return [round(x, 2) for x in os.getloadavg()]


def best(traces: Sequence[common.Trace], metric: Metric = Metric()) -> common.Trace:
    """The sweep entry with the smallest final ``metric``."""
    return common.best_trace(list(traces), metric.key)


def summary_methods(
    traces: Mapping[str, Sequence[common.Trace]],
    metric_keys: Mapping[str, str],
    metric: Metric = Metric(),
) -> dict[str, dict]:
    """``summary.json``'s ``methods``: the best sweep entry per method, with every entry
    listed, each with its lowest ``metric`` and the iteration it was reached at."""

    def entry(t):
        e = {"run": t.name, **common.summary_entry(t, metric_keys)}
        errors = t.metrics[metric.key]
        i = int(np.nanargmin(errors))
        e[f"lowest_{metric.key}"] = float(errors[i])  # a run that drifts up after it
        e[f"lowest_{metric.key}_iteration"] = int(t.iterations[i])
        return e

    return {
        m: {**entry(best(trs, metric)), "sweep": [entry(t) for t in trs]}
        for m, trs in traces.items()
    }


def time_budget(traces: Mapping[str, Sequence[common.Trace]], metric: Metric = Metric()) -> float:
    """Equal-time budget: the shortest total (timed) run time of the best entries."""
    return min(float(best(trs, metric).time_axis[-1]) for trs in traces.values())


def write_tables(
    out: pathlib.Path,
    title: str,
    methods: Mapping[str, dict],
    traces: Mapping[str, Sequence[common.Trace]],
    extra_columns: Callable[[dict], dict],
    notes: str = "",
    metric: Metric = Metric(),
) -> str:
    """``table.md``: the best run per method, then every sweep entry; returns the text."""
    budget = time_budget(traces, metric)
    final = f"final_{metric.key}"
    rows = [
        {
            "method": m,
            "best run": e["run"],
            metric.label: e[final],
            **extra_columns(e),
            "image loss": e.get("final_loss", math.nan),
            f"{metric.label} @ {budget:.1f} s": best(traces[m], metric).metric_at_time(
                metric.key, budget
            ),
            "s/iter": e["seconds_per_iteration"],
        }
        for m, e in methods.items()
    ]
    sweep_rows = [
        {
            "run": s["run"],
            metric.label: s[final],
            "lowest (iteration)": f"{s[f'lowest_{metric.key}']:.4g} "
            f"({s[f'lowest_{metric.key}_iteration']})",
            "image loss": s.get("final_loss", math.nan),
        }
        for e in methods.values()
        for s in e["sweep"]
    ]
    text = (
        f"{title}\n\n{notes}{common.markdown_table(rows)}\n\nEvery sweep entry:\n\n"
        f"{common.markdown_table(sweep_rows)}\n"
    )
    (out / "table.md").write_text(text)
    return text


@dataclasses.dataclass(frozen=True)
class Report:
    """What :func:`write_report` writes besides the traces.

    Attributes:
      title: the table's heading (the setting in one paragraph).
      curves: ``{metric: y label}``, each plotted against iteration and time.
      curve_title: the curves' title prefix (``"<curve_title>: <metric> vs <x>"``).
      metric_keys: ``summary.json`` name -> trace metric (``final_<metric>`` for each).
      setting: ``summary.json``'s ``setting``.
      figures: ``(best traces, out) -> [png]``: the experiment's own figures.
      extra_columns: more columns of the best-run table from a summary entry.
      notes: text between the title and the table.
      metric: the metric that picks the best entry.
      skipped: ``{method: reason}`` for methods not run.
      timing_baseline: a method: add the table of each method's time per iteration, its
        parts and the total's change against this one (:func:`timing_rows`).
    """

    title: str
    curves: Mapping[str, str]
    curve_title: str
    metric_keys: Mapping[str, str]
    setting: Mapping[str, Any]
    figures: Callable[[dict[str, common.Trace], pathlib.Path], list[pathlib.Path]] = (
        lambda best, out: []
    )
    extra_columns: Callable[[dict], dict] = lambda e: {}
    notes: str = ""
    metric: Metric = Metric()
    skipped: Mapping[str, str] = dataclasses.field(default_factory=dict)
    timing_baseline: str | None = None


def write_report(
    out: pathlib.Path,
    traces: Mapping[str, list[common.Trace]],
    samples: Mapping[str, Mapping[str, list[float]]],
    report: Report,
    started: float,
) -> dict:
    """``summary.json``, ``table.md``, the curves and the experiment's figures in ``out``;
    returns ``{"table", "total_seconds", "pngs", "methods"}``."""
    methods = summary_methods(traces, report.metric_keys, report.metric)
    best_traces = {m: best(trs, report.metric) for m, trs in traces.items()}
    pngs = [
        common.plot_curves(
            best_traces,
            m,
            out / f"{m}_vs_{x}.png",
            x=x,
            ylabel=label,
            title=f"{report.curve_title}: {m} vs {x}",
        )
        for m, label in report.curves.items()
        for x in ("iteration", "time")
    ]
    pngs += report.figures(best_traces, out)
    notes = report.notes + (f"Skipped: {dict(report.skipped)}\n\n" if report.skipped else "")
    table = write_tables(
        out, report.title, methods, traces, report.extra_columns, notes, report.metric
    )
    timing = None
    if report.timing_baseline is not None:
        timing = timing_rows(samples, report.timing_baseline)
        table += (
            f"\nTime per iteration (medians over {timing[0]['rounds']} interleaved iterations; "
            f"load average {load_average()}):\n\n{common.markdown_table(timing)}\n"
        )
        (out / "table.md").write_text(table)
    total = time.perf_counter() - started
    common.write_summary(
        out,
        methods,
        skipped=dict(report.skipped),
        pngs=[str(p) for p in pngs],
        total_seconds=total,
        timing_ms={
            m: {p: 1e3 * float(np.median(v)) for p, v in s.items()} for m, s in samples.items()
        },
        load_average=load_average(),
        timing=timing,
        setting=dict(report.setting),
    )
    return {"table": table, "total_seconds": total, "pngs": pngs, "methods": methods}


def main(
    description: str,
    default_out: str,
    run: Callable[[Any, pathlib.Path], dict],
    default_config: Callable[[bool], Any],
    argv=None,
    extra: Callable | None = None,
) -> dict:
    """Every Mitsuba experiment's command line: ``[--quick] [--out DIR]``; runs
    ``run(default_config(quick), out)`` and prints its table, time and figures."""
    args = common.parse_args(description, default_out=default_out, argv=argv, extra=extra)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = run(default_config(args.quick), args.out)
    print(summary["table"])
    print(f"Total {summary['total_seconds']:.1f} s. Summary: {args.out / 'summary.json'}")
    for p in summary["pngs"]:
        print(f"  {p}")
    return summary
