"""A number as ``sigma_d``: the paper's method (supplement eqs. 1, 6, 8), one value per leaf."""

from __future__ import annotations

import dataclasses
from numbers import Real
from typing import Any

import jax

from optax_bilateral._src import numerics
from optax_bilateral._src.rules.sigma import SigmaRule


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class Fixed(SigmaRule):
    """``sigma_d`` given as a number (>= 0; ``inf`` is a plain low-pass), in the guide's units.

    A Python number stays a constant of the compiled step (so changing it compiles anew); an
    array or a tracer (a schedule through :func:`optax.inject_hyperparams`) is an argument of
    it, and a negative or NaN one makes the update NaN, as it cannot raise.

    Attributes:
      value: the sigma_d, a number or a scalar array.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> params = jnp.full((8, 8, 3), 0.5)
        >>> a = ob.postfilter(sigma_d=0.1)                 # a number is Fixed(0.1)
        >>> b = ob.postfilter(sigma_d=ob.Fixed(0.1))
        >>> g = jnp.ones_like(params)
        >>> da, _ = a.update(g, a.init(params), params)
        >>> db, _ = b.update(g, b.init(params), params)
        >>> bool(jnp.all(da == db))
        True
    """

    value: Any

    def sigma(self, guide, plan, state, ctx):
        del guide, plan, ctx
        return self.value, state

    def guard(self, out, sigma):
        if isinstance(self.value, Real):  # checked when the transform was built
            return out
        return out * numerics.sigma_guard(sigma).astype(out.dtype)

    def tree_flatten(self):
        if isinstance(self.value, Real):
            return (), self.value
        return (self.value,), None

    @classmethod
    def tree_unflatten(cls, number, children):
        return cls(number if not children else children[0])
