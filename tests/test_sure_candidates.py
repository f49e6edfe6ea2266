"""The SURE study's candidates (experiments/sure_candidates.py, docs/auto_sigma.md) still run."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from experiments import sure_candidates as sure


def test_sure_candidate_steps_are_finite_and_follow_the_gradient():
    params = jnp.linspace(0.1, 1.0, 8 * 8).reshape(8, 8, 1)
    opt = sure.sbF_w05(0.01, spatial_axes=(0, 1))
    state = opt.init(params)
    step = jax.jit(opt.update)
    for i in range(3):  # from the second step on the noise probe and the risks are live
        g = params - 0.5 + 0.1 * jax.random.normal(jax.random.key(i), params.shape)
        u, state = step(g, state, params)
        params = optax.apply_updates(params, u)
        assert np.all(np.isfinite(np.asarray(u)))
    # A descent direction on 0.5 |x - 0.5|^2: updates oppose the noiseless gradient mostly.
    assert float(jnp.mean(u * (params - 0.5))) < 0
