# ruff: noqa  (a study kept in git history only: docs/research/camera_distance.md)
import inspect
import sys

import jax
import numpy as np

from experiments.tuning import scenes

LAGS = (1, 2, 4, 8, 16)


def lagcorr(z, axes, lag):
    cs = []
    for a in axes:
        n = z.shape[a]
        if n <= lag:
            continue
        x0 = np.take(z, np.arange(n - lag), axis=a)
        x1 = np.take(z, np.arange(lag, n), axis=a)
        den = np.sqrt((x0 * x0).sum() * (x1 * x1).sum())
        cs.append((x0 * x1).sum() / den if den > 0 else 0)
    return np.mean(cs) if cs else np.nan


for name in sys.argv[1:]:
    s = scenes.make(name)
    step = "step" in inspect.signature(s.grad).parameters
    leaves = jax.tree.leaves(s.init)
    for at in ("init", "mid"):
        p = (
            s.init
            if at == "init"
            else jax.tree.map(
                lambda a, b: 0.5 * a + 0.5 * b,
                s.init,
                s.data["target"]
                if "target" in s.data
                and jax.tree.structure(s.data["target"]) == jax.tree.structure(s.init)
                else s.init,
            )
        )
        for cam in (0, 1) if "two" in name else (0,):
            gs = []
            for k in range(8):
                key = jax.random.PRNGKey(100 + k)
                g = s.grad(s.data, p, key, cam) if step else s.grad(s.data, p, key)
                gs.append([np.asarray(x, np.float64) for x in jax.tree.leaves(g)])
            for li, leaf in enumerate(leaves):
                G = np.stack([g[li] for g in gs])
                z = G - G.mean(0)
                axes = tuple(range(min(leaf.ndim, 3))) if s.spatial_axes is None else s.spatial_axes
                if leaf.ndim >= 3 and leaf.shape[-1] in (1, 3):
                    axes = tuple(range(leaf.ndim - 1))
                if name.startswith("signal1d"):
                    axes = (0,)
                r = [lagcorr(z[j], axes, l) for j in range(8) for l in LAGS]
                r = np.array(r).reshape(8, len(LAGS)).mean(0)
                sig = np.sqrt((G.mean(0) ** 2).mean())
                noi = np.sqrt((z**2).mean())
                print(
                    f"{name:22s} {at:4s} cam{cam} leaf{li} {leaf.shape} axes{axes} corr@{LAGS}: "
                    + " ".join(f"{x:5.2f}" for x in r)
                    + f"  snr {sig / noi:.2f}",
                    flush=True,
                )
