"""Shared helpers for the experiments: run, time, summarise, plot.

An experiment script builds, for every method (and every sweep entry), a jitted
``step(carry, i) -> (carry, aux)`` and hands it to :func:`run_method`, which

* runs it for ``iterations`` steps under a tqdm bar,
* times each step on the wall clock (``jax.block_until_ready`` on the carry),
  keeping compilation (the first call) and evaluation out of the timing,
* calls ``evaluate(carry)`` every ``record_every`` steps (untimed) for metrics
  such as the parameter error, and records ``aux`` (e.g. the noisy training loss),

and returns a :class:`Trace`. The writers turn a dict of traces into
``summary.json``, a Markdown table and loss / error curve PNGs against iteration
and against wall-clock time.

Typical use::

    args = parse_args("texture recovery", default_out="results/texture")
    trace = run_method("adam", step, carry0, iterations=200,
                       evaluate=lambda c: {"param_error": err(c)},
                       hyperparameters={"learning_rate": 0.01})
    write_summary(args.out, {"adam": summary_entry(trace)})
    plot_curves({"adam": trace}, "param_error", args.out / "param_error.png")
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np

QUICK_ENV = "OPTAX_BILATERAL_QUICK"


def filtered_adam(
    learning_rate,
    b1=0.2,
    b2=None,
    eps=1e-8,
    *,
    sigma_d="auto",
    levels=None,
    prefilter=False,
    separable=True,
    guide="params",
    log_guide=False,
    spatial_axes=None,
    mask_unobserved=False,
    mu_dtype=None,
):
    """``bilateral_adam``'s chain for grids with the postfilter's knobs: the library's one
    builder (``filtered_chain``: ``optax.chain(prefilter(...)?, postfilter(b1, b2, eps, ...),
    optax.scale_by_learning_rate(learning_rate))``), every leaf by the settings' leaf rule
    (``bilateral_adam`` gives the leaves it does not filter to Adam). Every argument is named,
    so that ``optax.inject_hyperparams(filtered_adam, static_args=(...))`` takes any of them."""
    from optax_bilateral._src.optimizer.alias import filtered_chain

    return filtered_chain(
        learning_rate,
        b1,
        b2,
        eps,
        prefilter=prefilter,
        sigma_d=sigma_d,
        levels=levels,
        separable=separable,
        guide=guide,
        log_guide=log_guide,
        spatial_axes=spatial_axes,
        mask_unobserved=mask_unobserved,
        mu_dtype=mu_dtype,
    )


def quick_from_env() -> bool:
    """True when ``OPTAX_BILATERAL_QUICK`` is set to a non-empty value other than ``0``
    (tests set it)."""
    return os.environ.get(QUICK_ENV, "") not in ("", "0")


def parse_args(
    description: str,
    default_out: str,
    argv: Sequence[str] | None = None,
    extra: Callable[[argparse.ArgumentParser], None] | None = None,
) -> argparse.Namespace:
    """Common command line: ``--quick`` (also implied by ``OPTAX_BILATERAL_QUICK=1``) and
    ``--out DIR``.

    ``extra(parser)`` may add experiment-specific options. ``args.out`` is a ``pathlib.Path``.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"small, fast setting (also set by {QUICK_ENV}=1); used by the tests",
    )
    parser.add_argument(
        "--out",
        type=pathlib.Path,
        default=pathlib.Path(default_out),
        help=f"output directory (default: {default_out})",
    )
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    args.quick = bool(args.quick or quick_from_env())
    return args


@dataclasses.dataclass
class Trace:
    """Everything one optimisation run produced.

    Attributes:
      name: method name (e.g. ``"cross-bilateral"``).
      hyperparameters: JSON-able dict describing the run.
      iterations: ``(R,)`` 1-based iteration index of each record.
      wall_time: ``(R,)`` cumulative timed seconds (steps only) at each record.
      metrics: name -> ``(R,)`` array; ``aux`` values of the recorded step and
        ``evaluate`` values after it.
      step_seconds: ``(N,)`` wall time of every step; step 1 includes compilation.
      final: the final carry (e.g. the parameters), as returned by the last step.
      timed_seconds_per_iteration: if set (e.g. from :func:`time_steps_interleaved`),
        the cost of one step used for ``seconds_per_iteration`` and the time axis
        (``iterations * it``) instead of this run's own clock, which on a shared,
        loaded machine measures the neighbours as much as the method.
    """

    name: str
    hyperparameters: dict
    iterations: np.ndarray
    wall_time: np.ndarray
    metrics: dict[str, np.ndarray]
    step_seconds: np.ndarray
    final: Any = None
    timed_seconds_per_iteration: float | None = None

    @property
    def measured_seconds_per_iteration(self) -> float:
        """Median step time of this run, excluding step 1 (compilation)."""
        steps = self.step_seconds[1:] if len(self.step_seconds) > 1 else self.step_seconds
        return float(np.median(steps))

    @property
    def seconds_per_iteration(self) -> float:
        """``timed_seconds_per_iteration`` if set, else :attr:`measured_seconds_per_iteration`."""
        if self.timed_seconds_per_iteration is not None:
            return float(self.timed_seconds_per_iteration)
        return self.measured_seconds_per_iteration

    @property
    def compile_seconds(self) -> float:
        """Extra time of the first step over the median step: roughly the jit compile time."""
        return float(max(self.step_seconds[0] - self.measured_seconds_per_iteration, 0.0))

    def final_metric(self, key: str) -> float:
        """The last recorded (non-NaN) value of ``key``; NaN if there is none."""
        values = self.metrics[key]
        seen = np.nonzero(~np.isnan(values))[0]
        return float(values[seen[-1]]) if len(seen) else math.nan

    def metric_at_time(self, key: str, seconds: float) -> float:
        """Value of ``key`` at the last record whose cumulative step time is <= ``seconds``.

        Times are :attr:`time_axis` (compilation is not charged to anyone). Returns
        NaN when no record is that early.
        """
        values = self.metrics[key]
        keep = ~np.isnan(values)
        t = self.time_axis[keep]
        idx = np.searchsorted(t, seconds, side="right") - 1
        return float(values[keep][idx]) if idx >= 0 else math.nan

    def metric_at_iteration(self, key: str, iteration: int) -> float:
        """Value of ``key`` at the last record at or before ``iteration``; NaN if none."""
        values = self.metrics[key]
        keep = ~np.isnan(values)
        idx = np.searchsorted(self.iterations[keep], iteration, side="right") - 1
        return float(values[keep][idx]) if idx >= 0 else math.nan

    @property
    def rebased_wall_time(self) -> np.ndarray:
        """Cumulative step time at each record, with the compile overhead of step 1 removed."""
        return self.wall_time - self.compile_seconds

    @property
    def time_axis(self) -> np.ndarray:
        """Seconds at each record: ``iterations * timed_seconds_per_iteration`` if that is set,
        else :attr:`rebased_wall_time`."""
        if self.timed_seconds_per_iteration is not None:
            return self.iterations * float(self.timed_seconds_per_iteration)
        return self.rebased_wall_time


def run_method(
    name: str,
    step: Callable[[Any, int], tuple[Any, Mapping[str, Any]]],
    carry: Any,
    iterations: int,
    *,
    evaluate: Callable[[Any], Mapping[str, Any]] | None = None,
    record_every: int = 1,
    evaluate_every: int | None = None,
    hyperparameters: Mapping[str, Any] | None = None,
    progress: bool = True,
    first_iteration: int = 0,
    time_budget: float | None = None,
) -> Trace:
    """Runs ``carry, aux = step(carry, i)`` for ``i = first_iteration ..`` and records metrics.

    Args:
      name: method name, used for the progress bar and the trace.
      step: usually a jitted function; ``i`` is passed as a Python int (wrap it in
        ``jnp.asarray`` inside if it selects a PRNG key, to avoid recompiles).
      carry: initial state (params, optimizer state, ...).
      iterations: number of steps.
      evaluate: untimed ``carry -> {metric: scalar}``, called after every
        ``evaluate_every``-th step and after the last one; other records hold NaN
        for its metrics (plots skip them, :meth:`Trace.final_metric` uses the last).
      record_every: record ``aux`` every this many steps (the last step is always recorded).
      evaluate_every: defaults to ``record_every``; must be a multiple of it.
      hyperparameters: stored in the trace and the summary.
      progress: show a tqdm bar.
      first_iteration: index of the first step (to continue a run; see :func:`concat_traces`).
      time_budget: if given, stop as soon as the timed seconds, compilation
        excluded, reach it (``iterations`` is then a cap): equal-wall-time runs.
    """
    from tqdm.auto import tqdm

    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be a positive int, got {iterations!r}")
    if not isinstance(record_every, int) or record_every < 1:
        raise ValueError(f"record_every must be a positive int, got {record_every!r}")
    evaluate_every = record_every if evaluate_every is None else evaluate_every
    if not isinstance(evaluate_every, int) or evaluate_every < 1 or evaluate_every % record_every:
        raise ValueError(
            f"evaluate_every must be a positive multiple of record_every="
            f"{record_every}, got {evaluate_every!r}"
        )
    step_seconds = np.zeros(iterations)
    records: dict[str, list[float]] = {}
    rec_iter, rec_time = [], []
    elapsed = 0.0
    bar = tqdm(range(iterations), desc=name, disable=not progress, leave=False, dynamic_ncols=True)
    for i in bar:
        t0 = time.perf_counter()
        carry, aux = step(carry, first_iteration + i)
        jax.block_until_ready((carry, aux))
        dt = time.perf_counter() - t0
        step_seconds[i] = dt
        elapsed += dt
        last = i == iterations - 1
        if time_budget is not None and i >= 1:
            compile_extra = max(step_seconds[0] - float(np.median(step_seconds[1 : i + 1])), 0.0)
            last = last or elapsed - compile_extra >= time_budget
        if (i + 1) % record_every == 0 or last:
            values = {k: float(v) for k, v in dict(aux).items()}
            if evaluate is not None and ((i + 1) % evaluate_every == 0 or last):
                values.update({k: float(v) for k, v in evaluate(carry).items()})
            for k in set(records) | set(values):
                # A metric first seen late is NaN-padded at the earlier records.
                records.setdefault(k, [math.nan] * len(rec_iter)).append(values.get(k, math.nan))
            rec_iter.append(first_iteration + i + 1)
            rec_time.append(elapsed)
            if "loss" in values:
                bar.set_postfix(loss=f"{values['loss']:.4g}", refresh=False)
        if last:
            break
    bar.close()
    return Trace(
        name=name,
        hyperparameters=dict(hyperparameters or {}),
        iterations=np.asarray(rec_iter),
        wall_time=np.asarray(rec_time),
        metrics={k: np.asarray(v) for k, v in records.items()},
        step_seconds=step_seconds[: i + 1],
        final=carry,
    )


def time_steps_interleaved(
    steps: Mapping[str, tuple[Callable, Any]],
    rounds: int = 7,
    first_iteration: int = 0,
    inner: int = 1,
) -> dict[str, float]:
    """Median seconds per step of each ``step(carry, i)``, timed in alternation
    (:func:`time_steps_samples`, whose rounds these are the medians of)."""
    samples = time_steps_samples(steps, rounds, first_iteration, inner)
    return {k: float(np.median(v)) for k, v in samples.items()}


def paired_ratio(samples: Mapping[Any, Sequence[float]], a, b) -> float:
    """Median over rounds of ``samples[a][r] / samples[b][r]``: the ratio of two programs
    timed in the same round, so a slow stretch of a shared machine scales both sides.
    Less noisy than the ratio of the two medians when the load drifts between rounds."""
    x, y = np.asarray(samples[a], float), np.asarray(samples[b], float)
    if x.shape != y.shape or x.size == 0:
        raise ValueError(
            f"paired_ratio needs the same non-zero number of rounds for {a!r} "
            f"and {b!r}, got {x.size} and {y.size}"
        )
    return float(np.median(x / y))


def time_steps_samples(
    steps: Mapping[str, tuple[Callable, Any]],
    rounds: int = 7,
    first_iteration: int = 0,
    inner: int = 1,
) -> dict[str, list[float]]:
    """Seconds per step of each ``step(carry, i)`` in every round, timed in alternation.

    Round ``r`` runs every step ``inner`` times in a row, in turn, on its own evolving
    carry, so a burst of load from other processes hits all of them alike: the
    *ratios* are fair even on a shared machine. The order rotates every round (the
    first step of a round was measured ~10-30% slower on a loaded machine). A sample
    is the mean over its ``inner`` steps (several steps per sample average out
    dispatch jitter). Call after the steps are compiled (or add a round).
    """
    if not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds must be a positive int, got {rounds!r}")
    if not isinstance(inner, int) or inner < 1:
        raise ValueError(f"inner must be a positive int, got {inner!r}")
    carries = {k: c for k, (_, c) in steps.items()}
    times: dict[str, list[float]] = {k: [] for k in steps}
    names = list(steps)
    for r in range(rounds):
        for k in names[r % len(names) :] + names[: r % len(names)]:
            fn = steps[k][0]
            t0 = time.perf_counter()
            for j in range(inner):
                carries[k], aux = fn(carries[k], first_iteration + r * inner + j)
            jax.block_until_ready((carries[k], aux))
            times[k].append((time.perf_counter() - t0) / inner)
    return times


def concat_traces(
    first: Trace,
    second: Trace,
    name: str | None = None,
    hyperparameters: Mapping[str, Any] | None = None,
) -> Trace:
    """``second`` (run with ``first_iteration`` = the end of ``first``) appended to ``first``."""
    keys = set(first.metrics) | set(second.metrics)

    def get(tr, k):
        return tr.metrics.get(k, np.full(len(tr.iterations), np.nan))

    return Trace(
        name=name or first.name,
        hyperparameters=dict(
            hyperparameters if hyperparameters is not None else first.hyperparameters
        ),
        iterations=np.concatenate([first.iterations, second.iterations]),
        wall_time=np.concatenate([first.wall_time, first.wall_time[-1] + second.wall_time]),
        metrics={k: np.concatenate([get(first, k), get(second, k)]) for k in keys},
        step_seconds=np.concatenate([first.step_seconds, second.step_seconds]),
        final=second.final,
        timed_seconds_per_iteration=first.timed_seconds_per_iteration,
    )


def summary_entry(trace: Trace, metric_keys: Mapping[str, str] | None = None) -> dict:
    """The per-method dict of ``summary.json``.

    ``metric_keys`` maps summary key -> trace metric, default
    ``{"final_param_error": "param_error", "final_loss": "loss"}`` (keys whose
    metric the trace lacks are skipped).
    """
    if metric_keys is None:
        metric_keys = {"final_param_error": "param_error", "final_loss": "loss"}
    entry = {k: trace.final_metric(m) for k, m in metric_keys.items() if m in trace.metrics}
    entry["seconds_per_iteration"] = trace.seconds_per_iteration
    if trace.timed_seconds_per_iteration is not None:
        entry["measured_seconds_per_iteration"] = trace.measured_seconds_per_iteration
    entry["iterations"] = int(trace.iterations[-1])
    entry["hyperparameters"] = jsonable(trace.hyperparameters)
    return entry


def best_trace(traces: Sequence[Trace], metric: str) -> Trace:
    """The trace with the smallest final ``metric`` (NaN counts as worst)."""
    if not traces:
        raise ValueError("best_trace needs at least one trace")
    return min(traces, key=lambda t: (math.isnan(t.final_metric(metric)), t.final_metric(metric)))


def write_summary(
    out_dir: str | os.PathLike, methods: Mapping[str, dict], **extra: Any
) -> pathlib.Path:
    """Writes ``{"methods": methods, **extra}`` to ``out_dir/summary.json``; returns the path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "summary.json"
    path.write_text(json.dumps(jsonable({"methods": dict(methods), **extra}), indent=2) + "\n")
    return path


def markdown_table(
    rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None, floatfmt: str = ".4g"
) -> str:
    """A GitHub Markdown table; ``columns`` defaults to the keys of the first row."""
    if not rows:
        return ""
    columns = list(columns if columns is not None else rows[0].keys())

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return "nan" if math.isnan(v) else format(v, floatfmt)
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def plot_curves(
    traces: Mapping[str, Trace],
    metric: str,
    path: str | os.PathLike,
    *,
    x: str = "iteration",
    log_y: bool = True,
    title: str | None = None,
    ylabel: str | None = None,
) -> pathlib.Path:
    """One line per trace of ``metric`` against ``x`` ("iteration" or "time"); saves a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if x not in ("iteration", "time"):
        raise ValueError(f"x must be 'iteration' or 'time', got {x!r}")
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=120)
    for label, tr in traces.items():
        if metric not in tr.metrics:
            continue
        xs = tr.iterations if x == "iteration" else tr.time_axis
        ys = tr.metrics[metric]
        keep = np.isfinite(ys)
        ax.plot(xs[keep], ys[keep], label=label, lw=1.4, marker="." if keep.sum() < 30 else None)
    timed = any(t.timed_seconds_per_iteration is not None for t in traces.values())
    ax.set_xlabel(
        "iteration"
        if x == "iteration"
        else "seconds (iterations x interleaved step time)"
        if timed
        else "wall-clock seconds (steps only, no compile)"
    )
    ax.set_ylabel(ylabel or metric)
    if log_y:
        ax.set_yscale("log")
    ax.set_title(title or f"{metric} vs {x}")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_all_curves(
    traces: Mapping[str, Trace],
    out_dir: str | os.PathLike,
    metrics: Sequence[str] = ("loss", "param_error"),
) -> list[pathlib.Path]:
    """``{metric}_vs_{iteration,time}.png`` for every metric; returns the paths."""
    out = pathlib.Path(out_dir)
    return [
        plot_curves(traces, m, out / f"{m}_vs_{x}.png", x=x)
        for m in metrics
        for x in ("iteration", "time")
    ]


def jsonable(obj: Any) -> Any:
    """Converts numpy / jax scalars and arrays, tuples and inf to plain JSON values."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.ndarray, jax.Array)):
        return jsonable(np.asarray(obj).tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        # JSON has no inf/nan; a string keeps sigma_d=inf readable and the file valid.
        return v if math.isfinite(v) else str(v)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def fmt(x: Any, digits: int = 3) -> Any:
    """A float with ``digits`` significant digits for a Markdown table; other values as they are."""
    if isinstance(x, float):
        if not math.isfinite(x):
            return str(x)
        return f"{x:.{digits}g}"
    return x


def write_results(out: pathlib.Path, name: str, data: Mapping, md: str) -> None:
    """``out/<name>.json`` (``data``) and ``out/<name>.md`` (``md``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(jsonable(data), indent=1) + "\n")
    (out / f"{name}.md").write_text(md + "\n")


def write_rows(
    out: pathlib.Path, name: str, rows: Sequence[Mapping], intro: str, quick: bool
) -> str:
    """Prints and writes (:func:`write_results`) ``rows`` as a table after ``intro``; the
    JSON keeps the rows and whether the run was ``--quick``. Returns the markdown."""
    md = f"{intro}\n\n" + markdown_table([{k: fmt(v) for k, v in r.items()} for r in rows])
    print(md)
    write_results(out, name, {"rows": rows, "quick": quick}, md)
    return md


def save_figure(fig, path: pathlib.Path) -> pathlib.Path:
    """Saves an image grid (no ticks), closes it and returns ``path``."""
    import matplotlib.pyplot as plt

    for ax in fig.axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
