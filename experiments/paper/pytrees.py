"""The defaults on the pytrees users pass: grids beside weights, scalars and curves.

    python -m experiments.paper.pytrees [--quick] [--out DIR]

Five problems a new user brings, each optimiser at its best learning rate of
``0.0025 * 2^k`` (k = 0..7; median of 3 seeds):

* ``rosenbrock``: the 2-parameter Rosenbrock function from (-1, 1), lr 0.1, 10,000 steps
  (no sweep; the final point, its distance to the minimum (1, 1)).
* ``texture_mlp``: a 64x64x3 texture, a 2 -> 32 -> 32 -> 3 MLP of the pixel coordinates and
  a scalar exposure, ``image = exp(e) (texture + mlp(u, v))``, recovered from the image's
  residual with unit Gaussian noise per pixel (a Monte Carlo renderer's), 300 steps; the error
  is the mean |image - target image|.
* ``signal_1d``: a piecewise-smooth ``(1024,)`` signal from noisy gradients, 300 steps.
* ``volume_3d``: a ``(32, 32, 32)`` density without a channel axis, noisy gradients, 300 steps.
* ``holography``: a complex ``(64, 64)`` field from phase-shifting holography
  (:func:`holography`), noisy gradients, 300 steps.

Methods: ``optax.adam``; ``bilateral_adam`` with its defaults; on ``texture_mlp`` also the
texture through ``bilateral_adam`` and the rest through ``optax.adam``
(``optax.multi_transform``); on the 1-D, 3-D and complex grids also ``spatial_axes`` given.
Writes ``pytrees.json``, ``pytrees.md`` and ``pytrees.png`` (error against learning rate).
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

import optax_bilateral as ob
from experiments import common

LEARNING_RATES = tuple(0.0025 * 2**k for k in range(8))


# ----------------------------------------------------------------------------------- problems


def _mlp_init(key, sizes=(2, 32, 32, 3), scale=1.0):
    keys = jax.random.split(key, len(sizes) - 1)
    return [
        {
            "w": scale * jax.random.normal(k, (a, b)) / np.sqrt(a),
            "b": jnp.zeros((b,)),
        }
        for k, a, b in zip(keys, sizes[:-1], sizes[1:])
    ]


def _mlp(layers, x):
    for i, layer in enumerate(layers):
        x = x @ layer["w"] + layer["b"]
        if i < len(layers) - 1:
            x = jnp.tanh(x)
    return x


def _coords(size):
    u = jnp.linspace(-1, 1, size)
    return jnp.stack(jnp.meshgrid(u, u, indexing="ij"), -1)


def texture_mlp(size: int):
    """``(init, grad(params, key), error(params))`` of the texture + MLP + exposure problem."""
    key = jax.random.PRNGKey(7)
    rng = np.random.default_rng(7)
    blocks = rng.uniform(0.1, 0.6, (8, 8, 3))
    texture = jnp.asarray(np.kron(blocks, np.ones((size // 8, size // 8, 1))), jnp.float32)
    true = {"texture": texture, "mlp": _mlp_init(key, scale=0.5), "exposure": jnp.float32(0.3)}
    xy = _coords(size)

    def image(p):
        return jnp.exp(p["exposure"]) * (p["texture"] + 0.2 * _mlp(p["mlp"], xy))

    target = image(true)
    init = {
        "texture": jnp.full((size, size, 3), 0.35, jnp.float32),
        "mlp": _mlp_init(jax.random.fold_in(key, 1), scale=0.5),
        "exposure": jnp.float32(0.0),
    }

    def grad(p, k):
        residual = image(p) - target + jax.random.normal(k, target.shape)
        _, vjp = jax.vjp(image, p)
        return vjp(residual / size)[0]

    return init, grad, lambda p: jnp.mean(jnp.abs(image(p) - target))


def _piecewise(n, pieces, rng):
    edges = np.sort(rng.choice(np.arange(1, n), pieces - 1, replace=False))
    values = rng.uniform(0.2, 0.8, pieces)
    return np.repeat(values, np.diff(np.concatenate([[0], edges, [n]])))


def signal_1d(n: int):
    rng = np.random.default_rng(3)
    target = jnp.asarray(_piecewise(n, 12, rng) + 0.05 * np.sin(np.arange(n) / 9), jnp.float32)
    init = jnp.full((n,), 0.5, jnp.float32)

    def grad(p, k):
        return p - target + jax.random.normal(k, p.shape)

    return init, grad, lambda p: jnp.mean(jnp.abs(p - target))


def volume_3d(n: int):
    rng = np.random.default_rng(4)
    blocks = rng.uniform(0.1, 0.9, (4, 4, 4))
    target = jnp.asarray(np.kron(blocks, np.ones((n // 4,) * 3)), jnp.float32)
    init = jnp.full((n, n, n), 0.5, jnp.float32)

    def grad(p, k):
        return p - target + jax.random.normal(k, p.shape)

    return init, grad, lambda p: jnp.mean(jnp.abs(p - target))


def holography(n: int):
    """A complex ``(n, n)`` field (piecewise-constant amplitude and phase) from phase-shifting
    holography: the intensities ``|z + r_k|^2`` under 4 reference waves ``r_k = i^k``, with
    complex Gaussian noise on the gradient (the steepest-descent direction, ``conj`` of JAX's)."""
    rng = np.random.default_rng(5)
    amplitude = np.kron(rng.uniform(0.4, 1.0, (4, 4)), np.ones((n // 4, n // 4)))
    phase = np.kron(rng.uniform(-1.0, 1.0, (4, 4)), np.ones((n // 4, n // 4)))
    target = jnp.asarray(amplitude * np.exp(1j * phase), jnp.complex64)
    refs = jnp.asarray([1, 1j, -1, -1j], jnp.complex64)[:, None, None]
    measured = jnp.abs(target + refs) ** 2
    loss = lambda z: 0.25 * jnp.sum((jnp.abs(z + refs) ** 2 - measured) ** 2)

    def grad(z, k):
        re, im = jax.random.normal(k, (2, *z.shape))
        return jnp.conj(jax.grad(loss)(z)) + 2.0 * (re + 1j * im)

    init = jnp.zeros((n, n), jnp.complex64)
    return init, grad, lambda z: jnp.mean(jnp.abs(z - target))


def rosenbrock_point(opt: optax.GradientTransformation, steps: int) -> np.ndarray:
    """The point ``opt`` reaches on Rosenbrock's function from (-1, 1) after ``steps``."""
    f = lambda p: (1 - p[0]) ** 2 + 100 * (p[1] - p[0] ** 2) ** 2

    def body(carry, _):
        p, state = carry
        u, state = opt.update(jax.grad(f)(p), state, p)
        return (optax.apply_updates(p, u), state), None

    p0 = jnp.asarray([-1.0, 1.0], jnp.float32)
    (p, _), _ = jax.lax.scan(body, (p0, opt.init(p0)), None, length=steps)
    return np.asarray(p)


# ----------------------------------------------------------------------------------- runs


def errors(problem, make, steps: int, rates: Sequence[float], seeds: Sequence[int]) -> np.ndarray:
    """The final errors, ``(len(rates), len(seeds))``, of ``make(learning_rate)`` from each
    seed: one compiled program for every rate and seed (the rate injected, both vmapped)."""
    init, grad, error = problem

    def one(lr, key):
        opt = optax.inject_hyperparams(make)(learning_rate=lr)

        def body(carry, k):
            p, state = carry
            u, state = opt.update(grad(p, k), state, p)
            return (optax.apply_updates(p, u), state), None

        (p, _), _ = jax.lax.scan(body, (init, opt.init(init)), jax.random.split(key, steps))
        return error(p)

    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    run = jax.jit(jax.vmap(jax.vmap(one, (None, 0)), (0, None)))
    return np.asarray(run(jnp.asarray(rates, jnp.float32), keys))


def best_error(problem, make: Callable[..., optax.GradientTransformation], steps, rates, seeds):
    """``(best median error, its learning rate, {lr: median error})``."""
    medians = np.median(errors(problem, make, steps, rates, seeds), axis=1)
    curve = {float(lr): float(e) for lr, e in zip(rates, medians)}
    best = min(curve, key=lambda lr: curve[lr])
    return curve[best], best, curve


def _texture_apart(learning_rate):
    labels = {"texture": "grid", "mlp": "other", "exposure": "other"}
    transforms = {"grid": ob.bilateral_adam(learning_rate), "other": optax.adam(learning_rate)}
    return optax.multi_transform(transforms, labels)


def methods(name: str) -> dict[str, Callable[[float], optax.GradientTransformation]]:
    out = {"optax.adam": optax.adam, "bilateral_adam (defaults)": ob.bilateral_adam}
    if name == "texture_mlp":
        out["texture: bilateral_adam, rest: optax.adam"] = _texture_apart
    if name == "signal_1d":
        out["bilateral_adam, spatial_axes=(0,)"] = functools.partial(
            ob.bilateral_adam, spatial_axes=(0,)
        )
    if name in ("volume_3d", "holography"):
        axes = (0, 1, 2) if name == "volume_3d" else (0, 1)
        out[f"bilateral_adam, spatial_axes={axes}"] = functools.partial(
            ob.bilateral_adam, spatial_axes=axes
        )
    return out


def run(quick: bool) -> dict:
    steps = 30 if quick else 300
    seeds: Sequence[int] = (0,) if quick else (0, 1, 2)
    rates = LEARNING_RATES[2:5:2] if quick else LEARNING_RATES
    problems = {
        "texture_mlp": texture_mlp(16 if quick else 64),
        "signal_1d": signal_1d(128 if quick else 1024),
        "volume_3d": volume_3d(8 if quick else 32),
        "holography": holography(16 if quick else 64),
    }
    rows, curves = [], {}
    todo = [(p, m) for p in problems for m in methods(p)]
    for name, method in tqdm(todo, desc="pytrees"):
        with warnings.catch_warnings():  # the leaf rule's warnings are the point here
            warnings.simplefilter("ignore", ob.LeafRuleWarning)
            err, lr, errors = best_error(problems[name], methods(name)[method], steps, rates, seeds)
        rows.append({"problem": name, "method": method, "best lr": lr, "error": err})
        curves[(name, method)] = errors
    rosen_steps = 1000 if quick else 10_000
    rosen = {
        "optax.adam(0.1)": rosenbrock_point(optax.adam(0.1), rosen_steps),
        "bilateral_adam(0.1)": rosenbrock_point(ob.bilateral_adam(0.1), rosen_steps),
    }
    for method, point in rosen.items():
        rows.append(
            {
                "problem": f"rosenbrock, {rosen_steps} steps",
                "method": method,
                "best lr": 0.1,
                "error": float(np.linalg.norm(point - 1.0)),
                "final point": [round(float(x), 4) for x in point],
            }
        )
    return {"rows": rows, "curves": curves, "steps": steps, "seeds": list(seeds)}


def _plot(curves, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({p for p, _ in curves})
    fig, axes = plt.subplots(1, len(names), figsize=(4.5 * len(names), 3.6), squeeze=False)
    for ax, name in zip(axes[0], names):
        for (p, method), errors in curves.items():
            if p == name:
                ax.plot(list(errors), list(errors.values()), "o-", label=method)
        ax.set(xscale="log", yscale="log", xlabel="learning rate", ylabel="final error", title=name)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict:
    args = common.parse_args("the defaults on mixed pytrees", "results/pytrees", argv)
    quick = args.quick or common.quick_from_env()
    data = run(quick)
    md = "\n".join(
        [
            f"# The defaults on mixed pytrees ({'quick: not meaningful' if quick else 'full'})",
            "",
            f"Best learning rate of 0.0025 * 2^k per method, median of {len(data['seeds'])} "
            f"seed(s), {data['steps']} steps; `python -m experiments.paper.pytrees`.",
            "",
            common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in data["rows"]]),
        ]
    )
    args.out.mkdir(parents=True, exist_ok=True)
    _plot(data["curves"], args.out / "pytrees.png")
    data["curves"] = {f"{p} / {m}": v for (p, m), v in data["curves"].items()}
    common.write_results(args.out, "pytrees", data, md)
    print(md)
    return data


if __name__ == "__main__":
    main()
