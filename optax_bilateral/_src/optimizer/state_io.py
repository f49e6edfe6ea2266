"""Saving and restoring optimizer state: ``.npz`` of the flattened pytree.

The state of every transform here (and of optax's own) is a plain pytree of
arrays, so a checkpoint needs no pickling: the leaves in ``jax.tree.leaves``
order, each with its path and dtype name. ``load_state`` rebuilds the tree from a
template (``like``: an ``init`` result or its ``jax.eval_shape``), checks that
paths, shapes and dtypes agree, and returns arrays bit-identical to the saved
ones, so a resumed run reproduces an uninterrupted one exactly.

In a multi-process run (``jax.process_count() > 1``) no process can read a whole
sharded array, so each process writes a part file, ``<path>.<i>-of-<n>``, of the
blocks its devices hold, each with its place in the global array; ``load_state``
gives each device its block, read from the parts.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import re
import tempfile
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src.optimizer.prefix import leaf_names

_FORMAT = "optax_bilateral.state/1"
_PART_FORMAT = "optax_bilateral.state-part/1"


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
      path: the file to write (replaced if it exists). In a multi-process run every
        process calls ``save_state`` with the same ``path`` and writes its part,
        ``<path>.<i>-of-<n>`` (process ``i`` of ``n``), on a file system all of them
        read; the call returns once every part is written.
      state: the optimizer state, e.g. ``opt.init(params)`` or the state an update
        returned; any pytree of arrays, sharded across processes or not.

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
    path = os.fspath(path)
    if jax.process_count() > 1:
        _save_part(path, state)
        return
    arrays = {f"leaf_{i:05d}": _raw(x) for i, x in enumerate(leaves)}
    arrays["__format__"] = np.asarray(_FORMAT)
    arrays["__paths__"] = np.asarray(leaf_names(state, root="") or [""], dtype=str)
    arrays["__dtypes__"] = np.asarray([str(np.asarray(x).dtype) for x in leaves] or [""], dtype=str)
    _write_npz(path, arrays)


def _write_npz(path: str, arrays: dict[str, np.ndarray]) -> None:
    """Writes ``arrays`` to a temporary file next to ``path`` and moves it into place."""
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
        or ``jax.eval_shape(opt.init, params)``; its structure, shapes and dtypes, and
        the shardings of its leaves that span several devices.

    Returns:
      The saved state as JAX arrays, with ``like``'s tree structure. A leaf of ``like``
      sharded over several devices (``opt.init`` of sharded parameters; a
      ``jax.eval_shape`` result inside ``jax.set_mesh``) comes back with that sharding,
      each device's block read alone (``jax.make_array_from_callback``): in a
      multi-process run each process reads only the blocks its devices hold. A
      checkpoint restores under any sharding and process count, from one file or from
      the parts a multi-process run wrote.

    Raises:
      ValueError: the file is not such a checkpoint, or its leaves' paths, shapes
        or dtypes differ from ``like``'s (a different optimizer or parameters), or the
        parts of a multi-process checkpoint are incomplete or do not cover a block.
      FileNotFoundError: neither ``path`` nor its parts exist.

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
    names = leaf_names(like, root="")
    with contextlib.ExitStack() as files:
        blocks = _open_checkpoint(os.fspath(path), files)
        saved_names, saved_dtypes, shapes = blocks.names, blocks.dtypes, blocks.shapes
        if len(saved_names) != len(leaves) or saved_names != names:
            missing = sorted(set(names) - set(saved_names))[:3]
            extra = sorted(set(saved_names) - set(names))[:3]
            raise ValueError(
                f"the state in {path} has {len(saved_names)} leaves, but like has {len(leaves)}; "
                f"they must come from the same optimizer and parameters (only in like: {missing}, "
                f"only in the file: {extra})"
            )
        out = []
        for i, (x, name, dt) in enumerate(zip(leaves, names, saved_dtypes)):
            want = jnp.dtype(x.dtype if hasattr(x, "dtype") else jnp.result_type(x))
            if jnp.dtype(dt) != want:
                raise ValueError(f"state leaf {name} was saved as {dt}, but like has {want}")
            if shapes[i] != tuple(np.shape(x)):
                raise ValueError(
                    f"state leaf {name} was saved with shape {shapes[i]}, but like has "
                    f"{tuple(np.shape(x))}"
                )
            block = lambda index, i=i, name=name, want=want: blocks.read(i, index, name).view(want)
            sharding = _multi_device_sharding(x, name)
            if sharding is None:
                out.append(jnp.asarray(block(())))
            else:
                out.append(jax.make_array_from_callback(shapes[i], sharding, block))
    return jax.tree.unflatten(treedef, out)


# --------------------------------------------------------------------------- sharded leaves


def _multi_device_sharding(x: Any, name: str) -> jax.sharding.Sharding | None:
    """``like``'s sharding for a leaf that spans several devices, else None (one device)."""
    sharding = getattr(x, "sharding", None)
    if isinstance(sharding, jax.sharding.NamedSharding) and isinstance(
        sharding.mesh, jax.sharding.AbstractMesh
    ):
        mesh = jax.sharding.get_mesh()  # jax.eval_shape's shardings name an abstract mesh
        if mesh.empty or mesh.shape_tuple != sharding.mesh.shape_tuple:
            raise ValueError(
                f"state leaf {name} of like is sharded over an abstract mesh "
                f"{dict(sharding.mesh.shape)}: pass like=opt.init(params), or call load_state "
                "inside jax.set_mesh(mesh) with that mesh"
            )
        sharding = jax.sharding.NamedSharding(mesh, sharding.spec)
    if not isinstance(sharding, jax.sharding.Sharding) or len(sharding.device_set) < 2:
        return None
    return sharding


def _blocks_of(x: Any) -> list[tuple[tuple[slice, ...], Any]]:
    """The distinct blocks of ``x`` this process holds, each with its global index."""
    if not isinstance(x, jax.Array):
        return [((), x)]
    seen, out = set(), []
    for shard in x.addressable_shards:
        key = tuple(s.indices(n)[:2] for s, n in zip(shard.index, x.shape))
        if key not in seen:
            seen.add(key)
            out.append((shard.index, shard.data))
    return out


def _save_part(path: str, state: Any) -> None:
    """This process's part of a multi-process checkpoint; returns when all are written."""
    from jax.experimental import multihost_utils

    leaves = jax.tree.leaves(state)
    arrays, meta = {}, []
    for i, x in enumerate(leaves):
        shape = tuple(np.shape(x))
        starts, stops = [], []
        for j, (index, data) in enumerate(_blocks_of(x)):
            span = [s.indices(n)[:2] for s, n in zip(index, shape)] or []
            span += [(0, n) for n in shape[len(span) :]]
            starts.append([a for a, _ in span])
            stops.append([b for _, b in span])
            arrays[f"leaf_{i:05d}_{j:05d}"] = _raw(data)
        meta.append({"shape": list(shape), "starts": starts, "stops": stops})
    arrays["__format__"] = np.asarray(_PART_FORMAT)
    arrays["__paths__"] = np.asarray(leaf_names(state, root="") or [""], dtype=str)
    arrays["__dtypes__"] = np.asarray([str(jnp.result_type(x)) for x in leaves] or [""], dtype=str)
    arrays["__blocks__"] = np.asarray(json.dumps(meta))
    _write_npz(f"{path}.{jax.process_index()}-of-{jax.process_count()}", arrays)
    multihost_utils.sync_global_devices(f"optax_bilateral.save_state {path}")


class _Checkpoint:
    """The leaves of one checkpoint file or of a multi-process checkpoint's parts."""

    def __init__(self, names, dtypes, shapes, pieces, files, path):
        self.names, self.dtypes, self.shapes = names, dtypes, shapes
        self._pieces, self._files, self._path = pieces, files, path
        self._cached: tuple[Any, Any] = (None, None)

    def read(self, i: int, index: tuple[slice, ...], name: str) -> np.ndarray:
        """Leaf ``i``'s block at ``index`` (a tuple of slices), from the pieces it overlaps."""
        shape = self.shapes[i]
        span = [s.indices(n)[:2] for s, n in zip(index, shape)]
        span += [(0, n) for n in shape[len(span) :]]
        lo, hi = np.array([a for a, _ in span], int), np.array([b for _, b in span], int)
        out, filled = None, np.zeros(hi - lo, bool)
        for f, key, start, stop in self._pieces[i]:
            a, b = np.maximum(lo, start), np.minimum(hi, stop)
            dst = tuple(slice(p - s, q - s) for p, q, s in zip(a, b, lo))
            if np.any(a >= b) or filled[dst].all():
                if out is None and filled.size == 0:  # an empty block: only its dtype
                    out = np.empty(tuple(hi - lo), self._piece(f, key).dtype)
                continue
            piece = self._piece(f, key)
            if np.array_equal(start, lo) and np.array_equal(stop, hi):
                return piece  # the block as stored: no copy
            if out is None:
                out = np.empty(tuple(hi - lo), piece.dtype)
            out[dst] = piece[tuple(slice(p - s, q - s) for p, q, s in zip(a, b, start))]
            filled[dst] = True
            if filled.all():
                break
        if out is None or not filled.all():
            raise ValueError(f"the checkpoint {self._path} lacks part of state leaf {name}")
        return out

    def _piece(self, f: int, key: str) -> np.ndarray:
        # Devices ask for their blocks one by one: a piece several blocks share is read once.
        if self._cached[0] != (f, key):
            self._cached = ((f, key), self._files[f][key])
        return self._cached[1]


def _open_checkpoint(path: str, files: contextlib.ExitStack) -> _Checkpoint:
    """``path`` as written by one process, or the parts ``<path>.<i>-of-<n>`` of n processes."""
    if os.path.exists(path):
        data = files.enter_context(np.load(path, allow_pickle=False))
        if "__format__" not in data or str(data["__format__"]) != _FORMAT:
            raise ValueError(f"{path} is not an optimizer state written by save_state")
        n = sum(1 for k in data.files if k.startswith("leaf_"))
        names = [str(s) for s in data["__paths__"]][:n]
        dtypes = [str(d) for d in data["__dtypes__"]][:n]
        keys = [f"leaf_{i:05d}" for i in range(n)]
        shapes = [_npz_shape(data, k) for k in keys]
        pieces = [[(0, k, np.zeros(len(s), int), np.array(s, int))] for k, s in zip(keys, shapes)]
        return _Checkpoint(names, dtypes, shapes, pieces, [data], path)
    parts = _part_files(path)
    datas = [files.enter_context(np.load(p, allow_pickle=False)) for p in parts]
    heads = []
    for p, data in zip(parts, datas):
        if "__format__" not in data or str(data["__format__"]) != _PART_FORMAT:
            raise ValueError(f"{p} is not a part of an optimizer state written by save_state")
        heads.append(
            (
                [str(s) for s in data["__paths__"]],
                [str(d) for d in data["__dtypes__"]],
                json.loads(str(data["__blocks__"])),
            )
        )
    names, dtypes, meta = heads[0]
    if any((h[0], h[1]) != (names, dtypes) for h in heads[1:]):
        raise ValueError(f"the parts of {path} hold different states (paths or dtypes differ)")
    n = len(meta)
    shapes = [tuple(m["shape"]) for m in meta]
    pieces: list[list] = [[] for _ in range(n)]
    for f, (_, _, meta_f) in enumerate(heads):
        for i, m in enumerate(meta_f):
            for j, (start, stop) in enumerate(zip(m["starts"], m["stops"])):
                pieces[i].append(
                    (f, f"leaf_{i:05d}_{j:05d}", np.array(start, int), np.array(stop, int))
                )
    return _Checkpoint(names[:n], dtypes[:n], shapes, pieces, datas, path)


def _part_files(path: str) -> list[str]:
    """The complete set of parts ``<path>.<i>-of-<n>``; errors if there is none or a gap."""
    found: dict[int, dict[int, str]] = {}
    for p in glob.glob(glob.escape(path) + ".*-of-*"):
        m = re.fullmatch(re.escape(path) + r"\.(\d+)-of-(\d+)", p)
        if m:
            found.setdefault(int(m[2]), {})[int(m[1])] = p
    if not found:
        raise FileNotFoundError(f"no optimizer state at {path} (nor its parts {path}.<i>-of-<n>)")
    if len(found) > 1:
        raise ValueError(
            f"{path} has parts of checkpoints from {sorted(found)} processes; remove the stale ones"
        )
    ((n, by_index),) = found.items()
    if sorted(by_index) != list(range(n)):
        missing = sorted(set(range(n)) - set(by_index))
        raise ValueError(f"the checkpoint {path} lacks the parts of processes {missing} (of {n})")
    return [by_index[i] for i in range(n)]


def _npz_shape(data: Any, key: str) -> tuple[int, ...]:
    """A member's shape, read from its header (the array itself is read when needed)."""
    with data.zip.open(key + ".npy") as f:
        version = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0
        if version != (1, 0):
            read = np.lib.format.read_array_header_2_0
        return tuple(read(f)[0])
