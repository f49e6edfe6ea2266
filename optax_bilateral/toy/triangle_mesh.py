"""Toy mesh scene: recover a cube (sharp edges) from a sphere, with noisy gradients.

The renderer models only what the scene needs, on the CPU:

* **Cameras**: ``num_views`` orthographic views from quasi-random directions
  around the object, ``resolution^2`` pixels over ``[-extent, extent]^2``.
* **Visibility** (not differentiated): a NumPy z-buffer rasteriser finds, for
  one jittered sample per pixel, the front-facing triangle it sees.
* **Shading** (differentiated): Lambertian with face normals under six coloured
  directional lights (+-x, +-y, +-z; each colour channel sees one axis, with
  weights 1 and 0.4 on the two signs, so a colour determines the normal).
  Each pixel estimates it with **one uniformly chosen light** (next-event
  estimation, ``6 L_k max(0, n . l_k)``): Monte Carlo noise, like a path tracer
  with one light sample. The gradient uses two independent light samples,
  ``(I1 - I*) dI2``, which is unbiased for the gradient of ``(I - I*)^2 / 2``.
* **Soft silhouettes** (differentiated): coverage ``sigmoid(s / tau)`` with ``s`` the
  signed pixel distance to the nearest silhouette edge of the mesh (edges between
  a front- and a back-facing triangle), evaluated in a band around the outline,
  compared with the target's exact coverage at the same jittered sample.
* **Per-iteration noise**: a random subset of the views, fresh sub-pixel jitter
  and fresh light choices every iteration.

The target is an axis-aligned cube rendered exactly (ray-box intersection,
all lights), the initial mesh an icosphere. Geometry error: symmetric Hausdorff
distance between dense surface samples (:func:`hausdorff_to_cube`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# Light directions and colours: channel c sees axis c, weight 1 on +, 0.4 on -.
LIGHT_DIRS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32
)
LIGHT_COLORS = np.array(
    [[1, 0, 0], [0.4, 0, 0], [0, 1, 0], [0, 0.4, 0], [0, 0, 1], [0, 0, 0.4]], np.float32
)
# Silhouette softness in pixels, and the band (in pixels) where it is evaluated:
# sigmoid(4 / 0.5) = 0.9997, so outside the band coverage is binary to 3e-4.
TAU_PX = 0.5
BAND_PX = 4


# ----------------------------------------------------------------------------
# Meshes


def icosphere(frequency: int, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic sphere: each icosahedron face split into ``frequency^2`` triangles.

    ``V = 10 frequency^2 + 2`` vertices (16 -> 2562, 32 -> 10242, 59 -> 34812,
    129 -> 166412), faces counter-clockwise seen from outside.

    Args:
      frequency: subdivisions per icosahedron edge (a positive int).
      radius: the sphere's radius (default 1).

    Returns:
      ``(vertices, faces)``: ``(V, 3)`` float32 and ``(20 frequency^2, 3)`` int32.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> vertices, faces = tm.icosphere(2)
        >>> vertices.shape, faces.shape
        ((42, 3), (80, 3))
    """
    if isinstance(frequency, bool) or not isinstance(frequency, int) or frequency < 1:
        raise ValueError(f"frequency must be a positive int, got {frequency!r}")
    t = (1 + 5**0.5) / 2
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ]
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ]
    )
    k = frequency
    ii, jj = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
    keep = (ii + jj) <= k
    ii, jj = ii[keep], jj[keep]
    local = -np.ones((k + 1, k + 1), int)
    local[ii, jj] = np.arange(len(ii))
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    up = (i + j) <= k - 1
    down = (i + j) <= k - 2
    tri = np.concatenate(
        [
            np.stack([local[i[up], j[up]], local[i[up] + 1, j[up]], local[i[up], j[up] + 1]], -1),
            np.stack(
                [
                    local[i[down] + 1, j[down]],
                    local[i[down] + 1, j[down] + 1],
                    local[i[down], j[down] + 1],
                ],
                -1,
            ),
        ]
    )
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    pts = (
        a[:, None]
        + (b - a)[:, None] * (ii / k)[None, :, None]
        + (c - a)[:, None] * (jj / k)[None, :, None]
    ).reshape(-1, 3)
    pts /= np.linalg.norm(pts, axis=-1, keepdims=True)
    faces = (tri[None] + len(ii) * np.arange(20)[:, None, None]).reshape(-1, 3)
    # Points on shared icosahedron edges appear twice; merge them.
    _, first, inverse = np.unique(np.round(pts, 9), axis=0, return_index=True, return_inverse=True)
    return (radius * pts[first]).astype(np.float32), inverse.ravel()[faces].astype(np.int32)


def sample_surface(vertices, faces, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points uniformly distributed over the area of a triangle mesh.

    Args:
      vertices: ``(V, 3)`` positions.
      faces: ``(F, 3)`` int triangles.
      count: the number of points.
      rng: a ``np.random.Generator``.

    Returns:
      ``(count, 3)`` float64 points.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> vertices, faces = tm.icosphere(2)
        >>> tm.sample_surface(vertices, faces, 5, np.random.default_rng(0)).shape
        (5, 3)
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(tri), size=count, p=area / area.sum())
    u, w = rng.random((count, 1)), rng.random((count, 1))
    flip = (u + w) > 1
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    t = tri[idx]
    return t[:, 0] + u * (t[:, 1] - t[:, 0]) + w * (t[:, 2] - t[:, 0])


def sample_cube_surface(half: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points uniform on the surface of the cube ``[-half, half]^3``.

    Args:
      half: half the cube's side.
      count: the number of points.
      rng: a ``np.random.Generator``.

    Returns:
      ``(count, 3)`` float64 points, each with one coordinate at ``+-half``.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> p = tm.sample_cube_surface(0.5, 4, np.random.default_rng(0))
        >>> p.shape, bool(np.all(np.abs(p).max(axis=1) == 0.5))
        ((4, 3), True)
    """
    axis = rng.integers(0, 3, count)
    sign = rng.choice([-1.0, 1.0], count)
    p = rng.uniform(-half, half, (count, 3))
    p[np.arange(count), axis] = sign * half
    return p


def hausdorff_to_cube(vertices, faces, half: float, count: int = 20000, seed: int = 0) -> float:
    """Symmetric Hausdorff distance between a mesh and the cube ``[-half, half]^3``.

    Mesh -> cube uses the exact distance of each mesh sample (and vertex) to the
    cube surface; cube -> mesh the nearest mesh sample (``scipy.spatial.KDTree``),
    so that direction is accurate to about the sample spacing.

    Args:
      vertices: ``(V, 3)`` positions.
      faces: ``(F, 3)`` int triangles.
      half: half the cube's side.
      count: surface samples on each side (default 20000).
      seed: the samples' seed (default 0).

    Returns:
      The distance, a float in world units.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> vertices, faces = tm.icosphere(2)
        >>> round(tm.hausdorff_to_cube(vertices, faces, 0.55, count=500), 2)   # the unit sphere
        0.45
    """
    from scipy.spatial import KDTree

    rng = np.random.default_rng(seed)
    a = np.concatenate([sample_surface(vertices, faces, count, rng), np.asarray(vertices, float)])
    q = np.abs(a) - half  # signed distance to a box, exact
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    d_mesh_to_cube = np.abs(outside + inside).max()
    b = sample_cube_surface(half, count, rng)
    d_cube_to_mesh = KDTree(a).query(b)[0].max()
    return float(max(d_mesh_to_cube, d_cube_to_mesh))


# ----------------------------------------------------------------------------
# Scene


class Scene(NamedTuple):
    """Static scene description (NumPy arrays).

    Attributes:
      frames: ``(N, 3, 3)`` camera frames, rows ``right, up, d``; the camera looks
        along ``-d`` (it sits on the ``+d`` side).
      resolution: pixels per side.
      extent: the image covers ``[-extent, extent]^2`` in world units.
      cube_half: half side of the target cube.
      views_per_iteration: views rendered per optimisation step.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> scene = tm.make_scene(num_views=4, resolution=8)
        >>> scene.frames.shape, scene.pixel_size
        ((4, 3, 3), 0.3)
    """

    frames: np.ndarray
    resolution: int
    extent: float
    cube_half: float
    views_per_iteration: int

    @property
    def pixel_size(self) -> float:
        return 2 * self.extent / self.resolution


def make_scene(
    num_views: int = 16,
    resolution: int = 64,
    extent: float = 1.2,
    cube_half: float = 0.55,
    views_per_iteration: int = 2,
    seed: int = 1,
) -> Scene:
    """Cameras on quasi-random directions (scrambled Sobol, ``scipy.stats.qmc``).

    Args:
      num_views: the number of orthographic cameras (default 16).
      resolution: pixels per side (default 64).
      extent: the images cover ``[-extent, extent]^2`` (default 1.2).
      cube_half: half side of the target cube (default 0.55).
      views_per_iteration: views rendered per optimisation step (default 2).
      seed: the directions' scrambling seed (default 1).

    Returns:
      A :class:`Scene`.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> tm.make_scene(num_views=4, resolution=8).resolution
        8
    """
    from optax_bilateral.triangle_mesh import sphere_directions

    d = sphere_directions(num_views, seed=seed, lloyd=False)
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]])
    right = np.cross(helper, d)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    up = np.cross(d, right)
    frames = np.stack([right, up, d], axis=1).astype(np.float32)
    return Scene(frames, int(resolution), float(extent), float(cube_half), int(views_per_iteration))


def _pixel_centres(scene: Scene) -> np.ndarray:
    r = scene.resolution
    c = (np.arange(r) + 0.5) * scene.pixel_size - scene.extent
    y, x = np.meshgrid(c[::-1], c, indexing="ij")  # row 0 at the top
    return np.stack([x.ravel(), y.ravel()], axis=-1).astype(np.float32)


def _target_hits(scene: Scene, frame: np.ndarray, xy: np.ndarray):
    """Exact ray / cube intersection for orthographic rays: (hit mask, exact RGB)."""
    origin = xy[:, :1] * frame[0] + xy[:, 1:] * frame[1] + 10.0 * frame[2]
    direction = -frame[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        t0 = (-scene.cube_half - origin) * inv
        t1 = (scene.cube_half - origin) * inv
    tmin = np.minimum(t0, t1)
    t_enter = tmin.max(axis=1)
    t_exit = np.maximum(t0, t1).min(axis=1)
    hit = t_enter <= t_exit
    axis = tmin.argmax(axis=1)
    normal = np.zeros((len(xy), 3), np.float32)
    normal[np.arange(len(xy)), axis] = -np.sign(direction[axis])
    rgb = np.maximum(normal @ LIGHT_DIRS.T, 0) @ LIGHT_COLORS
    return hit, (rgb * hit[:, None]).astype(np.float32)


def render_target(scene: Scene, view: int) -> np.ndarray:
    """Noise-free target image ``(R, R, 3)`` at pixel centres.

    The cube ``[-cube_half, cube_half]^3`` under all six lights (ray-box intersection).

    Args:
      scene: the :class:`Scene`.
      view: the camera's index.

    Returns:
      ``(R, R, 3)`` float RGB, ``R`` the scene's resolution; 0 where the cube is missed.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> tm.render_target(tm.make_scene(num_views=4, resolution=8), 0).shape
        (8, 8, 3)
    """
    _, rgb = _target_hits(scene, scene.frames[view], _pixel_centres(scene))
    return rgb.reshape(scene.resolution, scene.resolution, 3)


# ----------------------------------------------------------------------------
# Visibility (NumPy, not differentiated)


def _rasterize(scene: Scene, frame, vertices, faces, xy):
    """Front-facing triangle seen by each sample ``xy`` (``-1``: background)."""
    r, px = scene.resolution, scene.pixel_size
    p2 = vertices @ frame[:2].T  # (V, 2) image-plane coordinates
    h = vertices @ frame[2]  # height towards the camera: larger is closer
    tri = p2[faces]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    front = np.nonzero(area > 1e-12)[0]
    out = np.full(r * r, -1, np.int64)
    if len(front) == 0:
        return out, area
    tri, area_f, hf = tri[front], area[front], h[faces[front]]
    # Pixel column / row ranges whose cell can hold a sample inside the triangle.
    col = (tri[..., 0] + scene.extent) / px
    row = (scene.extent - tri[..., 1]) / px
    c0 = np.clip(np.floor(col.min(1)), 0, r - 1).astype(int)
    c1 = np.clip(np.floor(col.max(1)), 0, r - 1).astype(int)
    r0 = np.clip(np.floor(row.min(1)), 0, r - 1).astype(int)
    r1 = np.clip(np.floor(row.max(1)), 0, r - 1).astype(int)
    wc, wr = int((c1 - c0).max()) + 1, int((r1 - r0).max()) + 1
    oc, orow = np.meshgrid(np.arange(wc), np.arange(wr), indexing="xy")
    cols = c0[:, None] + oc.ravel()[None]
    rows = r0[:, None] + orow.ravel()[None]
    valid = (cols <= c1[:, None]) & (rows <= r1[:, None])
    fi, k = np.nonzero(valid)
    pix = rows[fi, k] * r + cols[fi, k]
    s = xy[pix]
    ta, tb, tc = tri[fi, 0], tri[fi, 1], tri[fi, 2]
    w0 = (tb[:, 0] - s[:, 0]) * (tc[:, 1] - s[:, 1]) - (tb[:, 1] - s[:, 1]) * (tc[:, 0] - s[:, 0])
    w1 = (tc[:, 0] - s[:, 0]) * (ta[:, 1] - s[:, 1]) - (tc[:, 1] - s[:, 1]) * (ta[:, 0] - s[:, 0])
    w2 = area_f[fi] - w0 - w1
    inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
    fi, pix = fi[inside], pix[inside]
    depth = (w0[inside] * hf[fi, 0] + w1[inside] * hf[fi, 1] + w2[inside] * hf[fi, 2]) / area_f[fi]
    order = np.lexsort((-depth, pix))  # per pixel, the closest first
    pix, fi = pix[order], fi[order]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    out[pix[first]] = front[fi[first]]
    return out, area


def _edge_faces(faces: np.ndarray):
    """Unique edges ``(E, 2)`` and their two adjacent faces ``(E, 2)`` (closed meshes)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    if len(key) % 2 or np.any(key[0::2] != key[1::2]):
        raise ValueError("the mesh must be closed and manifold (every edge in exactly two faces)")
    return key[0::2], np.stack([owner[0::2], owner[1::2]], axis=1)


class Frame(NamedTuple):
    """One iteration's non-differentiable rendering data (fixed shapes, for jit).

    Built by :meth:`MeshRenderer.frame` for ``B`` views, ``P`` pixel samples per view and
    ``Q`` silhouette-band samples (padded).

    Attributes:
      frames: ``(B, 3, 3)`` the views' camera frames.
      xy: ``(B, P, 2)`` sample positions in the image plane.
      face: ``(B, P)`` the visible face, or -1.
      target_hit: ``(B, P)`` bool, whether the sample sees the cube.
      target_rgb: ``(B, P, 3)`` the target's colour there.
      lights: ``(B, P, 2)`` two independent light indices per sample.
      band_xy: ``(B, Q, 2)`` silhouette-band samples.
      band_edge: ``(B, Q, 2)`` vertex indices of the nearest silhouette edge.
      band_sign: ``(B, Q)`` +1 covered by the mesh, -1 not.
      band_target: ``(B, Q)`` target coverage (0/1).
      band_mask: ``(B, Q)`` 1 for real entries, 0 for padding.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> vertices, faces = tm.icosphere(2)
        >>> renderer = tm.MeshRenderer(tm.make_scene(num_views=4, resolution=8), faces)
        >>> frame = renderer.frame(0.6 * vertices, np.random.default_rng(0))
        >>> frame.face.shape                                  # 2 views of 8x8 samples
        (2, 64)
    """

    frames: np.ndarray  # (B, 3, 3)
    xy: np.ndarray  # (B, P, 2) sample positions in the image plane
    face: np.ndarray  # (B, P) visible face or -1
    target_hit: np.ndarray  # (B, P) bool
    target_rgb: np.ndarray  # (B, P, 3)
    lights: np.ndarray  # (B, P, 2) two independent light indices per sample
    band_xy: np.ndarray  # (B, Q, 2) silhouette-band samples
    band_edge: np.ndarray  # (B, Q, 2) vertex indices of the nearest silhouette edge
    band_sign: np.ndarray  # (B, Q) +1 covered by the mesh, -1 not
    band_target: np.ndarray  # (B, Q) target coverage (0/1)
    band_mask: np.ndarray  # (B, Q) 1 for real entries, 0 for padding


class MeshRenderer:
    """Builds per-iteration rendering data and the differentiable loss for one mesh topology.

    Each iteration: :meth:`frame` (NumPy: visibility, targets, silhouette bands for a
    random subset of views), then :meth:`loss` (JAX, differentiable in the vertices):
    its first output's gradient is the noisy Monte Carlo gradient.

    Args:
      scene: the :class:`Scene`.
      faces: ``(F, 3)`` int triangles (fixed; the vertices change).

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> import jax
        >>> vertices, faces = tm.icosphere(2)
        >>> renderer = tm.MeshRenderer(tm.make_scene(num_views=4, resolution=8), faces)
        >>> frame = renderer.frame(0.6 * vertices, np.random.default_rng(0))
        >>> grads = jax.grad(lambda v: renderer.loss(v, frame)[0])(0.6 * vertices)
        >>> grads.shape
        (42, 3)
    """

    def __init__(self, scene: Scene, faces):
        self.scene = scene
        self.faces = np.asarray(faces, np.int64)
        self.edges, self.edge_faces = _edge_faces(self.faces)
        self.centres = _pixel_centres(scene)
        self._band_cap = 256

    def frame(self, vertices, rng: np.random.Generator, views=None) -> Frame:
        """Visibility, targets and silhouette bands for a random subset of views."""
        sc = self.scene
        v = np.asarray(vertices, np.float64)
        if views is None:
            views = rng.choice(len(sc.frames), size=sc.views_per_iteration, replace=False)
        n = sc.resolution**2
        per_view, bands = [], []
        for view in views:
            frame = sc.frames[view].astype(np.float64)
            xy = self.centres + (rng.random((n, 2)) - 0.5) * sc.pixel_size
            face, area = _rasterize(sc, frame, v, self.faces, xy)
            hit, rgb = _target_hits(sc, frame.astype(np.float32), xy.astype(np.float32))
            lights = rng.integers(0, len(LIGHT_DIRS), (n, 2))
            per_view.append((frame, xy, face, hit, rgb, lights))
            bands.append(self._band(v, frame, area, xy, face, hit))
        q = max(len(b[0]) for b in bands)
        while self._band_cap < q:  # grow in steps of 2x so jit recompiles rarely
            self._band_cap *= 2
        q = self._band_cap
        band = [
            np.zeros((len(views), q, 2), np.float32),
            np.zeros((len(views), q, 2), np.int32),
            np.zeros((len(views), q), np.float32),
            np.zeros((len(views), q), np.float32),
            np.zeros((len(views), q), np.float32),
        ]
        for i, b in enumerate(bands):
            m = len(b[0])
            for arr, val in zip(band, b):
                arr[i, :m] = val
            band[4][i, :m] = 1.0
        stack = lambda k, dt: np.stack([p[k] for p in per_view]).astype(dt)
        return Frame(
            stack(0, np.float32),
            stack(1, np.float32),
            stack(2, np.int32),
            stack(3, bool),
            stack(4, np.float32),
            stack(5, np.int32),
            *band,
        )

    def _band(self, v, frame, area, xy, face, hit):
        """Samples within BAND_PX of the mesh's outline, each with its nearest silhouette edge."""
        from scipy.ndimage import binary_dilation, binary_erosion
        from scipy.spatial import KDTree

        r = self.scene.resolution
        front = area[self.edge_faces] > 0
        sil = self.edges[front[:, 0] != front[:, 1]]
        covered = (face >= 0).reshape(r, r)
        if len(sil) == 0:
            return (np.zeros((0, 2)), np.zeros((0, 2), int), np.zeros(0), np.zeros(0))
        st = np.ones((3, 3), bool)
        near = (
            binary_dilation(covered, st, iterations=BAND_PX)
            & np.logical_not(binary_erosion(covered, st, iterations=BAND_PX, border_value=0))
        ).ravel()
        idx = np.nonzero(near)[0]
        p = xy[idx]
        p2 = v @ frame[:2].T
        a, b = p2[sil[:, 0]], p2[sil[:, 1]]
        # Candidates: the edges with the closest midpoints (edges are ~pixel-sized),
        # then the exact point-segment distance picks among them.
        k = min(6, len(sil))
        cand = KDTree(0.5 * (a + b)).query(p, k=k)[1].reshape(len(p), k)
        ca, cb = a[cand], b[cand]
        ab = cb - ca
        t = np.clip(((p[:, None] - ca) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-20), 0, 1)
        d2 = ((ca + t[..., None] * ab - p[:, None]) ** 2).sum(-1)
        nearest = sil[cand[np.arange(len(p)), d2.argmin(axis=1)]]
        sign = np.where(face[idx] >= 0, 1.0, -1.0)
        return p, nearest, sign, hit[idx].astype(np.float32)

    @functools.partial(jax.jit, static_argnums=0)
    def loss(self, vertices, frame: Frame, silhouette_weight: float = 1.0):
        """Surrogate loss whose gradient is the noisy Monte Carlo gradient; returns (surrogate,
        loss).

        ``loss`` is the single-sample image loss ``mean (I1 - I*)^2`` plus the silhouette
        term, what a user of a real Monte Carlo renderer would see (noisy).
        """
        faces = jnp.asarray(self.faces)
        n_pix = frame.xy.shape[1]
        f = jnp.maximum(frame.face, 0)
        tri = vertices[faces[f]]  # (B, P, 3, 3)
        normal = jnp.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
        normal = normal / jnp.sqrt(jnp.sum(normal * normal, -1, keepdims=True) + 1e-20)
        ldir, lcol = jnp.asarray(LIGHT_DIRS), jnp.asarray(LIGHT_COLORS)
        n_lights = ldir.shape[0]

        def one_sample(k):  # unbiased single-light estimate of the Lambertian sum
            return n_lights * jnp.maximum(jnp.sum(normal * ldir[k], -1), 0)[..., None] * lcol[k]

        i1, i2 = one_sample(frame.lights[..., 0]), one_sample(frame.lights[..., 1])
        both = ((frame.face >= 0) & frame.target_hit)[..., None]
        resid = jnp.where(both, i1 - frame.target_rgb, 0.0)
        shade_sur = jnp.sum(jax.lax.stop_gradient(resid) * i2) / n_pix
        shade_loss = 0.5 * jnp.sum(resid**2) / n_pix
        # Soft silhouette in the band around the outline.
        frames = jnp.asarray(frame.frames)
        e = vertices[frame.band_edge]  # (B, Q, 2, 3)
        a = jnp.einsum("bqc,bkc->bqk", e[..., 0, :], frames[:, :2])
        b = jnp.einsum("bqc,bkc->bqk", e[..., 1, :], frames[:, :2])
        ab, ap = b - a, frame.band_xy - a
        len2 = jnp.sum(ab * ab, -1)
        # Padding entries have a zero-length edge; keep their (masked) gradient finite.
        t = jnp.clip(jnp.sum(ap * ab, -1) / jnp.where(len2 > 1e-12, len2, 1.0), 0.0, 1.0)
        d = jnp.sqrt(jnp.sum((a + t[..., None] * ab - frame.band_xy) ** 2, -1) + 1e-20)
        cov = jax.nn.sigmoid(frame.band_sign * d / (self.scene.pixel_size * TAU_PX))
        sil = 0.5 * jnp.sum(frame.band_mask * (cov - frame.band_target) ** 2) / n_pix
        return shade_sur + silhouette_weight * sil, shade_loss + silhouette_weight * sil

    def __hash__(self):
        return id(self)

    def __eq__(self, other):
        return self is other


def render(scene: Scene, vertices, faces, view: int) -> np.ndarray:
    """Noise-free image ``(R, R, 3)`` of the mesh (all lights, pixel centres, no AA).

    Args:
      scene: the :class:`Scene`.
      vertices: ``(V, 3)`` positions.
      faces: ``(F, 3)`` int triangles.
      view: the camera's index.

    Returns:
      ``(R, R, 3)`` float32 RGB; 0 where no triangle is hit.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> vertices, faces = tm.icosphere(2)
        >>> tm.render(tm.make_scene(num_views=4, resolution=8), 0.6 * vertices, faces, 0).shape
        (8, 8, 3)
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    frame = scene.frames[view].astype(np.float64)
    face, _ = _rasterize(scene, frame, v, f, _pixel_centres(scene).astype(np.float64))
    tri = v[f[np.maximum(face, 0)]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
    rgb = np.maximum(n @ LIGHT_DIRS.T, 0) @ LIGHT_COLORS
    rgb[face < 0] = 0.0
    return rgb.reshape(scene.resolution, scene.resolution, 3).astype(np.float32)


def image_error(scene: Scene, vertices, faces) -> float:
    """Mean squared error of noise-free renders against the target over all views.

    Args:
      scene: the :class:`Scene`.
      vertices: ``(V, 3)`` positions.
      faces: ``(F, 3)`` int triangles.

    Returns:
      The error, a float (0 for a mesh that renders exactly as the cube).

    Example::

        >>> import numpy as np
        >>> from optax_bilateral.toy import triangle_mesh as tm
        >>> vertices, faces = tm.icosphere(2)
        >>> tm.image_error(tm.make_scene(num_views=4, resolution=8), 0.6 * vertices, faces) > 0
        True
    """
    errs = [
        np.mean((render(scene, vertices, faces, i) - render_target(scene, i)) ** 2)
        for i in range(len(scene.frames))
    ]
    return float(np.mean(errs))
