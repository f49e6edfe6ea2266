"""Reading an optimizer's state in the tests: the postfilter's, wherever the chain put it
(written here rather than with ``optax.tree.get``, which the oldest supported optax lacks)."""


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
