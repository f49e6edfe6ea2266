"""Vertex normals, sphere directions and the paper's bilateral normal filter ``B``.

The paper (supplement §3) replaces Large Steps' postfilter ``M^-1`` by a cross-bilateral
filter whose spatial kernel is ``M^-1`` and whose data term compares vertex normals ``n``
with von Mises-Fisher kernels, evaluated against a fixed set of sphere directions ``s_k``
(splat, diffuse, slice), as the authors do:

    w_k(i)   = exp((max(n_i . s_k, -1) - 1) / sigma_d)     (splat)
    phi_k(i) = exp((max(n_i . s_k, -1) - 1) / sigma_phi)   (slice)
    (B m)_i  = sum_k phi_k(i) [M^-1 (w_k * m)]_i / sum_k phi_k(i) [M^-1 w_k]_i

so ``B_ij = [M^-1]_ij K(n_i, n_j) / sum_j [M^-1]_ij K(n_i, n_j)`` with
``K(n_i, n_j) = sum_k phi_k(i) w_k(j)``. ``M^-1`` is non-negative and row-stochastic;
hence ``B`` is too (the bounded-step argument of supplement §1.3 holds when ``m`` and ``v``
share ``B``), and as ``sigma_d -> inf`` every ``w_k = 1`` and ``B = M^-1``: Large Steps.
The ``-1`` in the exponents is a global factor that cancels between numerator and
denominator; it keeps the weights in ``(0, 1]`` so that a small sigma does not overflow
float32.
"""

from __future__ import annotations

import functools
import math
import numbers
import operator
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src import numerics
from optax_bilateral._src.mesh.config import (
    DEFAULT_DIRECTIONS,
    DEFAULT_LAMBDA,
    DEFAULT_WIDTH,
    NORMALS,
    FilterSetting,
    NormalFilter,
    NormalWeighting,
    SolverSetting,
    UnitNormals,
    check_directions,
    deprecated_keywords,
    filter_of,
    solver_of,
)
from optax_bilateral._src.mesh.laplacian import (
    Faces,
    Field,
    MeshLaplacian,
    Positions,
    System,
    factor_order,
    merge,
    solve_columns,
    spread,
)
from optax_bilateral._src.validation import check_positive, is_concrete


def _unit(x):
    norm = jnp.sqrt(jnp.sum(x * x, axis=-1, keepdims=True))
    return x / jnp.where(norm > 0, norm, 1.0)


def vertex_normals(
    vertices: Positions, faces: Faces, weighting: NormalWeighting = "area"
) -> UnitNormals:
    """Unit vertex normals (the guide of the bilateral filter).

    Args:
      vertices: ``(V, 3)`` positions.
      faces: ``(F, 3)`` int triangles (counter-clockwise seen from outside) or a
        :class:`MeshLaplacian` (then ``vertices`` are the input vertices, seams included).
      weighting: how face normals are averaged: ``"area"`` (by face area, the
        default), ``"uniform"`` (unit face normals, unweighted: what the authors' code
        computes, up to ``O(1/F)``; docs/triangle_mesh.md) or ``"angle"`` (by the corner angles).

    Returns:
      ``(V, 3)`` unit normals, the dtype of ``vertices``; a vertex whose faces' normals
      cancel gets a zero normal.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> # the top vertex
        >>> print(np.round(np.asarray(obm.vertex_normals(verts, faces)[4], float), 3))
        [0. 0. 1.]
    """
    if weighting not in NORMALS:
        raise ValueError(f"weighting (normals) must be one of {NORMALS}, got {weighting!r}")
    vertices = jnp.asarray(vertices)
    if isinstance(faces, MeshLaplacian):
        f, mesh = faces.faces, faces
        vertices = merge(mesh, vertices)
    else:
        f, mesh = jnp.asarray(faces), None
    corners = [vertices[f[:, k]] for k in range(3)]
    face_n = jnp.cross(corners[1] - corners[0], corners[2] - corners[0])  # |.| = twice the area
    if weighting != "area":
        face_n = _unit(face_n)
    n = jnp.zeros_like(vertices)
    for k in range(3):
        w = face_n
        if weighting == "angle":
            e0 = corners[(k + 1) % 3] - corners[k]
            e1 = corners[(k + 2) % 3] - corners[k]
            angle = jnp.arctan2(jnp.linalg.norm(jnp.cross(e0, e1), axis=-1), jnp.sum(e0 * e1, -1))
            w = face_n * angle[:, None]
        n = n.at[f[:, k]].add(w)
    n = _unit(n)
    return n if mesh is None else spread(mesh, n)


def normals_of(normal_filter: NormalFilter, mesh: MeshLaplacian):
    """``positions -> (V, 3) unit normals``, as the filter's ``normals`` setting says."""
    if callable(normal_filter.normals):
        return normal_filter.normals
    weighting = normal_filter.normals
    return lambda x: vertex_normals(x, mesh, weighting)


def sphere_directions(
    num: int = DEFAULT_DIRECTIONS, seed: int = 0, *, lloyd: bool = True
) -> np.ndarray:
    """``num`` quasi-random unit vectors: scrambled Sobol points mapped to the sphere.

    ``(u1, u2) -> (sqrt(1-z^2) cos 2 pi u1, sqrt(1-z^2) sin 2 pi u1, z)`` with
    ``z = 1 - 2 u2`` preserves area, so uniform points stay uniform. With
    ``lloyd=True`` (default) the points are first relaxed by SciPy's Lloyd step, as
    the authors' ``Sobol(d=2, scramble=True, optimization="lloyd", seed=0)``: for
    ``num=32, seed=0`` these are their directions. A non-power-of-two ``num`` takes
    the first ``num`` of the next power of two. Imports ``scipy.stats.qmc`` (SciPy is
    not a dependency of the library; pass explicit directions to avoid it).

    Args:
      num: the number of directions (>= 1; default 32, :data:`DEFAULT_DIRECTIONS`).
      seed: the scrambling seed (default 0, the authors').
      lloyd: relax the points with SciPy's Lloyd step first (default True).

    Returns:
      ``(num, 3)`` float64 unit vectors.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral import triangle_mesh as obm
        >>> s = obm.sphere_directions(8)
        >>> s.shape, bool(np.allclose(np.linalg.norm(s, axis=1), 1.0))
        ((8, 3), True)
    """
    if isinstance(num, bool) or not isinstance(num, numbers.Integral) or num < 1:
        raise ValueError(f"num (number of sphere directions) must be a positive int, got {num!r}")
    try:
        from scipy.stats import qmc
    except ImportError as e:  # pragma: no cover - scipy is in the experiments extra
        raise ImportError(
            "sphere_directions needs scipy (scipy.stats.qmc); install scipy or "
            "pass directions= as a (K, 3) array of unit vectors"
        ) from e
    # seed=, not rng=: the legacy stream, the authors' directions (SciPy's decorator that keeps
    # seed= hides it from type checkers).
    sampler = qmc.Sobol(
        d=2,
        scramble=True,
        seed=seed,  # pyright: ignore[reportCallIssue]
        optimization="lloyd" if lloyd else None,
    )
    # A power-of-two prefix keeps the balance.
    u = sampler.random_base2(math.ceil(math.log2(num)))[:num]
    z = 1.0 - 2.0 * u[:, 1]
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = 2.0 * np.pi * u[:, 0]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def directions_of(normal_filter: NormalFilter) -> np.ndarray | None:
    """The filter's ``(K, 3)`` sphere directions, or None where ``B = M^-1`` (no data term)."""
    if normal_filter.is_large_steps:
        return None
    directions = normal_filter.directions
    if isinstance(directions, numbers.Integral):
        return sphere_directions(int(directions))
    return check_directions(directions)


def _cosines(n, s):
    """``(U, K)`` dot products ``n_i . s_k``, the three products written out: XLA fuses them
    into the exponentials that read them, where a dot of depth three is a library call of its
    own."""
    return n[:, 0, None] * s[:, 0] + n[:, 1, None] * s[:, 1] + n[:, 2, None] * s[:, 2]


def _vmf(cosines, sigma, xp=jnp):
    """``exp((max(n . s, -1) - 1) / sigma)`` from :func:`_cosines`: the authors' clamp,
    shifted into (0, 1]."""
    return xp.exp((xp.maximum(cosines, -1.0) - 1.0) / sigma)


def _fibonacci_sphere(num: int) -> np.ndarray:
    """``num`` near-uniform unit vectors on a golden-angle spiral."""
    i = np.arange(num) + 0.5
    z = 1.0 - 2.0 * i / num
    r = np.sqrt(1.0 - z * z)
    angle = np.pi * (1.0 + math.sqrt(5.0)) * i
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=-1)


def kernel_bases(
    directions: np.ndarray, sigma_d: float, sigma_phi: float, tol: float, *, samples: int = 1024
) -> tuple[np.ndarray, np.ndarray] | None:
    """The data term ``K(a, b) = sum_k phi_k(a) w_k(b)`` compressed to fewer terms.

    ``K = Phi W^T`` over the sphere has rank at most ``K``, and for smooth kernels far less
    (its singular values fall by degree of spherical harmonics: 1, 3, 5, 7 of them). The
    truncated SVD of ``Phi W^T`` over ``samples`` near-uniform normals (and the zero normal
    of a vertex whose faces cancel) gives ``(K, r)`` matrices with
    ``K_r(a, b) = (phi(a) A_phi) . (w(b) A_w)``, ``r`` the least rank whose relative error
    on those normals is at most ``tol`` (on other normals the error measured at most 1.05
    ``tol``). Splatting with ``w A_w`` and slicing with ``phi A_phi`` takes ``r (C + 1)``
    solve columns, not ``K (C + 1)``; since ``K_r >= (1 - tol) K > 0``, ``B`` stays
    non-negative and row-stochastic.

    Args:
      directions: ``(K, 3)`` unit vectors.
      sigma_d: the splat width (a concrete number ``> 0``).
      sigma_phi: the slice width (a concrete number ``> 0``).
      tol: the largest relative error of ``K_r`` on the sample normals, in ``[0, 0.5)``
        (``0``: None).
      samples: how many normals (a Fibonacci sphere, ``>= 16``) the error is measured on.

    Returns:
      ``(A_w, A_phi)``, float64 ``(K, r)``, or None where only ``r = K`` holds ``tol``.
      The transforms compute them once per setting (:class:`NormalFilter`'s ``kernel_tol``).

    Example::

        >>> from optax_bilateral import triangle_mesh as obm
        >>> dirs = obm.sphere_directions(32)
        >>> a_w, a_phi = obm.kernel_bases(dirs, 0.5, 0.4, 0.02)   # the defaults
        >>> a_w.shape                                # 16 terms: 64 solve columns, not 128
        (32, 16)
        >>> print(obm.kernel_bases(dirs, 0.02, 0.02, 0.02))       # narrow lobes: all 32
        None
    """
    directions = check_directions(directions)
    for value, name in ((sigma_d, "sigma_d"), (sigma_phi, "sigma_phi")):
        if not is_concrete(value):
            raise TypeError(f"{name} must be a concrete number here (it is read on the host)")
        check_positive(value, name)
    if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not 0 <= tol < 0.5:
        raise ValueError(f"tol must be a real number >= 0 and < 0.5, got {tol!r}")
    if isinstance(samples, bool) or not isinstance(samples, numbers.Integral) or samples < 16:
        raise ValueError(f"samples must be an int >= 16, got {samples!r}")
    key = tuple(map(tuple, directions.tolist()))
    widths = float(np.asarray(sigma_d)), float(np.asarray(sigma_phi))
    return _kernel_bases(key, *widths, float(tol), int(samples))


@functools.lru_cache(maxsize=64)
def _kernel_bases(directions, sigma_d, sigma_phi, tol, samples):
    s = np.asarray(directions)
    if tol <= 0:
        return None
    normals = np.concatenate([_fibonacci_sphere(samples), np.zeros((1, 3))])
    cosines = _cosines(normals, s)
    phi, w = _vmf(cosines, sigma_phi, np), _vmf(cosines, sigma_d, np)
    exact = phi @ w.T
    q_phi, r_phi = np.linalg.qr(phi)
    q_w, r_w = np.linalg.qr(w)
    u, singular, vt = np.linalg.svd(r_phi @ r_w.T)
    left, right = q_phi @ u, q_w @ vt.T
    approx = np.zeros_like(exact)
    for rank in range(1, len(s)):
        t = rank - 1
        approx += singular[t] * np.outer(left[:, t], right[:, t])
        # A kernel that underflows to 0 somewhere has no relative error there: no rank holds.
        with np.errstate(divide="ignore", invalid="ignore"):
            error = np.max(np.abs(approx - exact) / exact)
        if error <= tol:
            scale = np.sqrt(singular[:rank])
            # Least squares, not R^-1: repeated directions leave Phi rank-deficient.
            a_phi = np.linalg.lstsq(phi, left[:, :rank] * scale, rcond=None)[0]
            a_w = np.linalg.lstsq(w, right[:, :rank] * scale, rcond=None)[0]
            return a_w, a_phi
    return None


def _bilateral(host, graph, x, n, terms, widths, solve, x0):
    """Splat (w_k * x, w_k), diffuse with one solve, slice with phi_k, divide. ``graph`` is
    ``(neighbors, degree)``, ``terms`` ``(directions, bases)`` with ``bases`` None or
    ``(A_w, A_phi)`` (:func:`kernel_bases`), ``widths`` ``(sigma_d, sigma_phi)``, ``solve``
    ``(lambda_, tol, maxiter)``.

    Returns the filtered ``(U, C)`` field and the diffused ``(U, r (C + 1))`` columns.
    """
    (s, bases), (sigma_d, sigma_phi) = terms, widths
    order = factor_order(host)
    if order is not None:
        # In the factor's order the extension sweeps the columns where XLA writes them.
        x, n = x[order.perm], n[order.perm]
    cosines = _cosines(n, s)  # (U, K)
    w, phi = _vmf(cosines, sigma_d), _vmf(cosines, sigma_phi)
    if bases is not None:
        w, phi = w @ bases[0], phi @ bases[1]  # (U, r)
    num_v, num_dirs, channels = x.shape[0], w.shape[1], x.shape[1]
    # The weights' column as x's channel of ones, computed once: the (U, r, C + 1) block is
    # then one product a value, not a concatenation XLA's loop selects into value by value.
    (ones,) = numerics.materialize((jnp.concatenate([x, jnp.ones((num_v, 1), x.dtype)], 1),))
    rhs = (w[:, :, None] * ones[:, None, :]).reshape(num_v, num_dirs * (channels + 1))
    (neighbors, degree), (lambda_, tol, maxiter) = graph, solve
    flat = solve_columns(
        host, neighbors, degree, rhs, lambda_, tol, maxiter, x0, ordered=order is not None
    )
    cols = flat.reshape(num_v, num_dirs, channels + 1)
    # The terms' sum written out, which XLA fuses into one loop (as a batched dot it did not).
    sliced = functools.reduce(operator.add, (phi[:, k, None] * cols[:, k] for k in range(num_dirs)))
    num, den = sliced[:, :channels], sliced[:, channels:]
    ok = den > jnp.finfo(x.dtype).tiny
    out = jnp.where(ok, num / jnp.where(ok, den, 1.0), x)
    if order is not None:
        return out[order.inverse], flat[order.inverse]
    return out, flat


_bilateral_jit = jax.jit(_bilateral, static_argnums=0)


class Operator(NamedTuple):
    """The operator ``B`` without its fields and its guide (the normals)."""

    system: System  # M = I + lambda L and its solver
    directions: Any  # (K, 3) unit vectors, or None where sigma_d is inf (B = M^-1)
    sigma_d: Any
    sigma_phi: Any
    bases: Any  # (A_w, A_phi) of kernel_bases, or None: every direction its own term

    @classmethod
    def of(cls, system: System, normal_filter: NormalFilter) -> Operator:
        # A welded seam's copies are rows, not a finer mesh: the distinct vertices set the width.
        normal_filter = normal_filter.on_mesh(system.mesh.num_merged)
        s = directions_of(normal_filter)
        sigma_d, sigma_phi = normal_filter.sigma_d, normal_filter.sigma_phi
        bases = None
        if s is not None and is_concrete(sigma_d) and is_concrete(sigma_phi):
            widths = float(np.asarray(sigma_d)), float(np.asarray(sigma_phi))
            bases = kernel_bases(s, *widths, normal_filter.kernel_tol)
        return cls(system, s, sigma_d, sigma_phi, bases)

    @property
    def terms(self) -> int:
        """How many splat/slice pairs ``B`` diffuses: the rank ``r`` or every direction."""
        if self.directions is None:
            return 0
        return len(self.directions) if self.bases is None else self.bases[0].shape[1]

    def columns(self, channels: int) -> int:
        """How many columns the solve of a ``channels``-wide field takes: ``r (C + 1)`` (each
        term's weighted field and its weight), or ``C`` for ``B = M^-1``."""
        return channels if self.directions is None else self.terms * (channels + 1)


def bilateral_fields(fields, normals, op: Operator, x0=None):
    """The operator B on a list of ``(V, C_i)`` fields; returns (fields, diffused columns)."""
    system = op.system
    mesh = system.mesh
    widths = [x.shape[1] for x in fields]
    splits = np.cumsum(widths)[:-1].tolist()
    x = merge(mesh, jnp.concatenate(fields, axis=1))
    dtype = x.dtype
    if op.directions is None:
        # Every splat weight is 1: the slice weights cancel and B = M^-1.
        out = system.solve(x, x0)
        flat = out
    else:
        as_dtype = lambda a: jnp.asarray(a, dtype)
        solve = (
            as_dtype(system.lambda_),
            as_dtype(system.tol),
            jnp.asarray(system.maxiter, jnp.int32),
        )
        out, flat = _bilateral_jit(
            system.host,
            (mesh.neighbors, mesh.degree),
            x,
            as_dtype(merge(mesh, jnp.asarray(normals))),
            (
                as_dtype(op.directions),
                None if op.bases is None else tuple(map(as_dtype, op.bases)),
            ),
            (as_dtype(op.sigma_d), as_dtype(op.sigma_phi)),
            solve,
            x0,
        )
    return jnp.split(spread(mesh, out), splits, axis=1), flat


def bilateral_normal_filter(
    fields: Sequence[Field],
    normals: Positions,
    mesh: MeshLaplacian,
    *,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: FilterSetting = DEFAULT_WIDTH,
    solver: SolverSetting = "cg",
    **deprecated: Any,
) -> list[jax.Array]:
    """Applies the paper's mesh cross-bilateral operator ``B`` to every field.

    ``(B x)_i = sum_k phi_k(i) [M^-1 (w_k * x)]_i / sum_k phi_k(i) [M^-1 w_k]_i`` with
    ``M = I + lambda L`` (``L = D - A`` the combinatorial Laplacian), sphere directions
    ``s_k``, splat weights ``w_k(i) = exp((max(n_i . s_k, -1) - 1) / sigma_d)`` and slice
    weights ``phi_k(i) = exp((max(n_i . s_k, -1) - 1) / sigma_phi)`` (the authors' code:
    von Mises-Fisher kernels evaluated against fixed directions; supplement §3). So
    ``B_ij = [M^-1]_ij K(n_i, n_j) / sum_j [M^-1]_ij K(n_i, n_j)`` with
    ``K(n_i, n_j) = sum_k phi_k(i) w_k(j)``: ``M^-1`` is non-negative and row-stochastic
    (``M 1 = 1``), hence so is ``B``. All fields go through the same solves, so e.g. Adam's ``m``
    and ``v`` get the same row-stochastic, non-negative operator (supplement §1.3).
    ``sigma_d = inf`` (concrete) skips the directions: ``B = M^-1``. Vertices whose
    denominator underflows (a sigma far below the spacing of the directions) keep
    their input value, i.e. that row of ``B`` is the identity.

    Args:
      fields: sequence of ``(V, C_i)`` arrays.
      normals: ``(V, 3)`` unit vertex normals (the guide).
      mesh: a :class:`MeshLaplacian`.
      lambda_: smoothing weight ``>= 0`` (may be traced).
      sigma_d: splat width ``> 0``, ``inf`` for Large Steps (may be traced), a
        :class:`DensityWidth` (the default: 0.5 up to 2562 vertices, wider on finer meshes),
        or a :class:`NormalFilter` (``sigma_d``, ``sigma_phi``, ``directions``; its
        ``normals`` is not read, the normals are given). By default ``sigma_phi`` 0.4 and 32
        directions.
      solver: ``"cg"``, ``"cholesky"``, a :class:`CG` or a :class:`Cholesky`; see
        :func:`smoothing_solve`.
      **deprecated: ``sigma_phi``, ``directions`` (fields of :class:`NormalFilter`),
        ``tol``, ``maxiter`` (of :class:`CG`): still applied for one release, with a
        ``DeprecationWarning``.

    Returns:
      A list with the filtered fields (shapes and dtypes as given).

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> mesh = obm.mesh_laplacian(faces)
        >>> normals = obm.vertex_normals(verts, faces)
        >>> ones, spike = jnp.ones((6, 1)), jnp.zeros((6, 1)).at[4].set(1.0)
        >>> out = obm.bilateral_normal_filter([ones, spike], normals, mesh, lambda_=1.0,
        ...                                   sigma_d=obm.NormalFilter(0.5, directions=8))
        >>> print(np.round(np.asarray(out[0][:, 0], float), 3))  # row-stochastic: constants stay
        [1. 1. 1. 1. 1. 1.]
    """
    accepted = ("sigma_phi", "directions", "tol", "maxiter")
    old = deprecated_keywords("bilateral_normal_filter", deprecated, accepted)
    system = System.of(mesh, solver_of(solver, old), lambda_)
    op = Operator.of(system, filter_of(sigma_d, old))
    fields = [jnp.asarray(x) for x in fields]
    for x in fields:
        if x.ndim != 2 or x.shape[0] != mesh.num_vertices:
            raise ValueError(
                f"every field must have shape (V, C) with V = {mesh.num_vertices}, got {x.shape}"
            )
    out, _ = bilateral_fields(fields, normals, op)
    return out
