"""Mesh transforms: Large Steps and the paper's bilateral normal filter (supplement §3).

Vertex positions ``x`` (``(V, 3)``, static triangle ``faces``), the combinatorial
Laplacian ``L = D - A`` (``D`` the vertex degrees, ``A`` the adjacency) and the
Large Steps system matrix ``M = I + lambda L`` (Nicolet et al. 2021).

Large Steps optimises ``u = M x`` with "uniform" Adam. Since ``M`` is symmetric,
``df/du = M^-1 df/dx``, and ``x = M^-1 u``; written on ``x`` the step is

    g~_t = M^-1 g_t                                   (prefilter, A = M^-1; eq. 1)
    m_t, v_t = EMAs of g~_t, g~_t^2                   (eqs. 2, 4)
    Delta_t = M^-1 m^_t / (sqrt(max_k v^_t,k) + eps)   (postfilter, B = M^-1; eqs. 6, 10)

with ``m^, v^`` bias-corrected and the max over every vertex and coordinate
(Large Steps' ``AdamUniform``). The paper keeps ``A = M^-1`` and replaces ``B`` by
a cross-bilateral filter whose spatial kernel is ``M^-1`` and whose data term
compares vertex normals ``n`` with a von Mises-Fisher kernel, evaluated against a
fixed set of sphere directions ``s_k`` (a splat / diffuse / slice scheme):

    w_k(i) = exp((n_i . s_k - 1) / sigma_d)
    (B m)_i = sum_k w_k(i) [M^-1 (w_k * m)]_i / sum_k w_k(i) [M^-1 w_k]_i

so ``B_ij = [M^-1]_ij K(n_i, n_j) / sum_j [M^-1]_ij K(n_i, n_j)`` with
``K(n_i, n_j) = sum_k w_k(i) w_k(j)``, a quadrature of
``int exp((n_i + n_j) . s / sigma_d) ds``, which decreases with the angle between
the normals. ``M`` is an M-matrix with ``M 1 = 1``, so ``M^-1`` is non-negative and
row-stochastic; hence ``B`` is too (the bounded-step argument of supplement §1.3
holds), and as ``sigma_d -> inf`` every ``w_k = 1`` and ``B = M^-1``: the method
becomes Large Steps. The ``-1`` in the exponent is a global factor
``exp(-1/sigma_d)`` that cancels between numerator and denominator; it keeps the
weights in ``(0, 1]`` so small ``sigma_d`` does not overflow float32.

Solver (measured on this project's 2-core CPU; numbers and commands in the
README / report): every solve is a preconditioned conjugate gradient
(``jax.scipy.sparse.linalg.cg``, Jacobi preconditioner ``1 + lambda deg``) on all
right-hand sides at once, as one ``(V, C)`` array, with a padded
neighbour table for the matrix-vector product. "Factorise once per mesh" here
means building that table and the degrees once, in NumPy, when the transform is
made. Why CG and not a sparse Cholesky:

* the library may depend on jax, optax and numpy only, and JAX has no CPU sparse
  Cholesky; CG is jit-able, runs on any backend and needs no host callback;
* ``lambda`` may be traced, so it can be scheduled (supplement §4 suggests decaying
  the smoothing weight) without refactorising;
* measured with ``python -m experiments.mesh --overhead`` (``lambda = 19``,
  ``tol = 1e-4``; float32 CG vs float64 SciPy SuperLU; medians of 5 interleaved
  repeats, two runs on a shared, heavily loaded 2-core CPU, so ranges):

  ========  ===  ============  =============  =================
  vertices  rhs  CG            SuperLU solve  SuperLU factorise
  ========  ===  ============  =============  =================
  10242     3    12-17 ms      4-11 ms        0.14-0.20 s
  10242     128  0.27-0.36 s   2.4-22 s
  34812     3    46-92 ms      49-50 ms       1.1-1.4 s
  34812     128  3.5-4.3 s     13-14 s
  166412    3    0.13-0.41 s   0.45-0.48 s    13.5-15.5 s
  166412    128  20-23 s       84-104 s
  ========  ===  ============  =============  =================

  so CG is at most ~3x slower for Large Steps' 3 columns (before counting the
  factorisation) and 3-8x faster for the bilateral filter's 128 columns;
* per-column CG (``vmap`` over ``cg``) was about 5x slower than one CG over the
  column-normalised block, so columns are scaled to unit norm first (the solve is
  linear, so this changes no result) and share one Krylov iteration.

The cost is ``O(iterations * V * degree * C)`` with ``C = K (channels + 1)``
right-hand sides for ``K`` directions; the iteration count grows like
``sqrt(1 + lambda * 2 * max_degree)``. Inexact solves perturb the operator by
about ``tol``; the numerator and denominator of each direction share one solve.

Cost against Large Steps: the bilateral postfilter solves ``K (C + 1) = 128``
columns (``K = 32`` directions, ``C = 3``, uniform second moment; 224 with
"filtered") where Large Steps solves ``2 x 3``. On this project's CPU the update
took 21-55x Large Steps' update and a whole toy-scene iteration 8-14x as long
(+770% to +1300%) at 10k-166k vertices; with ``directions=16, tol=1e-3`` the
update took 8-11x and an iteration +220% to +345%. The paper's +2.7% to +9.3%
(supplement Table 2) is on a GPU, where rendering dominates and a batched
triangular solve makes extra columns nearly free.

Directions: ``sphere_directions`` maps a scrambled Sobol sequence
(``scipy.stats.qmc``) to the sphere with the area-preserving cylindrical map. It
imports SciPy lazily, when a transform is *built* with an integer ``directions``;
pass a ``(K, 3)`` array of unit vectors instead to keep SciPy out entirely.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

# Large Steps' examples use lambda around 10-100; 19 is a common choice there.
DEFAULT_LAMBDA = 19.0
# The paper's default data term (supplement §3: "sigma_d around 0.5").
DEFAULT_SIGMA_D = 0.5
# "A few dozen" directions; a power of two keeps Sobol's balance properties.
DEFAULT_DIRECTIONS = 32
# Relative residual per right-hand side; 1e-4 perturbs the filter far below the
# Monte Carlo noise it removes (lambda=19, 10k vertices: 70 CG iterations at 1e-5, 40 at 1e-3).
DEFAULT_TOL = 1e-4
DEFAULT_MAXITER = 2000


# ----------------------------------------------------------------------------
# The mesh and its linear system


class MeshLaplacian(NamedTuple):
    """The combinatorial Laplacian of a triangle mesh, built once by :func:`mesh_laplacian`.

    Attributes:
      neighbors: ``(V, D)`` int32, the one-ring of every vertex padded with ``V``
        (which indexes an appended zero row), ``D`` the maximum degree.
      degree: ``(V,)`` float32 vertex degrees.
      faces: ``(F, 3)`` int32 triangles (for vertex normals).
    """

    neighbors: jax.Array
    degree: jax.Array
    faces: jax.Array

    @property
    def num_vertices(self) -> int:
        return self.degree.shape[0]


def mesh_laplacian(faces, num_vertices: int | None = None) -> MeshLaplacian:
    """Builds the combinatorial Laplacian ``L = D - A`` of a triangle mesh.

    Args:
      faces: ``(F, 3)`` integer array of vertex indices (concrete, not traced).
      num_vertices: number of vertices ``V``; default ``faces.max() + 1``.

    Returns:
      A :class:`MeshLaplacian`, to pass as ``faces`` to the mesh transforms so the
      table is built once (and, with ``optax.inject_hyperparams``, treated as static).
    """
    if isinstance(faces, MeshLaplacian):
        return faces
    try:
        f = np.asarray(faces)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        raise TypeError("faces must be concrete (a NumPy/JAX array, not traced); build "
                        "mesh_laplacian(faces) outside jit, or pass static_args=('faces',) "
                        "to optax.inject_hyperparams") from None
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F >= 1 (triangles), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"faces must be an integer array of vertex indices, got dtype {f.dtype}")
    if f.min() < 0:
        raise ValueError(f"faces must hold vertex indices >= 0, got {f.min()}")
    n = int(f.max()) + 1 if num_vertices is None else num_vertices
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < int(f.max()) + 1:
        raise ValueError(f"num_vertices must be an int > max(faces) = {int(f.max())}, got {num_vertices!r}")
    n = int(n)
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        raise ValueError("faces contains a degenerate triangle (a repeated vertex index)")
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    # An interior edge appears in two faces; the Laplacian counts it once.
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    src = np.concatenate([edges[:, 0], edges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0]])
    order = np.argsort(src, kind="stable")
    src, dst = src[order], dst[order]
    degree = np.bincount(src, minlength=n)
    start = np.concatenate([[0], np.cumsum(degree)[:-1]])
    width = max(int(degree.max()), 1)
    neighbors = np.full((n, width), n, dtype=np.int32)
    neighbors[src, np.arange(len(src)) - start[src]] = dst
    return MeshLaplacian(jnp.asarray(neighbors), jnp.asarray(degree, jnp.float32),
                         jnp.asarray(f, jnp.int32))


def _matvec(mesh: MeshLaplacian, lambda_, x):
    """``(I + lambda L) x`` for ``x`` of shape ``(V, C)``."""
    padded = jnp.concatenate([x, jnp.zeros((1, x.shape[1]), x.dtype)])
    # One row gather per neighbour slot, summed: XLA:CPU runs this 5-10x faster
    # than gathering the (V, D, C) block and reducing it (measured at 10k vertices).
    neighbour_sum = padded[mesh.neighbors[:, 0]]
    for j in range(1, mesh.neighbors.shape[1]):
        neighbour_sum = neighbour_sum + padded[mesh.neighbors[:, j]]
    return x + lambda_ * (mesh.degree.astype(x.dtype)[:, None] * x - neighbour_sum)


@jax.jit
def _solve(neighbors, degree, b, lambda_, tol, maxiter):
    # One compilation per shape, shared by every transform and eager call
    # (cg's while_loop would otherwise be retraced for each new closure).
    mesh = MeshLaplacian(neighbors, degree, jnp.zeros((0, 3), jnp.int32))
    dtype = b.dtype
    scale = jnp.sqrt(jnp.sum(b * b, axis=0))
    scale = jnp.where(scale > 0, scale, 1.0)
    inv_diag = (1.0 / (1.0 + lambda_ * degree.astype(dtype)))[:, None]
    b = b / scale
    # Start from the Jacobi guess rather than zeros: a constant x0 makes XLA
    # constant-fold the first matvec's gathers, which takes seconds at 166k vertices.
    x, _ = jax.scipy.sparse.linalg.cg(
        lambda v: _matvec(mesh, lambda_, v), b, x0=inv_diag * b, tol=tol, atol=0.0,
        maxiter=maxiter, M=lambda r: inv_diag * r)
    return x * scale


def smoothing_solve(mesh: MeshLaplacian, b, lambda_, *, tol: float = DEFAULT_TOL,
                    maxiter: int = DEFAULT_MAXITER):
    """Solves ``(I + lambda L) x = b`` with Jacobi-preconditioned CG (Large Steps' "smooth").

    Args:
      mesh: a :class:`MeshLaplacian`.
      b: ``(V,)`` or ``(V, C)`` right-hand sides (one system per column).
      lambda_: smoothing weight ``>= 0``; may be traced.
      tol: relative residual per column (columns are scaled to unit norm first,
        which the linear solve does not notice, and share one Krylov iteration).
      maxiter: iteration cap.

    Returns:
      ``x`` with the shape and dtype of ``b``.
    """
    b = jnp.asarray(b)
    if b.ndim not in (1, 2) or b.shape[0] != mesh.num_vertices:
        raise ValueError(f"b must have shape (V,) or (V, C) with V = {mesh.num_vertices}, "
                         f"got {b.shape}")
    squeeze = b.ndim == 1
    if squeeze:
        b = b[:, None]
    dtype = b.dtype if jnp.issubdtype(b.dtype, jnp.floating) else jnp.float32
    x = _solve(mesh.neighbors, mesh.degree, b.astype(dtype), jnp.asarray(lambda_, dtype),
               jnp.asarray(tol, dtype), jnp.asarray(maxiter, jnp.int32))
    return x[:, 0] if squeeze else x


# ----------------------------------------------------------------------------
# Normals, directions and the bilateral filter


def vertex_normals(vertices, faces):
    """Area-weighted unit vertex normals (the guide of the bilateral filter).

    Args:
      vertices: ``(V, 3)`` positions.
      faces: ``(F, 3)`` int triangles (counter-clockwise seen from outside) or a
        :class:`MeshLaplacian`.
    """
    f = faces.faces if isinstance(faces, MeshLaplacian) else jnp.asarray(faces)
    vertices = jnp.asarray(vertices)
    a, b, c = vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]]
    face_n = jnp.cross(b - a, c - a)  # length = twice the area: area weighting for free
    n = jnp.zeros_like(vertices)
    for k in range(3):
        n = n.at[f[:, k]].add(face_n)
    norm = jnp.sqrt(jnp.sum(n * n, axis=-1, keepdims=True))
    return n / jnp.where(norm > 0, norm, 1.0)


def sphere_directions(num: int = DEFAULT_DIRECTIONS, seed: int = 0) -> np.ndarray:
    """``num`` quasi-random unit vectors: scrambled Sobol points mapped to the sphere.

    ``(u1, u2) -> (sqrt(1-z^2) cos 2 pi u1, sqrt(1-z^2) sin 2 pi u1, z)`` with
    ``z = 1 - 2 u2`` preserves area, so uniform points stay uniform. Imports
    ``scipy.stats.qmc`` lazily (SciPy is not a dependency of the library; pass
    explicit directions to the transforms to avoid it).
    """
    if isinstance(num, bool) or not isinstance(num, numbers.Integral) or num < 1:
        raise ValueError(f"num (number of sphere directions) must be a positive int, got {num!r}")
    try:
        from scipy.stats import qmc
    except ImportError as e:  # pragma: no cover - scipy is in the experiments extra
        raise ImportError("sphere_directions needs scipy (scipy.stats.qmc); install scipy or "
                          "pass directions= as a (K, 3) array of unit vectors") from e
    sampler = qmc.Sobol(d=2, scramble=True, seed=seed)
    m = math.ceil(math.log2(num))
    u = sampler.random_base2(m)[:num]  # a power-of-two prefix keeps the balance
    z = 1.0 - 2.0 * u[:, 1]
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = 2.0 * np.pi * u[:, 0]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1).astype(np.float32)


def _as_directions(directions) -> jax.Array:
    if isinstance(directions, numbers.Integral) and not isinstance(directions, bool):
        return jnp.asarray(sphere_directions(int(directions)))
    d = np.asarray(directions, dtype=np.float32)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
        raise ValueError(f"directions must be an int (number of Sobol directions) or a (K, 3) "
                         f"array of unit vectors, got shape {d.shape}")
    if not np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4):
        raise ValueError("directions must be unit vectors")
    return jnp.asarray(d)


def _is_concrete_inf(x) -> bool:
    try:
        return bool(np.isinf(np.asarray(x)))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return False


@jax.jit
def _bilateral(neighbors, degree, x, n, s, lambda_, sigma_d, tol, maxiter):
    """Splat (w_k * x, w_k), diffuse with one solve, slice with w_k, divide."""
    w = jnp.exp((n @ s.T - 1.0) / sigma_d)  # (V, K)
    num_v, num_dirs, channels = x.shape[0], w.shape[1], x.shape[1]
    splat = jnp.concatenate([w[:, :, None] * x[:, None, :], w[:, :, None]], axis=2)
    diffused = _solve(neighbors, degree, splat.reshape(num_v, num_dirs * (channels + 1)),
                      lambda_, tol, maxiter).reshape(num_v, num_dirs, channels + 1)
    sliced = jnp.einsum("vk,vkc->vc", w, diffused)
    num, den = sliced[:, :channels], sliced[:, channels:]
    ok = den > jnp.finfo(x.dtype).tiny
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), x)


def bilateral_normal_filter(fields: Sequence[Any], normals, mesh: MeshLaplacian, *,
                            lambda_=DEFAULT_LAMBDA, sigma_d=DEFAULT_SIGMA_D,
                            directions=DEFAULT_DIRECTIONS, tol: float = DEFAULT_TOL,
                            maxiter: int = DEFAULT_MAXITER) -> list:
    """Applies the paper's mesh cross-bilateral operator ``B`` to every field.

    ``(B x)_i = sum_k w_k(i) [M^-1 (w_k * x)]_i / sum_k w_k(i) [M^-1 w_k]_i`` with
    ``M = I + lambda L`` and ``w_k(i) = exp((n_i . s_k - 1) / sigma_d)`` (see the
    module docstring). All fields go through the same solves, so e.g. Adam's
    ``m`` and ``v`` get the same row-stochastic, non-negative operator (supplement
    §1.3). ``sigma_d = inf`` (concrete) skips the directions: ``B = M^-1``.
    Vertices whose denominator underflows (``sigma_d`` far below the spacing of the
    directions) keep their input value, i.e. that row of ``B`` is the identity.

    Args:
      fields: sequence of ``(V, C_i)`` arrays.
      normals: ``(V, 3)`` unit vertex normals (the guide).
      mesh: a :class:`MeshLaplacian`.
      lambda_: smoothing weight ``>= 0`` (may be traced).
      sigma_d: data-term width ``> 0``, ``inf`` for Large Steps (may be traced).
      directions: int (that many Sobol directions, built with SciPy) or ``(K, 3)``.
      tol, maxiter: CG settings (:func:`smoothing_solve`).

    Returns:
      A list with the filtered fields.
    """
    fields = [jnp.asarray(x) for x in fields]
    for x in fields:
        if x.ndim != 2 or x.shape[0] != mesh.num_vertices:
            raise ValueError(f"every field must have shape (V, C) with V = {mesh.num_vertices}, "
                             f"got {x.shape}")
    widths = [x.shape[1] for x in fields]
    splits = np.cumsum(widths)[:-1].tolist()
    x = jnp.concatenate(fields, axis=1)
    if _is_concrete_inf(sigma_d):
        return jnp.split(smoothing_solve(mesh, x, lambda_, tol=tol, maxiter=maxiter), splits, axis=1)
    s = directions if isinstance(directions, jax.Array) else _as_directions(directions)
    dtype = x.dtype
    out = _bilateral(mesh.neighbors, mesh.degree, x, jnp.asarray(normals, dtype), s.astype(dtype),
                     jnp.asarray(lambda_, dtype), jnp.asarray(sigma_d, dtype),
                     jnp.asarray(tol, dtype), jnp.asarray(maxiter, jnp.int32))
    return jnp.split(out, splits, axis=1)


# ----------------------------------------------------------------------------
# Argument checks


def _concrete_float(x):
    try:
        return float(np.asarray(x))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def _check_lambda(lambda_):
    v = _concrete_float(lambda_)
    if v is not None and not (v >= 0.0 and math.isfinite(v)):
        raise ValueError(f"lambda_ (Laplacian smoothing weight) must be finite and >= 0, got {v}")


def _check_sigma(sigma_d):
    v = _concrete_float(sigma_d)
    if v is not None and not v > 0.0:
        raise ValueError(f"sigma_d must be > 0 (inf gives Large Steps), got {v}")


def _check_unit(x, name):
    v = _concrete_float(x)
    if v is not None and not 0.0 <= v < 1.0:
        raise ValueError(f"{name} must be in [0, 1), got {v}")


def _check_solver(tol, maxiter):
    # Concrete values only: optax.inject_hyperparams may pass them as (traced) arrays.
    t = _concrete_float(tol)
    if t is not None and not t > 0:
        raise ValueError(f"tol (CG relative residual) must be > 0, got {tol!r}")
    m = _concrete_float(maxiter)
    if isinstance(maxiter, bool) or (m is not None and not (m >= 1 and m == int(m))):
        raise ValueError(f"maxiter (CG iteration cap) must be a positive int, got {maxiter!r}")


def _check_leaf(x, mesh: MeshLaplacian, what: str, channels: int | None = None):
    if x.ndim != 2 or x.shape[0] != mesh.num_vertices or (channels and x.shape[1] != channels):
        want = f"({mesh.num_vertices}, {channels})" if channels else f"({mesh.num_vertices}, C)"
        raise ValueError(f"{what}: every leaf must have shape {want} (one row per mesh vertex), "
                         f"got {x.shape}")


def _safe_increment(count):
    return jnp.where(count < jnp.iinfo(jnp.int32).max, count + 1, count).astype(jnp.int32)


# ----------------------------------------------------------------------------
# Transforms


def laplacian_smoothing(faces, lambda_=DEFAULT_LAMBDA, *, tol: float = DEFAULT_TOL,
                        maxiter: int = DEFAULT_MAXITER) -> optax.GradientTransformation:
    """Large Steps' smoothing ``g -> (I + lambda L)^-1 g`` on every ``(V, C)`` leaf (stateless).

    Used before the moments it is the prefilter ``A`` (eq. 1), the gradient of the
    reparameterisation ``u = (I + lambda L) x``; used after ``scale_by_uniform_adam``
    it maps the step on ``u`` back to ``x``.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian` (built once).
      lambda_: smoothing weight ``>= 0``; may be traced / injected.
      tol, maxiter: CG settings.
    """
    mesh = mesh_laplacian(faces)
    _check_lambda(lambda_)
    _check_solver(tol, maxiter)

    def init_fn(params):
        del params
        return optax.EmptyState()

    def update_fn(updates, state, params=None):
        del params
        leaves, treedef = jax.tree.flatten(updates)
        for x in leaves:
            _check_leaf(x, mesh, "laplacian_smoothing")
        out = [smoothing_solve(mesh, x, lambda_, tol=tol, maxiter=maxiter).astype(x.dtype)
               for x in leaves]
        return jax.tree.unflatten(treedef, out), state

    return optax.GradientTransformation(init_fn, update_fn)


class ScaleByUniformAdamState(NamedTuple):
    """Moments of :func:`scale_by_uniform_adam` and :func:`mesh_postfilter`."""

    count: jax.Array
    mu: Any
    nu: Any


def _moments(updates, state, b1, b2):
    mu = jax.tree.map(lambda g, m: b1 * m + (1 - b1) * g, updates, state.mu)
    nu = jax.tree.map(lambda g, v: b2 * v + (1 - b2) * g * g, updates, state.nu)
    count = _safe_increment(state.count)
    t = count.astype(jnp.float32)
    c1 = 1 - jnp.asarray(b1, jnp.float32) ** t
    c2 = 1 - jnp.asarray(b2, jnp.float32) ** t
    return count, mu, nu, c1, c2


def _init_moments(params):
    zeros = lambda p: jnp.zeros_like(p)  # noqa: E731
    return ScaleByUniformAdamState(jnp.zeros([], jnp.int32), jax.tree.map(zeros, params),
                                   jax.tree.map(zeros, params))


def scale_by_uniform_adam(b1=0.9, b2=0.999, eps=1e-8) -> optax.GradientTransformation:
    """Large Steps' ``AdamUniform``: Adam with one second moment per leaf.

        m_t = b1 m_{t-1} + (1-b1) g_t,   v_t = b2 v_{t-1} + (1-b2) g_t^2
        Delta_t = m^_t / (sqrt(max_k v^_t,k) + eps)

    with bias-corrected ``m^, v^`` and the max over every entry of the leaf (all
    vertices and coordinates). Every vertex then moves with the same step scale,
    which keeps the reparameterised update of Large Steps uniform over the mesh.
    """
    _check_unit(b1, "b1")
    _check_unit(b2, "b2")

    def update_fn(updates, state, params=None):
        del params
        count, mu, nu, c1, c2 = _moments(updates, state, b1, b2)
        out = jax.tree.map(
            lambda m, v: ((m / c1.astype(m.dtype))
                          / (jnp.sqrt(jnp.max(v) / c2.astype(v.dtype)) + eps)).astype(m.dtype),
            mu, nu)
        return out, ScaleByUniformAdamState(count, mu, nu)

    return optax.GradientTransformation(_init_moments, update_fn)


def mesh_postfilter(faces, lambda_=DEFAULT_LAMBDA, sigma_d=DEFAULT_SIGMA_D, b1=0.9, b2=0.999,
                    eps=1e-8, *, second_moment: str = "uniform", directions=DEFAULT_DIRECTIONS,
                    tol: float = DEFAULT_TOL, maxiter: int = DEFAULT_MAXITER
                    ) -> optax.GradientTransformationExtraArgs:
    """Adam moments with the bilateral normal postfilter ``B`` (supplement eqs. 6-10).

        m_t, v_t = EMAs of the incoming (prefiltered) gradient   (eqs. 2, 4; unfiltered in the state)
        "uniform":  Delta_t = B m^_t / (sqrt(max_k v^_t,k) + eps)
        "filtered": Delta_t = B m^_t / (sqrt(B v^_t) + eps)       (same B for m and v, §1.3)

    ``B`` is :func:`bilateral_normal_filter` with the guide ``n`` = the vertex
    normals of ``params`` (the current positions; "cross-bilateral"). With
    ``sigma_d = inf`` and "uniform" this is Large Steps' postfilter ``M^-1``.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian`.
      lambda_: smoothing weight of ``M = I + lambda L`` (may be traced).
      sigma_d: data-term width on normals (``> 0``, ``inf`` = Large Steps; may be traced).
      b1, b2, eps: Adam's decay rates and epsilon (Large Steps uses 0.9, 0.999).
      second_moment: ``"uniform"`` (max over the leaf, as Large Steps) or ``"filtered"``.
      directions: int number of Sobol sphere directions (needs SciPy when built) or a
        ``(K, 3)`` array of unit vectors.
      tol, maxiter: CG settings.

    ``update(updates, state, params)`` needs ``params``: a pytree of ``(V, 3)``
    vertex-position leaves of this mesh (the updates have the same structure).
    """
    mesh = mesh_laplacian(faces)
    _check_lambda(lambda_)
    _check_sigma(sigma_d)
    _check_unit(b1, "b1")
    _check_unit(b2, "b2")
    _check_solver(tol, maxiter)
    if second_moment not in ("uniform", "filtered"):
        raise ValueError(f"second_moment must be 'uniform' or 'filtered', got {second_moment!r}")
    dirs = None if _is_concrete_inf(sigma_d) else _as_directions(directions)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        if params is None:
            raise ValueError("mesh_postfilter needs params (the vertex positions) to compute "
                             "the normals that guide the filter: call update(updates, state, params)")
        count, mu, nu, c1, c2 = _moments(updates, state, b1, b2)

        def step(m, v, x):
            _check_leaf(x, mesh, "mesh_postfilter params", channels=3)
            _check_leaf(m, mesh, "mesh_postfilter updates")
            m_hat = m / c1.astype(m.dtype)
            v_hat = v / c2.astype(v.dtype)
            normals = vertex_normals(x, mesh)
            kw = dict(lambda_=lambda_, sigma_d=sigma_d, directions=dirs, tol=tol, maxiter=maxiter)
            if second_moment == "uniform":
                (m_f,) = bilateral_normal_filter([m_hat], normals, mesh, **kw)
                denom = jnp.sqrt(jnp.max(v_hat)) + eps
            else:
                m_f, v_f = bilateral_normal_filter([m_hat, v_hat], normals, mesh, **kw)
                # B is non-negative, so B v >= 0 up to the CG tolerance; clip its round-off.
                denom = jnp.sqrt(jnp.maximum(v_f, 0.0)) + eps
            return (m_f / denom).astype(m.dtype)

        out = jax.tree.map(step, mu, nu, params)
        return out, ScaleByUniformAdamState(count, mu, nu)

    return optax.GradientTransformationExtraArgs(_init_moments, update_fn)


def large_steps(learning_rate, faces, lambda_=DEFAULT_LAMBDA, b1=0.9, b2=0.999, eps=1e-8, *,
                tol: float = DEFAULT_TOL, maxiter: int = DEFAULT_MAXITER
                ) -> optax.GradientTransformationExtraArgs:
    """Large Steps in Inverse Rendering of Geometry (Nicolet et al. 2021) on vertex positions.

        x <- x - lr M^-1 AdamUniform(M^-1 g),    M = I + lambda L

    which equals optimising ``u = M x`` with ``AdamUniform`` and reading back
    ``x = M^-1 u`` (``M`` symmetric, so ``df/du = M^-1 df/dx``). In the paper's terms:
    prefilter ``A = M^-1``, postfilter ``B = M^-1``, uniform second moment.

    Args:
      learning_rate: float or optax schedule.
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian`.
      lambda_: smoothing weight (may be traced / injected).
      b1, b2, eps: ``AdamUniform``'s parameters.
      tol, maxiter: CG settings.
    """
    mesh = mesh_laplacian(faces)
    return optax.chain(
        laplacian_smoothing(mesh, lambda_, tol=tol, maxiter=maxiter),
        scale_by_uniform_adam(b1, b2, eps),
        laplacian_smoothing(mesh, lambda_, tol=tol, maxiter=maxiter),
        optax.scale_by_learning_rate(learning_rate),
    )


def bilateral_large_steps(learning_rate, faces, lambda_=DEFAULT_LAMBDA, sigma_d=DEFAULT_SIGMA_D,
                          b1=0.9, b2=0.999, eps=1e-8, *, second_moment: str = "uniform",
                          directions=DEFAULT_DIRECTIONS, tol: float = DEFAULT_TOL,
                          maxiter: int = DEFAULT_MAXITER) -> optax.GradientTransformationExtraArgs:
    """The paper's mesh optimizer: Large Steps with a cross-bilateral postfilter on normals.

        g~ = M^-1 g,   m, v = EMAs of g~
        x <- x - lr B m^ / (sqrt(max v^) + eps)            ("uniform", default)
        x <- x - lr B m^ / (sqrt(B v^) + eps)              ("filtered")

    ``B`` diffuses with ``M^-1 = (I + lambda L)^-1`` but not across normals that
    differ (von Mises-Fisher data term of width ``sigma_d``, see
    :func:`bilateral_normal_filter`). ``sigma_d -> inf`` gives :func:`large_steps`.
    ``update`` needs ``params`` (the vertex positions give the normals).

    With ``optax.inject_hyperparams`` (to schedule ``lambda_``, ``sigma_d`` or the
    learning rate) pass a :class:`MeshLaplacian` as ``faces``, or list ``"faces"``
    (and ``"directions"`` if it is an array) in ``static_args``.
    """
    mesh = mesh_laplacian(faces)
    return optax.chain(
        laplacian_smoothing(mesh, lambda_, tol=tol, maxiter=maxiter),
        mesh_postfilter(mesh, lambda_, sigma_d, b1, b2, eps, second_moment=second_moment,
                        directions=directions, tol=tol, maxiter=maxiter),
        optax.scale_by_learning_rate(learning_rate),
    )
