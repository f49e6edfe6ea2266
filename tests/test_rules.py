"""sigma_d rules as objects: the shorthands, other constants, a rule of one's own, and
bilateral_adam's slim signature with its deprecation path."""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob

SHAPE = (16, 16, 3)
KEY = jax.random.PRNGKey(0)


def _steps(opt, steps=3, params=None):
    params = jnp.full(SHAPE, 0.5) if params is None else params
    state, out = opt.init(params), []
    for i in range(steps):
        g = 0.1 * jax.random.normal(jax.random.fold_in(KEY, i), SHAPE) + params - 0.3
        u, state = opt.update(g, state, params)
        params = optax.apply_updates(params, u)
        out.append(np.asarray(u))
    return out, state


def test_the_shorthands_are_the_default_rules():
    assert ob.auto_sigma() == ob.Auto() and ob.sure_sigma() == ob.Sure()
    a, _ = _steps(ob.bilateral_adam(0.05))
    b, _ = _steps(ob.bilateral_adam(0.05, sigma_d=ob.auto_sigma()))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_rules_are_frozen_and_hashable_and_another_constant_is_another_rule():
    rule = ob.auto_sigma(check_period=2)
    assert hash(rule) == hash(ob.auto_sigma(check_period=2)) and rule != ob.auto_sigma()
    with pytest.raises(dataclasses.FrozenInstanceError):
        rule.check_period = 3  # pyright: ignore[reportAttributeAccessIssue]
    # A constant changes the numbers (here: the heavier filter's sigma_d never engages on this
    # problem, the rate rule's factor does).
    a, _ = _steps(ob.bilateral_adam(0.05, sigma_d=ob.auto_sigma(rate_factor=4.0)))
    b, _ = _steps(ob.bilateral_adam(0.05))
    assert not np.allclose(a[-1], b[-1])


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        ({"check_period": 0}, ValueError, "check_period must be >= 1"),
        ({"check_period": 2.5}, TypeError, "check_period must be an int"),
        ({"residual_decay": 1.0}, ValueError, "residual_decay must be >= 0 and < 1"),
        ({"gate_bounds": (0.7, 0.5)}, ValueError, "gate_bounds must be a tuple"),
        ({"rate_factor": -1.0}, ValueError, "rate_factor must be > 0"),
        ({"rate_factor": float("nan")}, TypeError, "rate_factor must be a real number"),
        ({"colour": 1.0}, TypeError, "colour"),
    ],
)
def test_auto_sigma_refuses_bad_constants_naming_them(kwargs, err, match):
    with pytest.raises(err, match=match):
        ob.auto_sigma(**kwargs)


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        ({"factors": ()}, ValueError, "factors"),
        ({"factors": (1.0, 3.0), "first_factor": 10.0}, ValueError, "first_factor"),
        ({"risk_decay": 1.5}, ValueError, "risk_decay"),
        ({"auto": "auto"}, TypeError, "auto must be"),
    ],
)
def test_sure_sigma_refuses_bad_constants_naming_them(kwargs, err, match):
    with pytest.raises(err, match=match):
        ob.sure_sigma(**kwargs)


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class _Halved(ob.SigmaRule):
    """A rule of one's own: half of a fixed sigma_d, and no state."""

    value: float = 0.2

    def sigma(self, guide, plan, state, ctx):
        del guide, plan, ctx
        return self.value / 2, state


def test_a_rule_of_ones_own_plugs_in_as_sigma_d():
    a, _ = _steps(ob.bilateral_adam(0.05, sigma_d=_Halved(0.2)))
    b, _ = _steps(ob.bilateral_adam(0.05, sigma_d=0.1))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    # Per leaf too, beside the shorthands.
    params = {"tex": jnp.full(SHAPE, 0.5), "vol": jnp.full((8, 8, 8, 1), 0.5)}
    opt = ob.postfilter(sigma_d={"tex": _Halved(0.2), "vol": "auto"})
    state = opt.init(params)
    assert state.sigma_state["tex"] is None and isinstance(state.sigma_state["vol"], ob.AutoState)


def test_bilateral_adam_takes_ten_arguments_and_old_keywords_warn_and_still_apply():
    old = {"separable": False, "guide": "self", "mu_dtype": jnp.bfloat16}
    with pytest.warns(DeprecationWarning, match=r"bilateral_adam\(separable=...\).*postfilter"):
        opt = ob.bilateral_adam(0.05, sigma_d=0.1, **old)
    chain = optax.chain(
        ob.postfilter(0.2, sigma_d=0.1, **old, unfiltered_betas=(0.9, 0.999)),
        optax.scale_by_learning_rate(0.05),
    )
    a, sa = _steps(opt)
    b, sb = _steps(chain)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert sa[0].mu.dtype == jnp.bfloat16 and jax.tree.structure(sa) == jax.tree.structure(sb)
    with pytest.raises(TypeError, match="unexpected keyword argument 'sepearble'"):
        ob.bilateral_adam(0.05, sepearble=False)


def test_deprecated_weight_decay_is_decoupled_as_adamw():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        opt = ob.bilateral_adam(0.05, levels=0, weight_decay=0.1)
    params = jnp.linspace(0.5, 1.0, 10)
    u, _ = opt.update(jnp.zeros(10), opt.init(params), params)
    np.testing.assert_allclose(u, -0.05 * 0.1 * params, rtol=1e-6)  # zero gradient: decay only


def test_others_takes_the_leaves_that_are_not_filtered():
    params = {"tex": jnp.full(SHAPE, 0.5), "w": jnp.ones(5)}
    opt = ob.bilateral_adam(0.05, others=optax.sgd(0.5))
    grads = {"tex": jnp.ones(SHAPE), "w": jnp.full(5, 2.0)}
    u, _ = opt.update(grads, opt.init(params), params)
    np.testing.assert_allclose(u["w"], -0.5 * 2.0)  # plain SGD
    np.testing.assert_allclose(u["tex"], -0.05, rtol=1e-5)  # the filtered Adam's first step


def test_auto_sigma_gate_is_the_deprecated_name_of_gate_bounds():
    with pytest.warns(DeprecationWarning, match="gate_bounds"):
        rule = ob.auto_sigma(gate=(0.4, 0.6))
    assert rule == ob.auto_sigma(gate_bounds=(0.4, 0.6))
