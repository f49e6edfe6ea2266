"""Drive Mitsuba 3 scene parameters with an optax transform (``optax_bilateral.mitsuba``).

Mitsuba and Dr.Jit are imported when a function here is first called, never at
``import optax_bilateral`` or ``import optax_bilateral.mitsuba``. docs/mitsuba.md
has the user's loop, the measurements and the pitfalls.

Arrays cross between Dr.Jit and JAX through DLPack. On the CPU (``llvm_*``
variants) both directions share memory wherever the buffer is 64-byte aligned, as
JAX requires: Dr.Jit's own buffers (gradients, results) and JAX's are, so gradients
and, from the first step on, values cross without a copy (tests/test_mitsuba.py
checks the addresses); a tensor that wraps a NumPy array (e.g. an initial texture
``mi.TensorXf(np_array)``) may not be, and JAX then copies it. The scene stays the
one home of the parameter values: every step reads them from ``params``, so an edit
the user makes between steps is seen.
"""

from __future__ import annotations

import difflib
import functools
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

import jax
import jax.numpy as jnp
import optax

if TYPE_CHECKING:
    import drjit as dr
    import mitsuba as mi

MIN_LLVM_MAJOR = 16
"""The oldest libLLVM major version the ``llvm_*`` variants can use: Mitsuba 3.9's LLVM
kernels use ``fminimum``, which libLLVM 14 and 15 cannot compile (the first render aborts
the process with ``LLVM ERROR: Cannot select ... fminimum``)."""

GRID_NDIMS = (3, 4)
"""Parameter ranks :class:`SceneOptimizer` accepts: bitmap textures ``(H, W, C)`` and grid
volumes ``(D, H, W, C)``."""

INSTALL_HINT = (
    "pip install 'optax_bilateral[mitsuba]' (Mitsuba 3 and Dr.Jit, pinned), and for "
    "the llvm_* variants a libLLVM >= 16 on the system (Debian/Ubuntu: apt-get "
    "install libllvm19); see docs/mitsuba.md"
)


def _modules():
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as e:
        raise ImportError(
            f"optax_bilateral.mitsuba needs Mitsuba 3 and Dr.Jit: {INSTALL_HINT}"
        ) from e
    return mi, dr


def llvm_version() -> tuple[int, int, int] | None:
    """The libLLVM version Dr.Jit loaded, or ``None`` when it found none.

    Returns:
      ``(major, minor, patch)`` ints, or None.

    Raises:
      ImportError: Mitsuba 3 or Dr.Jit is not installed (the ``mitsuba`` extra).

    Example::

        >>> from optax_bilateral.mitsuba import llvm_version
        >>> version = llvm_version()          # e.g. (19, 1, 7)
        >>> version is None or len(version) == 3
        True
    """
    _, dr = _modules()
    major, minor, patch = (int(v) for v in dr.detail.llvm_version())
    return (major, minor, patch) if major >= 0 else None


def check_variant() -> str:
    """Raises unless the current Mitsuba variant is a differentiable one that can render here.

    Checks that a variant is set, that it is an AD variant (``*_ad_*``), and for the
    ``llvm_*`` variants that Dr.Jit loaded a libLLVM >= 16 (with an older one the first
    render aborts the whole process, which no ``try`` can catch). Renders nothing.

    Returns:
      The current variant's name.

    Raises:
      ImportError: Mitsuba 3 or Dr.Jit is not installed.
      RuntimeError: no variant is set, no libLLVM was found, or it is older than
        :data:`MIN_LLVM_MAJOR` (the message says what to install).
      ValueError: the variant is not differentiable.

    Example::

        >>> import mitsuba as mi
        >>> from optax_bilateral.mitsuba import check_variant
        >>> mi.set_variant("llvm_ad_rgb")
        >>> check_variant()
        'llvm_ad_rgb'
    """
    mi, _ = _modules()
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("no Mitsuba variant is set: call mi.set_variant('llvm_ad_rgb') first")
    if "_ad_" not in variant:
        raise ValueError(
            f"gradients need a differentiable Mitsuba variant (e.g. 'llvm_ad_rgb'), "
            f"but the current variant is {variant!r}"
        )
    if variant.startswith("llvm"):
        version = llvm_version()
        if version is None:
            raise RuntimeError(
                f"Dr.Jit found no libLLVM for the {variant!r} variant: {INSTALL_HINT}; "
                "set DRJIT_LIBLLVM_PATH to the library if it is not in /usr/lib"
            )
        if version[0] < MIN_LLVM_MAJOR:
            raise RuntimeError(
                f"Dr.Jit loaded libLLVM {'.'.join(map(str, version))}, but Mitsuba "
                f"{mi.__version__} needs libLLVM >= {MIN_LLVM_MAJOR} (older ones abort the first "
                "render with 'LLVM ERROR: Cannot select: ... fminimum'). Install a newer one "
                "(Debian/Ubuntu: apt-get install libllvm19); if Dr.Jit still picks the old one, "
                "set DRJIT_LIBLLVM_PATH to the new library (e.g. /usr/lib/x86_64-linux-gnu/"
                "libLLVM.so.19.1) before importing drjit"
            )
    return variant


def to_jax(tensor: dr.ArrayBase) -> jax.Array:
    """A Dr.Jit tensor as a JAX array through DLPack: no copy on the CPU when the buffer is
    64-byte aligned (Dr.Jit's own buffers are), else JAX copies it.

    Args:
      tensor: a Dr.Jit tensor (e.g. ``mi.TensorXf``, a value of ``mi.traverse(scene)``
        or ``dr.grad`` of one), any shape.

    Returns:
      A ``jax.Array`` with the tensor's shape and dtype.

    Example::

        >>> import numpy as np, mitsuba as mi
        >>> from optax_bilateral.mitsuba import to_jax
        >>> mi.set_variant("llvm_ad_rgb")
        >>> to_jax(mi.TensorXf(np.ones((4, 4, 3), np.float32))).shape
        (4, 4, 3)
    """
    return jnp.from_dlpack(tensor)


def _check_keys(params, keys) -> tuple[str, ...]:
    if isinstance(keys, str):
        keys = (keys,)
    try:
        keys = tuple(keys)
    except TypeError:
        raise TypeError(
            f"keys must be a parameter name or a sequence of names, got {type(keys).__name__}"
        ) from None
    if not keys:
        raise ValueError("keys must name at least one scene parameter, got none")
    for k in keys:
        if not isinstance(k, str):
            raise TypeError(f"keys must be strings (names in mi.traverse(scene)), got {k!r}")
    if len(set(keys)) != len(keys):
        raise ValueError(f"keys must be distinct, got {list(keys)}")
    names = list(params.keys())
    for k in keys:
        if k not in params:
            close = difflib.get_close_matches(k, names, n=3, cutoff=0.5)
            hint = f"; did you mean {close}?" if close else ""
            raise KeyError(
                f"{k!r} is not a parameter of this scene{hint} (print(params) lists them)"
            )
    return keys


def _check_value(key, value, dr) -> tuple[int, ...]:
    if not dr.is_tensor_v(value):
        raise TypeError(
            f"params[{key!r}] is a {type(value).__name__}, not a tensor: the helper "
            "drives bitmap textures (H, W, C) and grid volumes (D, H, W, C); "
            "use the key that ends in '.data'"
        )
    shape = tuple(int(s) for s in value.shape)
    if len(shape) not in GRID_NDIMS:
        raise ValueError(
            f"params[{key!r}] has shape {shape}; expected a bitmap texture (H, W, C) "
            "or a grid volume (D, H, W, C)"
        )
    if not dr.is_diff_v(value):
        raise TypeError(
            f"params[{key!r}] is not differentiable ({type(value).__name__}); "
            "use an AD variant such as 'llvm_ad_rgb'"
        )
    return shape


class ById:
    """A static jit argument compared by identity (transforms need not be hashable)."""

    def __init__(self, obj):
        self.obj = obj

    def __eq__(self, other):
        return isinstance(other, ById) and other.obj is self.obj

    def __hash__(self):
        return id(self.obj)

    def __call__(self, *args):
        return self.obj(*args)


class _Clamp:
    """``project`` given as ``{key: (lo, hi)}``: hashable, so equal ranges share one compiled
    step."""

    def __init__(self, ranges: Mapping[str, tuple[Any, Any]]):
        self.ranges = tuple(sorted(ranges.items()))

    def __call__(self, values):
        ranges = dict(self.ranges)
        return {k: jnp.clip(v, *ranges[k]) if k in ranges else v for k, v in values.items()}

    def __eq__(self, other):
        return isinstance(other, _Clamp) and other.ranges == self.ranges

    def __hash__(self):
        return hash(self.ranges)


def _projection(
    project: Callable[[dict], dict] | Mapping[str, tuple] | None, keys
) -> Callable[[dict], dict] | None:
    """``project`` as a function of the value dict, or None."""
    if project is None:
        return None
    if callable(project):
        return project
    if not isinstance(project, Mapping):
        raise TypeError(
            "project must be None, a callable values -> values, or a mapping "
            f"key -> (lo, hi); got {type(project).__name__}"
        )
    ranges = {}
    for k, bounds in project.items():
        if k not in keys:
            raise ValueError(
                f"project names {k!r}, which is not one of the optimized keys {list(keys)}"
            )
        try:
            lo, hi = bounds
        except (TypeError, ValueError):
            raise ValueError(
                f"project[{k!r}] must be a pair (lo, hi) (either may be None), got {bounds!r}"
            ) from None
        for b in (lo, hi):
            if b is not None and (isinstance(b, bool) or not isinstance(b, numbers.Real)):
                raise TypeError(f"project[{k!r}] bounds must be numbers or None, got {bounds!r}")
        if lo is not None and hi is not None and not lo <= hi:
            raise ValueError(f"project[{k!r}] must have lo <= hi, got {bounds!r}")
        ranges[k] = (None if lo is None else float(lo), None if hi is None else float(hi))
    return _Clamp(ranges)


def observed_texels(grad: jax.Array) -> jax.Array:
    """``(..., 1)`` mask of texels whose gradient is finite and non-zero in some channel.

    The library's rule for ``mask_unobserved=True``: a texel no ray reached this step
    has an all-zero gradient, and a non-finite gradient is never trusted.

    Args:
      grad: a gradient ``(..., C)``, channels last (a texture's ``(H, W, C)``, a
        volume's ``(D, H, W, C)``).

    Returns:
      A boolean array ``(..., 1)``: True where the texel counts as observed.

    Example::

        >>> import jax.numpy as jnp
        >>> from optax_bilateral.mitsuba import observed_texels
        >>> grad = jnp.array([[[0.0, 0.0]], [[0.0, 0.5]], [[jnp.nan, 1.0]]])   # (3, 1, 2)
        >>> observed_texels(grad)[:, 0, 0].tolist()
        [False, True, False]
    """
    finite = jnp.all(jnp.isfinite(grad), axis=-1, keepdims=True)
    return finite & jnp.any(grad != 0, axis=-1, keepdims=True)


def _keep_unobserved(new_state, old_state, observed: Mapping[str, jax.Array], shapes):
    """State leaves that mirror a parameter (found under its key, same shape) keep their
    old values at unobserved texels; every other leaf (counts, hyperparameters) advances."""

    def keep(path, new, old):
        last = path[-1] if path else None
        key = getattr(last, "key", None)
        if isinstance(key, str) and key in observed and tuple(jnp.shape(new)) == shapes[key]:
            return jnp.where(observed[key], new, old)
        return new

    return jax.tree_util.tree_map_with_path(keep, new_state, old_state)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3))
def _update(transform, project, mask_unobserved, shapes, grads, state, values):
    """One compiled step; the static arguments are hashable, so SceneOptimizers with the
    same transform object, projection and shapes share the compiled program."""
    shapes = dict(shapes)
    updates, new_state = transform.obj.update(grads, state, values)
    new_values = cast(dict, optax.apply_updates(values, updates))  # the dict of values
    if project is not None:
        new_values = project(new_values)
        if not isinstance(new_values, Mapping) or set(new_values) != set(values):
            raise ValueError(f"project must return a dict with the keys {sorted(values)}")
        for k, v in new_values.items():
            if tuple(jnp.shape(v)) != shapes[k]:
                raise ValueError(
                    f"project changed the shape of {k!r}: {shapes[k]} -> {jnp.shape(v)}"
                )
    if mask_unobserved:
        observed = {k: observed_texels(g) for k, g in grads.items()}
        new_values = {k: jnp.where(observed[k], new_values[k], values[k]) for k in values}
        new_state = _keep_unobserved(new_state, state, observed, shapes)
    new_values = {k: v.astype(values[k].dtype) for k, v in new_values.items()}
    return new_values, new_state


class SceneOptimizer:
    r"""Runs an optax ``GradientTransformation`` on chosen keys of a ``mi.SceneParameters``.

    The parameters are a dict ``{key: array}`` of the scene's tensors: bitmap
    textures ``(H, W, C)`` and grid volumes ``(D, H, W, C)``, channels last, which
    is the library's default leaf rule (all axes but the last are spatial). Per-key
    settings are pytree prefixes of that dict, e.g.
    ``bilateral_adam(lr, sigma_d={"medium.sigma_t.data": 1e-3, "medium.albedo.data": 0.2})``,
    and ``optax.multi_transform`` can give keys different transforms.

    One :meth:`step`, after the user's ``dr.backward(loss)``:

    1. reads the gradients ``dr.grad(params[key])`` and the current values as JAX
       arrays (DLPack; no copy on the CPU for 64-byte aligned buffers, see above);
    2. runs one jitted program: ``transform.update(grads, state, values)`` (the
       values are the transform's ``params``, i.e. the cross-bilateral guide),
       ``optax.apply_updates``, the projection ``project``, and with
       ``mask_unobserved`` the masking below;
    3. writes the values back (``params[key] = ...``, gradients enabled again,
       ``params.update()``) and returns the new state.

    The optimizer state is the transform's own pytree, returned by :meth:`init` and
    :meth:`step` and passed back in: ``ob.save_state`` / ``ob.load_state`` checkpoint
    it (with :meth:`values` and :meth:`set_values` for the scene's side).

    Args:
      transform: any ``optax.GradientTransformation`` (e.g. ``ob.bilateral_adam(...)``,
        ``optax.adam(...)``), learning-rate schedules included.
      params: ``mi.traverse(scene)``.
      keys: one parameter name or a sequence of them (``print(params)`` lists the names;
        a texture's is ``"<shape>.bsdf.<slot>.data"``).
      project: applied after every update: a mapping ``key -> (lo, hi)`` clamps (either
        bound may be ``None``), or a function ``values -> values`` on the dict of JAX
        arrays (traced with the update).
      mask_unobserved: texels whose gradient is zero in every channel (or non-finite)
        keep their value, untouched by the update and the projection, and the state
        leaves that mirror the parameter (found under its key with its shape, e.g.
        Adam's ``mu`` and ``nu``) keep their values there: the library's
        ``mask_unobserved=True`` rule for any transform (Mitsuba's ``mask_updates``).
        Give ``mask_unobserved=True`` to ``bilateral_adam`` as well so these texels
        also stay out of the filter's sums. Meant for texels no camera sees; at low
        spp many *seen* texels get no sample in a given step, and the filter is what
        spreads the gradient to them, so leave it off there (docs/mitsuba.md).

    Raises:
      KeyError: a key that is not in ``params``.
      TypeError: a value that is not a differentiable tensor, or keys or ``project``
        bounds of the wrong type.
      ValueError: a value that is not a (H, W, C) or (D, H, W, C) grid, or a
        malformed ``project``.
      RuntimeError: no AD variant, or an LLVM variant on a libLLVM older than 16.

    Example::

        >>> import numpy as np, drjit as dr, mitsuba as mi, optax_bilateral as ob
        >>> from optax_bilateral.mitsuba import SceneOptimizer
        >>> mi.set_variant("llvm_ad_rgb")
        >>> camera = mi.ScalarTransform4f().look_at(
        ...     origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0])
        >>> texture = mi.TensorXf(np.full((8, 8, 3), 0.5, np.float32))
        >>> scene = mi.load_dict({
        ...     "type": "scene", "integrator": {"type": "direct"}, "light": {"type": "constant"},
        ...     "sensor": {"type": "perspective", "to_world": camera,
        ...                "film": {"type": "hdrfilm", "width": 8, "height": 8}},
        ...     "plane": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {
        ...         "type": "bitmap", "raw": True, "data": texture}}}})
        >>> params = mi.traverse(scene)
        >>> key = "plane.bsdf.reflectance.data"
        >>> opt = SceneOptimizer(ob.bilateral_adam(0.05, sigma_d=0.1, levels=1), params, key,
        ...                      project={key: (0.0, 1.0)})
        >>> state = opt.init()
        >>> image = mi.render(scene, params, spp=4)
        >>> dr.backward(dr.mean(dr.square(image - 0.1), axis=None))   # darker than the target
        >>> state = opt.step(state)
        >>> float(opt.values()[key].mean()) < 0.5                    # the texture got darker
        True
    """

    def __init__(
        self,
        transform: optax.GradientTransformation,
        params: mi.SceneParameters,
        keys: str | Sequence[str],
        *,
        project: Mapping[str, tuple[Any, Any]] | Callable[[dict], dict] | None = None,
        mask_unobserved: bool = False,
    ) -> None:
        mi, dr = _modules()
        check_variant()
        if not (hasattr(transform, "init") and hasattr(transform, "update")):
            raise TypeError(
                f"transform must be an optax GradientTransformation, got {type(transform).__name__}"
            )
        if not isinstance(params, mi.SceneParameters):
            raise TypeError(
                f"params must be mi.traverse(scene) (mi.SceneParameters), got "
                f"{type(params).__name__}"
            )
        if not isinstance(mask_unobserved, bool):
            raise TypeError(f"mask_unobserved must be a bool, got {mask_unobserved!r}")
        self.transform = transform
        self.params = params
        self.keys = _check_keys(params, keys)
        self.shapes = {k: _check_value(k, params[k], dr) for k in self.keys}
        self._dtypes = {k: to_jax(dr.detach(params[k])).dtype for k in self.keys}
        for k, dtype in self._dtypes.items():
            if not jnp.issubdtype(dtype, jnp.floating):
                raise TypeError(
                    f"params[{k!r}] holds {dtype} values (a bitmap loaded from an 8-bit "
                    "image keeps them); optimize a float texture instead: "
                    f"params[{k!r}] = mi.TensorXf(values / 255.0)"
                )
        self.mask_unobserved = mask_unobserved
        project = _projection(project, self.keys)
        if project is not None and not isinstance(project, _Clamp):
            project = ById(project)
        self._static = (
            ById(transform),
            project,
            mask_unobserved,
            tuple(sorted(self.shapes.items())),
        )
        self._enable_grads()

    # -- scene side --------------------------------------------------------------------

    def _current(self, key) -> Any:
        _, dr = _modules()
        value: Any = self.params[key]  # a Dr.Jit tensor (the stubs say object)
        shape = tuple(int(s) for s in value.shape) if dr.is_tensor_v(value) else None
        if shape != self.shapes[key]:
            raise ValueError(
                f"params[{key!r}] now has shape {shape}, but this SceneOptimizer was "
                f"built for {self.shapes[key]}; after resizing a texture or volume, "
                "build a new SceneOptimizer and state"
            )
        return value

    def _enable_grads(self):
        _, dr = _modules()
        for k in self.keys:
            dr.enable_grad(self._current(k))
        self.params.update()

    def values(self) -> dict[str, jax.Array]:
        """The current values ``{key: array}`` (views of the scene's memory on the CPU)."""
        _, dr = _modules()
        return {k: to_jax(dr.detach(self._current(k))) for k in self.keys}

    def grads(self) -> dict[str, jax.Array]:
        """The gradients accumulated by ``dr.backward`` since the last step, ``{key: array}``."""
        _, dr = _modules()
        grads = {}
        for k in self.keys:
            value = self._current(k)
            if not dr.grad_enabled(value):
                raise ValueError(
                    f"params[{k!r}] does not track gradients (it was replaced after this "
                    "SceneOptimizer enabled them), so its gradient would read as zero; "
                    "write values with opt.set_values(...), or call "
                    f"dr.enable_grad(params[{k!r}]) and params.update() before rendering"
                )
            grads[k] = to_jax(dr.grad(value))
        return grads

    def set_values(self, values: Mapping[str, Any]) -> None:
        """Writes ``values`` (``{key: array}``, e.g. from a checkpoint) into the scene,
        gradients enabled, and calls ``params.update()``."""
        _, dr = _modules()
        if not isinstance(values, Mapping) or set(values) != set(self.keys):
            got = sorted(values) if isinstance(values, Mapping) else type(values).__name__
            raise ValueError(f"values must be a dict with the keys {sorted(self.keys)}, got {got}")
        for k in self.keys:
            current = self._current(k)
            v = jnp.asarray(values[k], dtype=self._dtypes[k])
            if tuple(v.shape) != self.shapes[k]:
                raise ValueError(
                    f"values[{k!r}] has shape {tuple(v.shape)}, expected {self.shapes[k]}"
                )
            new = type(current)(v)  # DLPack: the scene holds the JAX buffer
            dr.enable_grad(new)
            self.params[k] = new
        self.params.update()

    # -- optimizer side ----------------------------------------------------------------

    def init(self) -> optax.OptState:
        """The transform's initial state for the current values (a pytree of JAX arrays)."""
        return self.transform.init(self.values())

    def update(
        self, grads: Mapping[str, jax.Array], state: optax.OptState, values: Mapping[str, jax.Array]
    ) -> tuple[dict, optax.OptState]:
        """The compiled step without the scene: ``(new_values, new_state)`` from ``{key: array}``
        gradients and values (the update, the projection and the masking of :meth:`step`)."""
        # States from init() or load_state are uncommitted; committing them to the values'
        # device keeps jit from compiling the step a second time for the committed outputs.
        state = jax.device_put(state, next(iter(values.values())).sharding)
        return _update(*self._static, grads, state, values)

    def step(self, state: optax.OptState) -> optax.OptState:
        """One update from the gradients of the last ``dr.backward``; returns the new state.

        ``set_values(update(grads(), state, values()))``: the values are written back
        into the scene with gradients enabled (and the old gradients dropped), so the
        next render and ``dr.backward`` start afresh.
        """
        new_values, state = self.update(self.grads(), state, self.values())
        self.set_values(new_values)
        return state
