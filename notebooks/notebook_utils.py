"""Helpers shared by the notebooks in ``notebooks/``: batched texture runs, step statistics,
figures.

Imported by the notebooks as ``notebook_utils`` (their working directory is ``notebooks/``).

The notebooks compare many optimizer settings on the toy texture scene
(:mod:`optax_bilateral.toy.texture`, the paper's Fig. 5 setting). On a CPU one
XLA compilation of a render + filter step costs seconds, far more than a step
at the quick size, so :func:`run_texture` advances every run of every method
together in one compiled program: one ``jax.lax.scan`` over the iterations,
``jax.lax.map`` over the runs, and the runs of one method differ only in
hyperparameters injected with ``optax.inject_hyperparams`` (learning rate,
``sigma_d``). Every run sees the same Monte Carlo samples at the same
iteration (one key per iteration, shared), so differences between runs are not
sampling luck.

Typical use::

    prob = texture_problem(64)
    inject = optax.inject_hyperparams
    runs, timing = run_texture(prob, {
        "adam": Method(inject(optax.adam)(learning_rate=0.01), {"learning_rate": [0.003, 0.01]}),
        "ours": Method(inject(ob.bilateral_adam, static_args=("levels",))(
            learning_rate=0.02, sigma_d=0.1, levels=5, log_guide=True), {"sigma_d": [0.03, 0.1]}),
    }, iterations=100)
    runs["ours"].metrics["param_error"]        # (2, 100)
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from optax_bilateral.toy import texture as tex

# Only optax_bilateral is installed; experiments/ is imported from the repository.
if str(pathlib.Path(__file__).resolve().parents[1]) not in sys.path:
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from experiments import common

#: True when ``OPTAX_BILATERAL_QUICK=1`` (the test suite): notebooks then run at a small size.
QUICK = common.quick_from_env()


# ----------------------------------------------------------------------------- files


def repo_root() -> pathlib.Path:
    """The repository root (the folder holding ``experiments/``)."""
    return pathlib.Path(__file__).resolve().parents[1]


def results_dir(name: str = "notebooks") -> pathlib.Path:
    """``results/<name>/`` under the repository root (created; git-ignored)."""
    out = repo_root() / "results" / name
    out.mkdir(parents=True, exist_ok=True)
    return out


def save_figure(fig, name: str, folder: str = "notebooks") -> pathlib.Path:
    """Saves ``fig`` as ``results/<folder>/<name>.png`` and returns the path (the notebook still
    shows it).

    At the quick size the figure goes to ``results/<folder>/quick/`` instead, so that
    the test suite never overwrites the figures of a full-size run.
    """
    path = results_dir(f"{folder}/quick" if QUICK else folder) / f"{name}.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return path


def tree_nbytes(tree: Any) -> int:
    """Bytes held by the array leaves of ``tree`` (an optimizer state, parameters, ...)."""
    return int(sum(np.asarray(x).nbytes for x in jax.tree.leaves(tree)))


# ----------------------------------------------------------------------------- the problem


@dataclasses.dataclass(frozen=True)
class TextureProblem:
    """One texture-recovery problem: scene, target roughness, reference image, start.

    ``spp`` / ``spp_grad`` are the samples per pixel of the primal render and of
    its gradient (the paper's texture runs: 1 / 1); they are static (part of the
    compiled program). ``grad_samples`` = K averages K independent such loss
    gradients per iteration (gradient variance / K); it is traced, so runs at
    different K share one compiled program.
    """

    size: int
    target_name: str
    spp: int
    spp_grad: int
    grad_samples: int
    eval_spp: int
    scene: tex.TextureScene
    target: jax.Array  # (H, W) roughness
    reference: jax.Array  # (H, W) low-noise image of the target
    init: jax.Array  # (H, W) constant initial roughness
    key: jax.Array  # base key; iteration i uses fold_in(key, i)

    @property
    def initial_error(self) -> float:
        return float(jnp.mean(jnp.abs(self.init - self.target)))


def texture_problem(
    size: int,
    target: str = "camera",
    *,
    spp: int = 1,
    spp_grad: int = 1,
    grad_samples: int = 1,
    reference_spp: int = 256,
    eval_spp: int = 32,
    init_alpha: float = 0.1,
    seed: int = 0,
) -> TextureProblem:
    """Builds the texture scene at ``size``^2 texels with a ``target`` roughness
    (:func:`optax_bilateral.toy.texture.target_roughness`: ``"camera"`` piecewise
    smooth, ``"noise"`` i.i.d. high-frequency noise, ``"phantom"``)."""
    if isinstance(grad_samples, bool) or not isinstance(grad_samples, int) or grad_samples < 1:
        raise ValueError(f"grad_samples must be a positive int, got {grad_samples!r}")
    scene = tex.make_scene(size)
    alpha_t = jnp.asarray(tex.target_roughness(target, size, seed=seed))
    reference = tex.render_reference(alpha_t, scene, reference_spp, seed=seed)
    return TextureProblem(
        size=size,
        target_name=target,
        spp=spp,
        spp_grad=spp_grad,
        grad_samples=grad_samples,
        eval_spp=eval_spp,
        scene=scene,
        target=alpha_t,
        reference=reference,
        init=jnp.full((size, size), init_alpha, jnp.float32),
        key=jax.random.PRNGKey(seed + 1),
    )


def loss_and_grad(
    problem: TextureProblem, alpha, key, spp: int | None = None, spp_grad: int | None = None
):
    """The noisy training loss and its unbiased gradient at ``alpha`` (one Monte Carlo draw)."""
    spp = problem.spp if spp is None else spp
    spp_grad = problem.spp_grad if spp_grad is None else spp_grad

    def loss(a):
        return tex.loss_fn(tex.render(a, problem.scene, key, spp, spp_grad), problem.reference)

    return jax.value_and_grad(loss)(alpha)


def gradient_moments(problem: TextureProblem, alpha, n: int, key) -> tuple[jax.Array, jax.Array]:
    """Per-texel mean and variance of ``n`` independent gradient estimates at ``alpha``.

    Estimate ``i`` uses ``fold_in(key, i)`` with the problem's ``spp`` /
    ``spp_grad``; the mean of the first ``k`` is itself an unbiased gradient
    estimate whose variance is ``var / k``. ``n`` is traced (one compilation).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"n must be an int >= 2 (the variance needs two samples), got {n!r}")
    s, s2 = _problem_sums(problem, alpha, n, key)
    mean = s / n
    return mean, jnp.maximum(s2 / n - mean * mean, 0.0) * (n / (n - 1))


def mean_gradient(problem: TextureProblem, alpha, n: int, key) -> jax.Array:
    """The average of ``n`` independent gradient estimates (keys ``fold_in(key, i)``)."""
    return _problem_sums(problem, alpha, n, key)[0] / n


def _problem_sums(problem: TextureProblem, alpha, n: int, key) -> tuple[jax.Array, jax.Array]:
    """Sums of ``n`` gradient estimates and of their squares (``n`` traced: one program)."""
    return _gradient_sums(
        jnp.asarray(alpha),
        jnp.asarray(n, jnp.int32),
        key,
        problem.scene,
        problem.reference,
        spp=problem.spp,
        spp_grad=problem.spp_grad,
    )


@functools.partial(jax.jit, static_argnames=("spp", "spp_grad"))
def _gradient_sums(alpha, n, key, scene, reference, *, spp, spp_grad):
    def body(i, acc):
        k = jax.random.fold_in(key, i)
        g = jax.grad(lambda a: tex.loss_fn(tex.render(a, scene, k, spp, spp_grad), reference))(
            alpha
        )
        return acc[0] + g, acc[1] + g * g

    zero = jnp.zeros_like(alpha)
    return jax.lax.fori_loop(0, n, body, (zero, zero))


def image_loss(problem: TextureProblem, alpha) -> float:
    """Loss of a low-noise (``eval_spp`` Sobol samples) render of ``alpha``: the clean objective."""
    img = tex.render_reference(alpha, problem.scene, problem.eval_spp, seed=7)
    return float(tex.loss_fn(img, problem.reference))


# ----------------------------------------------------------------------------- batched runs

Probe = Callable[..., Mapping[str, jax.Array]]


@dataclasses.dataclass(frozen=True)
class Method:
    """One optimizer and the values of its injected hyperparameters to run.

    Attributes:
      opt: an optax transformation returning the *update* (``-lr * step``). With
        ``hyperparams`` it must be an ``optax.inject_hyperparams`` optimizer.
      hyperparams: name -> R values of injected hyperparameters; the R runs share
        one compiled program (``jax.vmap``). ``None``: one run.
      probe: optional ``probe(grads, updates, old_state, new_state, params) ->
        {name: scalar}``, evaluated inside every step of every run (e.g. step
        statistics for the bounded-step check).
    """

    opt: optax.GradientTransformation
    hyperparams: Mapping[str, Sequence[float]] | None = None
    probe: Probe | None = None


@dataclasses.dataclass
class Runs:
    """R optimisation runs of one :class:`Method`.

    Attributes:
      name: the method's name.
      hyperparams: name -> ``(R,)`` values that differ between the runs.
      metrics: name -> ``(R, T)`` per-iteration values: ``loss`` (the noisy
        training loss, before the step), ``param_error`` (mean ``|alpha -
        alpha_target|``, after the step) and whatever the probe returned.
      final: ``(R, H, W)`` final roughness.
      image_loss: ``(R,)`` loss of a low-noise render of ``final``.
    """

    name: str
    hyperparams: dict[str, np.ndarray]
    metrics: dict[str, np.ndarray]
    final: np.ndarray
    image_loss: np.ndarray

    def __len__(self) -> int:
        return self.final.shape[0]

    def label(self, r: int = 0) -> str:
        hp = ", ".join(f"{k}={v[r]:g}" for k, v in self.hyperparams.items())
        return f"{self.name} [{hp}]" if hp else self.name

    def final_error(self) -> np.ndarray:
        """``(R,)`` parameter error after the last step."""
        return self.metrics["param_error"][:, -1]

    def best(self, metric: str = "param_error") -> int:
        """Index of the run with the smallest final ``metric`` (NaN counts as worst)."""
        v = self.metrics[metric][:, -1]
        return int(np.argmin(np.where(np.isnan(v), np.inf, v)))

    def select(self, r: int, name: str | None = None) -> Runs:
        """Run ``r`` alone (R = 1), named ``name`` (default: its label)."""
        return Runs(
            name=name or self.label(r),
            hyperparams={k: v[r : r + 1] for k, v in self.hyperparams.items()},
            metrics={k: v[r : r + 1] for k, v in self.metrics.items()},
            final=self.final[r : r + 1],
            image_loss=self.image_loss[r : r + 1],
        )


@dataclasses.dataclass
class Timing:
    """Wall time of one :func:`run_texture` call."""

    seconds: float  # everything: init, compilation, steps, evaluation
    compile_seconds: float  # first chunk minus a typical chunk (0 if the program was cached)
    step_seconds: float  # per iteration, all runs together, compilation excluded


def _chunks(iterations: int, target: int = 25) -> int:
    """The largest divisor of ``iterations`` not above ``target`` (one compile serves every
    chunk)."""
    return max(d for d in range(1, min(target, iterations) + 1) if iterations % d == 0)


def run_texture(
    problem: TextureProblem,
    methods: Mapping[str, Method | optax.GradientTransformation],
    iterations: int,
    *,
    progress: bool = True,
    chunk: int | None = None,
) -> tuple[dict[str, Runs], Timing]:
    """Runs every method (every hyperparameter setting) on ``problem`` for ``iterations`` steps.

    All runs of all methods advance together in one compiled program: each
    iteration renders every run's texture with the same Monte Carlo samples
    (``grad_samples`` estimates with ``spp`` / ``spp_grad`` samples each, keys
    ``fold_in(fold_in(problem.key, i), j)``), averages their loss gradients, takes
    one step of each optimizer and clips to the roughness range. The recorded
    ``loss`` is the average of those noisy losses. The program is cached: calling
    again with the *same* optimizer objects, run counts, texture size and
    ``spp`` / ``spp_grad`` (e.g. on another target, or with another
    ``grad_samples``) does not recompile.

    Args:
      methods: name -> :class:`Method` (or a bare optimizer: one run).
      chunk: iterations per compiled ``lax.scan`` call (must divide
        ``iterations``); default: the largest divisor <= 25.

    Returns:
      ``(runs, timing)``: name -> :class:`Runs`, and the wall time of the call.
    """
    from tqdm.auto import tqdm

    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be a positive int, got {iterations!r}")
    chunk = _chunks(iterations) if chunk is None else chunk
    if not isinstance(chunk, int) or chunk < 1 or iterations % chunk:
        raise ValueError(
            f"chunk must be a positive divisor of iterations={iterations}, got {chunk!r}"
        )
    if not methods:
        raise ValueError("methods must name at least one optimizer")
    methods = {k: m if isinstance(m, Method) else Method(m) for k, m in methods.items()}
    t_start = time.perf_counter()
    names = tuple(methods)
    hps, carry = {}, []
    for name, m in methods.items():
        hps[name] = _check_hyperparams(name, m.hyperparams)
        carry.append(_batched_init(m.opt, problem.init, hps[name]))
    carry = tuple(carry)
    opts = tuple(methods[n].opt for n in names)
    probes = tuple(methods[n].probe for n in names)

    outs, chunk_seconds = [], []
    bar = tqdm(
        range(0, iterations, chunk),
        desc="iterations",
        unit_scale=chunk,
        leave=False,
        disable=not progress,
    )
    for start in bar:
        t0 = time.perf_counter()
        carry, out = _run_chunk(
            carry,
            jnp.asarray(start, jnp.int32),
            problem.key,
            jnp.asarray(problem.grad_samples, jnp.int32),
            problem.scene,
            problem.reference,
            problem.target,
            opts=opts,
            probes=probes,
            spp=problem.spp,
            spp_grad=problem.spp_grad,
            chunk=chunk,
        )
        out = jax.device_get(out)
        chunk_seconds.append(time.perf_counter() - t0)
        outs.append(out)
    bar.close()
    typical = float(np.median(chunk_seconds[1:])) if len(chunk_seconds) > 1 else chunk_seconds[0]
    runs = {}
    for k, name in enumerate(names):
        metrics = {m: np.concatenate([o[k][m] for o in outs], axis=0).T for m in outs[0][k]}
        final = np.asarray(carry[k][0])
        runs[name] = Runs(
            name=name,
            hyperparams=hps[name],
            metrics=metrics,
            final=final,
            image_loss=np.array([image_loss(problem, a) for a in final]),
        )
    timing = Timing(
        seconds=time.perf_counter() - t_start,
        compile_seconds=max(chunk_seconds[0] - typical, 0.0),
        step_seconds=typical / chunk,
    )
    return runs, timing


@functools.partial(jax.jit, static_argnames=("opts", "probes", "spp", "spp_grad", "chunk"))
def _run_chunk(
    carry,
    start,
    base_key,
    grad_samples,
    scene,
    reference,
    target,
    *,
    opts,
    probes,
    spp,
    spp_grad,
    chunk,
):
    def loss_and_grad_one(alpha, key):
        def loss(a, k):
            return tex.loss_fn(tex.render(a, scene, k, spp, spp_grad), reference)

        def body(j, acc):
            value, grad = jax.value_and_grad(loss)(alpha, jax.random.fold_in(key, j))
            return acc[0] + value, acc[1] + grad

        value, grad = jax.lax.fori_loop(0, grad_samples, body, (0.0, jnp.zeros_like(alpha)))
        return value / grad_samples, grad / grad_samples

    def update_one(opt, probe, grad, state, alpha):
        updates, new_state = opt.update(grad, state, alpha)
        new_alpha = jnp.clip(optax.apply_updates(alpha, updates), tex.ALPHA_MIN, tex.ALPHA_MAX)
        out = {"param_error": jnp.mean(jnp.abs(new_alpha - target))}
        if probe is not None:
            out.update(probe(grad, updates, state, new_state, alpha))
        return new_alpha, new_state, out

    def body(carry, i):
        key = jax.random.fold_in(base_key, i)
        # One render program for every run of every method (they differ only in alpha).
        # lax.map, not vmap: runs one after another, so the filters' lax.cond (all texels
        # observed or not) stays a branch instead of both branches under a batched select,
        # and only one run's render temporaries are alive at a time.
        alphas = jnp.concatenate([a for a, _ in carry])
        losses, grads = jax.lax.map(lambda a: loss_and_grad_one(a, key), alphas)
        new, outs, start = [], [], 0
        for (alpha, state), opt, probe in zip(carry, opts, probes):
            r = alpha.shape[0]
            g = grads[start : start + r]
            a, s, out = jax.lax.map(
                lambda x, opt=opt, probe=probe: update_one(opt, probe, *x), (g, state, alpha)
            )
            out["loss"] = losses[start : start + r]
            new.append((a, s))
            outs.append(out)
            start += r
        return tuple(new), tuple(outs)

    return jax.lax.scan(body, carry, start + jnp.arange(chunk))


def _check_hyperparams(name, hyperparams) -> dict[str, np.ndarray]:
    hp = {k: np.asarray(v, np.float32).reshape(-1) for k, v in (hyperparams or {}).items()}
    if len({len(v) for v in hp.values()}) > 1:
        raise ValueError(
            f"method {name!r}: hyperparams must all have the same length, got "
            f"{ {k: len(v) for k, v in hp.items()} }"
        )
    return hp


def _batched_init(opt, init, hp: Mapping[str, np.ndarray]):
    """``(R, H, W)`` parameters and a state with a leading run axis; ``hp`` set per run."""
    if not hp:
        state = opt.init(init)
        return init[None], jax.tree.map(lambda x: jnp.asarray(x)[None], state)
    state0 = opt.init(init)
    known = getattr(state0, "hyperparams", None)
    if known is None:
        raise TypeError(
            "hyperparams need an optax.inject_hyperparams optimizer, got a state "
            f"of type {type(state0).__name__}"
        )
    missing = set(hp) - set(known)
    if missing:
        raise ValueError(
            f"hyperparams {sorted(missing)} are not injected by this optimizer; "
            f"it injects {sorted(known)} (static args cannot be varied)"
        )
    r = len(next(iter(hp.values())))

    def one(values):
        s = opt.init(init)
        new = dict(s.hyperparams)
        for k, v in values.items():
            new[k] = jnp.asarray(v, new[k].dtype)
        return s._replace(hyperparams=new)

    states = jax.vmap(one)({k: jnp.asarray(v) for k, v in hp.items()})
    return jnp.broadcast_to(init, (r,) + init.shape), states


# ----------------------------------------------------------------------------- step statistics


def find_moments(state) -> Any:
    """The first sub-state with ``count``, ``mu`` and ``nu`` (Adam's or the postfilter's
    moments)."""

    def has(x):
        return all(hasattr(x, a) for a in ("count", "mu", "nu"))

    found = [x for x in jax.tree.leaves(state, is_leaf=has) if has(x)]
    if not found:
        raise ValueError(f"no (count, mu, nu) state in {type(state).__name__}")
    return found[0]


def bounded_step_probe(b1: float, b2: float) -> Probe:
    """A :func:`run_texture` probe for the bounded-step check of supplement §1.3.

    Returns per step ``max_step = max_j |Delta_j|`` (``Delta = -updates / lr``,
    the step before the learning rate; the optimizer must inject
    ``learning_rate``) and ``adam_ratio = max_k |m^_k| / sqrt(v^_k)``, Adam's own
    ratio on the optimizer's *unfiltered*, bias-corrected moments (texels with
    ``v = 0`` have ``m = 0`` and count as 0). A row-stochastic, non-negative ``B``
    applied to ``m`` and ``v`` with the same weights gives ``max_step <= adam_ratio``.
    """

    def probe(grads, updates, old_state, new_state, params):
        del grads, params
        lr = old_state.hyperparams["learning_rate"]
        delta = -updates / lr
        moments = find_moments(new_state)
        t = moments.count.astype(jnp.float32)
        m_hat = moments.mu / (1 - b1**t)
        v_hat = moments.nu / (1 - b2**t)
        ratio = jnp.where(
            v_hat > 0, jnp.abs(m_hat) / jnp.sqrt(jnp.where(v_hat > 0, v_hat, 1.0)), 0.0
        )
        return {"max_step": jnp.max(jnp.abs(delta)), "adam_ratio": jnp.max(ratio)}

    return probe


# ----------------------------------------------------------------------------- tables and plots


def table(
    rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None, floatfmt: str = ".4g"
) -> str:
    """A Markdown table (shown with ``IPython.display.Markdown`` or printed).

    ``|`` in names and text (``max |Δ|``) is escaped so that it does not split a cell.
    """
    if not rows:
        return ""
    columns = list(columns if columns is not None else rows[0].keys())

    def esc(v):
        return v.replace("|", "\\|") if isinstance(v, str) else v

    escaped = [{esc(c): esc(r[c]) for c in columns if c in r} for r in rows]
    return common.markdown_table(escaped, [esc(c) for c in columns], floatfmt)


def iterations_to_reach(curve: np.ndarray, value: float) -> int | None:
    """First iteration (1-based) at which ``curve`` is at or below ``value``; None if never."""
    hit = np.nonzero(np.asarray(curve) <= value)[0]
    return int(hit[0]) + 1 if len(hit) else None


def smooth(y: np.ndarray, width: int) -> np.ndarray:
    """Trailing moving average over ``width`` iterations (for the noisy 1-spp training loss)."""
    y = np.asarray(y, np.float64)
    if width <= 1:
        return y
    c = np.cumsum(np.insert(y, 0, 0.0))
    out = np.empty_like(y)
    for i in range(len(y)):
        lo = max(0, i + 1 - width)
        out[i] = (c[i + 1] - c[lo]) / (i + 1 - lo)
    return out


def plot_metric(
    ax,
    curves: Mapping[str, np.ndarray],
    *,
    ylabel: str,
    log_y: bool = True,
    smooth_width: int = 1,
    title: str | None = None,
) -> None:
    """One line per ``label -> (T,)`` curve against iteration (1-based)."""
    for label, y in curves.items():
        ax.plot(np.arange(1, len(y) + 1), smooth(y, smooth_width), label=label, lw=1.4)
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    if log_y:
        ax.set_yscale("log")
    if title:
        ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)


def sweep_rows(runs: Mapping[str, Runs], extra: Callable | None = None) -> list[dict]:
    """One table row per method and learning rate of a sweep, the best marked ``*``.

    ``extra(name, runs, i)`` may add columns (a dict), placed before ``best``.
    """
    rows = []
    for name, r in runs.items():
        for i in range(len(r)):
            row = {
                "method": name,
                "learning rate": float(r.hyperparams["learning_rate"][i]),
                "final param error": float(r.final_error()[i]),
                "image loss (low-noise render)": float(r.image_loss[i]),
            }
            if extra is not None:
                row.update(extra(name, r, i))
            row["best"] = "*" if i == r.best() else ""
            rows.append(row)
    return rows


def sweep_report(problem: TextureProblem, timing, rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown: the start error, the run time and the sweep table."""
    return (
        f"Initial param error {problem.initial_error:.4f}; {timing.seconds:.1f} s for all "
        f"runs ({timing.compile_seconds:.1f} s of it compilation).\n\n" + table(rows)
    )


def plot_best_curves(best: Mapping[str, Runs], suptitle: str):
    """Training loss and parameter error of each method's best run, side by side."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    plot_metric(
        axes[0],
        {k: v.metrics["loss"][0] for k, v in best.items()},
        ylabel="training loss (1 spp, moving average of 5)",
        smooth_width=5,
        title="loss, best learning rate of each",
    )
    plot_metric(
        axes[1],
        {k: v.metrics["param_error"][0] for k, v in best.items()},
        ylabel="mean |α − α_target|",
        title="parameter error",
    )
    fig.suptitle(suptitle)
    fig.tight_layout()
    return fig


def show_roughness(ax, alpha, title: str = "") -> None:
    """A roughness texture on the log colour scale of the targets."""
    from matplotlib.colors import LogNorm

    ax.imshow(np.asarray(alpha), cmap="viridis", norm=LogNorm(tex.ALPHA_MIN, tex.ALPHA_MAX))
    ax.set_title(title, fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])


# ----------------------------------------------------------------------------- volume


def run_volume(
    methods: Mapping[str, tuple[Callable[[float], optax.GradientTransformation], Sequence[float]]],
    *,
    size: int = 64,
    resolution: int = 32,
    n_views: int = 64,
    views_per_step: int = 4,
    iterations: int = 300,
    target_spp: int = 256,
    eval_every: int = 25,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, list[dict]]:
    """Volume recovery (:mod:`optax_bilateral.toy.volume`) for every method and learning rate.

    Args:
      methods: name -> ``(factory, learning_rates)``; ``factory(learning_rate)``
        returns the optimizer. Each method compiles once
        (``optax.inject_hyperparams``) and runs its learning rates one after another.
      size: voxels per axis; resolution, n_views: image side and number of cameras;
      views_per_step: cameras rendered per iteration (random, shared by all runs).
      target_spp: samples per pixel of the target images.

    Every iteration renders ``views_per_step`` random views with 1 spp primal and
    1 spp gradient (independent), steps and projects to the valid domain.

    Returns:
      name -> one dict per learning rate: ``learning_rate``, ``iterations``,
      ``loss`` (training loss per iteration), ``eval_iterations`` and
      ``param_error`` / ``density_error`` / ``albedo_error`` there
      (:func:`optax_bilateral.toy.volume.param_errors`), ``final`` parameters.
    """
    from tqdm.auto import tqdm

    from optax_bilateral.toy import volume as vol

    scene = vol.make_scene(resolution=resolution, n_views=n_views)
    target = {k: jnp.asarray(v) for k, v in vol.reference_volume(size).items()}
    init = {k: jnp.asarray(v) for k, v in vol.initial_volume(size).items()}
    base = jax.random.key(seed)
    views = jnp.arange(n_views)
    targets = jnp.concatenate(
        [
            vol.render_mean(
                target,
                scene,
                jax.random.fold_in(base, 1_000_000 + i),
                views[i : i + 4],
                spp=target_spp,
            )
            for i in range(0, n_views, 4)
        ]
    )
    errors = jax.jit(vol.param_errors)
    out: dict[str, list[dict]] = {}
    for name, (factory, lrs) in methods.items():
        opt = optax.inject_hyperparams(factory)(learning_rate=float(lrs[0]))

        @jax.jit
        def step(params, state, i, targets, opt=opt):
            key = jax.random.fold_in(base, i)
            k_views, k_render = jax.random.split(key)
            v = jax.random.choice(k_views, n_views, (views_per_step,), replace=False)
            loss, grads, _ = vol.loss_and_grad(params, scene, k_render, v, targets[v])
            updates, state = opt.update(grads, state, params)
            return vol.project(optax.apply_updates(params, updates), scene), state, loss

        out[name] = []
        for lr in lrs:
            params, state = init, opt.init(init)
            state.hyperparams["learning_rate"] = jnp.asarray(
                lr, state.hyperparams["learning_rate"].dtype
            )
            rec = {
                "learning_rate": float(lr),
                "loss": [],
                "eval_iterations": [],
                "param_error": [],
                "density_error": [],
                "albedo_error": [],
            }
            for i in tqdm(
                range(iterations), desc=f"{name} lr={lr:g}", leave=False, disable=not progress
            ):
                params, state, loss = step(params, state, jnp.asarray(i, jnp.int32), targets)
                rec["loss"].append(float(loss))
                if (i + 1) % eval_every == 0 or i == iterations - 1:
                    rec["eval_iterations"].append(i + 1)
                    for k, v in errors(params, target).items():
                        rec[k].append(float(v))
            rec = {k: np.asarray(v) if isinstance(v, list) else v for k, v in rec.items()}
            rec["iterations"] = np.arange(1, iterations + 1)
            rec["final"] = jax.device_get(params)
            out[name].append(rec)
    return out
