"""Saving and restoring optimizer state: ``.npz`` of the flattened pytree.

The state of every transform here (and of optax's own) is a plain pytree of
arrays, so a checkpoint needs no pickling: the leaves in ``jax.tree.leaves``
order, each with its path and dtype name. ``load_state`` rebuilds the tree from a
template (``like``: an ``init`` result or its ``jax.eval_shape``), checks that
paths, shapes and dtypes agree, and returns arrays bit-identical to the saved
ones, so a resumed run reproduces an uninterrupted one exactly.
"""

from __future__ import annotations

import os
import tempfile
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src.leaves import leaf_names

_FORMAT = "optax_bilateral.state/1"


def _raw(x) -> np.ndarray:
    """The leaf's bytes as a NumPy array of a type ``.npz`` stores natively."""
    a = np.asarray(x)
    if a.dtype.kind in "biufc":
        return a
    # bfloat16 and other ml_dtypes: store the bits under an unsigned int of the same width.
    return a.view(np.dtype(f"u{a.dtype.itemsize}"))


def save_state(path: str | os.PathLike, state: Any) -> None:
    """Writes ``state`` (any pytree of arrays) to ``path`` as an uncompressed ``.npz``.

    The file is written next to ``path`` and moved into place, so an interrupted
    save never leaves a truncated checkpoint. ``path`` is used exactly as given
    (no ``.npz`` is appended). Each leaf is stored under its pytree path with its exact
    bits (bfloat16 and other dtypes NumPy cannot store natively included), so that
    :func:`load_state` restores it bit for bit; ``None`` leaves (empty states) store
    nothing.

    Args:
      path: the file to write (replaced if it exists).
      state: the optimizer state, e.g. ``opt.init(params)`` or the state an update
        returned; any pytree of arrays.

    Example::

        >>> import os, tempfile, jax.numpy as jnp, optax_bilateral as ob
        >>> opt = ob.bilateral_adam(0.01, sigma_d=0.1, levels=2)
        >>> params = jnp.ones((16, 16, 3))
        >>> path = os.path.join(tempfile.mkdtemp(), "opt_state.npz")
        >>> ob.save_state(path, opt.init(params))
        >>> os.path.exists(path)
        True
    """
    leaves = jax.tree.leaves(state)
    arrays = {f"leaf_{i:05d}": _raw(x) for i, x in enumerate(leaves)}
    arrays["__format__"] = np.asarray(_FORMAT)
    arrays["__paths__"] = np.asarray(leaf_names(state) or [""], dtype=str)
    arrays["__dtypes__"] = np.asarray([str(np.asarray(x).dtype) for x in leaves] or [""], dtype=str)
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp_state_", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)  # pyright: ignore[reportArgumentType]  (names, not options)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def load_state(path: str | os.PathLike, like: Any) -> Any:
    """Reads a state written by :func:`save_state` into the structure of ``like``.

    Args:
      path: the file.
      like: a state of the same optimizer and parameters, e.g. ``opt.init(params)``
        or ``jax.eval_shape(opt.init, params)``; only its structure, shapes and
        dtypes are used.

    Returns:
      The saved state as JAX arrays, with ``like``'s tree structure.

    Raises:
      ValueError: the file is not such a checkpoint, or its leaves' paths, shapes
        or dtypes differ from ``like``'s (a different optimizer or parameters).

    Example::

        >>> import os, tempfile, jax, jax.numpy as jnp, optax_bilateral as ob
        >>> opt = ob.bilateral_adam(0.01, sigma_d=0.1, levels=2)
        >>> params = jnp.ones((16, 16, 3))
        >>> grads = jnp.full((16, 16, 3), 0.5)
        >>> _, state = opt.update(grads, opt.init(params), params)
        >>> path = os.path.join(tempfile.mkdtemp(), "opt_state.npz")
        >>> ob.save_state(path, state)
        >>> restored = ob.load_state(path, like=jax.eval_shape(opt.init, params))
        >>> bool(jnp.all(restored[0].mu == state[0].mu)), int(restored[0].count)
        (True, 1)
    """
    leaves, treedef = jax.tree.flatten(like)
    names = leaf_names(like)
    with np.load(os.fspath(path), allow_pickle=False) as data:
        if "__format__" not in data or str(data["__format__"]) != _FORMAT:
            raise ValueError(f"{path} is not an optimizer state written by save_state")
        saved_names = [str(n) for n in data["__paths__"]] if leaves else []
        saved_dtypes = [str(d) for d in data["__dtypes__"]] if leaves else []
        n_saved = sum(1 for k in data.files if k.startswith("leaf_"))
        if n_saved != len(leaves) or saved_names != names:
            missing = sorted(set(names) - set(saved_names))[:3]
            extra = sorted(set(saved_names) - set(names))[:3]
            raise ValueError(
                f"the state in {path} has {n_saved} leaves, but like has {len(leaves)}; they must "
                f"come from the same optimizer and parameters (only in like: {missing}, only in "
                f"the file: {extra})"
            )
        out = []
        for i, (x, name, dt) in enumerate(zip(leaves, names, saved_dtypes)):
            want = jnp.dtype(x.dtype if hasattr(x, "dtype") else jnp.result_type(x))
            if jnp.dtype(dt) != want:
                raise ValueError(f"state leaf {name} was saved as {dt}, but like has {want}")
            raw = data[f"leaf_{i:05d}"]
            if raw.shape != tuple(np.shape(x)):
                raise ValueError(
                    f"state leaf {name} was saved with shape {raw.shape}, but like has "
                    f"{tuple(np.shape(x))}"
                )
            out.append(jnp.asarray(raw.view(want)))
    return jax.tree.unflatten(treedef, out)
