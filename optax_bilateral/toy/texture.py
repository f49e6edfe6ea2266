"""Toy differentiable renderer: a glossy plane with a GGX roughness texture.

The scene of the paper's texture experiment (main paper Fig. 5), reduced to what
it needs. A flat plane ``z = 0`` spanning ``[-1, 1]^2`` carries a roughness
texture ``alpha`` (``H x W``, GGX's alpha, linear units). A distant pinhole camera
at ``camera_position`` looks at it; pixel ``(i, j)`` shows texel ``(i, j)`` (the
image is rendered in texture space, one primary ray through each texel centre).
The environment at infinity is a dim photograph on the sky, two small lamps and a
sun with a soft halo near the mirror direction. The sun is what makes pixels depend
strongly and non-linearly on roughness: a smooth texel shows a small, very bright
highlight, a rough one spreads it out (``I`` falls by ~40x from alpha 0.005 to 0.5),
and because every texel's mirror direction lies inside the sun's halo the pixel
value falls monotonically with roughness, so the texture can be recovered.

Pixel value (a perfect conductor, Fresnel = 1)::

    I(p) = \\int_{H^2} f(w_i, w_o; alpha_p) L(w_i) cos(theta_i) dw_i,
    f    = D(h; alpha) G1(w_i; alpha) G1(w_o; alpha) / (4 cos(theta_i) cos(theta_o))

with the GGX distribution ``D(h) = alpha^2 / (pi cos^4(theta_h) (alpha^2 + tan^2(theta_h))^2)``
and Smith's ``G1(w) = 2 cos(theta) / (cos(theta) + sqrt(alpha^2 + (1-alpha^2) cos^2(theta)))``.
``L = L_map + E p_sun``: the sun's radiance is ``E`` times its sampling density
``p_sun(w) = b / (2 pi (1 - c^2 + b^2 c^2)^{3/2})``, ``c = w . s`` (the gnomonic
projection of a 2-D Cauchy / Poisson kernel of width ``b`` around ``s``).

Estimator (unbiased for the value and for d/d alpha)
----------------------------------------------------
Each sample picks, from one uniform, GGX sampling of ``D(h) cos(theta_h)`` (with
probability ``1 - q``) or sun sampling (``q = alpha0 / (alpha0 + b/2)``), both at the
*detached* roughness ``alpha0 = stop_gradient(alpha)``; the weight is
``f(w_i; alpha) L(w_i) cos(theta_i) / [(1 - q) p_ggx(w_i; alpha0) + q p_sun(w_i)]``
(one-sample mixture importance sampling, the balance heuristic). The density is
held fixed while differentiating, so ``E[d weight / d alpha] = \\int df/d alpha L cos dw
= dI/d alpha``: the estimator is unbiased for the value and for the derivative,
with fixed samples (as Mitsuba's detached BSDF and emitter sampling).

Seeds (as Mitsuba's ``spp`` / ``spp_grad``): :func:`render` splits its ``key``
into a primal key and a gradient key. The returned image averages ``spp``
samples drawn with the primal key; its VJP (``jax.custom_vjp``) differentiates an
independent ``spp_grad``-sample estimate drawn with the gradient key. Independence
makes the gradient of a loss ``l(I)`` unbiased for ``l'(E[I]) dE[I]/d alpha``
(e.g. ``E[2 (I - I_ref) dI] = 2 (E[I] - I_ref) E[dI]``); reusing the primal
samples would correlate the two factors and bias it. An optimisation loop should
draw one key per iteration (``jax.random.fold_in(key, iteration)``).

The reference image is rendered at high sample count with a scrambled Sobol
point set (``scipy.stats.qmc``) shifted randomly per pixel (Cranley-Patterson
rotation): unbiased, and far less noisy than i.i.d. samples at equal count.
"""

from __future__ import annotations

import functools
import math
from typing import Literal, NamedTuple, overload

import jax
import jax.numpy as jnp
import numpy as np

#: The roughness range of the targets and the optimisation (GGX alpha).
ALPHA_MIN = 0.005
ALPHA_MAX = 0.5

#: The loss's denominator offset: mean((I - I_ref)^2 / (I_ref^2 + LOSS_EPS)).
LOSS_EPS = 1e-2

#: Default camera: far enough that view directions vary by only +-2.7 degrees, so
#: every texel's mirror direction stays inside the sun's halo.
CAMERA_POSITION = (0.0, -16.0, 13.5)


class TextureScene(NamedTuple):
    """Everything :func:`render` needs besides the roughness (a pytree of arrays).

    Attributes:
      wo: ``(H, W, 3)`` unit direction from each texel centre towards the camera.
      env: ``(N, N)`` radiance of the upper hemisphere without the sun,
        paraboloid-mapped (:func:`lookup_env`).
      sun_dir: ``(3,)`` unit direction of the sun's centre.
      sun_width: scalar ``b``, the halo's width (radians, roughly).
      sun_power: scalar ``E``, the sun's irradiance on a surface facing it.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> scene = tex.make_scene(8, env_size=32)      # 8x8 texels (the paper: 512)
        >>> scene.wo.shape, scene.env.shape, scene.shape
        ((8, 8, 3), (32, 32), (8, 8))
    """

    wo: jax.Array
    env: jax.Array
    sun_dir: jax.Array
    sun_width: jax.Array
    sun_power: jax.Array

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.wo.shape[:2]
        return h, w


# ----------------------------------------------------------------------------- scene


def camera_directions(size: int | tuple[int, int], camera_position=CAMERA_POSITION) -> np.ndarray:
    """``(H, W, 3)`` unit vectors from each texel centre of the plane towards the camera.

    Texel ``(i, j)`` sits at ``x = -1 + (j + 1/2) 2/W``, ``y = 1 - (i + 1/2) 2/H``
    (row 0 is the far edge of the plane, as in a photograph of it).

    Args:
      size: ``H = W`` (an int) or ``(H, W)``.
      camera_position: ``(x, y, z)`` of the camera, ``z > 0`` (default
        :data:`CAMERA_POSITION`).

    Returns:
      ``(H, W, 3)`` float32 unit vectors.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> tex.camera_directions((4, 6)).shape
        (4, 6, 3)
    """
    h, w = _size(size)
    cam = np.asarray(camera_position, np.float64)
    if cam.shape != (3,) or not cam[2] > 0:
        raise ValueError(
            f"camera_position must be (x, y, z) with z > 0 (above the plane), "
            f"got {camera_position!r}"
        )
    y = 1.0 - (np.arange(h) + 0.5) * 2.0 / h
    x = -1.0 + (np.arange(w) + 0.5) * 2.0 / w
    p = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.zeros((h, 1))), axis=-1)
    d = cam - p
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


def mirror_direction(camera_position=CAMERA_POSITION) -> np.ndarray:
    """The mirror reflection, about the plane's normal, of the view from the plane's centre.

    Args:
      camera_position: ``(x, y, z)`` of the camera (default :data:`CAMERA_POSITION`).

    Returns:
      A ``(3,)`` float64 unit vector: ``(-x, -y, z) / |(x, y, z)|``.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> print(tex.mirror_direction((0.0, -3.0, 4.0)))
        [-0.   0.6  0.8]
    """
    c = np.asarray(camera_position, np.float64)
    c = c / np.linalg.norm(c)
    return np.array([-c[0], -c[1], c[2]])


@functools.lru_cache(maxsize=4)
def environment_map(size: int = 1024) -> np.ndarray:
    """The environment without the sun: a dim photograph on the sky and two lamps.

    A ``size x size`` paraboloid map of the upper hemisphere (see :func:`lookup_env`).
    ``skimage.data.coffee`` (grey, radiance 0.02 .. 0.3) covers azimuth 0..180
    degrees, elevation 0..90 degrees (the half of the sky the plane reflects
    towards the camera); the other half is a dim gradient. Two soft-edged lamps
    (radiance 3) sit 25-35 degrees from the mirror direction: only rough texels see
    them, which adds Monte Carlo noise there.

    Args:
      size: the map's side ``N`` (default 1024).

    Returns:
      ``(N, N)`` float32 radiance (cached: the same array for the same size).

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> env = tex.environment_map(32)
        >>> env.shape, env.dtype.name
        ((32, 32), 'float32')
    """
    from scipy import ndimage, special
    from skimage import color, data

    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 8:
        raise ValueError(f"environment_map size must be an int >= 8, got {size!r}")
    u = -1.0 + (np.arange(size) + 0.5) * 2.0 / size
    v = 1.0 - (np.arange(size) + 0.5) * 2.0 / size
    uu, vv = np.meshgrid(u, v)
    rho2 = np.minimum(uu * uu + vv * vv, 1.0)  # outside the disc: the horizon
    z = (1.0 - rho2) / (1.0 + rho2)
    elev = np.degrees(np.arcsin(z))
    azim = np.degrees(np.arctan2(vv, uu))
    photo = color.rgb2gray(data.coffee())  # (400, 600): rows = elevation, cols = azimuth
    ph, pw = photo.shape
    rows = (90.0 - elev) / 90.0 * ph - 0.5
    cols = azim / 180.0 * pw - 0.5
    sampled = ndimage.map_coordinates(photo, [rows, cols], order=1, mode="nearest")
    env = np.where(azim >= 0.0, 0.02 + 0.28 * sampled, 0.02 + 0.08 * z)
    # Lamps: (azimuth, elevation, half-width, half-height) in degrees; 0.5-degree soft edges.
    for az, el, hw, hh in ((62.0, 52.0, 4.0, 3.0), (118.0, 30.0, 3.0, 5.0)):
        box = special.expit((hw - np.abs(azim - az)) / 0.5) * special.expit(
            (hh - np.abs(elev - el)) / 0.5
        )
        env = env + 3.0 * box
    return env.astype(np.float32)


def make_scene(
    size: int | tuple[int, int] = 512,
    *,
    env_size: int = 1024,
    camera_position=CAMERA_POSITION,
    sun_width: float = 0.06,
    sun_power: float = 3.0,
) -> TextureScene:
    """The default texture scene at ``size`` texels (an int or ``(H, W)``).

    The sun is centred on :func:`mirror_direction`; ``sun_width`` (radians) must
    exceed the spread of the texels' mirror directions for ``I(alpha)`` to be
    monotone (the default camera spreads them by +-0.047 rad).

    Args:
      size: ``H = W`` (an int) or ``(H, W)`` (default 512, the paper's).
      env_size: side of the environment map (default 1024; :func:`environment_map`).
      camera_position: ``(x, y, z)``, ``z > 0`` (default :data:`CAMERA_POSITION`).
      sun_width: the sun halo's width ``b`` in radians (> 0, default 0.06).
      sun_power: the sun's irradiance ``E`` (>= 0, default 3).

    Returns:
      A :class:`TextureScene`.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> scene = tex.make_scene((8, 12), env_size=32)
        >>> scene.shape
        (8, 12)
    """
    if not sun_width > 0 or not sun_power >= 0:
        raise ValueError(
            f"sun_width must be > 0 and sun_power >= 0, got {sun_width!r}, {sun_power!r}"
        )
    return TextureScene(
        wo=jnp.asarray(camera_directions(size, camera_position)),
        env=jnp.asarray(environment_map(env_size)),
        sun_dir=jnp.asarray(mirror_direction(camera_position), jnp.float32),
        sun_width=jnp.asarray(sun_width, jnp.float32),
        sun_power=jnp.asarray(sun_power, jnp.float32),
    )


# ----------------------------------------------------------------------------- targets


def _resize(img: np.ndarray, size) -> np.ndarray:
    from skimage import transform

    h, w = _size(size)
    if img.shape == (h, w):
        return img
    return np.asarray(transform.resize(img, (h, w), anti_aliasing=True, order=1))


def roughness_from_unit(u, lo: float = ALPHA_MIN, hi: float = ALPHA_MAX):
    """Maps ``u in [0, 1]`` to roughness ``lo (hi/lo)^u`` (log-uniform: equal steps of ``u``
    are equal *relative* changes of alpha, which is how roughness looks).

    Args:
      u: an array (or number) in ``[0, 1]``.
      lo: the roughness at ``u = 0`` (default :data:`ALPHA_MIN`, 0.005).
      hi: the roughness at ``u = 1`` (default :data:`ALPHA_MAX`, 0.5).

    Returns:
      The roughness, with ``u``'s shape.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> print(tex.roughness_from_unit(jnp.array([0.0, 0.5, 1.0])))
        [0.005 0.05  0.5  ]
    """
    return lo * (hi / lo) ** u


def target_roughness(
    name: str = "camera", size: int | tuple[int, int] = 512, seed: int = 0
) -> np.ndarray:
    """A target roughness texture in ``[ALPHA_MIN, ALPHA_MAX]`` (float32, ``(H, W)``).

    * ``"camera"``: piecewise smooth. ``skimage.data.camera`` after total-variation
      denoising (``skimage.restoration.denoise_tv_chambolle``, weight 0.15), which
      keeps its edges and flattens texture; bright = rough; log-uniform map
      (:func:`roughness_from_unit`).
    * ``"noise"``: high-frequency i.i.d. noise, log-uniform per texel (seeded):
      the case where spatial filtering is biased (supplement Fig. 4).
    * ``"phantom"``: piecewise constant, the Shepp-Logan phantom.

    Args:
      name: ``"camera"`` (default), ``"noise"`` or ``"phantom"``.
      size: ``H = W`` (an int) or ``(H, W)`` (default 512).
      seed: the ``"noise"`` target's seed.

    Returns:
      ``(H, W)`` float32 roughness.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> alpha = tex.target_roughness("camera", 16)
        >>> alpha.shape, bool(alpha.min() >= tex.ALPHA_MIN), bool(alpha.max() <= tex.ALPHA_MAX)
        ((16, 16), True, True)
    """
    from skimage import data, restoration

    if name == "camera":
        img = _resize(data.camera().astype(np.float64) / 255.0, size)
        u = restoration.denoise_tv_chambolle(img, weight=0.15)
    elif name == "phantom":
        u = _resize(data.shepp_logan_phantom(), size)
    elif name == "noise":
        u = np.random.default_rng(seed).uniform(size=_size(size))
    else:
        raise ValueError(f"name must be 'camera', 'noise' or 'phantom', got {name!r}")
    u = (u - u.min()) / max(u.max() - u.min(), 1e-12)
    return roughness_from_unit(u).astype(np.float32)


# ----------------------------------------------------------------------------- BRDF


def ggx_d(tan2_h, cos_h, alpha):
    """GGX normal distribution ``D = alpha^2 / (pi cos^4 (alpha^2 + tan^2)^2)``.

    Args:
      tan2_h: ``tan^2`` of the half vector's angle to the normal.
      cos_h: its cosine.
      alpha: GGX roughness (> 0). All three broadcast together.

    Returns:
      ``D`` (per steradian), the broadcast shape.

    Taking ``tan^2(theta_h)`` separately keeps near-mirror lobes accurate in float32.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> round(float(tex.ggx_d(0.0, 1.0, 0.5)), 5)    # 1 / (pi alpha^2) at the peak
        1.27324
    """
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    return a2 / (jnp.pi * c2 * c2 * jnp.square(a2 + tan2_h))


def smith_g1(cos_t, alpha):
    """Smith masking for GGX, ``G1 = 2 cos / (cos + sqrt(a^2 + (1 - a^2) cos^2))``.

    Args:
      cos_t: cosine of the direction's angle to the normal (> 0).
      alpha: GGX roughness ``a``. Both broadcast together.

    Returns:
      ``G1`` in ``(0, 1]``, the broadcast shape.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> float(tex.smith_g1(1.0, 0.3))                 # no masking at normal incidence
        1.0
    """
    a2 = alpha * alpha
    c2 = cos_t * cos_t
    return 2.0 * cos_t / (cos_t + jnp.sqrt(a2 + (1.0 - a2) * c2))


def sun_pdf(cos_b, width):
    """Solid-angle density of sun sampling, ``b / (2 pi (1 - c^2 + b^2 c^2)^{3/2})``
    for ``c > 0`` (0 otherwise).

    Args:
      cos_b: cosine of the angle to the sun's centre, ``c``.
      width: the halo's width ``b`` (> 0). Both broadcast together.

    Returns:
      The density (per steradian), the broadcast shape.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> round(float(tex.sun_pdf(1.0, 0.06)), 3)       # 1 / (2 pi b^2) at the centre
        44.21
    """
    c2 = cos_b * cos_b
    return jnp.where(
        cos_b > 0,
        width
        / (2 * jnp.pi)
        * jax.lax.rsqrt(jnp.maximum(1.0 - c2 + width * width * c2, 1e-30)) ** 3,
        0.0,
    )


def lookup_env(env, x, y, z):
    """Bilinear lookup of the paraboloid-mapped ``env`` at unit directions ``(x, y, z)``,
    ``z >= 0``.

    Direction ``w`` maps to ``(x, y) / (1 + z)`` in the unit disc (no trigonometry);
    ``env[r, c]`` covers ``u = -1 + (c + 1/2) 2/N`` (x), ``v = 1 - (r + 1/2) 2/N`` (y).

    Args:
      env: ``(N, N)`` radiance, e.g. :func:`environment_map`.
      x, y, z: the directions' components, arrays of one shape.

    Returns:
      The radiance, with the components' shape.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> env = jnp.arange(16.0).reshape(4, 4)
        >>> float(tex.lookup_env(env, jnp.array(0.0), jnp.array(0.0), jnp.array(1.0)))  # zenith
        7.5
    """
    n = env.shape[0]
    inv = 1.0 / (1.0 + z)
    c = jnp.clip((x * inv + 1.0) * (0.5 * n) - 0.5, 0.0, n - 1.0)
    r = jnp.clip((1.0 - y * inv) * (0.5 * n) - 0.5, 0.0, n - 1.0)
    r0 = jnp.minimum(jnp.floor(r), n - 2.0)
    c0 = jnp.minimum(jnp.floor(c), n - 2.0)
    fr = r - r0
    fc = c - c0
    i00 = r0.astype(jnp.int32) * n + c0.astype(jnp.int32)
    flat = env.reshape(-1)
    v00 = flat[i00]
    v01 = flat[i00 + 1]
    v10 = flat[i00 + n]
    v11 = flat[i00 + n + 1]
    return (1 - fr) * ((1 - fc) * v00 + fc * v01) + fr * ((1 - fc) * v10 + fc * v11)


def _sun_frame(s):
    """Two unit vectors completing the sun direction ``s`` to an orthonormal frame."""
    e1 = jnp.array([s[1], -s[0], 0.0]) / jnp.sqrt(
        s[0] ** 2 + s[1] ** 2
    )  # the sun is never at the zenith
    e2 = jnp.cross(s, e1)
    return e1, e2


@overload
def sample_weights(
    alpha, scene: TextureScene, u1, u2, with_score: Literal[False] = False
) -> jax.Array: ...


@overload
def sample_weights(
    alpha, scene: TextureScene, u1, u2, with_score: Literal[True]
) -> tuple[jax.Array, jax.Array]: ...


def sample_weights(alpha, scene: TextureScene, u1, u2, with_score: bool = False):
    """Per-sample estimates ``f L cos / p`` for uniforms ``u1, u2`` (broadcast against ``alpha``).

    The mixture density uses ``stop_gradient(alpha)``: the derivative flows only
    through ``f``. Vectors are separate x, y, z arrays (XLA on CPU vectorises those).
    With ``with_score``, also returns ``d log f / d alpha`` in closed form:
    ``2/a - 4a/(a^2 + tan^2 theta_h)`` from D plus ``-a (1-c^2) / (S (c + S))``,
    ``S = sqrt(a^2 + (1-a^2) c^2)``, from each G1 (one fused pass; far cheaper on
    CPU than reverse-mode through this function).

    Args:
      alpha: ``(H, W)`` GGX roughness.
      scene: the :class:`TextureScene` (``H x W`` texels).
      u1, u2: uniforms in ``[0, 1)``, e.g. ``(spp, H, W)``: which lobe or light and
        where in it.
      with_score: also return ``w * d log f / d alpha``.

    Returns:
      ``w``, the per-sample estimates (the broadcast shape of ``alpha``, ``u1``,
      ``u2``), or ``(w, w * score)`` with ``with_score``.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> scene = tex.make_scene(8, env_size=32)      # 8x8 texels (the paper: 512)
        >>> u = jax.random.uniform(jax.random.key(0), (2, 1, 8, 8))
        >>> w = tex.sample_weights(jnp.full((8, 8), 0.1), scene, u[0], u[1])
        >>> w.shape, bool(jnp.all(w >= 0))
        ((1, 8, 8), True)
    """
    wo, s, b = scene.wo, scene.sun_dir, scene.sun_width
    a0 = jax.lax.stop_gradient(alpha)
    ox, oy, oz = wo[..., 0], wo[..., 1], wo[..., 2]
    q = a0 / (a0 + 0.5 * b)  # sun sampling pays off for wide lobes
    use_sun = u1 < q
    v = jnp.where(use_sun, u1 / q, (u1 - q) / (1.0 - q))  # reuse u1 after picking the technique
    cphi, sphi = jnp.cos(2.0 * jnp.pi * u2), jnp.sin(2.0 * jnp.pi * u2)
    # GGX: tan^2(theta_h) = a0^2 v / (1 - v); h = (tan cos phi, tan sin phi, 1) (unnormalised).
    tan_h = a0 * jnp.sqrt(v / jnp.maximum(1.0 - v, 1e-12))
    hx, hy = tan_h * cphi, tan_h * sphi
    hn = jax.lax.rsqrt(1.0 + tan_h * tan_h)
    o_h = (ox * hx + oy * hy + oz) * hn
    gx, gy, gz = 2.0 * o_h * hx * hn - ox, 2.0 * o_h * hy * hn - oy, 2.0 * o_h * hn - oz
    # Sun: gnomonic offset of radius r = b sqrt(1/(1-v)^2 - 1) (2-D Cauchy inverse CDF).
    r = b * jnp.sqrt(jnp.maximum(1.0 / jnp.square(jnp.maximum(1.0 - v, 1e-12)) - 1.0, 0.0))
    e1, e2 = _sun_frame(s)
    tx, ty, tz = (s[k] + r * (cphi * e1[k] + sphi * e2[k]) for k in range(3))
    tn = jax.lax.rsqrt(1.0 + r * r)
    ix = jnp.where(use_sun, tx * tn, gx)
    iy = jnp.where(use_sun, ty * tn, gy)
    iz = jnp.where(use_sun, tz * tn, gz)

    # Evaluate f, both densities and L at w_i, whichever technique produced it.
    mx, my, mz = ix + ox, iy + oy, iz + oz  # half vector, unnormalised
    m2 = mx * mx + my * my + mz * mz
    ok = (iz > 1e-6) & (mz > 1e-6)
    mz_s = jnp.where(ok, mz, 1.0)
    tan2 = (mx * mx + my * my) / (mz_s * mz_s)
    cos_h = mz_s * jax.lax.rsqrt(m2)
    o_m = jnp.maximum((ox * mx + oy * my + oz * mz) * jax.lax.rsqrt(m2), 1e-6)
    cos_i = jnp.where(ok, iz, 1.0)
    f_cos = ggx_d(tan2, cos_h, alpha) * smith_g1(cos_i, alpha) * smith_g1(oz, alpha) / (4.0 * oz)
    p_ggx = ggx_d(tan2, cos_h, a0) * cos_h / (4.0 * o_m)
    p_sun = sun_pdf(ix * s[0] + iy * s[1] + iz * s[2], b)
    radiance = lookup_env(scene.env, ix, iy, cos_i) + scene.sun_power * p_sun
    p = (1.0 - q) * p_ggx + q * p_sun
    w = jnp.where(ok, f_cos * radiance / jnp.where(ok, p, 1.0), 0.0)
    if not with_score:
        return w
    a2 = alpha * alpha

    def dlog_g1(c):
        sq = jnp.sqrt(a2 + (1.0 - a2) * c * c)
        return -alpha * (1.0 - c * c) / (sq * (c + sq))

    score = 2.0 / alpha - 4.0 * alpha / (a2 + tan2) + dlog_g1(cos_i) + dlog_g1(oz)
    return w, w * score


def estimate(alpha, scene: TextureScene, u) -> jax.Array:
    """Monte Carlo estimate of the image from uniforms ``u`` of shape ``(spp, H, W, 2)``.

    ``I = mean_s w(alpha, u_s)`` (:func:`sample_weights`). Differentiable in ``alpha``
    in forward and reverse mode; its derivative is unbiased but correlated with ``I``
    (the same samples): :func:`render` decorrelates them for loss gradients.

    Args:
      alpha: ``(H, W)`` GGX roughness.
      scene: the :class:`TextureScene`.
      u: ``(spp, H, W, 2)`` uniforms in ``[0, 1)``.

    Returns:
      The ``(H, W)`` image.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> scene = tex.make_scene(8, env_size=32)      # 8x8 texels (the paper: 512)
        >>> u = jax.random.uniform(jax.random.key(0), (1, 8, 8, 2))
        >>> tex.estimate(jnp.full((8, 8), 0.1), scene, u).shape
        (8, 8)
    """
    return jnp.mean(sample_weights(alpha, scene, u[..., 0], u[..., 1]), axis=0)


def _check(alpha, scene, spp, name="spp"):
    if not isinstance(scene, TextureScene):
        raise TypeError(
            f"scene must be a TextureScene (see make_scene), got {type(scene).__name__}"
        )
    if jnp.shape(alpha) != scene.shape:
        raise ValueError(
            f"alpha must have the scene's texture shape {scene.shape}, got {jnp.shape(alpha)}"
        )
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ValueError(f"{name} must be a positive int, got {spp!r}")


@functools.partial(jax.custom_vjp, nondiff_argnums=())
def _render_split(alpha, scene, u_primal, u_grad):
    return estimate(alpha, scene, u_primal)


def _render_split_fwd(alpha, scene, u_primal, u_grad):
    return estimate(alpha, scene, u_primal), (alpha, scene, u_grad, u_primal)


def _render_split_bwd(res, ct):
    alpha, scene, u_grad, u_primal = res
    # Each pixel depends on its own texel only, so the VJP is ct * dI/d alpha, texel-wise;
    # dI/d alpha = mean(w * d log f / d alpha) equals jax.grad of estimate() (tested).
    _, dw = sample_weights(alpha, scene, u_grad[..., 0], u_grad[..., 1], with_score=True)
    zeros = jax.tree_util.tree_map(jnp.zeros_like, (scene, u_primal, u_grad))
    return (ct * jnp.mean(dw, axis=0),) + zeros


_render_split.defvjp(_render_split_fwd, _render_split_bwd)


def render(alpha, scene: TextureScene, key, spp: int = 1, spp_grad: int = 1) -> jax.Array:
    """A noisy image ``(H, W)``: ``spp`` samples for the value, ``spp_grad`` others for its VJP.

    ``key`` is split into a primal and a gradient key (``jax.random.split``);
    the two estimates are independent, so loss gradients are unbiased (module
    docstring). ``spp`` and ``spp_grad`` are static. Reverse mode only (``jax.grad``,
    ``jax.vjp``): the derivative is a custom VJP; for forward mode use :func:`estimate`.

    Args:
      alpha: ``(H, W)`` GGX roughness (the parameter).
      scene: the :class:`TextureScene`.
      key: a PRNG key.
      spp: samples per pixel of the value (>= 1, default 1: the paper's noisy setting).
      spp_grad: samples per pixel of the gradient (>= 1, default 1).

    Returns:
      The ``(H, W)`` image, ``alpha``'s float dtype.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> scene = tex.make_scene(8, env_size=32)      # 8x8 texels (the paper: 512)
        >>> alpha, target = jnp.full((8, 8), 0.1), jnp.full((8, 8), 0.5)
        >>> loss = lambda a: tex.loss_fn(tex.render(a, scene, jax.random.key(1)), target)
        >>> grads = jax.grad(loss)(alpha)                  # one noisy gradient
        >>> grads.shape, bool(jnp.all(jnp.isfinite(grads)))
        ((8, 8), True)
    """
    _check(alpha, scene, spp)
    _check(alpha, scene, spp_grad, "spp_grad")
    k_primal, k_grad = jax.random.split(key)
    h, w = scene.shape
    dtype = jnp.result_type(alpha, jnp.float32)
    u_p = jax.random.uniform(k_primal, (spp, h, w, 2), dtype)
    u_g = jax.random.uniform(k_grad, (spp_grad, h, w, 2), dtype)
    return _render_split(alpha, scene, u_p, u_g)


def render_reference(
    alpha, scene: TextureScene, spp: int = 1024, seed: int = 0, batch: int = 16
) -> jax.Array:
    """A low-noise image: ``spp`` scrambled-Sobol samples per pixel, each pixel's set shifted
    by its own uniform offset (mod 1), evaluated ``batch`` samples at a time.

    Unbiased (each shifted point is uniform); with smooth integrands the error falls
    faster than i.i.d. sampling's ``spp^-1/2``. ``spp`` is rounded up to a power of 2
    (Sobol balance) and to a multiple of ``batch``. Needs SciPy (``scipy.stats.qmc``).

    Args:
      alpha: ``(H, W)`` GGX roughness.
      scene: the :class:`TextureScene`.
      spp: samples per pixel (>= 1, default 1024).
      seed: scrambling and shift seed (default 0): the same seed, the same image.
      batch: samples evaluated at a time (bounded memory; default 16).

    Returns:
      The ``(H, W)`` float32 image.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> scene = tex.make_scene(8, env_size=32)      # 8x8 texels (the paper: 512)
        >>> tex.render_reference(jnp.full((8, 8), 0.1), scene, spp=16).shape
        (8, 8)
    """
    from scipy.stats import qmc

    _check(alpha, scene, spp)
    n = 1 << max(math.ceil(math.log2(spp)), 0)
    batch = min(batch, n)
    # seed=, not rng=: SciPy's legacy stream (the one the tests' reference images were made
    # with); the decorator that keeps seed= hides it from type checkers.
    sobol = qmc.Sobol(d=2, scramble=True, seed=seed)  # pyright: ignore[reportCallIssue]
    points = sobol.random(n).astype(np.float32)
    points = jnp.asarray(points.reshape(n // batch, batch, 1, 1, 2))
    shift = jax.random.uniform(jax.random.PRNGKey(seed), scene.shape + (2,), jnp.float32)
    return _reference(jnp.asarray(alpha, jnp.float32), scene, points, shift)


@jax.jit
def _reference(alpha, scene, points, shift):
    def body(acc, pts):
        u = jnp.mod(pts + shift, 1.0)
        return acc + jnp.sum(sample_weights(alpha, scene, u[..., 0], u[..., 1]), axis=0), None

    total, _ = jax.lax.scan(body, jnp.zeros(scene.shape, jnp.float32), points)
    return total / (points.shape[0] * points.shape[1])


def loss_fn(image, reference, eps: float = LOSS_EPS):
    """The paper's texture loss ``mean((I - I_ref)^2 / (I_ref^2 + eps))`` (relative MSE).

    No gradient flows into ``reference``.

    Args:
      image: the rendered image.
      reference: the target image, ``image``'s shape.
      eps: the denominator's offset (default :data:`LOSS_EPS`, 0.01).

    Returns:
      A scalar.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from optax_bilateral.toy import texture as tex
        >>> float(tex.loss_fn(jnp.array([1.0, 2.0]), jnp.array([1.0, 1.0]), eps=0.0))
        0.5
    """
    ref = jax.lax.stop_gradient(reference)
    return jnp.mean(jnp.square(image - ref) / (jnp.square(ref) + eps))


def _size(size) -> tuple[int, int]:
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        h = w = int(size)
    elif isinstance(size, (tuple, list)) and len(size) == 2:
        h, w = (int(s) for s in size)
    else:
        raise TypeError(f"size must be an int or (H, W), got {size!r}")
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive, got {size!r}")
    return h, w
