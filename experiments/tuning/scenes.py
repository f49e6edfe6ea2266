"""The problems of the tuning benchmark (:mod:`experiments.tuning`): grids recovered from noisy
gradients.

A :class:`Scene` is one inverse problem written as pure JAX functions, so that the
benchmark can compile one program that runs many optimisers, hyperparameters and
seeds at once:

* ``grad(data, params, key)``: an unbiased, noisy gradient of the scene's loss at
  ``params``; all randomness comes from ``key`` (iteration ``i`` of seed ``s`` uses
  ``fold_in(key(s), i)``, so every method sees the same noise at the same iteration);
  a ``grad`` with a ``step`` parameter also receives ``i`` (cameras taken in turn);
* ``project(data, params)``: the parameters clipped to the valid domain (after every step);
* ``error(data, params)``: the parameter error against the target (the benchmark's metric);
* ``data``: the arrays these functions read (passed to the compiled program as arguments,
  not baked into it as constants).

Scenes (:data:`SCENES`; ``quick`` is the test-suite size):

=====================  ==========================================================================
``texture``            toy glossy plane (:mod:`optax_bilateral.toy.texture`), roughness texture,
                       piecewise-smooth "camera" target, 1 spp / 1 spp gradients (paper Fig. 5)
``texture_noise``      the same with the i.i.d. high-frequency "noise" target (supplement Fig. 4:
                       spatial filtering is biased, Adam should win)
``texture_low_noise``  the camera target with 4 spp / 4 spp (16x less gradient variance than
                       1/1 near the optimum; Fig. 5's low-noise regime, where Adam catches up)
``volume``             toy participating medium (:mod:`optax_bilateral.toy.volume`), two leaves:
                       density (D, H, W, 1) and RGB albedo (D, H, W, 3), random views per step
``signal1d``           a 1-D piecewise-smooth signal (stored ``(N, 1)``) seen through a Gaussian
                       blur at a random 10% of samples per step, with fresh measurement noise
``deblur``             128x128 piecewise-constant unit-range image, Gaussian blur, each step's loss
                       on a random 5% pixel subset, 300 iterations (the problem of issue #17)
``deblur_x100``        ``deblur`` with the image (and so the parameters) in [0, 100]: the same
                       problem, so a scale-invariant method gives the same error; its error is
                       reported in the units of ``deblur`` (divided by 100)
=====================  ==========================================================================

:data:`RENDERED` holds the problems of issues #47 and #54, outside the default run:

=======================  ========================================================================
``mitsuba_close``        a Mitsuba 3 diffuse plane, 192^2 RGB albedo (``skimage.data.astronaut``),
``mitsuba_mid``          96^2 film, spp 1, seen at 0.5, 2 and 12 texels per pixel
``mitsuba_far``          (:mod:`experiments.tuning.camera_distance`; error at the resolution the
                         camera resolves)
``mitsuba_two_cameras``  the same plane from the close and the far camera in turn
``mitsuba_far_coffee``   ``mitsuba_far`` with another photograph (``skimage.data.coffee``)
``absorption_mc``        a 64^2 piecewise-constant absorption map with sharp edges in [0, 1],
                         1024 random rays per step, the unbiased gradient of the squared error of
                         ratio-tracking transmittance estimates (two independent estimates)
``absorption_edges``     the same from a 96^2 Shepp-Logan phantom (levels 0 to 1, edges 0.1 to 1
                         high), 4096 rays per step, 150 iterations: edges that stand out of the
                         noise
=======================  ========================================================================

:data:`HELD_OUT` holds ``signal1d`` at 256 and 4096 samples and ``deblur`` at 64x64 and 96x96
(the shapes scale with the image), and ``texture_mixed50`` / ``texture_mixed75`` (the camera
target with its right half / three quarters replaced by the noise target), outside the
default run: a rule fitted on the suite is checked on them (docs/auto_sigma.md).

Errors: ``texture*``: mean ``|alpha - alpha_target|`` over texels (roughness units);
``volume``: the mean of the density's mean absolute error and the target-density-weighted
mean absolute albedo error (:func:`optax_bilateral.toy.volume.param_errors`);
``signal1d``, ``deblur``: mean ``|x - x_target|``; ``deblur_x100``: that divided by 100.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from experiments.tuning import camera_distance
from experiments.tuning.problem import Scene, around

# ----------------------------------------------------------------------------- texture


def texture(
    quick: bool,
    target: str = "camera",
    spp: int = 1,
    spp_grad: int = 1,
    name: str = "texture",
    description: str | None = None,
    noise_fraction: float = 0.0,
) -> Scene:
    """The toy texture scene (:mod:`optax_bilateral.toy.texture`), seed 0, from a
    constant roughness of 0.1; ``noise_fraction`` of its columns (the right ones) take the
    ``"noise"`` target's values instead of ``target``'s."""
    from optax_bilateral.toy import texture as tex

    size, iterations = (32, 30) if quick else (64, 100)
    reference_spp = 64 if quick else 256
    target_np = np.array(tex.target_roughness(target, size, seed=0))  # a copy: edited below
    noisy = round(size * noise_fraction)
    if noisy:
        target_np[:, size - noisy :] = tex.target_roughness("noise", size, seed=0)[:, -noisy:]
    target_alpha = jnp.asarray(target_np)
    scene = tex.make_scene(size)
    data = {
        "scene": scene,
        "target": target_alpha,
        "reference": tex.render_reference(target_alpha, scene, reference_spp, seed=0),
    }

    def grad(data, alpha, key):
        def loss(a):
            return tex.loss_fn(tex.render(a, data["scene"], key, spp, spp_grad), data["reference"])

        return jax.grad(loss)(alpha)

    return Scene(
        name=name,
        description=description or f"toy texture {size}^2, {target} target, {spp}/{spp_grad} spp",
        init=jnp.full((size, size), 0.1, jnp.float32),
        spatial_axes=(0, 1),  # a one-channel image (the leaf rule leaves square 2-D to Adam)
        data=data,
        grad=grad,
        project=lambda data, a: jnp.clip(a, tex.ALPHA_MIN, tex.ALPHA_MAX),
        error=lambda data, a: jnp.mean(jnp.abs(a - data["target"])),
        iterations=iterations,
        learning_rates=around(0.02),
        log_guide=True,
        error_name="mean |alpha - alpha_target| (roughness)",
        config=dict(
            kind="texture",
            size=size,
            target=target,
            spp=spp,
            spp_grad=spp_grad,
            reference_spp=reference_spp,
            init_alpha=0.1,
            iterations=iterations,
            # Only where used, so the other texture scenes keep their cached grids' keys.
            **({"noise_fraction": noise_fraction} if noisy else {}),
        ),
    )


# ----------------------------------------------------------------------------- volume


def volume(quick: bool) -> Scene:
    """The toy volume (:mod:`optax_bilateral.toy.volume`): density and albedo leaves."""
    from optax_bilateral.toy import volume as vol

    if quick:
        cfg = dict(
            size=8,
            resolution=8,
            n_views=8,
            views_per_step=1,
            n_scatter=1,
            target_spp=16,
            iterations=20,
        )
    else:
        cfg = dict(
            size=16,
            resolution=12,
            n_views=32,
            views_per_step=1,
            n_scatter=1,
            target_spp=64,
            iterations=120,
        )
    scene = vol.make_scene(
        resolution=cfg["resolution"], n_views=cfg["n_views"], n_scatter=cfg["n_scatter"]
    )
    target = {k: jnp.asarray(v) for k, v in vol.reference_volume(cfg["size"]).items()}
    init = {k: jnp.asarray(v) for k, v in vol.initial_volume(cfg["size"]).items()}
    views = jnp.arange(scene.n_views)
    images = jnp.concatenate(
        [
            vol.render_mean(
                target,
                scene,
                jax.random.fold_in(jax.random.key(12345), i),
                views[i : i + 4],
                spp=cfg["target_spp"],
            )
            for i in range(0, scene.n_views, 4)
        ]
    )
    b = cfg["views_per_step"]

    def grad(data, params, key):
        k_views, k_render = jax.random.split(key)
        v = jax.random.choice(k_views, scene.n_views, (b,), replace=False)
        return vol.loss_and_grad(params, scene, k_render, v, data["images"][v])[1]

    return Scene(
        name="volume",
        description=(
            f"toy volume {cfg['size']}^3 (density + RGB albedo), {b} of "
            f"{cfg['n_views']} views of {cfg['resolution']}^2 px per step, 1/1 spp"
        ),
        init=init,
        data={"images": images, "target": target},
        grad=grad,
        project=lambda data, p: vol.project(p, scene),
        error=lambda data, p: vol.param_errors(p, data["target"])["param_error"],
        iterations=cfg["iterations"],
        learning_rates=around(0.05),
        error_name="(density MAE + density-weighted albedo MAE) / 2",
        config=dict(kind="volume", **cfg),
    )


# ----------------------------------------------------------------------------- 1-D signal


def piecewise_smooth_signal(n: int) -> np.ndarray:
    """A unit-range 1-D test signal: a ramp, plateaus, an oscillation and a parabola, with jumps."""
    t = (np.arange(n) + 0.5) / n
    x = np.select(
        [t < 0.2, t < 0.35, t < 0.6, t < 0.7, t < 0.9],
        [
            0.2 + 3.0 * t,
            np.full_like(t, 0.85),
            0.5 + 0.3 * np.sin(2 * np.pi * 6 * (t - 0.35)),
            np.full_like(t, 0.1),
            0.95 - 12.0 * (t - 0.8) ** 2,
        ],
        0.4,
    )
    return x.astype(np.float32)


def gaussian_kernel(sigma: float) -> np.ndarray:
    """Normalised 1-D Gaussian taps of radius ``ceil(3 sigma)``."""
    r = math.ceil(3 * sigma)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def _blur_axis(x, k, axis):
    """'same'-size convolution along ``axis`` with zero padding (a symmetric kernel: A = A^T).

    A sum of shifted slices: XLA fuses it into one loop (its CPU convolution of many short
    rows was ~20x slower here).
    """
    r = (k.shape[0] - 1) // 2
    n = x.shape[axis]
    pad = [(0, 0)] * x.ndim
    pad[axis] = (r, r)
    xp = jnp.pad(x, pad)
    return sum(k[j] * jax.lax.slice_in_dim(xp, j, j + n, axis=axis) for j in range(k.shape[0]))


def _masked_lsq_grad(blur, x, y, m):
    """Gradient of ``sum(m (A x - y)^2) / sum(m)`` for a symmetric ``A`` (``blur``):
    ``2 A (m (A x - y)) / sum(m)``, written out (autodiff's transposed slices were ~10x slower)."""
    return 2.0 * blur(jnp.where(m, blur(x) - y, 0.0)) / jnp.maximum(jnp.sum(m), 1)


def signal1d(quick: bool, n: int | None = None, name: str = "signal1d") -> Scene:
    """1-D deconvolution from random 10% subsets with fresh measurement noise each step;
    ``n`` samples (default 1024, quick 256)."""
    default, iterations = (256, 40) if quick else (1024, 300)
    n = default if n is None else n
    blur_sigma, fraction, noise = 2.0, 0.1, 0.1
    k = jnp.asarray(gaussian_kernel(blur_sigma))
    x_t = jnp.asarray(piecewise_smooth_signal(n))[:, None]
    y = _blur_axis(x_t, k, 0)

    def grad(data, x, key):
        k_mask, k_noise = jax.random.split(key)
        m = jax.random.uniform(k_mask, x.shape) < fraction
        obs = data["y"] + noise * jax.random.normal(k_noise, x.shape)
        return _masked_lsq_grad(lambda v: _blur_axis(v, data["k"], 0), x, obs, m)

    return Scene(
        name=name,
        description=(
            f"1-D piecewise-smooth signal, {n} samples (N, 1), blur sigma {blur_sigma:g}, "
            f"{fraction:.0%} samples per step, noise {noise:g}"
        ),
        init=jnp.full((n, 1), 0.5, jnp.float32),
        data={"y": y, "k": k, "target": x_t},
        grad=grad,
        project=lambda data, x: jnp.clip(x, 0.0, 1.0),
        error=lambda data, x: jnp.mean(jnp.abs(x - data["target"])),
        iterations=iterations,
        learning_rates=around(0.02),
        spatial_axes=(0,),
        config=dict(
            kind="signal1d",
            n=n,
            blur_sigma=blur_sigma,
            fraction=fraction,
            noise=noise,
            iterations=iterations,
            init=0.5,
            spatial_axes=[0],
        ),
    )


# ----------------------------------------------------------------------------- deblurring


def shapes_image(size: int, seed: int = 0, n_shapes: int = 12) -> np.ndarray:
    """A piecewise-constant unit-range image: rectangles and discs of random grey levels."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    img = np.full((size, size), rng.uniform(0.0, 1.0))
    for _ in range(n_shapes):
        value = rng.uniform(0.0, 1.0)
        cy, cx = rng.uniform(0.1, 0.9, 2) * size
        if rng.uniform() < 0.5:
            hy, hx = rng.uniform(0.05, 0.2, 2) * size
            inside = (np.abs(yy - cy) < hy) & (np.abs(xx - cx) < hx)
        else:
            inside = (yy - cy) ** 2 + (xx - cx) ** 2 < (rng.uniform(0.05, 0.18) * size) ** 2
        img[inside] = value
    img = (img - img.min()) / (img.max() - img.min())
    return img.astype(np.float32)


def _clip_to_scale(data, x):
    return jnp.clip(x, 0.0, data["scale"])


def _scaled_error(data, x):
    return jnp.mean(jnp.abs(x - data["target"])) / data["scale"]


def deblur(
    quick: bool, scale: float = 1.0, size: int | None = None, name: str | None = None
) -> Scene:
    """Deblurring from random 5% pixel subsets (issue #17's problem); ``scale`` multiplies the
    image; ``size`` pixels a side (default 128, quick 32; the shapes scale with it); ``name``
    defaults to ``deblur`` or ``deblur_x<scale>``."""
    default, iterations = (32, 40) if quick else (128, 300)
    size = default if size is None else size
    blur_sigma, fraction, noise = 1.5, 0.05, 0.02
    k = jnp.asarray(gaussian_kernel(blur_sigma))
    x_t = jnp.asarray(shapes_image(size)) * scale
    blur = lambda x, k: _blur_axis(_blur_axis(x, k, 0), k, 1)
    # The blurred image with fixed (not per-step) measurement noise: the data of the problem.
    y = blur(x_t, k) + scale * noise * jax.random.normal(jax.random.key(99), x_t.shape)

    def grad(data, x, key):
        m = jax.random.uniform(key, x.shape) < fraction
        return _masked_lsq_grad(lambda v: blur(v, data["k"]), x, data["y"], m)

    if name is None:
        name = "deblur" if scale == 1.0 else f"deblur_x{scale:g}"
    return Scene(
        name=name,
        description=(
            f"deblurring {size}^2 in [0, {scale:g}], blur sigma {blur_sigma:g}, "
            f"{fraction:.0%} pixels per step, noise {noise:g}"
        ),
        init=jnp.full((size, size), 0.5 * scale, jnp.float32),
        spatial_axes=(0, 1),  # a one-channel image (the leaf rule leaves square 2-D to Adam)
        # The scale is data, not a constant: both scales then share compiled programs.
        data={"y": y, "k": k, "target": x_t, "scale": jnp.float32(scale)},
        grad=grad,
        project=_clip_to_scale,
        error=_scaled_error,
        iterations=iterations,
        learning_rates=tuple(scale * lr for lr in around(0.02)),
        scale=scale,
        error_name="mean |x - x_target|" + ("" if scale == 1.0 else f" / {scale:g}"),
        config=dict(
            kind="deblur",
            size=size,
            blur_sigma=blur_sigma,
            fraction=fraction,
            noise=noise,
            scale=scale,
            iterations=iterations,
            init=0.5,
        ),
    )


# ----------------------------------------------------------------------------- absorption


def ray_points(rays, t):
    """Points ``(R, K, 2)`` at abscissae ``t`` ``(R, K)`` of rays ``(R, 2)`` (angle, offset): the
    line through the unit square's centre at offset ``offset`` along its normal, in (x, y)."""
    theta, offset = rays[:, 0:1], rays[:, 1:2]
    x = 0.5 - offset * jnp.sin(theta) + t * jnp.cos(theta)
    y = 0.5 + offset * jnp.cos(theta) + t * jnp.sin(theta)
    return jnp.stack([x, y], -1)


def lookup(grid, points):
    """Nearest-texel values of ``grid`` (N, N) over the unit square at ``points`` (..., 2);
    0 outside the square (a piecewise-constant field)."""
    n = grid.shape[0]
    ij = jnp.floor(points[..., ::-1] * n).astype(jnp.int32)  # (row, column) = (y, x)
    inside = jnp.all((ij >= 0) & (ij < n), axis=-1)
    ij = jnp.clip(ij, 0, n - 1)
    return jnp.where(inside, grid[ij[..., 0], ij[..., 1]], 0.0)


def transmittance_mc(sigma, rays, key, density: float, length: float, max_points: int):
    """Ratio-tracking estimates ``(R,)`` of ``exp(-density * integral of sigma)`` along the rays'
    chords of ``length`` (centred on the square's centre).

    With the majorant ``density`` (``sigma`` in [0, 1]): ``n ~ Poisson(density * length)``
    points uniform on the chord, ``prod_k (1 - sigma(x_k))``, whose mean is the transmittance
    (Novak et al. 2014) and whose derivative in ``sigma`` is unbiased too (the points do not
    depend on ``sigma``). ``n`` is cut at ``max_points`` (a Poisson tail below 1e-10 here).
    """
    k_n, k_t = jax.random.split(key)
    r = rays.shape[0]
    n = _poisson(k_n, density * length, max_points, (r, 1))
    t = (jax.random.uniform(k_t, (r, max_points)) - 0.5) * length
    used = jnp.arange(max_points)[None, :] < n
    factors = jnp.where(used, 1.0 - lookup(sigma, ray_points(rays, t)), 1.0)
    return jnp.prod(factors, axis=-1)


def _poisson(key, mean: float, most: int, shape):
    """Poisson(``mean``) counts cut at ``most``, by inverting the CDF (one comparison per
    count: ``jax.random.poisson``'s loop took seconds to compile)."""
    k = np.arange(most)
    cdf = np.cumsum(np.exp(k * math.log(mean) - mean - np.array([math.lgamma(i + 1) for i in k])))
    u = jax.random.uniform(key, shape)
    return jnp.sum(u[..., None] > jnp.asarray(cdf, jnp.float32), axis=-1)


def transmittance_quadrature(sigma, rays, density: float, length: float, points: int):
    """``exp(-density * integral of sigma)`` by the midpoint rule with ``points`` points a chord."""
    t = ((jnp.arange(points) + 0.5) / points - 0.5) * length
    values = lookup(sigma, ray_points(rays, jnp.broadcast_to(t, (rays.shape[0], points))))
    return jnp.exp(-density * length * jnp.mean(values, axis=-1))


def random_rays(key, count: int, reach: float):
    """``count`` rays (angle uniform in [0, pi), offset uniform in [-reach, reach])."""
    k_a, k_o = jax.random.split(key)
    theta = jax.random.uniform(k_a, (count,), maxval=jnp.pi)
    offset = jax.random.uniform(k_o, (count,), minval=-reach, maxval=reach)
    return jnp.stack([theta, offset], -1)


def absorption_grad(sigma, target_t, rays, key, density: float, length: float, max_points: int):
    """Unbiased gradient of ``mean_rays (T(sigma) - target_t)^2`` from two independent
    transmittance estimates: ``2 (T_a - target_t) dT_b / dsigma`` (one estimate in both
    factors would add the gradient of its variance)."""
    k_a, k_b = jax.random.split(key)
    estimate = lambda s, k: transmittance_mc(s, rays, k, density, length, max_points)
    t_a = estimate(sigma, k_a)
    _, vjp = jax.vjp(lambda s: estimate(s, k_b), sigma)
    return vjp(2.0 * (t_a - target_t) / rays.shape[0])[0]


def phantom(size: int) -> np.ndarray:
    """``skimage.data.shepp_logan_phantom`` at ``size`` x ``size`` (nearest-neighbour, so its
    edges stay sharp): levels 0, 0.1, 0.2, 0.3, 0.4 and 1 in [0, 1]."""
    from skimage import data, transform

    img = transform.resize(data.shepp_logan_phantom(), (size, size), order=0, anti_aliasing=False)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


#: The absorption maps: ``(target(size), size, iterations, rays per step)`` at the full size,
#: then the quick one. ``absorption_edges``' many rays make its edges stand out of the noise.
ABSORPTION = {
    "absorption_mc": (lambda n: shapes_image(n, seed=3), (64, 150, 1024), (16, 30, 64)),
    "absorption_edges": (phantom, (96, 150, 4096), (24, 30, 256)),
}


def absorption(quick: bool, name: str = "absorption_mc") -> Scene:
    """A piecewise-constant absorption map with sharp edges from Monte Carlo transmittances
    (:data:`ABSORPTION` names the maps)."""
    make_target, full, small = ABSORPTION[name]
    size, iterations, rays = small if quick else full
    cfg = dict(
        size=size,
        iterations=iterations,
        rays=rays,
        density=4.0,  # optical depth of a unit chord through sigma = 1 (the majorant)
        length=1.5,  # chords cover the square: its half-diagonal is 0.71
        max_points=32,  # P(Poisson(6) > 32) < 1e-10
        reference_points=8 * size,  # midpoint rule of the measured transmittances
        init=0.5,
    )
    if name != "absorption_mc":  # the map's name is part of the cache key (mc's key unchanged)
        cfg["target"] = name
    reach = 0.5 * math.sqrt(2.0)
    target = jnp.asarray(make_target(size))
    mc = dict(density=cfg["density"], length=cfg["length"])

    def grad(data, sigma, key):
        k_rays, k_mc = jax.random.split(key)
        r = random_rays(k_rays, rays, reach)
        measured = transmittance_quadrature(data["target"], r, points=cfg["reference_points"], **mc)
        return absorption_grad(sigma, measured, r, k_mc, max_points=cfg["max_points"], **mc)

    return Scene(
        name=name,
        description=(
            f"absorption {size}^2 (piecewise constant, sharp edges), {rays} random rays per step, "
            f"ratio-tracking transmittance, optical depth up to {cfg['density']:g} a unit chord"
        ),
        init=jnp.full((size, size), cfg["init"], jnp.float32),
        spatial_axes=(0, 1),  # a one-channel image (the leaf rule leaves square 2-D to Adam)
        data={"target": target},
        grad=grad,
        project=lambda data, s: jnp.clip(s, 0.0, 1.0),
        error=lambda data, s: jnp.mean(jnp.abs(s - data["target"])),
        iterations=iterations,
        # Wide: the best rates of Adam, the filter and the pyramid spread over 20x here.
        learning_rates=(0.0125, 0.025, 0.05, 0.1, 0.2),
        error_name="mean |sigma - sigma_target|",
        config=dict(kind="absorption_mc", **cfg),
    )


SCENES: dict[str, Callable[[bool], Scene]] = {
    "texture": lambda quick: texture(quick),
    "texture_noise": lambda quick: texture(quick, target="noise", name="texture_noise"),
    "texture_low_noise": lambda quick: texture(quick, spp=4, spp_grad=4, name="texture_low_noise"),
    "volume": volume,
    "signal1d": signal1d,
    "deblur": lambda quick: deblur(quick),
    "deblur_x100": lambda quick: deblur(quick, scale=100.0),
}


#: The suite's problems at other sizes, kept out of :data:`SCENES` (and so out of the default
#: run) to check rules fitted on the suite (``--only-scenes signal1d_n256,...``).
HELD_OUT: dict[str, Callable[[bool], Scene]] = {
    "signal1d_n256": lambda q: signal1d(q, n=64 if q else 256, name="signal1d_n256"),
    "signal1d_n4096": lambda q: signal1d(q, n=1024 if q else 4096, name="signal1d_n4096"),
    "deblur_n64": lambda q: deblur(q, size=16 if q else 64, name="deblur_n64"),
    "deblur_n96": lambda q: deblur(q, size=24 if q else 96, name="deblur_n96"),
    # The camera target with its right half / three quarters replaced by the noise target:
    # where the filter is right on part of a leaf and wrong on the rest.
    "texture_mixed50": lambda q: texture(q, noise_fraction=0.5, name="texture_mixed50"),
    "texture_mixed75": lambda q: texture(q, noise_fraction=0.75, name="texture_mixed75"),
}


def _camera_distance(
    cameras: tuple[str, ...], name: str, photo: str = "astronaut"
) -> Callable[[bool], Scene]:
    def make(quick: bool) -> Scene:
        return camera_distance.scene(quick, cameras, name, photo)

    return make


#: Problems whose gradients are a renderer's Monte Carlo estimates (issue #47): a Mitsuba 3
#: texture seen from three camera distances and from two cameras in turn
#: (:mod:`experiments.tuning.camera_distance`; Mitsuba required), and a sharp-edged absorption map
#: from ratio-tracking transmittances; outside the default run (``--only-scenes``).
RENDERED: dict[str, Callable[[bool], Scene]] = {
    "mitsuba_close": _camera_distance(("close",), "mitsuba_close"),
    "mitsuba_mid": _camera_distance(("mid",), "mitsuba_mid"),
    "mitsuba_far": _camera_distance(("far",), "mitsuba_far"),
    "mitsuba_two_cameras": _camera_distance(("close", "far"), "mitsuba_two_cameras"),
    "mitsuba_far_coffee": _camera_distance(("far",), "mitsuba_far_coffee", photo="coffee"),
    "absorption_mc": absorption,
    "absorption_edges": lambda quick: absorption(quick, "absorption_edges"),
}
ALL: dict[str, Callable[[bool], Scene]] = {**SCENES, **HELD_OUT, **RENDERED}


def make(name: str, quick: bool = False) -> Scene:
    """The scene ``name`` (one of :data:`SCENES`, :data:`HELD_OUT` or :data:`RENDERED`)."""
    if name not in ALL:
        raise ValueError(f"unknown scene {name!r}; choose from {sorted(ALL)}")
    return ALL[name](quick)
