"""Measures the numbers quoted in the README's "Robustness" section.

    .venv/bin/python docs/robustness_numbers.py

Small grids, a few seconds of compute (plus compile time).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob

KEY = jax.random.PRNGKey(7)
SHAPE = (8, 8, 2)
THETA = jax.random.uniform(KEY, SHAPE)
NOISE = jax.random.normal(jax.random.fold_in(KEY, 1), SHAPE)
LR = 0.1


def run(opt, grads, theta=THETA):
    upd = jax.jit(opt.update)
    state = opt.init(theta)
    out = []
    for g in grads:
        u, state = upd(g, state, theta)
        out.append(u)
    return out, state


def finite(tree):
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


def umax(u):
    return float(jnp.max(jnp.abs(u))) / LR


def main():
    print(
        "clip limits |g| <= sqrt(max/2):",
        {
            str(d.dtype if hasattr(d, "dtype") else d): math.sqrt(float(jnp.finfo(d).max) / 2)
            for d in (jnp.float32, jnp.bfloat16, jnp.float16)
        },
    )
    opt = ob.bilateral_adam(LR, sigma_d=0.3, levels=2)
    for name, g in [
        ("zeros", jnp.zeros(SHAPE)),
        ("+-1e30", 1e30 * jnp.sign(NOISE)),
        ("+-1e-30", 1e-30 * jnp.sign(NOISE)),
        ("denormal 1e-40", 1e-40 * jnp.sign(NOISE)),
    ]:
        for eps in (1e-8, 0.0):
            u, s = run(ob.bilateral_adam(LR, eps=eps, sigma_d=0.3, levels=2), [g] * 3)
            print(
                f"g={name:15s} eps={eps:g}: max|u|/lr per step {[f'{umax(x):.4g}' for x in u]}, "
                f"finite updates {finite(u)}, finite state {finite(s)}"
            )
    for sig in (0.0, 1e-30, 1e30, np.inf):
        u, _ = run(ob.bilateral_adam(LR, sigma_d=sig, levels=2), [NOISE])
        print(
            f"sigma_d={sig:g}: max|u|/lr {umax(u[0]):.6f}, "
            f"mean|u|/lr {float(jnp.mean(jnp.abs(u[0]))) / LR:.4f}"
        )

    # One finite outlier: v ~ 1e38 in its footprint shrinks the neighbours' steps until b2^t
    # decays it (b2 = 0.36: 1e38 * 0.36^t < 1 after ~87 steps).
    steps = 120
    for sig in (0.3, np.inf):
        o = ob.bilateral_adam(LR, sigma_d=sig, levels=2)
        u, s = run(o, [NOISE.at[3, 4, 0].set(1e30)] + [NOISE] * (steps - 1))
        ref, _ = run(o, [NOISE] * steps)
        near = np.zeros(SHAPE, bool)
        near[1:6, 2:7] = True
        near[3, 4, 0] = False
        ratio = {
            t: float(jnp.mean(jnp.abs(u[t][near])) / jnp.mean(jnp.abs(ref[t][near])))
            for t in (0, 1, 10, 40, 80, 100, 119)
        }
        print(
            f"spike 1e30 at one texel, sigma_d={sig}: finite {finite(u) and finite(s)}, "
            f"max|u|/lr {max(umax(x) for x in u):.4f}; 5x5 neighbours' mean |step| / clean run's "
            f"at step t: " + ", ".join(f"t={t}: {r:.3g}" for t, r in ratio.items())
        )

    for b1, b2 in [
        (0.0, 0.0),
        (0.0, 0.999999),
        (0.999999, 0.999999),
        (0.999999, None),
        (0.999999, 0.0),
    ]:
        u, s = run(ob.bilateral_adam(LR, b1=b1, b2=b2, sigma_d=0.3, levels=2), [NOISE] * 5)
        print(
            f"b1={b1} b2={b2}: time-constant gradient, max|u|/lr per step "
            f"{[round(umax(x), 4) for x in u]}, finite {finite(u) and finite(s)}"
        )

    # 10,000 steps, as tests/test_robustness.py::test_ten_thousand_steps_no_nan_no_drift.
    target = jnp.where(jnp.arange(8)[:, None, None] < 4, 0.2, 0.8) * jnp.ones(SHAPE)
    opt = ob.bilateral_adam(LR / 10, sigma_d=0.2, levels=3)

    @jax.jit
    def long(theta0):
        def body(carry, t):
            theta, state = carry
            g = 2 * (theta - target) + jax.random.normal(jax.random.fold_in(KEY, t), theta.shape)
            u, state = opt.update(g, state, theta)
            theta = optax.apply_updates(theta, u)
            return (theta, state), (jnp.max(jnp.abs(u)), jnp.sqrt(jnp.mean((theta - target) ** 2)))

        return jax.lax.scan(body, (theta0, opt.init(theta0)), jnp.arange(10_000))

    (theta, state), (um, err) = long(THETA)
    err = np.asarray(err)
    print(
        f"10k steps: finite {finite(theta) and finite(state)}, "
        f"max|u|/lr {float(jnp.max(um)) / (LR / 10):.4f}, "
        f"rms error step 1 {err[0]:.4f}, mean over 4000-5000 {err[4000:5000].mean():.4f}, "
        f"over 9000-10000 {err[-1000:].mean():.4f}"
    )


if __name__ == "__main__":
    main()
