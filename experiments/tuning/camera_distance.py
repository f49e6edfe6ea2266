"""Mitsuba 3 scenes of the tuning benchmark (issue #47): one texture seen from several camera
distances, where the best filter settings move with how many texels a pixel sees.

The scene, built in code: a diffuse square plane (Mitsuba's ``rectangle``, side
:data:`PLANE_SIDE`, normal +y) whose RGB albedo is a ``bitmap`` texture of ``T x T``
texels (``raw=True``), lit by :func:`experiments.mitsuba.texture.environment_map` (a sky
and a sun: the shading of every 1-spp sample is noisy), seen straight down by perspective
cameras of field of view :data:`FOV` and film ``R x R``. A camera at distance ``d`` sees
a square of side ``2 d tan(FOV / 2)`` of the plane, so a pixel covers

    texels per pixel = (T / PLANE_SIDE) * 2 d tan(FOV / 2) / R

texels along a side (:func:`texels_per_pixel`; :func:`camera_distance` inverts it).
The cameras (:data:`CAMERAS`) are ``close`` (0.5 texels per pixel: the camera sees the
central quarter of the plane's side), ``mid`` (2: the whole plane fills the film) and
``far`` (12: the plane covers ``T / 12`` pixels).

The gradient: the texture goes to Mitsuba through :func:`jax.pure_callback` (one call per
run of a vmapped batch), which renders with the ``prb`` integrator at ``spp`` samples per
pixel with a seed drawn from the run's key, takes ``mean((I - I_ref)^2)`` against a
high-spp reference render of the target from the same camera, and returns ``dr.grad`` of
the texture. Mitsuba draws the differential pass with a seed decorrelated from the primal
one, so the gradient is an unbiased estimate of the gradient of ``mean((E[I] - I_ref)^2)``.
A scene of several cameras takes them in turn, one per iteration.

The error is the mean error of the texture *at the resolution the camera resolves*: the
texture and the target are cropped to the texels the camera sees and box-filtered over
``round(texels per pixel)``-texel blocks (none below one texel per pixel) before their
mean absolute difference (:func:`resolved_error`): what a far camera cannot see
(detail within a pixel) is not counted against a method. With several cameras, the mean
of the cameras' errors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from experiments.tuning.problem import Scene, around

#: The plane's side in scene units (Mitsuba's ``rectangle`` spans [-1, 1]^2).
PLANE_SIDE = 2.0
#: The cameras' field of view, degrees.
FOV = 40.0
#: Texels per pixel of the named cameras.
CAMERAS = {"close": 0.5, "mid": 2.0, "far": 12.0}
#: The middle of each camera's first learning-rate grid (a scene takes its cameras' largest):
#: a far camera's texels see a pixel's gradient rarely, and want larger steps.
LEARNING_RATES = {"close": 0.02, "mid": 0.02, "far": 0.08}
KEY = "plane.bsdf.reflectance.data"
REFERENCE_SEED = 1 << 20  # render seeds of the runs are drawn from their keys below 2^20


def camera_distance(tpp: float, texture: int, film: int, fov: float = FOV) -> float:
    """The distance at which a camera sees ``tpp`` texels per pixel (see the module docstring)."""
    return tpp * film * PLANE_SIDE / (texture * 2 * math.tan(math.radians(fov) / 2))


def texels_per_pixel(distance: float, texture: int, film: int, fov: float = FOV) -> float:
    """Texels per pixel along a side of a camera at ``distance`` looking straight at the plane."""
    return texture / PLANE_SIDE * 2 * distance * math.tan(math.radians(fov) / 2) / film


def visible_texels(tpp: float, texture: int, film: int) -> int:
    """The side, in texels, of the plane's central square that the camera sees."""
    return min(texture, round(tpp * film))


def resolved_error(x, target, tpp: float, film: int):
    """Mean ``|x - target|`` over the texels the camera sees, both box-filtered over
    ``round(tpp)``-texel blocks (a block average is what one pixel measures)."""
    t = x.shape[0]
    side = visible_texels(tpp, t, film)
    k = max(1, round(tpp))
    side -= side % k
    lo = (t - side) // 2

    def blocks(a):
        a = a[lo : lo + side, lo : lo + side]
        return a.reshape(side // k, k, side // k, k, -1).mean(axis=(1, 3))

    return jnp.mean(jnp.abs(blocks(x) - blocks(target)))


#: The photographs a plane may carry (``skimage.data`` names).
PHOTOS = ("astronaut", "coffee")


def target_albedo(size: int, photo: str = "astronaut") -> np.ndarray:
    """A photograph of :data:`PHOTOS` (``skimage.data``; its central square) as a
    ``(size, size, 3)`` albedo in [0.02, 0.98] (anti-aliased resize)."""
    from skimage import data, transform

    if photo not in PHOTOS:
        raise ValueError(f"photo must be one of {PHOTOS}, got {photo!r}")
    img = getattr(data, photo)() / 255.0
    h, w = img.shape[:2]
    side = min(h, w)
    img = img[(h - side) // 2 : (h + side) // 2, (w - side) // 2 : (w + side) // 2]
    img = transform.resize(img, (size, size), anti_aliasing=True)
    return np.clip(img, 0.02, 0.98).astype(np.float32)


def scene_dict(albedo: np.ndarray, cameras: Sequence[str], film: int, env: np.ndarray) -> dict:
    """The Mitsuba scene: the plane with ``albedo`` ``(T, T, 3)``, one sensor per camera name
    (in order), the environment ``env``."""
    import mitsuba as mi

    texture = albedo.shape[0]
    out = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "plane": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),  # normal +y
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "bitmap", "raw": True, "data": mi.TensorXf(albedo)},
            },
        },
        "emitter": {"type": "envmap", "bitmap": mi.Bitmap(env)},
    }
    for j, name in enumerate(cameras):
        d = camera_distance(CAMERAS[name], texture, film)
        out[f"sensor_{j}_{name}"] = {
            "type": "perspective",
            "fov": FOV,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[0, d, 0], target=[0, 0, 0], up=[0, 0, 1]
            ),
            "film": {
                "type": "hdrfilm",
                "width": film,
                "height": film,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
        }
    return out


class Renderer:
    """One Mitsuba scene and its reference renders; :meth:`grad` is the callback."""

    def __init__(self, target: np.ndarray, cameras: Sequence[str], film: int, cfg: dict):
        from experiments.mitsuba import common as mc
        from experiments.mitsuba.texture import environment_map

        mi, dr = mc.setup()
        self.spp = cfg["spp"]
        self.scene = mi.load_dict(scene_dict(target, cameras, film, environment_map(cfg["env"])))
        self.params = mi.traverse(self.scene)
        with dr.suspend_grad():
            self.references = [
                mi.render(self.scene, sensor=j, spp=cfg["reference_spp"], seed=REFERENCE_SEED)
                for j in range(len(cameras))
            ]
        dr.eval(self.references)

    def grad(self, texture, seed, camera) -> np.ndarray:
        """``d mean((I - I_ref)^2) / d texture`` of one ``spp`` render from ``camera``."""
        import drjit as dr
        import mitsuba as mi

        value = mi.TensorXf(np.asarray(texture, np.float32))
        dr.enable_grad(value)
        self.params[KEY] = value
        self.params.update()
        j = int(camera)
        image = mi.render(self.scene, self.params, sensor=j, spp=self.spp, seed=int(seed))
        dr.backward(dr.mean(dr.square(image - self.references[j]), axis=None))
        return np.array(dr.grad(self.params[KEY]), np.float32)


def scene(quick: bool, cameras: Sequence[str], name: str, photo: str = "astronaut") -> Scene:
    """The plane carrying ``photo`` (one of :data:`PHOTOS`) seen from ``cameras`` (names of
    :data:`CAMERAS`, taken in turn)."""
    for c in cameras:
        if c not in CAMERAS:
            raise ValueError(f"cameras must be names of {sorted(CAMERAS)}, got {c!r}")
    if quick:
        cfg = dict(texture=48, film=24, spp=1, reference_spp=32, env=32, iterations=12)
    else:
        cfg = dict(texture=192, film=96, spp=1, reference_spp=256, env=128, iterations=60)
    texture, film = cfg["texture"], cfg["film"]
    target = target_albedo(texture, photo)
    if photo != "astronaut":  # part of the cache key (the astronaut scenes' keys unchanged)
        cfg["photo"] = photo
    renderer = Renderer(target, cameras, film, cfg)
    tpps = [CAMERAS[c] for c in cameras]
    shape = jax.ShapeDtypeStruct((texture, texture, 3), jnp.float32)

    def grad(data, params, key, step):
        seed = jax.random.randint(key, (), 0, REFERENCE_SEED)
        camera = jnp.asarray(step) % len(cameras)
        return jax.pure_callback(
            renderer.grad, shape, params, seed, camera, vmap_method="sequential"
        )

    def error(data, x):
        return sum(resolved_error(x, data["target"], t, film) for t in tpps) / len(tpps)

    views = ", ".join(f"{c} ({CAMERAS[c]:g} texels/px)" for c in cameras)
    return Scene(
        name=name,
        description=(
            f"Mitsuba diffuse plane, {texture}^2 RGB albedo ({photo}), {film}^2 film, "
            f"spp {cfg['spp']}, camera{'s in turn' if len(cameras) > 1 else ''} {views}"
        ),
        init=jnp.full((texture, texture, 3), 0.5, jnp.float32),
        data={"target": jnp.asarray(target)},
        grad=grad,
        project=lambda data, x: jnp.clip(x, 0.0, 1.0),
        error=error,
        iterations=cfg["iterations"],
        learning_rates=around(max(LEARNING_RATES[c] for c in cameras)),
        error_name="mean |albedo - target| at the resolution each camera resolves",
        config=dict(kind="mitsuba_plane", cameras=list(cameras), tpp=tpps, fov=FOV, **cfg),
        batch=8,
    )
