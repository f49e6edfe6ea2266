"""Toy participating-medium scene: a heterogeneous volume seen by many cameras.

The paper's second grid application (main paper Figs. 8-9, supplement Table 1):
recover a voxel grid of extinction and RGB albedo from images. This module
models only what that needs, in JAX, small enough for a CPU.

Scene
-----
* The medium fills the unit cube ``[0, 1]^3``. The parameters are a dict
  ``{"density": (D, H, W, 1), "albedo": (D, H, W, 3)}`` of values at voxel
  centres ``((i + 1/2) / D, (j + 1/2) / H, (k + 1/2) / W)`` (axes 0, 1, 2 are
  x, y, z), looked up trilinearly with clamp-to-edge. Channels-last, so the
  library's default leaf rule filters the three spatial axes of both leaves.
* Extinction ``sigma_t(x) = density_scale * density(x)``, scattering
  ``sigma_s(x) = sigma_t(x) * albedo(x)`` (per RGB channel). The valid domain is
  ``0 <= density <= density_max`` and ``0 <= albedo <= 1``; the renderer does not
  clamp (a clamp would zero or halve gradients at the bounds), so optimisers
  should :func:`project` after each step, as Mitsuba's volume tutorials do.
* Light: a sun (directional light of direction ``sun_direction``, pointing
  *towards* the sun) with an isotropic phase function, and a sky/ground
  gradient ``L_env(omega)`` seen *only* as the background behind the medium
  (its in-scattering is not modelled). Single scattering only.
* Cameras: ``n_views`` pinhole cameras on a Fibonacci sphere of radius
  ``camera_distance`` around the cube's centre, looking at it; square images of
  ``resolution`` pixels, box pixel filter.

Radiance along a camera ray ``x(t) = o + t omega``, entering the cube at
``t = 0`` (shifted) and leaving it at ``t = L``:

.. math::
    I = T(0, L)\\,L_{env}(\\omega)
        + \\int_0^L T(0, t)\\, \\sigma_s(x(t))\\, T_{sun}(x(t))\\, S\\, dt,
    \\qquad T(a, b) = e^{-\\int_a^b \\sigma_t},

where ``S = sun_radiance`` already includes the isotropic phase ``1/4pi`` and
``T_sun(x)`` is the transmittance from ``x`` to the cube's boundary towards the
sun.

Estimator (unbiased; primal and gradient share the formula, not the samples)
---------------------------------------------------------------------------
Random numbers never depend on the parameters, so each estimate is a smooth
function of the voxel values and its reverse-mode derivative is an unbiased
estimate of the derivative of the expectation.

1. *Pixel*: one uniformly jittered position per pixel sample (box filter).
2. *Transmittance by ratio tracking* (Cramer 1978; Novak et al. 2014): draw the
   points ``t_1 < t_2 < ...`` of a Poisson process of rate
   ``mu = density_scale * density_max`` (exponential gaps) on the segment; then
   ``T_hat(0, t) = prod_{t_j < t} (1 - sigma_t(x(t_j)) / mu)``. By the Poisson
   process' generating functional, ``E[T_hat] = exp(-int sigma_t) = T`` for any
   ``sigma_t`` (it is bounded in [0, 1] when ``sigma_t <= mu``, i.e. in the valid
   domain). One process per camera ray serves ``T(0, L)`` and every ``T(0, t_m)``.
3. *In-scattering*: ``n_scatter`` stratified distances ``t_m = (m + u_m) L / M``;
   the integral is estimated by ``(L / M) sum_m T_hat(0, t_m) sigma_s(x(t_m))
   T_sun_hat(x(t_m)) S``, with an independent ratio-tracking process on each
   shadow ray for ``T_sun_hat``. Independent factors, so the product is unbiased.
4. *Fixed sizes for JAX*: a process uses at most ``n_track`` (camera) or
   ``n_shadow`` (shadow) points. The cap is chosen so that the probability of
   a longer process on the longest chord (``sqrt(3)``) is below
   ``truncation_probability`` (default 1e-7): the estimator is unbiased up to
   that truncation, which is far below every test's statistical resolution.

Loss gradients: for ``loss = mean((I - I_ref)^2)`` the gradient
``2/N J^T (I - I_ref)`` needs ``I`` and ``J`` from *independent* samples, or it
is biased by their covariance; :func:`loss_and_grad` renders the primal with
one key and back-propagates a second, independent estimate with another (as
Mitsuba's ``spp`` / ``spp_grad``).

The reference volume (:func:`reference_volume`) is procedural and embedded: a
smoke-like density (a rising plume of Gaussian blobs modulated by a fixed
sum-of-sines turbulence, softly thresholded) and a three-colour checker albedo.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral.toy import _volume_sampling as sampling

Params = Mapping[str, jax.Array]

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


# --------------------------------------------------------------------------- scene


@dataclasses.dataclass(frozen=True, eq=False)
class VolumeScene:
    """Cameras, light and estimator settings. Hashable by identity (a static jit argument).

    Attributes:
      resolution: image side in pixels.
      origins, forward, right, up: ``(n_views, 3)`` camera frames.
      tan_half_fov: tangent of half the field of view.
      sun_direction: ``(3,)`` unit vector towards the sun.
      sun_radiance: ``(3,)`` sun irradiance times the isotropic phase ``1/4pi``.
      sky_zenith, sky_horizon, ground: ``(3,)`` colours of the background gradient.
      density_scale: ``sigma_t = density_scale * density`` (per unit length).
      density_max: upper bound of ``density`` (valid domain); the majorant is
        ``density_scale * density_max``.
      n_track, n_shadow: caps on ratio-tracking points per camera / shadow ray.
      n_scatter: in-scattering distances per camera ray.
      truncation_probability: bound on the probability that a process on the
        longest chord needs more points than its cap.

    Build it with :func:`make_scene`, which derives the camera frames and the caps.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> scene = vol.make_scene(resolution=4, n_views=2)
        >>> scene.origins.shape, scene.n_views, scene.majorant
        ((2, 3), 2, 4.0)
    """

    resolution: int
    origins: np.ndarray
    forward: np.ndarray
    right: np.ndarray
    up: np.ndarray
    tan_half_fov: float
    sun_direction: np.ndarray
    sun_radiance: np.ndarray
    sky_zenith: np.ndarray
    sky_horizon: np.ndarray
    ground: np.ndarray
    density_scale: float
    density_max: float
    n_track: int
    n_shadow: int
    n_scatter: int
    truncation_probability: float

    @property
    def n_views(self) -> int:
        return int(self.origins.shape[0])

    @property
    def majorant(self) -> float:
        """Rate ``mu`` of the ratio-tracking Poisson processes (per unit length)."""
        return float(self.density_scale * self.density_max)


def _poisson_cap(mean: float, tail: float) -> int:
    """Smallest k with P(Poisson(mean) > k) <= tail."""
    from scipy import stats

    return int(stats.poisson.isf(tail, mean))


def camera_directions(n_views: int) -> np.ndarray:
    """``(n_views, 3)`` unit vectors on a Fibonacci sphere (deterministic, near-uniform).

    Args:
      n_views: the number of directions (>= 1).

    Returns:
      ``(n_views, 3)`` float64 unit vectors.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> vol.camera_directions(4).shape
        (4, 3)
    """
    i = np.arange(n_views, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n_views
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = i * _GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def make_scene(
    resolution: int = 32,
    n_views: int = 64,
    *,
    camera_distance: float = 2.2,
    density_scale: float = 4.0,
    density_max: float = 1.0,
    n_scatter: int = 2,
    truncation_probability: float = 1e-7,
    sun_direction=(0.45, -0.35, 0.82),
    sun_radiance=(2.2, 2.0, 1.8),
    sky_zenith=(0.25, 0.40, 0.75),
    sky_horizon=(0.75, 0.80, 0.85),
    ground=(0.30, 0.25, 0.20),
) -> VolumeScene:
    """Builds the scene: ``n_views`` cameras around the unit cube, a sun and a sky.

    Args:
      resolution: image side in pixels (e.g. 32 - 64 on a CPU).
      n_views: number of cameras (the paper uses 64).
      camera_distance: distance of the cameras from the cube's centre (> sqrt(3)/2).
      density_scale: extinction per unit length at ``density = 1``.
      density_max: the valid domain's upper bound of ``density``.
      n_scatter: in-scattering samples per camera ray.
      truncation_probability: sets the ratio-tracking caps (see module docstring).
      sun_direction: towards the sun; normalised here. Its components must be non-zero.
      sun_radiance, sky_zenith, sky_horizon, ground: RGB radiances.

    Returns:
      A :class:`VolumeScene` (hashable by identity: build it once and reuse it, since
      every new scene compiles the renderer anew).

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> scene = vol.make_scene(resolution=4, n_views=2)
        >>> scene.resolution, scene.n_views
        (4, 2)
    """
    for name, v in (("resolution", resolution), ("n_views", n_views), ("n_scatter", n_scatter)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"{name} must be a positive int, got {v!r}")
    if not camera_distance > math.sqrt(3.0) / 2.0:
        raise ValueError(
            f"camera_distance must exceed sqrt(3)/2 (outside the cube), got {camera_distance}"
        )
    if not (density_scale > 0 and density_max > 0):
        raise ValueError(
            f"density_scale and density_max must be > 0, got {density_scale}, {density_max}"
        )
    if not 0 < truncation_probability < 1:
        raise ValueError(f"truncation_probability must be in (0, 1), got {truncation_probability}")
    sun = np.asarray(sun_direction, np.float64)
    if sun.shape != (3,) or np.any(sun == 0):
        raise ValueError(
            f"sun_direction must be a 3-vector with non-zero components, got {sun_direction!r}"
        )
    sun = sun / np.linalg.norm(sun)

    d = camera_directions(n_views)
    origins = 0.5 + camera_distance * d
    forward = -d
    world_up = np.where(np.abs(d[:, 2:3]) > 0.99, [[0.0, 1.0, 0.0]], [[0.0, 0.0, 1.0]])
    right = np.cross(forward, world_up)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    up = np.cross(right, forward)
    # The cube's bounding sphere (radius sqrt(3)/2) just fits in the image.
    tan_half_fov = math.tan(math.asin(math.sqrt(3.0) / 2.0 / camera_distance))

    majorant = density_scale * density_max
    cap = _poisson_cap(majorant * math.sqrt(3.0), truncation_probability)
    f32 = lambda a: np.asarray(a, np.float32)
    return VolumeScene(
        resolution=int(resolution),
        origins=f32(origins),
        forward=f32(forward),
        right=f32(right),
        up=f32(up),
        tan_half_fov=float(tan_half_fov),
        sun_direction=f32(sun),
        sun_radiance=f32(sun_radiance),
        sky_zenith=f32(sky_zenith),
        sky_horizon=f32(sky_horizon),
        ground=f32(ground),
        density_scale=float(density_scale),
        density_max=float(density_max),
        n_track=cap,
        n_shadow=cap,
        n_scatter=int(n_scatter),
        truncation_probability=float(truncation_probability),
    )


# ------------------------------------------------------------------ volumes


def _voxel_centres(shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    axes = [(np.arange(n, dtype=np.float64) + 0.5) / n for n in shape]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    return x, y, z


# Plume: (centre x, y, z, radius, amplitude) of Gaussian blobs rising and bending in z.
_BLOBS = (
    (0.50, 0.50, 0.22, 0.16, 1.00),
    (0.46, 0.54, 0.38, 0.14, 0.90),
    (0.40, 0.58, 0.52, 0.13, 0.85),
    (0.36, 0.55, 0.66, 0.12, 0.80),
    (0.40, 0.46, 0.78, 0.11, 0.75),
    (0.62, 0.38, 0.30, 0.09, 0.70),
    (0.30, 0.68, 0.72, 0.08, 0.60),
)
# Turbulence: (frequency vector in cycles per unit, phase, amplitude), a few octaves.
_WAVES = (
    ((2.0, 1.0, 3.0), 0.3, 0.50),
    ((-3.0, 2.0, 1.0), 1.7, 0.45),
    ((1.0, -4.0, 2.0), 4.1, 0.35),
    ((5.0, 3.0, -2.0), 2.6, 0.25),
    ((-4.0, -6.0, 3.0), 0.9, 0.20),
    ((7.0, -2.0, 6.0), 5.3, 0.15),
    ((-9.0, 5.0, 8.0), 3.4, 0.10),
)
# Albedo palette (RGB in [0, 1]) of the three-colour checker.
_PALETTE = np.array([[0.90, 0.55, 0.15], [0.15, 0.65, 0.80], [0.85, 0.85, 0.80]])


def reference_volume(size: int = 64, *, checker_cells: int = 4) -> dict[str, np.ndarray]:
    """The embedded target: ``{"density": (n, n, n, 1), "albedo": (n, n, n, 3)}``, float32.

    Deterministic and analytic (no random generator, no downloads), so every
    resolution samples the same continuous field:

    * density: ``sum_k a_k exp(-|x - c_k|^2 / 2 r_k^2) * (1 + 0.6 turb(x))``, with
      ``turb`` a fixed sum of sines, passed through a steep soft threshold into
      ``[0, 0.9]``: a smoke plume with wispy, fairly sharp boundaries.
    * albedo: a three-colour 3-D checker of ``checker_cells`` cells per axis
      (``(i + j + k) mod 3`` of the cell indices): sharp edges. Finer checkers
      (8 cells) average out along camera rays through the semi-transparent
      medium and are not recoverable from 32-pixel images.

    Args:
      size: the grid's side ``n`` (>= 2, default 64).
      checker_cells: checker cells per axis of the albedo (default 4).

    Returns:
      ``{"density": (n, n, n, 1), "albedo": (n, n, n, 3)}``, float32, density in
      ``[0, 0.9]``, albedo in ``[0, 1]``.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> target = vol.reference_volume(8)
        >>> target["density"].shape, target["albedo"].shape
        ((8, 8, 8, 1), (8, 8, 8, 3))
    """
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 2:
        raise ValueError(f"size must be an int >= 2, got {size!r}")
    if (
        isinstance(checker_cells, bool)
        or not isinstance(checker_cells, (int, np.integer))
        or checker_cells < 1
    ):
        raise ValueError(f"checker_cells must be a positive int, got {checker_cells!r}")
    x, y, z = _voxel_centres((size,) * 3)
    base = np.zeros_like(x)
    for cx, cy, cz, r, a in _BLOBS:
        base += a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / (2 * r * r))
    turb = np.zeros_like(x)
    for (fx, fy, fz), phase, amp in _WAVES:
        turb += amp * np.sin(2 * np.pi * (fx * x + fy * y + fz * z) + phase)
    raw = base * (1.0 + 0.6 * turb)
    # Steep logistic threshold: empty space outside, a dense core inside.
    density = 0.9 / (1.0 + np.exp(-(raw - 0.45) * 14.0))
    density = np.where(density < 0.02, 0.0, density)
    cells = [np.floor(c * checker_cells).astype(np.int64) for c in (x, y, z)]
    albedo = _PALETTE[(cells[0] + cells[1] + cells[2]) % 3]
    return {"density": density[..., None].astype(np.float32), "albedo": albedo.astype(np.float32)}


def initial_volume(
    size: int = 64, *, density: float = 0.05, albedo: float = 0.5
) -> dict[str, np.ndarray]:
    """A constant starting volume of the same structure as :func:`reference_volume`.

    Args:
      size: the grid's side ``n`` (>= 2, default 64).
      density: the constant density (default 0.05).
      albedo: the constant albedo of every RGB channel (default 0.5).

    Returns:
      ``{"density": (n, n, n, 1), "albedo": (n, n, n, 3)}``, float32.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> {k: v.shape for k, v in vol.initial_volume(8).items()}
        {'density': (8, 8, 8, 1), 'albedo': (8, 8, 8, 3)}
    """
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 2:
        raise ValueError(f"size must be an int >= 2, got {size!r}")
    return {
        "density": np.full((size,) * 3 + (1,), density, np.float32),
        "albedo": np.full((size,) * 3 + (3,), albedo, np.float32),
    }


def project(params: Params, scene: VolumeScene | None = None, *, density_max: float | None = None):
    """Clips the parameters to the valid domain: ``0 <= density <= density_max``,
    ``0 <= albedo <= 1``.

    Args:
      params: ``{"density": (D, H, W, 1), "albedo": (D, H, W, 3)}``.
      scene: its ``density_max`` is the bound when ``density_max`` is not given.
      density_max: the density's upper bound (default: the scene's, else 1).

    Returns:
      The clipped parameters (same structure and shapes).

    Raises:
      TypeError, ValueError: ``params`` is not such a dict of those shapes.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> p = vol.project({"density": jnp.full((4, 4, 4, 1), 2.0),
        ...                  "albedo": jnp.full((4, 4, 4, 3), -1.0)}, density_max=1.0)
        >>> float(p["density"].max()), float(p["albedo"].min())
        (1.0, 0.0)
    """
    if density_max is None:
        density_max = 1.0 if scene is None else scene.density_max
    _check_params(params)
    return {
        "density": jnp.clip(params["density"], 0.0, density_max),
        "albedo": jnp.clip(params["albedo"], 0.0, 1.0),
    }


def _check_params(params) -> None:
    if not isinstance(params, Mapping) or set(params) != {"density", "albedo"}:
        raise TypeError(
            "params must be a dict with exactly the keys 'density' and 'albedo', got "
            f"{type(params).__name__} with keys "
            f"{sorted(params) if isinstance(params, Mapping) else '-'}"
        )
    d, a = np.shape(params["density"]), np.shape(params["albedo"])
    if len(d) != 4 or d[-1] != 1:
        raise ValueError(f"params['density'] must have shape (D, H, W, 1), got {d}")
    if a != d[:3] + (3,):
        raise ValueError(
            f"params['albedo'] must have shape {d[:3] + (3,)} (the density's grid, RGB), got {a}"
        )


def param_errors(params: Params, target: Params) -> dict[str, jax.Array]:
    """Parameter-space errors against the target volume.

    * ``density_error``: mean absolute voxel error of ``density``.
    * ``albedo_error``: mean absolute albedo error (over RGB), weighted by the
      target density: albedo is unobservable (and irrelevant) where there is no medium.
    * ``param_error``: the mean of the two (both are in the same [0, 1] units).

    Args:
      params: ``{"density": (D, H, W, 1), "albedo": (D, H, W, 3)}``.
      target: the same structure and shapes (e.g. :func:`reference_volume`).

    Returns:
      ``{"density_error", "albedo_error", "param_error"}``, scalars.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> errors = vol.param_errors(vol.initial_volume(8), vol.reference_volume(8))
        >>> sorted(errors), round(float(errors["param_error"]), 4)
        (['albedo_error', 'density_error', 'param_error'], 0.2175)
    """
    d = jnp.mean(jnp.abs(params["density"] - target["density"]))
    w = target["density"][..., 0]
    a = jnp.sum(w * jnp.mean(jnp.abs(params["albedo"] - target["albedo"]), axis=-1)) / jnp.sum(w)
    return {"density_error": d, "albedo_error": a, "param_error": 0.5 * (d + a)}


# ---------------------------------------------------------------- estimator


def _background(scene: VolumeScene, d: jax.Array) -> jax.Array:
    """Sky above the horizon (zenith..horizon by elevation), ground below."""
    z = d[..., 2:3]
    sky = scene.sky_horizon + (scene.sky_zenith - scene.sky_horizon) * jnp.sqrt(
        jnp.clip(z, 0.0, 1.0)
    )
    return jnp.where(z >= 0, sky, scene.ground)


def _radiance(params: Params, scene: VolumeScene, key, o: jax.Array, d: jax.Array) -> jax.Array:
    """Single-sample radiance estimate along rays o + t d, o, d: (R, 3) -> (R, 3).

    Tracking arrays are point-major, (K, R) and (Ks, M, R), so the prefix products
    scan over the leading axis.
    """
    density = params["density"]
    grid4 = jnp.concatenate([density, params["albedo"]], axis=-1)
    mu = scene.majorant
    scale = scene.density_scale
    n_rays = o.shape[0]
    m, k, ks = scene.n_scatter, scene.n_track, scene.n_shadow
    # One draw for all of a ray's random numbers (fewer RNG kernels to compile):
    # K camera gaps, M scattering offsets, Ks x M shadow gaps.
    u = jax.random.uniform(key, (k + m * (1 + ks), n_rays))
    u_sc = u[k : k + m]  # (M, R)
    u_sh = u[k + m :].reshape(ks, m, n_rays)

    t0, length = sampling.cube_interval(o, d)
    entry = o + t0[:, None] * d

    # Ratio tracking along the camera ray: points of a rate-mu Poisson process.
    tc = jnp.cumsum(-jnp.log1p(-u[:k]), axis=0) / mu  # (K, R) sorted
    sig = scale * sampling.trilinear(density, entry + tc[..., None] * d)[..., 0]
    factor = jnp.where(tc < length, 1.0 - sig / mu, 1.0)
    prefix = sampling.prefix_products(factor)  # (K + 1, R)
    t_end = prefix[-1]

    # In-scattering at stratified distances, each with a shadow ray to the sun.
    ts = (jnp.arange(m)[:, None] + u_sc) * (length / m)  # (M, R)
    # Points are sorted, so T_hat(0, t_m) is the prefix product over the points before t_m
    # (a one-hot sum: its reverse mode is elementwise, unlike take_along_axis' scatter).
    before = jnp.sum(tc[:, None, :] < ts, axis=0)  # (M, R)
    pick = jnp.arange(k + 1)[:, None, None] == before
    t_cam = jnp.sum(jnp.where(pick, prefix[:, None, :], 0.0), axis=0)  # (M, R)
    xs = jnp.clip(entry + ts[..., None] * d, 0.0, 1.0)  # (M, R, 3)
    local = sampling.trilinear(grid4, xs)
    sig_s = scale * local[..., :1] * local[..., 1:]  # (M, R, 3)
    sun = jnp.asarray(scene.sun_direction)
    exit_len = sampling.exit_distance(xs, sun)  # (M, R)
    tsh = jnp.cumsum(-jnp.log1p(-u_sh), axis=0) / mu  # (Ks, M, R)
    sig_sh = scale * sampling.trilinear(density, xs + tsh[..., None] * sun)[..., 0]
    t_sun = sampling.prefix_products(jnp.where(tsh < exit_len, 1.0 - sig_sh / mu, 1.0))[-1]
    inscatter = (length / m)[:, None] * jnp.sum((t_cam * t_sun)[..., None] * sig_s, axis=0)
    return t_end[:, None] * _background(scene, d) + inscatter * jnp.asarray(scene.sun_radiance)


def _camera_rays(scene: VolumeScene, views: jax.Array, jitter: jax.Array | None):
    """Rays of the given views: origins, directions (V, H, W, S, 3); jitter (V, H, W, S, 2)
    or None."""
    n = scene.resolution
    pix = jnp.arange(n, dtype=jnp.float32)
    if jitter is None:
        jx = jy = jnp.full((1, 1, 1, 1), 0.5)
    else:
        jx, jy = jitter[..., 0], jitter[..., 1]
    sx = ((pix[None, None, :, None] + jx) / n * 2.0 - 1.0) * scene.tan_half_fov  # (V, H, W, S)
    sy = (1.0 - (pix[None, :, None, None] + jy) / n * 2.0) * scene.tan_half_fov
    fw = jnp.asarray(scene.forward)[views][:, None, None, None, :]
    rt = jnp.asarray(scene.right)[views][:, None, None, None, :]
    up = jnp.asarray(scene.up)[views][:, None, None, None, :]
    d = fw + sx[..., None] * rt + sy[..., None] * up
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    o = jnp.broadcast_to(jnp.asarray(scene.origins)[views][:, None, None, None, :], d.shape)
    return o, d


def _check_views(scene: VolumeScene, views) -> jax.Array:
    views = jnp.asarray(views)
    if views.ndim != 1 or not jnp.issubdtype(views.dtype, jnp.integer):
        raise ValueError(
            f"views must be a 1-D integer array of camera indices, got shape "
            f"{views.shape} and dtype {views.dtype}"
        )
    return views


@functools.partial(jax.jit, static_argnames=("scene", "spp", "jitter"))
def render(
    params: Params, scene: VolumeScene, key: jax.Array, views, spp: int = 1, jitter: bool = True
) -> jax.Array:
    """Monte Carlo image estimate ``(len(views), resolution, resolution, 3)``: the mean of
    ``spp`` samples.

    Each sample is one jittered ray through the pixel with the estimator of the
    module docstring; the same ``key`` gives the same image. ``jitter=False``
    shoots every sample through the pixel centre (the pixel's radiance at its
    centre instead of its box-filtered radiance; used by the tests). Jitted, with
    ``scene``, ``spp`` and ``jitter`` static.

    Args:
      params: ``{"density": (D, H, W, 1), "albedo": (D, H, W, 3)}``.
      scene: the :class:`VolumeScene`.
      key: a PRNG key.
      views: int array of camera indices into the scene's views.
      spp: samples per pixel (>= 1, default 1).
      jitter: jitter each sample within its pixel (default True).

    Returns:
      ``(len(views), resolution, resolution, 3)`` float32 RGB.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> scene = vol.make_scene(resolution=4, n_views=2)   # 4x4 images (the paper: 64 views)
        >>> params = vol.initial_volume(8)                     # an 8^3 grid
        >>> vol.render(params, scene, jax.random.key(0), jnp.array([0, 1])).shape
        (2, 4, 4, 3)
    """
    _check_params(params)
    views = _check_views(scene, views)
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise ValueError(f"spp must be a positive int, got {spp!r}")
    n = scene.resolution
    k_pix, k_rad = jax.random.split(key)
    shape = (views.shape[0], n, n, spp)
    jit_xy = jax.random.uniform(k_pix, shape + (2,)) if jitter else None
    o, d = _camera_rays(scene, views, jit_xy)
    d = jnp.broadcast_to(d, shape + (3,))
    o = jnp.broadcast_to(o, shape + (3,))
    rad = _radiance(params, scene, k_rad, o.reshape(-1, 3), d.reshape(-1, 3))
    return jnp.mean(rad.reshape(shape + (3,)), axis=3)


@functools.partial(jax.jit, static_argnames=("scene", "spp", "batch", "jitter"))
def render_mean(
    params: Params,
    scene: VolumeScene,
    key: jax.Array,
    views,
    spp: int = 256,
    batch: int = 16,
    jitter: bool = True,
) -> jax.Array:
    """A high-sample estimate: ``spp`` samples per pixel, rendered ``batch`` at a time
    (bounded memory).

    ``spp`` is rounded up to a multiple of ``batch``.

    Args:
      params: ``{"density": (D, H, W, 1), "albedo": (D, H, W, 3)}``.
      scene: the :class:`VolumeScene`.
      key: a PRNG key.
      views: int array of camera indices.
      spp: samples per pixel (default 256).
      batch: samples rendered at a time (default 16).
      jitter: as in :func:`render`.

    Returns:
      ``(len(views), resolution, resolution, 3)`` float32 RGB.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> scene = vol.make_scene(resolution=4, n_views=2)   # 4x4 images (the paper: 64 views)
        >>> params = vol.initial_volume(8)                     # an 8^3 grid
        >>> vol.render_mean(params, scene, jax.random.key(0), jnp.array([0]), spp=4, batch=2).shape
        (1, 4, 4, 3)
    """
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch must be a positive int, got {batch!r}")
    chunks = -(-spp // batch)

    def body(acc, k):
        return acc + render(params, scene, k, views, spp=batch, jitter=jitter), None

    n = scene.resolution
    acc0 = jnp.zeros((jnp.shape(views)[0], n, n, 3), jnp.float32)
    acc, _ = jax.lax.scan(body, acc0, jax.random.split(key, chunks))
    return acc / chunks


@functools.partial(jax.jit, static_argnames=("scene", "spp", "spp_grad", "jitter"))
def loss_and_grad(
    params: Params,
    scene: VolumeScene,
    key: jax.Array,
    views,
    targets: jax.Array,
    spp: int = 1,
    spp_grad: int = 1,
    jitter: bool = True,
):
    """Noisy ``mean((I - I_ref)^2)`` over the given views, and an unbiased estimate of its gradient.

    The primal ``I_a`` uses ``spp`` samples from one half of ``key``; the
    gradient is ``J_b^T (2 (I_a - I_ref) / N)`` with ``J_b`` the derivative of an
    independent ``spp_grad``-sample estimate ``I_b`` (the other half of ``key``).
    Since ``I_a`` and ``J_b`` are independent, the expectation is the exact
    gradient of ``mean((E[I] - I_ref)^2)``. The returned loss is that of ``I_a``
    (it includes the estimator's variance).

    Args:
      params: ``{"density": (D, H, W, 1), "albedo": (D, H, W, 3)}``.
      scene: the :class:`VolumeScene`.
      key: a PRNG key (split into the primal's and the gradient's).
      views: int array of camera indices.
      targets: ``(len(views), resolution, resolution, 3)`` reference images.
      spp: samples per pixel of the primal ``I_a`` (default 1).
      spp_grad: samples per pixel of ``I_b``, whose derivative is used (default 1).
      jitter: as in :func:`render`.

    Returns:
      ``(loss, grads, image)``: grads has the structure of ``params``; image is ``I_a``.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import volume as vol
        >>> scene = vol.make_scene(resolution=4, n_views=2)   # 4x4 images (the paper: 64 views)
        >>> params = vol.initial_volume(8)                     # an 8^3 grid
        >>> targets = jnp.zeros((2, 4, 4, 3))
        >>> loss, grads, image = vol.loss_and_grad(params, scene, jax.random.key(0),
        ...                                        jnp.array([0, 1]), targets)
        >>> grads["density"].shape, grads["albedo"].shape, image.shape
        ((8, 8, 8, 1), (8, 8, 8, 3), (2, 4, 4, 3))
    """
    k_a, k_b = jax.random.split(key)
    image = render(params, scene, k_a, views, spp=spp, jitter=jitter)
    if targets.shape != image.shape:
        raise ValueError(
            f"targets must have shape {image.shape} (views, H, W, RGB), got {targets.shape}"
        )
    residual = image - targets
    cot = 2.0 * residual / residual.size
    _, vjp = jax.vjp(lambda p: render(p, scene, k_b, views, spp=spp_grad, jitter=jitter), params)
    (grads,) = vjp(cot)
    return jnp.mean(jnp.square(residual)), grads, image
