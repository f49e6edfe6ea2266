"""Reading an optimizer's state in the tests: the postfilter's, wherever the chain put it
(written here rather than with ``optax.tree.get``, which the oldest supported optax lacks),
and a postfilter's state set up for one step, to observe what its sigma_d rule does."""

import jax.numpy as jnp


def _walk(x):
    yield x
    if isinstance(x, dict):
        x = list(x.values())
    if isinstance(x, (tuple, list)):
        for y in x:
            yield from _walk(y)


def filtered_state(state):
    """The one :class:`~optax_bilateral.PostfilterState` in ``state`` (``bilateral_adam``'s
    filtered leaves, and with its defaults every leaf)."""
    (found,) = [s for s in _walk(state) if type(s).__name__ == "PostfilterState"]
    return found


def with_filtered_state(state, post):
    """``state`` with its :class:`~optax_bilateral.PostfilterState` replaced by ``post``."""
    return tuple(post if type(s).__name__ == "PostfilterState" else s for s in state)


def at_step(state, count, **fields):
    """``state``, one leaf's :class:`~optax_bilateral.PostfilterState`, whose next update is
    step ``count + 1``, with ``fields`` replaced: ``mu`` and ``nu`` (the moments) and any
    field of its rule's state (``AutoState``, ``SureState``), each cast to the dtype of the
    one it replaces."""
    cast = lambda old, new: jnp.asarray(new, old.dtype)
    moments = {k: cast(getattr(state, k), fields.pop(k)) for k in ("mu", "nu") if k in fields}
    rule = state.sigma_state  # None for a number
    if fields:
        rule = rule._replace(**{k: cast(getattr(rule, k), x) for k, x in fields.items()})
    count = jnp.asarray(count, state.count.dtype)
    return state._replace(count=count, sigma_state=rule, **moments)
