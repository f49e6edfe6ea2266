# %% [markdown]
# # Memoryless filtering: β1 = β2 = 0 (supplement §1.1–1.2, Fig. 1)
#
# **The paper's claims.** With no temporal filtering (β1 = β2 = 0) the three update rules become
#
# | | update | supplement |
# |---|---|---|
# | Adam | `g / sqrt(g²) = sign(g)` | eq. 15 |
# | prefilter | `A g / sqrt((A g)²) = sign(A g)` | eq. 16 |
# | postfilter | `B g / sqrt(B g²)` | eq. 17 |
#
# 1. Adam and the prefilter make constant-size (sign) steps; the postfilter is a ratio of *spatial*
#    first and second moments, so it still adapts its step to the local signal-to-noise ratio:
#    writing `g = ĝ + n`, an ideal filter gives `Δ_j = ĝ_j / sqrt(ĝ_j² + Σ_k B_jk n_k²)` (eq. 24),
#    which shrinks as the noise grows.
# 2. "With no temporal filtering or low values of β1, postfiltering converges much faster than
#    Adam" (§1.1, Fig. 1, texture and volume recovery).
# 3. Memoryless optimizers keep no `m_t`, `v_t` buffers: "this reduces each of their memory
#    overhead by 2/3rd" (Fig. 1 caption).
#
# This notebook measures all three on the toy texture scene (`optax_bilateral.toy.texture`, the
# paper's Fig. 5 setting: a GGX roughness texture seen through a noisy 1-spp renderer), and on the
# toy volume scene at the full size only.
#
# Run: `OPTAX_BILATERAL_QUICK=1` gives the test-suite size (32² texels, 40 iterations, F = 3);
# without it the paper-like size (512² texels, 1 spp primal / 1 spp gradient, F = 5, 150
# iterations). `python notebooks/build_notebooks.py --execute memoryless` runs it and saves the
# executed copy in `results/notebooks/`; every figure is also saved there as PNG (in
# `results/notebooks/quick/` at the quick size).

# %%
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import optax
from IPython.display import Markdown, display

import optax_bilateral as ob

import notebook_utils as nu

T0 = time.perf_counter()
QUICK = nu.QUICK
if QUICK:
    SIZE, ITERATIONS, LEVELS = 32, 40, 3
    LRS = [0.01, 0.03]
    REFERENCE_SPP = EVAL_SPP = 64  # one compiled reference renderer serves both
    N_SAMPLES, KS, REPEATS = 64, [1, 4, 16], 2
else:
    SIZE, ITERATIONS, LEVELS = 512, 150, 5
    LRS = [0.003, 0.01, 0.03, 0.1]
    REFERENCE_SPP, EVAL_SPP = 256, 64
    N_SAMPLES, KS, REPEATS = 1024, [1, 4, 16, 64, 256], 4
SIGMA_D = 0.1  # the paper's (the library default is "auto"); log guide, as its texture runs
NOISE_SCALES = [0.0, 0.1, 0.3, 1.0, 3.0, 10.0]
print(
    f"quick={QUICK}: {SIZE}^2 texels, {ITERATIONS} iterations, F={LEVELS}, sigma_d={SIGMA_D}, "
    f"learning rates {LRS}"
)

# %% [markdown]
# ## The three memoryless optimizers
#
# All three are written with the library's public transforms. `optax.adam(b1=0, b2=0)` is eq. 15
# (`m̂ / (sqrt(v̂) + ε) = g / (|g| + ε)`), but optax still allocates `m` and `v` for it; the
# stateless sign step is `optax.sign_sgd`. The prefilter is `prefilter` followed by Adam's scaling
# with β1 = β2 = 0 (eq. 16), the postfilter is `bilateral_adam(b1=0, b2=0)` (eq. 17), which keeps no
# moment buffers. Each is wrapped in `optax.inject_hyperparams` so that the learning-rate sweep
# shares one compiled program.


# %%
def adam0(learning_rate):
    """eq. 15: sign(g)."""
    return optax.adam(learning_rate, b1=0.0, b2=0.0)


def prefilter0(learning_rate):
    """eq. 16: sign(A g)."""
    return optax.chain(
        ob.prefilter(SIGMA_D, LEVELS, log_guide=True, spatial_axes=(0, 1)),
        ob.scale_by_adam(b1=0.0, b2=0.0),
        optax.scale_by_learning_rate(learning_rate),
    )


def postfilter0(learning_rate):
    """eq. 17: B g / sqrt(B g^2)."""
    return ob.bilateral_adam(
        learning_rate,
        b1=0.0,
        b2=0.0,
        sigma_d=SIGMA_D,
        levels=LEVELS,
        log_guide=True,
        spatial_axes=(0, 1),
    )


FACTORIES = {
    "Adam (sign g)": adam0,
    "prefilter (sign A g)": prefilter0,
    "postfilter (B g / sqrt(B g²))": postfilter0,
}

# %% [markdown]
# ## Recovery with no temporal filtering (Fig. 1)
#
# Start from a constant roughness 0.1; the target is the piecewise-smooth `"camera"` texture. Each
# method runs at every learning rate of the sweep; all runs see the same Monte Carlo samples at the
# same iteration. Reported: the best learning rate of each method by final parameter error
# (mean |α − α_target|), the loss of a low-noise render of the result, and the first iteration at
# which each method reaches the error Adam ends with.

# %%
prob = nu.texture_problem(SIZE, reference_spp=REFERENCE_SPP, eval_spp=EVAL_SPP)
methods = {
    name: nu.Method(optax.inject_hyperparams(f)(learning_rate=LRS[0]), {"learning_rate": LRS})
    for name, f in FACTORIES.items()
}
runs, timing = nu.run_texture(prob, methods, ITERATIONS)
best = {name: r.select(r.best(), name) for name, r in runs.items()}
adam_final = best["Adam (sign g)"].final_error()[0]
rows = nu.sweep_rows(
    runs,
    lambda name, r, i: {
        "iterations to Adam's final error": nu.iterations_to_reach(
            r.metrics["param_error"][i], adam_final
        )
    },
)
display(Markdown(nu.sweep_report(prob, timing, rows)))

# %%
fig = nu.plot_best_curves(best, f"β1 = β2 = 0, texture {SIZE}²")
print(nu.save_figure(fig, "memoryless_curves"))
plt.show()

# %%
fig, axes = plt.subplots(2, 4, figsize=(12, 6.2))
nu.show_roughness(axes[0, 0], prob.target, "target roughness (log scale)")
axes[1, 0].imshow(np.asarray(prob.reference), cmap="gray")
axes[1, 0].set_title("reference image", fontsize=8)
axes[1, 0].set_axis_off()
for c, (name, r) in enumerate(best.items(), start=1):
    nu.show_roughness(axes[0, c], r.final[0], f"{name}\nerr {r.final_error()[0]:.4f}")
    axes[1, c].imshow(np.abs(r.final[0] - np.asarray(prob.target)), cmap="magma", vmin=0, vmax=0.1)
    axes[1, c].set_title("|α − α_target| (0 … 0.1)", fontsize=8)
    axes[1, c].set_axis_off()
fig.tight_layout()
print(nu.save_figure(fig, "memoryless_textures"))
plt.show()

# %% [markdown]
# ## Optimizer state size
#
# Bytes held by each optimizer's state pytree for this texture (`opt.init(params)`, summed over
# array leaves), next to the parameters themselves. The paper's "2/3 less memory" compares
# parameters + `m` + `v` with parameters alone. The filter's temporaries during an update are not
# state and are not counted here.

# %%
alpha0 = prob.init
param_bytes = nu.tree_nbytes(alpha0)
state_of = {
    "optax.adam(b1=0.2, b2=0.36)": optax.adam(0.01, b1=0.2, b2=0.36),
    "bilateral_adam(b1=0.2) (postfilter)": ob.bilateral_adam(
        0.01, b1=0.2, sigma_d=SIGMA_D, levels=LEVELS, log_guide=True, spatial_axes=(0, 1)
    ),
    "optax.adam(b1=0, b2=0) (eq. 15)": adam0(0.01),
    "optax.sign_sgd (eq. 15, stateless)": optax.sign_sgd(0.01),
    "prefilter + scale_by_adam(0, 0) (eq. 16)": prefilter0(0.01),
    "bilateral_adam(b1=0, b2=0) (eq. 17)": postfilter0(0.01),
}
reference_total = param_bytes + nu.tree_nbytes(state_of["optax.adam(b1=0.2, b2=0.36)"].init(alpha0))
mem_rows = []
for name, opt in state_of.items():
    sb = nu.tree_nbytes(opt.init(alpha0))
    mem_rows.append(
        {
            "optimizer": name,
            "state bytes": sb,
            "state / params": sb / param_bytes,
            "params + state vs Adam(0.2)": (param_bytes + sb) / reference_total,
        }
    )
display(Markdown(f"Parameters: {param_bytes} bytes ({SIZE}² float32).\n\n" + nu.table(mem_rows)))
memoryless_post = nu.tree_nbytes(postfilter0(0.01).init(alpha0))
assert memoryless_post < 64, "the memoryless postfilter must keep no per-texel buffers"

# %% [markdown]
# ## Eq. 24: the postfilter's step shrinks as the gradient noise grows
#
# At a fixed roughness halfway (in log space) between the start and the target, draw `N` independent
# 1-spp gradient estimates: their per-texel mean is `ĝ` (the true gradient up to a `1/N` variance)
# and their per-texel variance is `σ²`. Two ways to vary the noise:
#
# * **Monte Carlo:** `g_K` = the average of `K` fresh 1-spp gradients (noise variance `σ²/K`);
# * **synthetic:** `g = ĝ + s σ z`, `z ~ N(0, 1)` per texel (noise variance `s² σ²`, `s = 0 … 10`).
#
# For each noisy gradient we measure the mean step magnitude `mean_j |Δ_j|` of the three memoryless
# rules, and compare the postfilter with two predictions: eq. 24 with an ideal filter
# (`|ĝ_j| / sqrt(ĝ_j² + (B σ²)_j)`) and the same ratio with the actual filter `B`
# (`|B ĝ|_j / sqrt((B ĝ²)_j + (B σ²)_j)`, i.e. eq. 23 with each sum replaced by its expectation).
# The x-axis is the noise-to-signal ratio `sqrt(mean σ²_noise) / sqrt(mean ĝ²)`. Adam's step is
# `sign(g)`: its magnitude is 1 wherever `g ≠ 0` (texels whose sample hit nothing get exactly 0),
# whatever the noise.

# %%
alpha_mid = jnp.sqrt(prob.init * prob.target)
g_hat, g_var = nu.gradient_moments(prob, alpha_mid, N_SAMPLES, jax.random.PRNGKey(1000))
post_step = ob.postfilter(
    b1=0.0, b2=0.0, sigma_d=SIGMA_D, levels=LEVELS, log_guide=True, spatial_axes=(0, 1)
)
adam_step = ob.scale_by_adam(b1=0.0, b2=0.0)


@jax.jit
def step_sizes(g, alpha, g_hat, noise_var):
    d_post, _ = post_step.update(g, post_step.init(alpha), alpha)
    d_adam, _ = adam_step.update(g, adam_step.init(alpha), alpha)
    guide = jnp.log(jnp.abs(alpha) + 1e-8)  # the postfilter's log-domain guide
    bg, bg2, bh, bh2, bn = ob.atrous_bilateral(
        (g, g * g, g_hat, g_hat**2, noise_var),
        guide,
        sigma_d=SIGMA_D,
        levels=LEVELS,
        spatial_axes=(0, 1),
    )
    eq17 = bg / (jnp.sqrt(bg2) + 1e-8)
    return {
        "Adam": jnp.mean(jnp.abs(d_adam)),
        "prefilter": jnp.mean(jnp.abs(jnp.sign(bg))),  # A = B: same guide and settings
        "postfilter": jnp.mean(jnp.abs(d_post)),
        "eq. 24, ideal B": jnp.mean(jnp.abs(g_hat) / jnp.sqrt(g_hat**2 + bn + 1e-30)),
        "eq. 24, actual B": jnp.mean(jnp.abs(bh) / jnp.sqrt(bh2 + bn + 1e-30)),
        "max |post - eq. 17|": jnp.max(jnp.abs(d_post - eq17)),
        "max |Adam - sign g|": jnp.max(jnp.abs(d_adam - jnp.sign(g))),
        "noise/signal": jnp.sqrt(jnp.mean(noise_var) / jnp.mean(g_hat**2)),
        "|post| map": jnp.abs(d_post),
    }


def average(results):
    return {k: np.mean([np.asarray(r[k]) for r in results], axis=0) for k in results[0]}


mc, synthetic = {}, {}
for k in KS:
    draws = [
        nu.mean_gradient(prob, alpha_mid, k, jax.random.PRNGKey(2000 + 97 * rep + k))
        for rep in range(REPEATS)
    ]
    mc[k] = average([step_sizes(g, alpha_mid, g_hat, g_var / k) for g in draws])
for s in NOISE_SCALES:
    zs = [jax.random.normal(jax.random.PRNGKey(3000 + rep), g_hat.shape) for rep in range(REPEATS)]
    synthetic[s] = average(
        [step_sizes(g_hat + s * jnp.sqrt(g_var) * z, alpha_mid, g_hat, s * s * g_var) for z in zs]
    )

cols = [
    "noise/signal",
    "Adam",
    "prefilter",
    "postfilter",
    "eq. 24, actual B",
    "eq. 24, ideal B",
    "max |post - eq. 17|",
]
rows24 = [{"noise": f"MC, K = {k}", **{c: float(mc[k][c]) for c in cols}} for k in KS] + [
    {"noise": f"synthetic, s = {s:g}", **{c: float(synthetic[s][c]) for c in cols}}
    for s in NOISE_SCALES
]
display(Markdown(nu.table(rows24, ["noise"] + cols)))
worst = max(float(r["max |post - eq. 17|"]) for r in rows24)
# float32 filter sums of ~1e3 terms: a few ulps of a ratio bounded by 1.
assert worst < 1e-4, (
    f"the memoryless postfilter should be B g / (sqrt(B g^2) + eps), off by {worst}"
)

# %%
fig, axes = plt.subplots(1, 4, figsize=(15, 3.6), gridspec_kw={"width_ratios": [1.6, 1, 1, 1]})
ax = axes[0]
xs_mc = [float(mc[k]["noise/signal"]) for k in KS]
xs_syn = [float(synthetic[s]["noise/signal"]) for s in NOISE_SCALES[1:]]
for key, color in (("Adam", "C0"), ("prefilter", "C1"), ("postfilter", "C2")):
    ax.plot(
        xs_syn,
        [synthetic[s][key] for s in NOISE_SCALES[1:]],
        "-",
        color=color,
        label=f"{key} (synthetic)",
    )
    ax.plot(xs_mc, [mc[k][key] for k in KS], "o", color=color, label=f"{key} (MC, K spp)")
ax.plot(
    xs_syn,
    [synthetic[s]["eq. 24, actual B"] for s in NOISE_SCALES[1:]],
    "k--",
    lw=1,
    label="eq. 24 with the actual B",
)
ax.plot(
    xs_syn,
    [synthetic[s]["eq. 24, ideal B"] for s in NOISE_SCALES[1:]],
    "k:",
    lw=1,
    label="eq. 24, ideal B",
)
ax.set_xscale("log")
ax.set_xlabel("noise / signal (RMS)")
ax.set_ylabel("mean |Δ| (step / learning rate)")
ax.set_ylim(0, 1.05)
ax.grid(True, alpha=0.3)
ax.legend(fontsize=7)
ax.set_title("step magnitude vs gradient noise")
axes[1].imshow(
    np.abs(np.asarray(g_hat)),
    cmap="magma",
    vmax=float(np.percentile(np.abs(np.asarray(g_hat)), 99)),
)
axes[1].set_title(f"|ĝ| (mean of {N_SAMPLES} 1-spp gradients)", fontsize=8)
for ax, k in ((axes[2], KS[-1]), (axes[3], KS[0])):
    ax.imshow(mc[k]["|post| map"], cmap="viridis", vmin=0, vmax=1)
    ax.set_title(f"postfilter |Δ|, K = {k} spp (0 … 1)", fontsize=8)
for ax in axes[1:]:
    ax.set_axis_off()
fig.tight_layout()
print(nu.save_figure(fig, "memoryless_eq24"))
plt.show()

# %% [markdown]
# ## Volume recovery (Fig. 1, right)
#
# The same comparison on the toy participating medium (`optax_bilateral.toy.volume`: density and
# RGB albedo grids, ratio-tracking renders, 1 spp primal / 1 spp gradient). It runs only at the
# full size: at the quick size the volume renderer's and 3-D filter's compilation alone would take
# most of the test budget.

# %%
if QUICK:
    print("volume comparison skipped at the quick size (OPTAX_BILATERAL_QUICK=1)")
else:
    VOL = dict(
        size=64,
        resolution=32,
        n_views=64,
        views_per_step=4,
        iterations=300,
        target_spp=256,
        levels=4,
        sigma_d={"density": 0.05, "albedo": 0.1},
    )
    vol_methods = {
        "Adam (sign g)": (
            lambda learning_rate: optax.adam(learning_rate, b1=0.0, b2=0.0),
            [0.003, 0.01, 0.03],
        ),
        "postfilter (B g / sqrt(B g²))": (
            lambda learning_rate: ob.bilateral_adam(
                learning_rate, b1=0.0, b2=0.0, sigma_d=VOL["sigma_d"], levels=VOL["levels"]
            ),
            [0.01, 0.03, 0.1],
        ),
    }
    vol_runs = nu.run_volume(
        vol_methods, **{k: v for k, v in VOL.items() if k not in ("levels", "sigma_d")}
    )
    vol_best = {name: min(rs, key=lambda r: r["param_error"][-1]) for name, rs in vol_runs.items()}
    vol_rows = [
        {
            "method": name,
            "learning rate": r["learning_rate"],
            "final param error": float(r["param_error"][-1]),
            "density error": float(r["density_error"][-1]),
            "albedo error": float(r["albedo_error"][-1]),
            "best": "*" if r is vol_best[name] else "",
        }
        for name, rs in vol_runs.items()
        for r in rs
    ]
    display(Markdown(nu.table(vol_rows)))
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for name, r in vol_best.items():
        axes[0].plot(r["iterations"], nu.smooth(r["loss"], 10), label=name)
        axes[1].plot(r["eval_iterations"], r["param_error"], label=name)
    axes[0].set_ylabel("training loss (moving average of 10)")
    axes[1].set_ylabel("parameter error")
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"β1 = β2 = 0, volume {VOL['size']}³")
    fig.tight_layout()
    print(nu.save_figure(fig, "memoryless_volume"))
    plt.show()

# %%
print(f"notebook ran in {time.perf_counter() - T0:.1f} s")

# %% [markdown]
# ## What we measured (full size)
#
# Measured with `python notebooks/build_notebooks.py --execute memoryless` (no
# `OPTAX_BILATERAL_QUICK`), 2026-11-24, library of main at 76e7e61, on a shared 2-core CPU (load
# 11–16 from other jobs): 2333 s wall in total; the outputs above are that run's. Texture 512²,
# F = 5, σ_d = 0.1 (log guide), 150 iterations, 1 spp / 1 spp, start error 0.0807.
#
# **Claim 2 (Fig. 1, faster convergence) — agrees.** Best learning rate of each (of 0.003, 0.01,
# 0.03, 0.1): Adam (sign g) ends at param error **0.0543** (lr 0.01) with a low-noise image loss of
# 14.7 at the end: every texel keeps jumping by ±lr. The prefilter (sign A g) ends at **0.0153**
# (lr 0.01); the postfilter at **0.0077** (lr 0.03), 7× below Adam, with image loss 0.059. The
# postfilter reaches Adam's final error after **5** iterations (Adam: 150), the prefilter after 9.
#
# **Claim 3 (memory) — agrees, with one caveat.** The memoryless postfilter's state is 4 bytes (the
# step count) against 2,097,156 for Adam with β1 = 0.2 (`m`, `v`): parameters + state fall to
# **1/3** of Adam's. `optax.adam(b1=0, b2=0)` and `prefilter + scale_by_adam(0, 0)` still allocate
# `m` and `v` (optax does not special-case β = 0); `optax.sign_sgd` is the stateless sign step.
#
# **Claim 1 (eq. 24, noise-adaptive step) — agrees.** As the noise-to-signal ratio of the gradient
# grows from 0.14 (K = 256 averaged 1-spp gradients) to 2.27 (K = 1), the postfilter's mean step
# falls from **0.776 to 0.214**, while Adam's stays at **0.97–1.00** (below 1 only where a 1-spp
# gradient is exactly 0) and the prefilter's at 1. Eq. 24 with the actual filter predicts 0.763 and
# 0.211 (within 2 %); with an ideal filter, 0.829 and 0.215. The synthetic sweep continues the trend
# to 0.037 at a ratio of 22.7, where the prediction (0.023) underestimates: with strong noise the
# ratio of filtered sums is no longer close to the ratio of their expectations. The library's
# memoryless postfilter equals `B g / (sqrt(B g²) + ε)` exactly (max difference 0).
#
# **Volume (Fig. 1, right) — agrees.** 64³ density + RGB albedo, 32² images, 4 of 64 views per
# iteration, 300 iterations, F = 4, σ_d = {density 0.05, albedo 0.1}; start error 0.2162 (density
# 0.145, albedo 0.288). Sign-step Adam barely moves from the start at any learning rate tried (best
# 0.2154 at lr 0.003; 0.2202 at 0.01; 0.238 at 0.03); the memoryless postfilter lowers the error to
# **0.1515** (lr 0.1, the largest tried; density error 0.145 → 0.083). Neither is converged after
# 300 iterations.
#
# (An earlier run, 2026-11-22, before the library's redesign, gave the same texture and eq. 24
# numbers to the digits shown (prefilter 0.0154), and on the volume a postfilter error of 0.1878
# at lr 0.01 (now 0.1809 at that rate) with sign-step Adam at 0.2178 or worse.)
