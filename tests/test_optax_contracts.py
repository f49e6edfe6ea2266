"""optax's contracts for its contributed optimizers, checked on ``bilateral_adam``.

The same targets and properties as ``optax/contrib/_common_test.py`` of the installed optax
(written here, not copied): the parabola, Rosenbrock's function, a matrix parabola and a
mixed 1-D + 2-D target; ``optax.tree.map_params``, extra keyword arguments, no
recompilation, ``inject_hyperparams``, dtype preservation, ``MultiSteps``, a state whose
shapes and dtypes survive a ``lax.cond``, and learning-rate schedules. Four settings:
the defaults (these small leaves are not filtered: Adam's own rule), a numeric ``sigma_d``,
``spatial_axes`` forcing the filter onto every leaf, and ``sparse_adam`` on every leaf.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from experiments.benchmarks.compiles import CompileCounter

# (name, factory of learning_rate -> optimizer)
SETTINGS = {
    "defaults": ob.bilateral_adam,
    "sigma_d=0.1": functools.partial(ob.bilateral_adam, sigma_d=0.1),
    "filtered": functools.partial(
        ob.bilateral_adam, sigma_d=0.1, levels=1, spatial_axes=lambda x: tuple(range(x.ndim))
    ),
    # sparse_adam with its rule and its coarse path on every leaf.
    "sparse_adam": functools.partial(
        ob.sparse_adam, levels=1, coarse_levels=2, spatial_axes=lambda x: tuple(range(x.ndim))
    ),
}


def _parabola(dtype):
    final = jnp.array([1.0, -1.0, 1.0], dtype)
    return jnp.array([-1.0, 10.0, 1.0], dtype), final, lambda p: jnp.sum((p - final) ** 2)


def _rosenbrock(dtype):
    f = lambda p: (1.0 - p[0]) ** 2 + 100.0 * (p[1] - p[0] ** 2) ** 2
    return jnp.zeros((2,), dtype), jnp.array([1.0, 1.0], dtype), f


def _matrix_parabola(dtype):
    final = jnp.array([[3.0, -2.0], [1.0, 4.0]], dtype)
    return jnp.zeros((2, 2), dtype), final, lambda p: jnp.sum((p - final) ** 2)


def _mixed(dtype):
    final = (jnp.array([1.0, -1.0, 2.0], dtype), jnp.array([[1.0, 0.0], [-1.0, 1.0]], dtype))
    init = (jnp.zeros((3,), dtype), jnp.zeros((2, 2), dtype))
    f = lambda p: jnp.sum((p[0] - final[0]) ** 2) + jnp.sum((p[1] - final[1]) ** 2)
    return init, final, f


TARGETS = {
    "parabola": _parabola,
    "rosenbrock": _rosenbrock,
    "matrix": _matrix_parabola,
    "mixed": _mixed,
}


def _run(opt, target, steps, dtype=jnp.float32):
    params, final, f = target(dtype)

    def body(carry, _):
        p, s = carry
        u, s = opt.update(jax.grad(f)(p), s, p)
        return (optax.apply_updates(p, u), s), None

    (params, _), _ = jax.lax.scan(body, (params, opt.init(params)), None, length=steps)
    return params, final


@pytest.mark.parametrize("target", list(TARGETS))
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_converges_and_tree_map_params_works(setting, target):
    """Each target's minimum to 3e-2 after 30,000 steps at lr 1e-2 (optax's criterion). A
    filtered leaf averages its entries with neighbours whose guide (the parameters) is near:
    still a descent to the same fixed point (``|B m| <= c sqrt(B v)``, and ``m = 0`` there),
    which the assertion checks too."""
    opt = SETTINGS[setting](1e-2)
    params, _, _ = TARGETS[target](jnp.float32)
    state = opt.init(params)
    mapped = optax.tree_utils.tree_map_params(opt, lambda v: v, state)
    assert jax.tree.structure(mapped) == jax.tree.structure(state)
    params, final = jax.jit(functools.partial(_run, opt, TARGETS[target], 30_000))()
    for got, want in zip(jax.tree.leaves(params), jax.tree.leaves(final)):
        np.testing.assert_allclose(got, want, rtol=3e-2, atol=3e-2)


@pytest.mark.parametrize("setting", ["filtered", "filtered auto"])
def test_a_filtered_complex_leaf_converges_on_the_parabola(setting):
    """optax's parabola on complex parameters (real and imaginary parts to reach), the leaf
    filtered, to optax's 3e-2 after 30,000 steps. The update takes the conjugate of
    ``jax.grad`` (JAX's convention: for a real loss of complex parameters that is the
    steepest-descent direction; ``optax.adam`` needs it too, and ends 3e2 away without it)."""
    all_axes = lambda x: tuple(range(x.ndim))
    opt = (
        SETTINGS["filtered"](1e-2)
        if setting == "filtered"
        else ob.bilateral_adam(1e-2, levels=1, spatial_axes=all_axes)  # sigma_d="auto"
    )
    final = jnp.array([1.0 + 0.5j, -1.0, 1.0 - 1.0j], jnp.complex64)
    params = jnp.array([-1.0, 10.0, 1.0], jnp.complex64)
    loss = lambda p: jnp.sum(jnp.abs(p - final) ** 2)
    assert list(ob.filtered_axes(params, spatial_axes=all_axes, levels=1).values()) == [(0,)]

    def body(carry, _):
        p, s = carry
        u, s = opt.update(jnp.conj(jax.grad(loss)(p)), s, p)
        return (optax.apply_updates(p, u), s), None

    (params, _), _ = jax.jit(
        lambda: jax.lax.scan(body, (params, opt.init(params)), None, length=30_000)
    )()
    np.testing.assert_allclose(params, final, rtol=3e-2, atol=3e-2)


MAP_PARAMS = {
    "defaults": lambda: ob.bilateral_adam(0.02),  # "auto": a rule state per filtered leaf
    "prefilter + postfilter": lambda: optax.chain(
        ob.prefilter(), ob.postfilter(), optax.scale_by_learning_rate(0.02)
    ),
    "memoryless": lambda: ob.postfilter(b1=0.0, b2=0.0),
}


@pytest.mark.parametrize("setting", list(MAP_PARAMS))
def test_tree_map_params_maps_the_moments_of_filtered_leaves(setting):
    # Filtered float and complex textures beside an unfiltered vector: f reaches every
    # parameter-shaped tree (the moments) and nothing else (rule states, counts); the
    # partition-spec idiom of optax's docstring gives a tree of the state's structure.
    params = {
        "tex": jnp.linspace(0, 1, 16 * 16 * 3).reshape(16, 16, 3),
        "wave": jnp.exp(1j * jnp.linspace(0, 3, 8 * 8 * 2)).reshape(8, 8, 2).astype(jnp.complex64),
        "w": jnp.ones(4),
    }
    opt = MAP_PARAMS[setting]()
    grads = jax.tree.map(lambda p: 0.1 * jnp.ones_like(p), params)
    _, state = opt.update(grads, opt.init(params), params)
    mapped = optax.tree_utils.tree_map_params(opt, lambda p: p + 1, state)
    assert jax.tree.structure(mapped) == jax.tree.structure(state)
    moments = {"mu", "nu"}
    changed, kept = 0, 0
    for (path, new), old in zip(
        jax.tree_util.tree_flatten_with_path(mapped)[0], jax.tree.leaves(state)
    ):
        field = next((k.name for k in path if hasattr(k, "name") and k.name in moments), None)
        if field is None:  # rule states, counts: untouched
            np.testing.assert_array_equal(new, old, err_msg=jax.tree_util.keystr(path))
            kept += 1
        else:
            np.testing.assert_allclose(new, old + 1, err_msg=jax.tree_util.keystr(path))
            changed += 1
    assert kept > 0 and changed == (6 if setting != "memoryless" else 0)
    specs = jax.tree.map(lambda p: jax.sharding.PartitionSpec(*[None] * p.ndim), params)
    state_specs = optax.tree_utils.tree_map_params(
        opt, lambda _, spec: spec, state, specs, transform_non_params=lambda _: None
    )
    is_spec = lambda x: isinstance(x, jax.sharding.PartitionSpec)
    spec_leaves = [x for x in jax.tree.leaves(state_specs, is_leaf=is_spec) if is_spec(x)]
    assert len(spec_leaves) == (6 if setting != "memoryless" else 0)
    # The mapped state still updates.
    opt.update(grads, mapped, params)


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_extra_args_are_accepted_and_nothing_recompiles(setting):
    opt = SETTINGS[setting](1e-2)
    params, _, f = _rosenbrock(jnp.float32)

    @jax.jit
    def step(p, s):
        value, g = jax.value_and_grad(f)(p)
        u, s = opt.update(g, s, p, value=value, unexpected_extra_arg=1)
        return optax.apply_updates(p, u), s

    state = opt.init(params)
    params, state = step(params, state)
    with CompileCounter() as compiles:
        step(params, state)
    assert compiles.count == 0


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_inject_hyperparams_gives_the_same_updates_and_states(setting):
    factory = SETTINGS[setting]
    hparams = {"learning_rate": 1e-3}
    params = [-jnp.ones((2, 3)), jnp.ones((2, 5, 2))]
    grads = [jnp.ones((2, 3)), -jnp.ones((2, 5, 2))]
    opt = factory(**hparams)
    # levels (how many passes are compiled) and spatial_axes (a callable here, which
    # inject_hyperparams would take for a schedule) are static, as optax's own test makes
    # its optimizers' structural arguments.
    static = ("levels", "spatial_axes") + (("coarse_levels",) if setting == "sparse_adam" else ())
    injected = optax.inject_hyperparams(factory, static_args=static)(**hparams)
    u, s = jax.jit(opt.update)(grads, jax.jit(opt.init)(params), params)
    ui, si = jax.jit(injected.update)(grads, jax.jit(injected.init)(params), params)
    for a, b in zip(jax.tree.leaves((u, s)), jax.tree.leaves((ui, si.inner_state))):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("dtype", ["bfloat16", "float32"])
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_updates_keep_the_params_dtype_also_under_multisteps(setting, dtype):
    opt = SETTINGS[setting](1e-2)
    params = jnp.array([1.0, 2.0], dtype)
    grads = jax.grad(lambda x: jnp.sum(x**2))(params)
    updates, _ = jax.jit(opt.update)(grads, jax.jit(opt.init)(params), params)
    assert updates.dtype == params.dtype
    acc = optax.MultiSteps(opt, every_k_schedule=4)
    updates, _ = jax.jit(acc.update)(grads, jax.jit(acc.init)(params), params)
    np.testing.assert_array_equal(updates, jnp.zeros_like(grads))  # accumulating: no step yet


@pytest.mark.parametrize("dtype", ["float16", "bfloat16", "float32", "float64"])
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_state_shapes_and_dtypes_survive_a_cond(setting, dtype):
    """The state after an update has the shapes and dtypes (weak types included) of the one
    before: ``lax.cond`` between them compiles."""
    with jax.enable_x64(dtype == "float64"):
        opt = SETTINGS[setting](1e-2)
        params, _, f = _parabola(jnp.dtype(dtype))
        state = opt.init(params)

        @jax.jit
        def step(p, s):
            g = jax.grad(f)(p)
            take = jax.random.randint(jax.random.key(0), (), 0, 2) == 0
            u, s = jax.lax.cond(take, lambda: opt.update(g, s, p), lambda: (p, s))
            return optax.apply_updates(p, u), s

        for _ in range(2):
            params, new_state = step(params, state)
            assert params.dtype == jnp.dtype(dtype)
            take = jax.random.randint(jax.random.key(0), (), 0, 2) == 0
            state = jax.lax.cond(take, lambda s=state: s, lambda n=new_state: n)


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_a_constant_schedule_is_the_constant_learning_rate(setting):
    with_schedule = SETTINGS[setting](optax.constant_schedule(1e-3))
    with_number = SETTINGS[setting](1e-3)
    a, _ = _run(with_schedule, _parabola, 10)
    b, _ = _run(with_number, _parabola, 10)
    np.testing.assert_allclose(a, b, rtol=1e-6)
