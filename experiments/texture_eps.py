"""Adam's eps on the texture experiment's gradients: ours (1e-8) against the authors' 1e-25.

    python -m experiments.texture_eps [--quick] [--out DIR]

The authors' texture runs pass ``eps=1e-25`` (volume: 1e-15) to their optimizer;
this library's default is 1e-8. Per-texel gradients of an image loss are small,
so eps may damp the step. On the texture experiment's problem
(``experiments.texture``: its scene, target, noise and the cross-bilateral method
at ``sigma_d = 0.1``, log guide, lr 0.02, b1 0.2), this measures

* the step: along the eps = 1e-8 trajectory, the update that eps = 1e-25 gives from
  the same state and gradient (the moments do not depend on eps), as the relative
  L2 difference and the median per-texel ratio, with the gradient's scale;
* the result: the parameter error (mean |alpha - target|) after the run, with each eps.

Writes ``eps.json`` and ``eps.md`` to DIR (default ``results/texture_eps``).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments import common
from experiments import texture as texp
from optax_bilateral.toy import texture as tex

EPS = {"ours": 1e-8, "authors (texture)": 1e-25, "authors (volume)": 1e-15}


def _optimizer(eps: float, cfg) -> optax.GradientTransformation:
    return ob.bilateral_adam(
        0.02, cfg.b1_filtered, eps=eps, sigma_d=0.1, levels=cfg.levels, log_guide=True
    )


def run(quick: bool, out) -> dict:
    from tqdm.auto import tqdm

    cfg = texp.default_config(quick)
    prob = texp.Problem(cfg)

    @jax.jit
    def grad_at(alpha, i):
        key = jax.random.fold_in(prob.base_key, i)  # the experiment's noise, iteration i
        return jax.grad(
            lambda a: tex.loss_fn(
                tex.render(a, prob.scene, key, cfg.spp, cfg.spp_grad), prob.reference
            )
        )(alpha)

    opts = {k: _optimizer(e, cfg) for k, e in EPS.items()}
    updates = {k: jax.jit(o.update) for k, o in opts.items()}
    finals, step_rows = {}, []
    check = set(np.unique(np.geomspace(1, cfg.iterations, 6).astype(int)))
    for name in EPS:
        alpha, state = prob.init, opts[name].init(prob.init)
        for i in tqdm(range(1, cfg.iterations + 1), desc=f"eps {EPS[name]:g}"):
            g = grad_at(alpha, i)
            u, new_state = updates[name](g, state, alpha)
            if name == "ours" and i in check:
                row = {
                    "iteration": i,
                    "median |g|": float(jnp.median(jnp.abs(g))),
                    "max |g|": float(jnp.max(jnp.abs(g))),
                }
                for other in EPS:
                    if other == "ours":
                        continue
                    v, _ = updates[other](g, state, alpha)
                    ratio = jnp.abs(v) / jnp.maximum(jnp.abs(u), 1e-30)
                    row[f"rel L2 diff vs {other}"] = float(
                        jnp.linalg.norm(v - u) / jnp.linalg.norm(u)
                    )
                    row[f"median |step {other}| / |step ours|"] = float(jnp.median(ratio))
                step_rows.append(row)
            state = new_state
            alpha = jnp.clip(optax.apply_updates(alpha, u), tex.ALPHA_MIN, tex.ALPHA_MAX)
        finals[name] = {
            "eps": EPS[name],
            "final_param_error": float(jnp.mean(jnp.abs(alpha - prob.target))),
        }
    result = {
        "final": finals,
        "steps": step_rows,
        "setting": {
            "size": cfg.size,
            "iterations": cfg.iterations,
            "levels": cfg.levels,
            "b1": cfg.b1_filtered,
            "learning_rate": 0.02,
            "sigma_d": 0.1,
            "log_guide": True,
            "target": cfg.target,
            "quick": quick,
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "eps.json").write_text(json.dumps(common.jsonable(result), indent=2) + "\n")
    md = (
        f"# Adam eps on the texture experiment ({cfg.size}^2, {cfg.iterations} iterations, "
        "cross-bilateral, sigma_d 0.1, log guide, lr 0.02)\n\n## Final parameter error\n\n"
        + common.markdown_table([{"run": k, **v} for k, v in finals.items()], floatfmt=".6g")
        + "\n\n## The step with the authors' eps, from ours' state and gradient\n\n"
        + common.markdown_table(step_rows, floatfmt=".4g")
        + "\n"
    )
    (out / "eps.md").write_text(md)
    print(md)
    return result


def main(argv=None):
    args = common.parse_args(
        "Adam eps on the texture experiment: 1e-8 vs the authors' 1e-25",
        "results/texture_eps",
        argv,
    )
    return run(args.quick, args.out)


if __name__ == "__main__":
    main()
