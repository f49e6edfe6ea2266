"""Mitsuba's own optimizer interface (``drjit.opt.Optimizer``) driven by optax transforms.

``mi.ad.Adam`` and the other Dr.Jit optimizers are dictionaries that own the parameters
they optimize: ``opt[key] = params[key]``, ``params.update(opt)``, ``opt.step()``. The
classes here subclass the pinned ``drjit.opt.Optimizer`` (Dr.Jit 1.5), so a Mitsuba
script swaps one line; the step itself runs in JAX: per key, the gradient and the value
cross to JAX through DLPack (no copy on the CPU for 64-byte aligned buffers, as
:func:`to_jax`), one compiled program applies the key's optax transform, and the result
crosses back as the key's new Dr.Jit value.

This module imports Dr.Jit at import time; ``optax_bilateral.mitsuba`` imports it on first
use of :class:`OptaxOptimizer` or :class:`BilateralAdam` (``import optax_bilateral.mitsuba``
alone imports neither Dr.Jit nor Mitsuba).
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Callable, Hashable, Mapping
from typing import Any, NamedTuple, cast

import drjit as dr
import jax
import jax.numpy as jnp
import numpy as np
import optax
from drjit.opt import Optimizer

from optax_bilateral._src.mitsuba.bridge import GRID_NDIMS, ById, observed_texels, to_jax
from optax_bilateral._src.optimizer.alias import PAPER_B1, filtered_chain
from optax_bilateral._src.optimizer.transforms import called_as, scale_by_adam
from optax_bilateral._src.rules.registry import DEFAULT_SIGMA_D

LearningRate = float | dr.ArrayBase | Callable[[Any], Any]


class KeyState(NamedTuple):
    """What :class:`OptaxOptimizer` keeps per key besides the value (the ``extra`` slot of
    ``drjit.opt.Optimizer.state``).

    Attributes:
      count: the number of steps this key has taken since it was registered or reset (the
        argument of a learning-rate schedule).
      state: the key's optax state (a pytree of JAX arrays).
      transform: the key's ``optax.GradientTransformation``.
    """

    count: int
    state: optax.OptState
    transform: optax.GradientTransformation


def is_grid(value: Any) -> bool:
    """True for a Dr.Jit tensor shaped like a bitmap texture ``(H, W, C)`` or a grid volume
    ``(D, H, W, C)``."""
    return bool(dr.is_tensor_v(value)) and len(value.shape) in GRID_NDIMS


def _scalar(x: Any, what: str) -> float:
    """A learning rate or gradient scale (a number, a one-entry Dr.Jit or JAX array) as a float."""
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size != 1:
        raise ValueError(f"{what} must be a scalar, got an array of {a.size} entries")
    return float(a[0])


def _check_lr(lr: Any, what: str) -> None:
    if callable(lr) or isinstance(lr, dr.ArrayBase | jax.Array):
        return
    if isinstance(lr, bool) or not isinstance(lr, numbers.Real):
        raise TypeError(
            f"{what} must be a number, a one-entry Dr.Jit array or an optax schedule "
            f"(a callable of the step count), got {type(lr).__name__}"
        )
    if not (math.isfinite(float(lr)) and float(lr) >= 0):
        raise ValueError(f"{what} must be finite and >= 0, got {lr!r}")


def _restore_where(observed, new_tree, old_tree, shape):
    """Leaves of the key's shape (moments and other per-entry state) keep their old values
    where ``observed`` is False; the others (counts, scales) advance."""
    return jax.tree.map(
        lambda n, o: jnp.where(observed, n, o) if jnp.shape(n) == shape else n, new_tree, old_tree
    )


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _apply(transform: ById, mask: str | None, view, grad, state, value, lr, grad_scale):
    """One key's step: ``value + lr * updates`` with the transform's updates on the value
    seen as ``view`` (a shape), and with ``mask`` ("texel" or "component") unobserved
    entries keep their value and state."""
    shape = value.shape
    grad = grad.reshape(view) * grad_scale.astype(grad.dtype)
    value = value.reshape(view)
    updates, new_state = transform.obj.update(grad, state, value)
    new_value = value + lr.astype(value.dtype) * updates
    if mask is not None:
        observed = observed_texels(grad) if mask == "texel" else grad != 0
        new_value = jnp.where(observed, new_value, value)
        new_state = _restore_where(observed, new_state, state, value.shape)
    return new_value.astype(value.dtype).reshape(shape), new_state


class OptaxOptimizer(Optimizer):
    r"""A ``drjit.opt.Optimizer`` (the interface of ``mi.ad.Adam``) that applies an optax
    transform to every key.

    Used as Mitsuba's own optimizers are::

        opt = OptaxOptimizer(optax.adam(0.01))   # instead of mi.ad.Adam(lr=0.01)
        opt[key] = params[key]
        params.update(opt)
        for it in range(n):
            image = mi.render(scene, params, spp=1, seed=it)
            dr.backward(loss(image))
            opt.step()
            opt[key] = dr.clip(opt[key], 0.0, 1.0)   # writing a value keeps its state
            params.update(opt)

    Each key has its own optax state, created from its value when the key is registered
    (``opt[key] = value``) and kept when a value of the same shape is written (a clip, a
    projection); a value of another shape (an upsampled texture) starts afresh, as in
    Dr.Jit. :meth:`step` updates each key with ``value + lr * updates``, where
    ``updates`` are the transform's (its own learning rate included) and ``lr`` (default
    1) is a multiplier that :meth:`set_learning_rate` sets globally or per key. The
    transform sees the key's value as a JAX array: a texture ``(H, W, C)``, a volume
    ``(D, H, W, C)``, a ``Color3f`` as ``(3, 1)``, a flat ``Float`` (e.g. a mesh's
    ``vertex_positions``) as ``(N,)``, unless ``shapes`` gives the key another shape:
    ``obm.bilateral_large_steps`` wants a mesh's positions as ``(V, 3)``, so
    ``shapes={"shape.vertex_positions": (-1, 3)}`` (docs/mitsuba.md, "Meshes").

    State: :meth:`state_dict` returns every value, step count, learning rate and optax
    state as one pytree; ``ob.save_state(path, opt.state_dict())`` writes it and
    ``opt.load_state_dict(ob.load_state(path, opt.state_dict()))`` restores it into an
    optimizer with the same keys, after which a run continues bit for bit as one that
    was not interrupted.

    Args:
      transform: any ``optax.GradientTransformation`` (``optax.adam(1e-2)``,
        ``ob.bilateral_adam(...)``, ``obm.bilateral_large_steps(...)``, a chain), applied to
        each key separately; its ``update`` gets the key's value as ``params``.
      params: optional ``{key: value}`` to register at once (as ``opt.update(params)``).
      lr: a multiplier of the transform's updates (default 1), a number, a one-entry
        Dr.Jit array or an optax schedule of the key's step count.
      shapes: ``{key: shape}``: the shape the transform sees a key's value in (a reshape,
        ``-1`` allowed), e.g. ``(-1, 3)`` for a mesh's flat ``vertex_positions``; the
        optimizer still holds (and ``params.update(opt)`` writes) the value as registered.
      mask_updates: entries without a gradient keep their value and their state (the
        state's leaves with the value's shape): per texel (every channel's gradient zero,
        or a non-finite one) for textures and volumes, per entry for other keys, as
        Dr.Jit's ``mask_updates``.
      promote_fp16: keep half-precision parameters in single precision (Dr.Jit's option).

    Raises:
      TypeError: ``transform`` is not a ``GradientTransformation``, or a bad ``lr``.
      ValueError: a negative or non-finite ``lr``.

    Example::

        >>> import drjit as dr, mitsuba as mi, optax
        >>> from optax_bilateral.mitsuba import OptaxOptimizer
        >>> mi.set_variant("llvm_ad_rgb")
        >>> opt = OptaxOptimizer(optax.sgd(0.5))
        >>> opt["x"] = mi.Float(1.0, 2.0)
        >>> dr.backward(dr.sum(dr.square(opt["x"])))      # gradient 2 x
        >>> opt.step()
        >>> opt["x"]
        [0, 0]
    """

    def __init__(
        self,
        transform: optax.GradientTransformation,
        params: Mapping[str, dr.ArrayBase] | None = None,
        *,
        lr: LearningRate = 1.0,
        shapes: Mapping[str, tuple[int, ...]] | None = None,
        mask_updates: bool = False,
        promote_fp16: bool = True,
    ) -> None:
        if not (hasattr(transform, "init") and hasattr(transform, "update")):
            raise TypeError(
                f"transform must be an optax GradientTransformation, got {type(transform).__name__}"
            )
        self.transform = transform
        self._init_common(lr, params, mask_updates, promote_fp16, shapes)

    def _init_common(self, lr, params, mask_updates, promote_fp16, shapes=None) -> None:
        _check_lr(lr, "lr")
        if shapes is not None and not isinstance(shapes, Mapping):
            raise TypeError(f"shapes must be a dict {{key: shape}}, got {type(shapes).__name__}")
        self.shapes = {k: tuple(int(n) for n in v) for k, v in (shapes or {}).items()}
        for name, flag in (("mask_updates", mask_updates), ("promote_fp16", promote_fp16)):
            if not isinstance(flag, bool):
                raise TypeError(f"{name} must be a bool, got {flag!r}")
        super().__init__(
            cast(Any, lr), params, mask_updates=mask_updates, promote_fp16=promote_fp16
        )

    # -- per key: which transform ------------------------------------------------------

    def transform_for(self, key: str, value: dr.ArrayBase) -> optax.GradientTransformation:
        """The transform a newly registered (or reset) ``key`` gets; here always the one."""
        del key, value
        return self.transform

    def _reset(self, key: str, value: dr.ArrayBase, promoted: bool, /) -> None:
        transform = self.transform_for(key, value)
        # A reset keeps a per-key learning rate (Dr.Jit's Adam drops it).
        lr = self.state[key][2] if key in self.state else None
        x = to_jax(dr.detach(value))
        view = self.view(key, x.shape)
        # Committed to the value's device as the step's outputs are: one compilation, not two.
        state = jax.device_put(transform.init(x.reshape(view)), x.sharding)
        self.state[key] = value, promoted, lr, KeyState(0, state, transform)

    def view(self, key: str, shape: tuple[int, ...]) -> tuple[int, ...]:
        """The shape the transform sees ``key``'s value (of ``shape``) in."""
        if key not in self.shapes:
            return tuple(shape)
        target = self.shapes[key]
        size, known = math.prod(shape), math.prod(n for n in target if n != -1)
        free = target.count(-1)
        if free > 1 or known <= 0 or size % known or (free == 0 and known != size):
            raise ValueError(
                f"shapes[{key!r}] = {target} does not fit its value of shape {tuple(shape)}"
            )
        return tuple(size // known if n == -1 else n for n in target)

    # -- learning rates ----------------------------------------------------------------

    def set_learning_rate(
        self,
        value: LearningRate | Mapping[str, LearningRate | None] | None = None,
        /,
        **kwargs: LearningRate | None,
    ) -> None:
        """Sets the learning rate globally (``opt.set_learning_rate(1e-3)``) or per key
        (``opt.set_learning_rate({key: 1e-3})``, ``None`` to return to the global one).

        As Dr.Jit's, plus ints and optax schedules (``count -> rate``, evaluated at the
        key's step count), and a clear error for an unknown key.
        """
        if isinstance(value, Mapping):
            for k, lr in value.items():
                if k not in self.state:
                    raise KeyError(f"{k!r} is not a parameter of this optimizer: {list(self)}")
                if lr is not None:
                    _check_lr(lr, f"the learning rate of {k!r}")
                entry = self.state[k]
                self.state[k] = (entry[0], entry[1], cast(Any, lr), entry[3])
        elif value is not None:
            _check_lr(value, "the learning rate")
            self.lr = cast(Any, value)
        if kwargs:
            self.set_learning_rate(kwargs)

    def _rate(self, lr: Any, count: int) -> float:
        rate = lr(count) if callable(lr) else lr
        return _scalar(rate, "the learning rate")

    # -- the step ----------------------------------------------------------------------

    def mask_rule(self, value: dr.ArrayBase) -> str | None:
        """``mask_updates``' rule for a value: per texel for grids, per entry otherwise."""
        if not self.mask_updates:
            return None
        return "texel" if is_grid(value) else "component"

    def step(
        self,
        *,
        eval: bool = True,
        grad_scale: Any = None,
        active: Any = None,
    ) -> None:
        """One update of every key from the gradients of the last ``dr.backward``.

        Per key: the gradient and the value as JAX arrays (DLPack), one compiled program
        (the transform's update, ``value + lr * updates``, the mask of
        ``mask_updates``), and the result as the key's new value, gradients enabled and
        zero. The values are always evaluated (``eval`` is accepted for Dr.Jit's
        signature); ``grad_scale`` multiplies the gradients and ``active=False`` skips
        the step, as ``drjit.opt.GradScaler`` uses them.
        """
        del eval
        if active is not None and not _scalar(active, "active"):
            return
        scale = jnp.float32(1.0 if grad_scale is None else _scalar(grad_scale, "grad_scale"))
        grads = {k: dr.grad(entry[0]) for k, entry in self.state.items()}
        dr.eval(*grads.values())
        for key, (value, promoted, lr, extra) in list(self.state.items()):
            x = to_jax(dr.detach(value))
            rate = jnp.float32(self._rate(self.lr if lr is None else lr, extra.count))
            new_x, new_state = _apply(
                ById(extra.transform),
                self.mask_rule(value),
                self.view(key, x.shape),
                to_jax(grads[key]),
                extra.state,
                x,
                rate,
                scale,
            )
            new_value = type(value)(new_x)  # DLPack: Dr.Jit holds the JAX buffer
            dr.enable_grad(new_value)
            new_extra = KeyState(extra.count + 1, new_state, extra.transform)
            self.state[key] = new_value, promoted, lr, new_extra

    # -- checkpoints -------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed run needs, as one pytree of arrays.

        ``{"lr": global rate, "keys": {key: {"value", "lr", "count", "state"}}}``: the
        values (the optimizer owns them, as Dr.Jit's do), per-key learning rates, step
        counts and optax states. A learning rate that is a schedule or unset is stored as
        NaN (the code that built the optimizer restores it). Save it with
        ``ob.save_state(path, opt.state_dict())``.
        """
        return {
            "lr": _stored_rate(self.lr),
            "keys": {
                k: {
                    "value": to_jax(dr.detach(value)),
                    "lr": _stored_rate(lr),
                    "count": np.int64(extra.count),
                    "state": extra.state,
                }
                for k, (value, _, lr, extra) in self.state.items()
            },
        }

    def load_state_dict(self, saved: Mapping[str, Any]) -> None:
        """Restores :meth:`state_dict`'s pytree (e.g. ``ob.load_state(path,
        opt.state_dict())``) into this optimizer, whose keys must be the saved ones with
        the same shapes and transforms. Call ``params.update(opt)`` afterwards."""
        keys = saved.get("keys") if isinstance(saved, Mapping) else None
        if not isinstance(keys, Mapping) or set(keys) != set(self.state):
            got = sorted(keys) if isinstance(keys, Mapping) else type(saved).__name__
            raise ValueError(
                f"the saved state must hold the keys {sorted(self.state)} (register them "
                f"first, as the saved run did), got {got}"
            )
        new_states = {}
        for k, entry in keys.items():
            value, promoted, lr, extra = self.state[k]
            x = to_jax(dr.detach(value))
            saved_x = jnp.asarray(entry["value"])
            if saved_x.shape != x.shape or saved_x.dtype != x.dtype:
                raise ValueError(
                    f"the saved value of {k!r} is {saved_x.dtype}{list(saved_x.shape)}, "
                    f"but the registered one is {x.dtype}{list(x.shape)}"
                )
            state = jax.device_put(jax.tree.map(jnp.asarray, entry["state"]), x.sharding)
            if jax.tree.structure(state) != jax.tree.structure(extra.state):
                raise ValueError(
                    f"the saved optax state of {k!r} does not match this optimizer's "
                    "transform for it (another transform or settings?)"
                )
            new_value = type(value)(saved_x)
            dr.enable_grad(new_value)
            rate = _loaded_rate(entry["lr"], lr)
            count = int(np.asarray(entry["count"]))
            new_states[k] = new_value, promoted, rate, KeyState(count, state, extra.transform)
        self.state.update(new_states)
        self.lr = cast(Any, _loaded_rate(saved["lr"], self.lr))

    def __repr__(self) -> str:
        rates = {"default": self.lr} | {k: s[2] for k, s in self.state.items() if s[2] is not None}
        return (
            f"{type(self).__name__}[\n  parameters = {list(self.keys())},\n  lr = {rates},\n"
            f"  mask_updates = {self.mask_updates},\n  transform = {self._describe()}\n]"
        )

    def _describe(self) -> str:
        return type(self.transform).__name__


def _stored_rate(lr: Any) -> np.float64:
    if lr is None or callable(lr):
        return np.float64(np.nan)
    return np.float64(_scalar(lr, "the learning rate"))


def _loaded_rate(saved: Any, current: Any) -> Any:
    rate = float(np.asarray(saved))
    return current if math.isnan(rate) else rate


# ------------------------------------------------------------------------------------------
# BilateralAdam


def _per_key(setting: Any, key: str, name: str) -> Any:
    """A setting given as ``{key: value}`` resolved for ``key``; any other value as is."""
    if not isinstance(setting, Mapping):
        return setting
    if key not in setting:
        raise KeyError(
            f"{name} is a dict without an entry for {key!r}; give one value for every key, "
            f"or a dict with every key you register (it has {sorted(setting)})"
        )
    return setting[key]


_CHAINS: dict[Hashable, optax.GradientTransformation] = {}


def filtered_adam(
    b1, b2, eps, sigma_d, levels, prefilter, spatial_axes, log_guide, mask_unobserved
) -> optax.GradientTransformation:
    """The grid keys' transform, without the learning rate: ``chain(prefilter?,
    postfilter, scale(-1))``. Equal settings give the same object (one compilation)."""
    args = (b1, b2, eps, sigma_d, levels, prefilter, spatial_axes, log_guide, mask_unobserved)
    try:
        cached = _CHAINS.get(args)
    except TypeError:  # an unhashable setting (e.g. a dict of axes): build it each time
        cached, args = None, None
    if cached is not None:
        return cached
    with called_as("BilateralAdam"):
        chain = filtered_chain(
            1.0,
            PAPER_B1 if b1 is None else b1,
            b2,
            eps,
            prefilter=prefilter,
            sigma_d=sigma_d,
            levels=levels,
            spatial_axes=spatial_axes,
            log_guide=log_guide,
            mask_unobserved=mask_unobserved,
        )
    if args is not None:
        _CHAINS[args] = chain
    return chain


@functools.cache
def adam_rule(eps: float) -> optax.GradientTransformation:
    """The other keys' default transform, without the learning rate: Adam (b1 0.9, b2
    0.999)."""
    return optax.chain(scale_by_adam(eps=eps), optax.scale_by_learning_rate(1.0))


class BilateralAdam(OptaxOptimizer):
    r"""``mi.ad.Adam`` with spatiotemporal bilateral filtering of textures and volumes: the
    paper's optimizer (``ob.bilateral_adam``) as a drop-in Dr.Jit optimizer.

    A Mitsuba script changes one line::

        opt = BilateralAdam(lr=0.1)               # was: opt = mi.ad.Adam(lr=0.01)
        opt[key] = params[key]
        params.update(opt)
        # ... dr.backward(loss); opt.step(); opt[key] = dr.clip(opt[key], 0, 1);
        # params.update(opt)

    Keys whose value is a bitmap texture ``(H, W, C)`` or a grid volume ``(D, H, W, C)``
    (a Dr.Jit tensor of 3 or 4 axes, channels last) get the filtered Adam step of
    ``ob.bilateral_adam`` (supplement eq. 14, or eq. 11 with ``prefilter``), guided by
    the key's current value:

    .. math::
        \theta_t = \theta_{t-1} - \eta\,
        \frac{B_t m_t/(1-\beta_1^t)}{\sqrt{B_t v_t/(1-\beta_2^t)} + \epsilon}

    built as ``optax.chain(ob.prefilter(...)?, ob.postfilter(b1, b2, eps, ...))`` with
    ``mask_unobserved=mask_updates``. Every other key (a colour, a scalar, mesh vertex
    positions) gets ``others``, by default Adam's rule (``ob.scale_by_adam()``: b1 0.9,
    b2 0.999, this ``eps``), as ``mi.ad.Adam`` would give it (up to rounding: Dr.Jit
    folds the bias corrections into the rate).

    Everything else is :class:`OptaxOptimizer`'s: one state per key, kept when a value
    of the same shape is written (``opt[key] = dr.clip(opt[key], 0, 1)``) and started
    afresh at another shape, :meth:`set_learning_rate` globally or per key (numbers or
    optax schedules of the key's step count), ``reset(key)``, :meth:`state_dict` /
    :meth:`load_state_dict` for checkpoints.

    Args:
      lr: the learning rate (a number, a one-entry Dr.Jit array, or an optax schedule
        of the key's step count).
      params: optional ``{key: value}`` to register at once.
      b1: the filtered keys' first-moment decay (None: the library's, 0.2).
      b2: their second-moment decay (None: ``1 - (1 - b1)^2``).
      eps: added to the denominator (every key).
      sigma_d: the filter's data-term scale (``"auto"``, the default, a number, or
        ``"sure"``; see ``ob.postfilter``).
      levels: F, the number of a-trous levels (None: the library's default).
      prefilter: also filter the gradient before the moments (supplement eq. 11).
      spatial_axes: the filtered axes of a grid key (None: every axis but the last, the
        channels, as Mitsuba stores textures and volumes).
      log_guide: guide with ``log(|value| + 1e-8)`` (the paper's texture runs).
      others: the transform of keys that are not grids, without a learning rate (the
        optimizer's ``lr`` applies), e.g. ``ob.scale_by_adam(b1=0.8)`` or
        ``optax.scale_by_rms()``; None: Adam's rule.
      mask_updates: texels without a gradient (all channels zero, or non-finite) keep
        their value and moments and stay out of the filter's sums (the library's
        ``mask_unobserved``); other keys' entries are masked as Dr.Jit does. For texels
        no camera sees; at 1 spp many seen texels get no sample in a step, and the
        filter is what gives them one (docs/mitsuba.md).
      promote_fp16: keep half-precision parameters in single precision (Dr.Jit's option).

    ``sigma_d``, ``levels``, ``prefilter``, ``spatial_axes`` and ``log_guide`` may be
    dicts ``{key: value}`` for per-key settings (every registered grid key needs an
    entry).

    Raises:
      TypeError, ValueError: a bad argument (raised here, or at registration for
        per-key settings), with the library's message.

    Example::

        >>> import drjit as dr, mitsuba as mi, numpy as np
        >>> from optax_bilateral.mitsuba import BilateralAdam
        >>> mi.set_variant("llvm_ad_rgb")
        >>> opt = BilateralAdam(lr=0.05, sigma_d=0.1, levels=2)
        >>> opt["texture"] = mi.TensorXf(np.full((16, 16, 3), 0.5, np.float32))
        >>> opt["colour"] = mi.Color3f(0.5, 0.5, 0.5)
        >>> loss = dr.mean(dr.square(opt["texture"] - 0.2), axis=None) + dr.sum(opt["colour"].x)
        >>> dr.backward(loss)
        >>> opt.step()
        >>> opt["texture"] = dr.clip(opt["texture"], 0.0, 1.0)     # keeps the key's state
        >>> round(float(np.mean(opt["texture"])), 3)             # Adam's first step: -lr
        0.45
        >>> opt["colour"]                                          # only x had a gradient
        [[0.45, 0.5, 0.5]]
    """

    def __init__(
        self,
        lr: LearningRate,
        params: Mapping[str, dr.ArrayBase] | None = None,
        *,
        b1: float | None = None,
        b2: float | None = None,
        eps: float = 1e-8,
        sigma_d: Any = DEFAULT_SIGMA_D,
        levels: Any = None,
        prefilter: Any = False,
        spatial_axes: Any = None,
        log_guide: Any = False,
        others: optax.GradientTransformation | None = None,
        mask_updates: bool = False,
        promote_fp16: bool = True,
    ) -> None:
        if others is not None and not (hasattr(others, "init") and hasattr(others, "update")):
            raise TypeError(
                f"others must be an optax GradientTransformation, got {type(others).__name__}"
            )
        self.settings = dict(
            sigma_d=sigma_d,
            levels=levels,
            prefilter=prefilter,
            spatial_axes=spatial_axes,
            log_guide=log_guide,
        )
        self.b1, self.b2, self.eps = b1, b2, eps
        self.others = (
            adam_rule(eps)
            if others is None
            else optax.chain(others, optax.scale_by_learning_rate(1.0))
        )
        # Builds (and so checks) the grid transform now for settings that are not per key.
        if not any(isinstance(s, Mapping) for s in self.settings.values()):
            self._grid_transform(None, mask_updates)
        self._init_common(lr, params, mask_updates, promote_fp16)

    def _grid_transform(
        self, key: str | None, mask: bool, ndim: int = 3
    ) -> optax.GradientTransformation:
        s = {n: v if key is None else _per_key(v, key, n) for n, v in self.settings.items()}
        if s["spatial_axes"] is None:  # Mitsuba's grids are channels last
            s["spatial_axes"] = tuple(range(ndim - 1))
        return filtered_adam(
            self.b1,
            self.b2,
            self.eps,
            s["sigma_d"],
            s["levels"],
            s["prefilter"],
            s["spatial_axes"],
            s["log_guide"],
            mask,
        )

    def transform_for(self, key: str, value: dr.ArrayBase) -> optax.GradientTransformation:
        """The filtered Adam for a grid (:func:`is_grid`), ``others`` for any other key."""
        if is_grid(value):
            return self._grid_transform(key, self.mask_updates, len(value.shape))
        return self.others

    def _describe(self) -> str:
        others = "Adam" if self.others is adam_rule(self.eps) else "others"
        return f"filtered Adam on grids (b1 = {self.b1}, {self.settings}), {others} elsewhere"
