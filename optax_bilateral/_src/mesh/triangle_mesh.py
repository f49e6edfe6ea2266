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
compares vertex normals ``n`` with von Mises-Fisher kernels, evaluated against a
fixed set of sphere directions ``s_k`` (splat, diffuse, slice), as the authors do:

    w_k(i)   = exp((max(n_i . s_k, -1) - 1) / sigma_d)     (splat)
    phi_k(i) = exp((max(n_i . s_k, -1) - 1) / sigma_phi)   (slice)
    (B m)_i  = sum_k phi_k(i) [M^-1 (w_k * m)]_i / sum_k phi_k(i) [M^-1 w_k]_i

so ``B_ij = [M^-1]_ij K(n_i, n_j) / sum_j [M^-1]_ij K(n_i, n_j)`` with
``K(n_i, n_j) = sum_k phi_k(i) w_k(j)``. ``M`` is an M-matrix with ``M 1 = 1``, so
``M^-1`` is non-negative and row-stochastic; hence ``B`` is too (the bounded-step
argument of supplement §1.3 holds when ``m`` and ``v`` share ``B``), and as
``sigma_d -> inf`` every ``w_k = 1`` and ``B = M^-1``: Large Steps. The ``-1`` in
the exponents is a global factor that cancels between numerator and denominator;
it keeps the weights in ``(0, 1]`` so that a small sigma does not overflow float32.

Solvers (``solver=``): ``"cg"`` (default), Jacobi-preconditioned conjugate gradients
on all right-hand sides at once (columns scaled to unit norm share one Krylov
iteration), jit-able on any backend with a traced ``lambda``; ``"cholesky"``, a
sparse Cholesky factor of ``M`` computed once per (mesh, lambda) on the host by
CHOLMOD through ``cholespy`` (the ``cholesky`` extra) and called through
``jax.pure_callback`` inside ``lax.custom_linear_solve``, so ``jit``, ``grad``
(w.r.t. the right-hand side, the vertices and lambda) and ``vmap`` keep working.
``warm_start=True`` keeps each CG solution in the transform's state and starts the
next step's CG there. docs/triangle_mesh.md has the measured costs of each.

Seams: a mesh with duplicated vertices (UV or normal seams) is welded by
``mesh_laplacian(faces, weld_positions=vertices)``: the Laplacian, the normals and
the filters act on the merged vertices, :func:`weld_gradients` sums the copies'
gradients (the chain rule of ``x = x_merged[index]``), and every copy gets the
merged vertex's update, so seams do not open (as Mitsuba's Large Steps does).
"""

from __future__ import annotations

import collections
import functools
import hashlib
import math
import numbers
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, get_args

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax

from optax_bilateral._src import numerics

# Large Steps' examples use lambda around 10-100; the authors' mesh run uses 19.
DEFAULT_LAMBDA = 19.0
"""The default smoothing weight ``lambda`` of ``M = I + lambda L`` (the authors' mesh run)."""
# The paper's default data term (supplement §3: "sigma_d around 0.5"); the authors'
# code splats with sigma_d and slices with sigma_phi = 0.4.
DEFAULT_SIGMA_D = 0.5
"""The default splat width ``sigma_d`` on normals of the mesh filter (supplement §3)."""
DEFAULT_SIGMA_PHI = 0.4
"""The default slice width ``sigma_phi`` on normals (the authors' code)."""
# "A few dozen" directions (the authors' n_filter_samples); a power of two keeps Sobol's balance.
DEFAULT_DIRECTIONS = 32
"""The default number of sphere directions ``s_k`` of the filter (:func:`sphere_directions`)."""
# Relative residual per right-hand side (docs/triangle_mesh.md: iterations against tol).
DEFAULT_TOL = 1e-4
"""The default CG tolerance: relative residual per right-hand side."""
DEFAULT_MAXITER = 2000
"""The default cap on CG iterations per solve."""

Solver = Literal["cg", "cholesky"]
NormalWeighting = Literal["area", "uniform", "angle"]
Prefilter = Literal["smooth", "bilateral", "off"]
PostfilterV = Literal["uniform", "bilateral", "smooth"]

SOLVERS: tuple[Solver, ...] = get_args(Solver)
"""The values of ``solver=``: Jacobi-preconditioned CG, or CHOLMOD through ``cholespy``."""
NORMALS: tuple[NormalWeighting, ...] = get_args(NormalWeighting)
"""The values of ``normals=`` (and :func:`vertex_normals`' ``weighting``)."""
PREFILTERS: tuple[Prefilter, ...] = get_args(Prefilter)
"""The values of :func:`bilateral_large_steps`' ``prefilter=``."""
POSTFILTERS_V: tuple[PostfilterV, ...] = get_args(PostfilterV)
"""The values of ``postfilter_v=`` (the second moment's filter, :func:`mesh_postfilter`)."""


# ----------------------------------------------------------------------------
# The mesh and its linear system


class MeshLaplacian(NamedTuple):
    """The combinatorial Laplacian of a triangle mesh, built once by :func:`mesh_laplacian`.

    Attributes:
      neighbors: ``(U, D)`` int32, the one-ring of every (merged) vertex padded with
        ``U`` (which indexes an appended zero row), ``D`` the maximum degree.
      degree: ``(U,)`` float32 vertex degrees.
      faces: ``(F, 3)`` int32 triangles over the merged vertices (for the normals).
      index: ``(V,)`` int32 merged vertex of every input vertex, or None (no welding).
      first: ``(U,)`` int32 one input vertex of every merged vertex, or None.

    ``V`` is the number of input vertices, ``U <= V`` of merged ones (``U = V`` without
    welding). A NamedTuple of arrays, so it can be passed through ``jax.jit``; the mesh
    transforms accept it as ``faces`` (the table is then built once).

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> mesh = obm.mesh_laplacian(faces)
        >>> mesh.neighbors.shape, mesh.degree.tolist(), mesh.index is None
        ((6, 4), [4.0, 4.0, 4.0, 4.0, 4.0, 4.0], True)
    """

    neighbors: jax.Array
    degree: jax.Array
    faces: jax.Array
    index: jax.Array | None = None
    first: jax.Array | None = None

    @property
    def num_vertices(self) -> int:
        """``V``, the number of rows of the fields (input vertices, seams included)."""
        return self.degree.shape[0] if self.index is None else self.index.shape[0]

    @property
    def num_merged(self) -> int:
        """``U``, the number of distinct vertices the Laplacian acts on."""
        return self.degree.shape[0]


if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike, Float, Int

    Faces = Int[ArrayLike, "F 3"] | MeshLaplacian
    Positions = Float[ArrayLike, "V 3"]  # vertex positions or unit normals
    UnitNormals = Float[Array, "V 3"]
    Field = Float[ArrayLike, "V *C"]
    FieldOut = Float[Array, "V *C"]
    Directions = int | Float[ArrayLike, "K 3"]
    Normals = NormalWeighting | Callable[[Array], UnitNormals]
else:
    Faces = Positions = UnitNormals = Field = FieldOut = Directions = Normals = Any


def _concrete_faces(faces) -> np.ndarray:
    try:
        return np.asarray(faces)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        raise TypeError(
            "faces must be concrete (a NumPy/JAX array, not traced); build "
            "mesh_laplacian(faces) outside jit, or pass static_args=('faces',) "
            "to optax.inject_hyperparams"
        ) from None


def mesh_laplacian(
    faces: Faces, num_vertices: int | None = None, *, weld_positions: Positions | None = None
) -> MeshLaplacian:
    """Builds the combinatorial Laplacian ``L = D - A`` of a triangle mesh.

    Args:
      faces: ``(F, 3)`` integer array of vertex indices (concrete, not traced).
      num_vertices: number of vertices ``V``; default ``faces.max() + 1``.
      weld_positions: optional ``(V, 3)`` vertex positions; vertices at exactly the
        same position (the duplicates a renderer keeps at UV or normal seams) are
        merged for the Laplacian, the normals and the filters, so that a seam does
        not open. Use it with :func:`weld_gradients` first in the chain (the
        aliases add it).

    Returns:
      A :class:`MeshLaplacian`, to pass as ``faces`` to the mesh transforms so the
      table is built once (and, with ``optax.inject_hyperparams``, treated as static).

    Raises:
      ValueError: ``faces`` is not a concrete ``(F, 3)`` integer array of indices in
        ``[0, V)``, or ``weld_positions`` is not ``(V, 3)``.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> obm.mesh_laplacian(faces).degree.tolist()       # every vertex has 4 neighbours
        [4.0, 4.0, 4.0, 4.0, 4.0, 4.0]
        >>> seam = jnp.concatenate([verts, verts[:1]])      # vertex 6 duplicates vertex 0
        >>> welded = obm.mesh_laplacian(np.where(faces == 0, 6, faces), 7, weld_positions=seam)
        >>> welded.degree.shape, bool(welded.index[0] == welded.index[6])   # 6 merged vertices
        ((6,), True)
    """
    if isinstance(faces, MeshLaplacian):
        return faces
    f = _concrete_faces(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F >= 1 (triangles), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"faces must be an integer array of vertex indices, got dtype {f.dtype}")
    if f.min() < 0:
        raise ValueError(f"faces must hold vertex indices >= 0, got {f.min()}")
    n = int(f.max()) + 1 if num_vertices is None else num_vertices
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < int(f.max()) + 1:
        raise ValueError(
            f"num_vertices must be an int > max(faces) = {int(f.max())}, got {num_vertices!r}"
        )
    n = int(n)
    index = first = None
    if weld_positions is not None:
        pos = np.asarray(weld_positions)
        if pos.shape != (n, 3):
            raise ValueError(f"weld_positions must have shape (V, 3) = ({n}, 3), got {pos.shape}")
        _, first, index = np.unique(pos, axis=0, return_index=True, return_inverse=True)
        index = index.reshape(-1)
        f = index[f]
        n = len(first)
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        raise ValueError(
            "faces contains a degenerate triangle (a repeated vertex index"
            + (", after welding equal positions)" if index is not None else ")")
        )
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
    as_index = lambda a: None if a is None else jnp.asarray(a, jnp.int32)
    return MeshLaplacian(
        jnp.asarray(neighbors),
        jnp.asarray(degree, jnp.float32),
        jnp.asarray(f, jnp.int32),
        as_index(index),
        as_index(first),
    )


def _merge(mesh: MeshLaplacian, x):
    """A field on the input vertices -> the merged vertices (copies hold equal values)."""
    return x if mesh.first is None else x[mesh.first]


def _spread(mesh: MeshLaplacian, x):
    """A field on the merged vertices -> every input vertex (copies get the same value)."""
    return x if mesh.index is None else x[mesh.index]


def _matvec(neighbors, degree, lambda_, x):
    """``(I + lambda L) x`` for ``x`` of shape ``(U, C)``."""
    padded = jnp.concatenate([x, jnp.zeros((1, x.shape[1]), x.dtype)])
    # One row gather per neighbour slot, summed: XLA:CPU runs this 5-10x faster
    # than gathering the (U, D, C) block and reducing it.
    neighbour_sum = padded[neighbors[:, 0]]
    for j in range(1, neighbors.shape[1]):
        neighbour_sum = neighbour_sum + padded[neighbors[:, j]]
    return x + lambda_ * (degree.astype(x.dtype)[:, None] * x - neighbour_sum)


class _Cholesky:
    """Host-side sparse Cholesky factors of ``I + lambda L`` (CHOLMOD through cholespy).

    One per mesh (see :func:`_host_cholesky`), with the factors of the last few lambda
    values, so a schedule over a few values does not refactorise every step.
    """

    MAX_FACTORS = 4

    def __init__(self, neighbors: np.ndarray, degree: np.ndarray):
        try:
            import cholespy
        except ImportError as e:
            raise ImportError(
                "solver='cholesky' needs cholespy: pip install "
                "'optax_bilateral[cholesky]' (or use solver='cg')"
            ) from e
        self._cholespy: Any = cholespy  # a compiled extension without type information
        u = len(degree)
        rows = np.repeat(np.arange(u), neighbors.shape[1])
        keep = neighbors.ravel() < u
        diag = np.arange(u)
        self._ii = np.concatenate([diag, rows[keep]]).astype(np.int32)
        self._jj = np.concatenate([diag, neighbors.ravel()[keep]]).astype(np.int32)
        self._degree = np.asarray(degree, np.float64)
        self._off = int(keep.sum())
        self._factors: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def factor(self, lam: float):
        with self._lock:
            if lam in self._factors:
                self._factors.move_to_end(lam)
                return self._factors[lam]
            values = np.concatenate([1.0 + lam * self._degree, np.full(self._off, -lam)])
            fac = self._cholespy.CholeskySolverD(
                len(self._degree), self._ii, self._jj, values, self._cholespy.MatrixType.COO
            )
            self._factors[lam] = fac
            while len(self._factors) > self.MAX_FACTORS:
                self._factors.popitem(last=False)
            return fac

    def solve(self, b: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``b``: ``(*batch, U, C)``; ``lam``: ``(*batch)`` (vmap broadcasts both)."""
        b, lam = np.asarray(b), np.asarray(lam, np.float64)
        batch = b.shape[:-2]
        flat_b = b.reshape((-1,) + b.shape[-2:])
        flat_lam = np.broadcast_to(lam, batch).reshape(-1)
        out = np.empty(flat_b.shape, b.dtype)
        for value in np.unique(flat_lam):
            which = np.nonzero(flat_lam == value)[0]
            # All batch members with this lambda as the columns of one solve.
            rhs = (
                flat_b[which[0]] if len(which) == 1 else np.concatenate(list(flat_b[which]), axis=1)
            )
            rhs = np.require(rhs, np.float64, ["C", "W"])  # cholespy takes writable C arrays
            x = np.empty_like(rhs)
            self.factor(float(value)).solve(rhs, x)
            out[which] = np.stack(np.split(x, len(which), axis=1))
        return out.reshape(b.shape)


_HOSTS: collections.OrderedDict[bytes, _Cholesky] = collections.OrderedDict()
_HOSTS_LOCK = threading.Lock()


def _host_cholesky(mesh: MeshLaplacian) -> _Cholesky:
    """The factor cache of this mesh's Laplacian (shared by every transform built on it)."""
    try:
        nb = np.asarray(mesh.neighbors)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        raise TypeError(
            "solver='cholesky' needs a concrete MeshLaplacian (built outside jit)"
        ) from None
    key = hashlib.blake2b(nb.tobytes() + str(nb.shape).encode(), digest_size=16).digest()
    with _HOSTS_LOCK:
        if key not in _HOSTS:
            _HOSTS[key] = _Cholesky(nb, np.asarray(mesh.degree))
            while len(_HOSTS) > 8:
                _HOSTS.popitem(last=False)
        _HOSTS.move_to_end(key)
        return _HOSTS[key]


def _solve(host, neighbors, degree, b, lambda_, tol, maxiter, x0):
    """``(I + lambda L)^-1 b`` for ``b`` of shape ``(U, C)``; ``host`` None means CG."""
    matvec = lambda v: _matvec(neighbors, degree, lambda_, v)
    if host is not None:

        def solve(_, rhs):
            return jax.pure_callback(
                host.solve,
                jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                rhs,
                lambda_,
                vmap_method="broadcast_all",
            )

        return lax.custom_linear_solve(matvec, b, solve, symmetric=True)
    scale = jnp.sqrt(jnp.sum(b * b, axis=0))
    scale = jnp.where(scale > 0, scale, 1.0)
    inv_diag = (1.0 / (1.0 + lambda_ * degree.astype(b.dtype)))[:, None]
    b = b / scale
    # The Jacobi guess rather than zeros (a constant x0 makes XLA constant-fold the
    # first matvec's gathers, seconds at 166k vertices), or the previous solution.
    guess = inv_diag * b
    if x0 is not None:
        guess = jnp.where(jnp.any(x0 != 0), x0 / scale, guess)  # all zeros: the first step
    x, _ = jax.scipy.sparse.linalg.cg(
        matvec, b, x0=guess, tol=tol, atol=0.0, maxiter=maxiter, M=lambda r: inv_diag * r
    )
    return x * scale


# One compilation per shape and solver, shared by every transform and eager call.
_solve_jit = jax.jit(_solve, static_argnums=0)


def _check_solver_name(solver):
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")


def _host_for(mesh, solver):
    _check_solver_name(solver)
    return _host_cholesky(mesh) if solver == "cholesky" else None


def _solve_merged(mesh, host, b, lambda_, tol, maxiter, x0=None):
    """Solves on the merged vertices; ``b`` and ``x0`` are ``(U, C)``."""
    dtype = b.dtype
    return _solve_jit(
        host,
        mesh.neighbors,
        mesh.degree,
        b,
        jnp.asarray(lambda_, dtype),
        jnp.asarray(tol, dtype),
        jnp.asarray(maxiter, jnp.int32),
        x0,
    )


def smoothing_solve(
    mesh: MeshLaplacian,
    b: Field,
    lambda_: jax.typing.ArrayLike,
    *,
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
    x0: Field | None = None,
) -> FieldOut:
    """Solves ``(I + lambda L) x = b`` (Large Steps' "smooth").

    Args:
      mesh: a :class:`MeshLaplacian`.
      b: ``(V,)`` or ``(V, C)`` right-hand sides (one system per column). On a welded
        mesh the copies of a vertex must hold equal values (one is read).
      lambda_: smoothing weight ``>= 0``; may be traced (with ``"cholesky"``, each new
        value is factorised on the host, the last four are kept).
      solver: ``"cg"`` (Jacobi-preconditioned CG, columns scaled to unit norm share
        one Krylov iteration) or ``"cholesky"`` (needs ``cholespy``).
      tol: CG relative residual per column.
      maxiter: CG iteration cap.
      x0: optional CG starting point with the shape of ``b`` (e.g. the last solution).

    Returns:
      ``x`` with the shape and dtype of ``b``.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> mesh = obm.mesh_laplacian(faces)
        >>> b = jnp.zeros(6).at[4].set(1.0)
        >>> x = obm.smoothing_solve(mesh, b, lambda_=1.0)
        >>> print(np.round(np.asarray(x, float), 3))  # M^-1 is row-stochastic: sums stay 1
        [0.143 0.143 0.143 0.143 0.314 0.114]
    """
    host = _host_for(mesh, solver)
    b = jnp.asarray(b)
    if b.ndim not in (1, 2) or b.shape[0] != mesh.num_vertices:
        raise ValueError(
            f"b must have shape (V,) or (V, C) with V = {mesh.num_vertices}, got {b.shape}"
        )
    squeeze = b.ndim == 1
    if squeeze:
        b = b[:, None]
        x0 = None if x0 is None else jnp.asarray(x0)[:, None]
    dtype = b.dtype if jnp.issubdtype(b.dtype, jnp.floating) else jnp.float32
    b = b.astype(dtype)
    if x0 is not None:
        x0 = jnp.asarray(x0, dtype)
        if x0.shape != b.shape:
            raise ValueError(f"x0 must have the shape of b, {b.shape}, got {x0.shape}")
        x0 = _merge(mesh, x0)
    x = _spread(mesh, _solve_merged(mesh, host, _merge(mesh, b), lambda_, tol, maxiter, x0))
    return x[:, 0] if squeeze else x


# ----------------------------------------------------------------------------
# Normals, directions and the bilateral filter


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
        vertices = _merge(mesh, vertices)
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
    return n if mesh is None else _spread(mesh, n)


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
    u = sampler.random_base2(math.ceil(math.log2(num)))[
        :num
    ]  # a power-of-two prefix keeps the balance
    z = 1.0 - 2.0 * u[:, 1]
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = 2.0 * np.pi * u[:, 0]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _as_directions(directions) -> np.ndarray:
    if isinstance(directions, numbers.Integral) and not isinstance(directions, bool):
        return sphere_directions(int(directions))
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
        raise ValueError(
            f"directions must be an int (number of Sobol directions) or a (K, 3) "
            f"array of unit vectors, got shape {d.shape}"
        )
    if not np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4):
        raise ValueError("directions must be unit vectors")
    return d


def _is_concrete_inf(x) -> bool:
    try:
        return bool(np.isinf(np.asarray(x)))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return False


def _vmf(n, s, sigma):
    """``exp((max(n . s, -1) - 1) / sigma)``: the authors' clamp, shifted into (0, 1]."""
    return jnp.exp((jnp.maximum(n @ s.T, -1.0) - 1.0) / sigma)


def _bilateral(host, graph, x, n, s, widths, solve, x0):
    """Splat (w_k * x, w_k), diffuse with one solve, slice with phi_k, divide. ``graph`` is
    ``(neighbors, degree)``, ``widths`` ``(sigma_d, sigma_phi)``, ``solve`` ``(lambda_, tol,
    maxiter)``.

    Returns the filtered ``(U, C)`` field and the diffused ``(U, K (C + 1))`` columns.
    """
    sigma_d, sigma_phi = widths
    w = _vmf(n, s, sigma_d)  # (U, K)
    phi = _vmf(n, s, sigma_phi)
    num_v, num_dirs, channels = x.shape[0], w.shape[1], x.shape[1]
    splat = jnp.concatenate([w[:, :, None] * x[:, None, :], w[:, :, None]], axis=2)
    rhs = splat.reshape(num_v, num_dirs * (channels + 1))
    (neighbors, degree), (lambda_, tol, maxiter) = graph, solve
    flat = _solve(host, neighbors, degree, rhs, lambda_, tol, maxiter, x0)
    sliced = jnp.einsum("vk,vkc->vc", phi, flat.reshape(num_v, num_dirs, channels + 1))
    num, den = sliced[:, :channels], sliced[:, channels:]
    ok = den > jnp.finfo(x.dtype).tiny
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), x), flat


_bilateral_jit = jax.jit(_bilateral, static_argnums=0)


class _Operator(NamedTuple):
    """What the mesh operator ``B`` needs besides its fields and its guide (the normals)."""

    mesh: MeshLaplacian
    host: Any  # the factorised solver, or None for CG
    directions: Any  # (K, 3) unit vectors, or None where sigma_d is inf (B = M^-1)
    lambda_: Any
    sigma_d: Any
    sigma_phi: Any
    tol: float
    maxiter: int


def _bilateral_fields(fields, normals, op: _Operator, x0=None):
    """The operator B on a list of ``(V, C_i)`` fields; returns (fields, diffused columns)."""
    mesh = op.mesh
    widths = [x.shape[1] for x in fields]
    splits = np.cumsum(widths)[:-1].tolist()
    x = _merge(mesh, jnp.concatenate(fields, axis=1))
    dtype = x.dtype
    if _is_concrete_inf(op.sigma_d):
        # Every splat weight is 1: the slice weights cancel and B = M^-1.
        out = _solve_merged(mesh, op.host, x, op.lambda_, op.tol, op.maxiter, x0)
        flat = out
    else:
        as_dtype = lambda a: jnp.asarray(a, dtype)
        out, flat = _bilateral_jit(
            op.host,
            (mesh.neighbors, mesh.degree),
            x,
            as_dtype(_merge(mesh, jnp.asarray(normals))),
            as_dtype(op.directions),
            (as_dtype(op.sigma_d), as_dtype(op.sigma_phi)),
            (as_dtype(op.lambda_), as_dtype(op.tol), jnp.asarray(op.maxiter, jnp.int32)),
            x0,
        )
    return jnp.split(_spread(mesh, out), splits, axis=1), flat


def bilateral_normal_filter(
    fields: Sequence[Field],
    normals: Positions,
    mesh: MeshLaplacian,
    *,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: jax.typing.ArrayLike = DEFAULT_SIGMA_D,
    sigma_phi: jax.typing.ArrayLike = DEFAULT_SIGMA_PHI,
    directions: Directions = DEFAULT_DIRECTIONS,
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
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
      sigma_d: splat width ``> 0``, ``inf`` for Large Steps (may be traced).
      sigma_phi: slice width ``> 0`` (may be traced; ``inf``: unweighted slice).
      directions: int (that many Sobol directions, built with SciPy) or ``(K, 3)``.
      solver: ``"cg"`` (Jacobi-preconditioned CG) or ``"cholesky"`` (needs ``cholespy``);
        see :func:`smoothing_solve`.
      tol: CG relative residual per column.
      maxiter: CG iteration cap.

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
        ...                                   sigma_d=0.5, directions=8)
        >>> print(np.round(np.asarray(out[0][:, 0], float), 3))  # row-stochastic: constants stay
        [1. 1. 1. 1. 1. 1.]
    """
    host = _host_for(mesh, solver)
    fields = [jnp.asarray(x) for x in fields]
    for x in fields:
        if x.ndim != 2 or x.shape[0] != mesh.num_vertices:
            raise ValueError(
                f"every field must have shape (V, C) with V = {mesh.num_vertices}, got {x.shape}"
            )
    s = None if _is_concrete_inf(sigma_d) else _as_directions(directions)
    op = _Operator(mesh, host, s, lambda_, sigma_d, sigma_phi, tol, maxiter)
    out, _ = _bilateral_fields(fields, normals, op)
    return out


# ----------------------------------------------------------------------------
# Argument checks and numerics


def _concrete_float(x):
    try:
        return float(np.asarray(x))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


def _check_lambda(lambda_):
    v = _concrete_float(lambda_)
    if v is not None and not (v >= 0.0 and math.isfinite(v)):
        raise ValueError(f"lambda_ (Laplacian smoothing weight) must be finite and >= 0, got {v}")


def _check_sigma(sigma, name="sigma_d"):
    v = _concrete_float(sigma)
    if v is not None and not v > 0.0:
        raise ValueError(f"{name} must be > 0 (inf turns its weights off), got {v}")


def _check_unit(x, name):
    v = _concrete_float(x)
    if v is not None and not 0.0 <= v < 1.0:
        raise ValueError(f"{name} must be in [0, 1), got {v}")


def _check_choice(value, name, choices):
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def _check_normals(normals):
    if not callable(normals):
        _check_choice(normals, "normals", NORMALS)


def _check_solver(solver, tol, maxiter, warm_start=False):
    _check_solver_name(solver)
    if warm_start and solver != "cg":
        raise ValueError(
            f"warm_start starts the CG from the last solution; it does not apply to "
            f"solver={solver!r} (a direct solve)"
        )
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
        raise ValueError(
            f"{what}: every leaf must have shape {want} (one row per mesh vertex), got {x.shape}"
        )


def _bias_correction(b, count, dtype):
    """Adam's ``1 - b^t`` in ``dtype``: the grid transforms' policy (exact for b near 1)."""
    return numerics.bias_correction(b, count).astype(dtype)


# ----------------------------------------------------------------------------
# Transforms


class SmoothingState(NamedTuple):
    """State of :func:`laplacian_smoothing` and :func:`bilateral_smoothing`.

    Attributes:
      count: the number of updates so far, an int32 scalar.
      x0: with ``warm_start=True``, the last solutions (the CG's next starting point,
        ``(U, C)`` per leaf); else None.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> state = obm.laplacian_smoothing(faces, warm_start=True).init(verts)
        >>> type(state).__name__, int(state.count), state.x0.shape
        ('SmoothingState', 0, (6, 3))
    """

    count: jax.Array
    x0: Any


def _smoothing_init(warm_start: bool, columns: Callable[[Any], int]):
    def init_fn(params):
        if not warm_start:
            return SmoothingState(jnp.zeros([], jnp.int32), None)
        return SmoothingState(
            jnp.zeros([], jnp.int32),
            jax.tree.map(lambda p: jnp.zeros((p.shape[0], columns(p)), p.dtype), params),
        )

    return init_fn


def _weld(mesh: MeshLaplacian, index: jax.Array, g):
    """The copies' gradients summed on their merged vertex, and the sum given to every copy."""
    _check_leaf(g, mesh, "weld_gradients")
    return _spread(mesh, jax.ops.segment_sum(g, index, num_segments=mesh.num_merged))


def weld_gradients(faces: Faces) -> optax.GradientTransformationExtraArgs:
    """Sums the gradients of a welded vertex's copies and gives every copy the sum.

    ``x = x_merged[index]`` (copies of a seam vertex) gives
    ``df/dx_merged = sum of the copies' df/dx``: the gradient of the merged vertex.
    Identity for a mesh built without ``weld_positions``. The mesh aliases put it
    first; a hand-built chain needs it before the first smoothing.

    Args:
      faces: a :class:`MeshLaplacian` built with ``weld_positions`` (or ``(F, 3)``
        triangles, or a mesh without welding: then the identity).

    Returns:
      A stateless ``optax.GradientTransformationExtraArgs`` on ``(V, C)`` leaves.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> seam = jnp.concatenate([verts, verts[:1]])      # vertex 6 duplicates vertex 0
        >>> mesh = obm.mesh_laplacian(np.where(faces == 0, 6, faces), 7, weld_positions=seam)
        >>> weld = obm.weld_gradients(mesh)
        >>> grads = jnp.zeros((7, 3)).at[0, 0].set(1.0).at[6, 0].set(2.0)
        >>> updates, _ = weld.update(grads, weld.init(grads))
        >>> updates[:, 0].tolist()                       # both copies get the sum
        [3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0]
    """
    mesh = mesh_laplacian(faces)

    def update_fn(updates, state, params=None, **extra_args):
        del params, extra_args
        if mesh.index is None:
            return updates, state
        return jax.tree.map(functools.partial(_weld, mesh, mesh.index), updates), state

    return optax.GradientTransformationExtraArgs(lambda params: optax.EmptyState(), update_fn)


def laplacian_smoothing(
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    *,
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
    warm_start: bool = False,
) -> optax.GradientTransformationExtraArgs:
    """Large Steps' smoothing ``g -> (I + lambda L)^-1 g`` on every ``(V, C)`` leaf.

    Used before the moments it is the prefilter ``A`` (eq. 1), the gradient of the
    reparameterisation ``u = (I + lambda L) x``; used after ``scale_by_uniform_adam``
    it maps the step on ``u`` back to ``x``.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian` (built once).
      lambda_: smoothing weight ``>= 0``; may be traced / injected.
      solver: ``"cg"`` (Jacobi-preconditioned CG) or ``"cholesky"`` (needs ``cholespy``);
        see :func:`smoothing_solve`.
      tol: CG relative residual per column (default 1e-4).
      maxiter: CG iteration cap (default 2000).
      warm_start: keep the last solution in the state and start the CG there.

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`SmoothingState`) on
      ``(V, C)`` leaves; ``update`` needs no ``params``.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> grads = jnp.zeros((6, 3)).at[4, 2].set(1.0)     # pull the top vertex up
        >>> smooth = obm.laplacian_smoothing(faces, lambda_=1.0)
        >>> updates, _ = smooth.update(grads, smooth.init(verts))
        >>> print(np.round(np.asarray(updates[:, 2], float), 3))           # (I + L)^-1 g
        [0.143 0.143 0.143 0.143 0.314 0.114]
    """
    mesh = mesh_laplacian(faces)
    _check_lambda(lambda_)
    _check_solver(solver, tol, maxiter, warm_start)
    host = _host_for(mesh, solver)
    warm_start = bool(warm_start)

    def update_fn(updates, state, params=None, **extra_args):
        del params, extra_args
        leaves, treedef = jax.tree.flatten(updates)
        starts = treedef.flatten_up_to(state.x0) if warm_start else [None] * len(leaves)
        out, sols = [], []
        for x, x0 in zip(leaves, starts):
            _check_leaf(x, mesh, "laplacian_smoothing")
            sol = _solve_merged(
                mesh,
                host,
                _merge(mesh, x),
                lambda_,
                tol,
                maxiter,
                None if x0 is None else _merge(mesh, x0),
            )
            sols.append(_spread(mesh, sol))
            out.append(sols[-1].astype(x.dtype))
        new = SmoothingState(
            jnp.asarray(optax.safe_increment(state.count)),
            jax.tree.unflatten(treedef, sols) if warm_start else None,
        )
        return jax.tree.unflatten(treedef, out), new

    return optax.GradientTransformationExtraArgs(
        _smoothing_init(warm_start, lambda p: p.shape[1]), update_fn
    )


def _normals_fn(normals, mesh):
    if callable(normals):
        return normals
    return lambda x: vertex_normals(x, mesh, normals)


def bilateral_smoothing(
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: jax.typing.ArrayLike = DEFAULT_SIGMA_D,
    *,
    sigma_phi: jax.typing.ArrayLike = DEFAULT_SIGMA_PHI,
    directions: Directions = DEFAULT_DIRECTIONS,
    normals: Normals = "area",
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
    warm_start: bool = False,
) -> optax.GradientTransformationExtraArgs:
    """The bilateral normal filter ``g -> B g`` on every ``(V, 3)`` leaf (the authors'
    ``prefilter="bilateral"``), guided by the normals of ``params``.

    ``B`` is :func:`bilateral_normal_filter`'s operator: ``M^-1 = (I + lambda L)^-1``
    diffusion that does not cross normals which differ (von Mises-Fisher splat of width
    ``sigma_d``, slice of width ``sigma_phi``); ``sigma_d = inf`` gives
    :func:`laplacian_smoothing`.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian`.
      lambda_: smoothing weight ``>= 0`` of ``M = I + lambda L`` (default 19; may be
        traced).
      sigma_d: splat width on normals (``> 0``, default 0.5; ``inf`` = no data term; may
        be traced).
      sigma_phi: slice width (``> 0``, default 0.4; may be traced).
      directions: int number of Sobol sphere directions (default 32; needs SciPy) or a
        ``(K, 3)`` array of unit vectors.
      normals: ``"area"`` (default), ``"uniform"``, ``"angle"`` (see
        :func:`vertex_normals`) or a callable ``positions -> (V, 3) unit normals``.
      solver: ``"cg"`` or ``"cholesky"``; see :func:`smoothing_solve`.
      tol: CG relative residual per column (default 1e-4).
      maxiter: CG iteration cap (default 2000).
      warm_start: keep the last solutions in the state and start the CG there.

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`SmoothingState`);
      ``update(updates, state, params)`` needs ``params``, the ``(V, 3)`` positions.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> grads = jnp.zeros((6, 3)).at[4, 2].set(1.0)     # pull the top vertex up
        >>> smooth = obm.bilateral_smoothing(faces, lambda_=1.0, directions=8)
        >>> updates, _ = smooth.update(grads, smooth.init(verts), verts)
        >>> print(np.round(np.asarray(updates[:, 2], float), 3))  # spreads less than M^-1 g
        [0.051 0.037 0.044 0.032 0.126 0.034]
    """
    mesh = mesh_laplacian(faces)
    _check_lambda(lambda_)
    _check_sigma(sigma_d)
    _check_sigma(sigma_phi, "sigma_phi")
    _check_solver(solver, tol, maxiter, warm_start)
    _check_normals(normals)
    host = _host_for(mesh, solver)
    dirs = None if _is_concrete_inf(sigma_d) else _as_directions(directions)
    normals_of = _normals_fn(normals, mesh)
    warm_start = bool(warm_start)
    width = lambda p: p.shape[1] if dirs is None else len(dirs) * (p.shape[1] + 1)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        if params is None:
            raise ValueError(
                "bilateral_smoothing needs params (the vertex positions) to compute "
                "the normals that guide the filter: call update(updates, state, params)"
            )
        leaves, treedef = jax.tree.flatten(updates)
        xs = treedef.flatten_up_to(params)
        starts = treedef.flatten_up_to(state.x0) if warm_start else [None] * len(leaves)
        out, sols = [], []
        for g, x, x0 in zip(leaves, xs, starts):
            _check_leaf(x, mesh, "bilateral_smoothing params", channels=3)
            _check_leaf(g, mesh, "bilateral_smoothing updates")
            op = _Operator(mesh, host, dirs, lambda_, sigma_d, sigma_phi, tol, maxiter)
            (gf,), flat = _bilateral_fields([g], normals_of(x), op, x0)
            sols.append(flat)
            out.append(gf.astype(g.dtype))
        new = SmoothingState(
            jnp.asarray(optax.safe_increment(state.count)),
            jax.tree.unflatten(treedef, sols) if warm_start else None,
        )
        return jax.tree.unflatten(treedef, out), new

    def init_fn(params):
        # The diffused columns live on the merged vertices.
        if not warm_start:
            return SmoothingState(jnp.zeros([], jnp.int32), None)
        return SmoothingState(
            jnp.zeros([], jnp.int32),
            jax.tree.map(lambda p: jnp.zeros((mesh.num_merged, width(p)), p.dtype), params),
        )

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


class ScaleByUniformAdamState(NamedTuple):
    """State of :func:`scale_by_uniform_adam`.

    Attributes:
      count: the number of updates so far, an int32 scalar.
      mu: the first moment, like the parameters.
      nu: the second moment, like the parameters (per entry; the max is taken at each
        step).

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> state = obm.scale_by_uniform_adam().init(verts)
        >>> type(state).__name__, int(state.count), state.nu.shape
        ('ScaleByUniformAdamState', 0, (6, 3))
    """

    count: jax.Array
    mu: Any
    nu: Any


class MeshPostfilterState(NamedTuple):
    """State of :func:`mesh_postfilter`: the *unfiltered* moments (eqs. 2, 4).

    Attributes:
      count: the number of updates so far, an int32 scalar.
      mu: the first moment ``m_t``, like the parameters.
      nu: the second moment ``v_t``, like the parameters.
      x0: with ``warm_start=True``, the last solutions of the filter's solves; else
        None.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> state = obm.mesh_postfilter(faces, directions=8).init(verts)
        >>> type(state).__name__, state.mu.shape, state.x0
        ('MeshPostfilterState', (6, 3), None)
    """

    count: jax.Array
    mu: Any
    nu: Any
    x0: Any = None


def _moments(updates, mu, nu, count, b1, b2):
    a1, a2 = numerics.one_minus(b1), numerics.one_minus(b2)
    mu = jax.tree.map(lambda g, m: b1 * m + a1 * g, updates, mu)
    nu = jax.tree.map(lambda g, v: b2 * v + a2 * g * g, updates, nu)
    return jnp.asarray(optax.safe_increment(count)), mu, nu


def _zeros_like_tree(params):
    return jax.tree.map(jnp.zeros_like, params)


def scale_by_uniform_adam(
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
) -> optax.GradientTransformationExtraArgs:
    """Large Steps' ``AdamUniform``: Adam with one second moment per leaf.

        m_t = b1 m_{t-1} + (1-b1) g_t,   v_t = b2 v_{t-1} + (1-b2) g_t^2
        Delta_t = m^_t / (sqrt(max_k v^_t,k) + eps)

    with bias-corrected ``m^, v^`` and the max over every entry of the leaf (all
    vertices and coordinates). Every vertex then moves with the same step scale,
    which keeps the reparameterised update of Large Steps uniform over the mesh.

    Args:
      b1: decay rate of the first moment, in [0, 1) (default 0.9).
      b2: decay rate of the second moment, in [0, 1) (default 0.999).
      eps: added to the denominator (default 1e-8).

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state
      :class:`ScaleByUniformAdamState`); any leaf shape.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> opt = obm.scale_by_uniform_adam()
        >>> grads = jnp.array([[0.5, 0.0, -1.0], [0.25, 0.0, 0.0]])
        >>> updates, _ = opt.update(grads, opt.init(grads))
        >>> print(np.round(np.asarray(updates, float), 3))  # g / max|g| at the first step
        [[ 0.5   0.   -1.  ]
         [ 0.25  0.    0.  ]]
    """
    _check_unit(b1, "b1")
    _check_unit(b2, "b2")

    def init_fn(params):
        return ScaleByUniformAdamState(
            jnp.zeros([], jnp.int32), _zeros_like_tree(params), _zeros_like_tree(params)
        )

    def update_fn(updates, state, params=None, **extra_args):
        del params, extra_args
        count, mu, nu = _moments(updates, state.mu, state.nu, state.count, b1, b2)

        def step(m, v):
            c1, c2 = _bias_correction(b1, count, m.dtype), _bias_correction(b2, count, v.dtype)
            return ((m / c1) / (jnp.sqrt(jnp.max(v) / c2) + eps)).astype(m.dtype)

        return jax.tree.map(step, mu, nu), ScaleByUniformAdamState(count, mu, nu)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def mesh_postfilter(
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: jax.typing.ArrayLike = DEFAULT_SIGMA_D,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    sigma_phi: jax.typing.ArrayLike = DEFAULT_SIGMA_PHI,
    postfilter_v: PostfilterV = "uniform",
    directions: Directions = DEFAULT_DIRECTIONS,
    normals: Normals = "area",
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
    warm_start: bool = False,
) -> optax.GradientTransformationExtraArgs:
    """Adam moments with the bilateral normal postfilter ``B`` (supplement eqs. 6-10).

        m_t, v_t = EMAs of the incoming (prefiltered) gradient  (eqs. 2, 4; kept unfiltered)
        "uniform":   Delta_t = B m^_t / (sqrt(max_k v^_t,k) + eps)
        "bilateral": Delta_t = B m^_t / (sqrt(B v^_t) + eps)       (same B for m and v, §1.3)
        "smooth":    Delta_t = B m^_t / (sqrt(M^-1 v^_t) + eps)    (the authors'; not bounded)

    ``B`` is :func:`bilateral_normal_filter` with the guide ``n`` = the vertex
    normals of ``params`` (the current positions; "cross-bilateral"). With
    ``sigma_d = inf`` and "uniform" this is Large Steps' postfilter ``M^-1``.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian`.
      lambda_: smoothing weight of ``M = I + lambda L`` (may be traced). The authors'
        ``compute_matrix(alpha=lambda/(1+lambda))`` is ``M / (1 + lambda)``
        (docs/triangle_mesh.md maps the two).
      sigma_d: splat width on normals (``> 0``, ``inf`` = Large Steps; may be traced).
      b1: Adam's first-moment decay rate (Large Steps uses 0.9).
      b2: Adam's second-moment decay rate (Large Steps uses 0.999).
      eps: Adam's epsilon.
      sigma_phi: slice width (the authors' 0.4 by default; may be traced).
      postfilter_v: ``"uniform"`` (max over the leaf, as Large Steps), ``"bilateral"``
        (``B v``) or ``"smooth"`` (``M^-1 v``).
      directions: int number of Sobol sphere directions (the authors' Lloyd-relaxed
        set; needs SciPy when built) or a ``(K, 3)`` array of unit vectors.
      normals: ``"area"``, ``"uniform"`` (the authors'), ``"angle"`` (see
        :func:`vertex_normals`) or a callable ``positions -> (V, 3) unit normals``.
      solver: ``"cg"`` (Jacobi-preconditioned CG) or ``"cholesky"`` (needs ``cholespy``);
        see :func:`smoothing_solve`.
      tol: CG relative residual per column.
      maxiter: CG iteration cap.
      warm_start: keep the last solutions in the state and start the CG there.

    ``update(updates, state, params)`` needs ``params``: a pytree of ``(V, 3)``
    vertex-position leaves of this mesh (the updates have the same structure).

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`MeshPostfilterState`)
      returning ``Delta_t`` (no learning rate; :func:`bilateral_large_steps` chains it).

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> grads = jnp.zeros((6, 3)).at[4, 2].set(1.0)     # pull the top vertex up
        >>> post = obm.mesh_postfilter(faces, lambda_=1.0, directions=8)
        >>> step, state = post.update(grads, post.init(verts), verts)
        >>> # B m^ / sqrt(max v^), m^ = g at t = 1
        >>> print(np.round(np.asarray(step[:, 2], float), 3))
        [0.051 0.037 0.044 0.032 0.126 0.034]
    """
    mesh = mesh_laplacian(faces)
    _check_lambda(lambda_)
    _check_sigma(sigma_d)
    _check_sigma(sigma_phi, "sigma_phi")
    _check_unit(b1, "b1")
    _check_unit(b2, "b2")
    _check_solver(solver, tol, maxiter, warm_start)
    _check_choice(postfilter_v, "postfilter_v", POSTFILTERS_V)
    _check_normals(normals)
    host = _host_for(mesh, solver)
    dirs = None if _is_concrete_inf(sigma_d) else _as_directions(directions)
    normals_of = _normals_fn(normals, mesh)
    warm_start = bool(warm_start)
    k = 1 if dirs is None else len(dirs)
    op = _Operator(mesh, host, dirs, lambda_, sigma_d, sigma_phi, tol, maxiter)

    def widths(p):
        """Columns of the solves that a leaf needs: B on m (and v), then M^-1 v."""
        c = p.shape[1]
        if postfilter_v == "bilateral":
            return ((2 * c + (0 if dirs is None else 1)) * k,)
        bil = ((c + (0 if dirs is None else 1)) * k,)
        return bil + ((c,) if postfilter_v == "smooth" else ())

    def init_fn(params):
        x0 = None
        if warm_start:
            x0 = jax.tree.map(
                lambda p: tuple(jnp.zeros((mesh.num_merged, w), p.dtype) for w in widths(p)), params
            )
        return MeshPostfilterState(
            jnp.zeros([], jnp.int32), _zeros_like_tree(params), _zeros_like_tree(params), x0
        )

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        if params is None:
            raise ValueError(
                "mesh_postfilter needs params (the vertex positions) to compute "
                "the normals that guide the filter: call update(updates, state, params)"
            )
        count, mu, nu = _moments(updates, state.mu, state.nu, state.count, b1, b2)
        flat_m, treedef = jax.tree.flatten(mu)
        flat_v = treedef.flatten_up_to(nu)
        flat_x = treedef.flatten_up_to(params)
        flat_x0 = treedef.flatten_up_to(state.x0) if warm_start else [None] * len(flat_m)
        outs, sols = [], []
        for m, v, x, x0 in zip(flat_m, flat_v, flat_x, flat_x0):
            _check_leaf(x, mesh, "mesh_postfilter params", channels=3)
            _check_leaf(m, mesh, "mesh_postfilter updates")
            c1, c2 = _bias_correction(b1, count, m.dtype), _bias_correction(b2, count, v.dtype)
            out, leaf_sols = _postfilter_step(
                m / c1, v / c2, normals_of(x), op, postfilter_v, eps, x0
            )
            outs.append(out.astype(m.dtype))
            sols.append(leaf_sols)
        x0_new = jax.tree.unflatten(treedef, sols) if warm_start else None
        return (jax.tree.unflatten(treedef, outs), MeshPostfilterState(count, mu, nu, x0_new))

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def _postfilter_step(m_hat, v_hat, normals, op: _Operator, postfilter_v, eps, x0):
    """``B m^ / (sqrt(v~) + eps)``, ``v~`` as ``postfilter_v`` says, and the solutions (the
    next warm start): ``B`` on both moments, their max, or ``M^-1 v^``."""
    first = None if x0 is None else x0[0]
    if postfilter_v == "bilateral":
        (m_f, v_f), flat = _bilateral_fields([m_hat, v_hat], normals, op, first)
        sols = (flat,)
    else:
        (m_f,), flat = _bilateral_fields([m_hat], normals, op, first)
        sols = (flat,)
        if postfilter_v == "uniform":
            v_f = jnp.max(v_hat)
        else:
            v_s = _solve_merged(
                op.mesh,
                op.host,
                _merge(op.mesh, v_hat),
                op.lambda_,
                op.tol,
                op.maxiter,
                None if x0 is None else x0[1],
            )
            sols += (v_s,)
            v_f = _spread(op.mesh, v_s)
    # B and M^-1 are non-negative, so v_f >= 0 up to the solver; clip its round-off.
    return m_f / (jnp.sqrt(jnp.maximum(v_f, 0.0)) + eps), sols


def large_steps(
    learning_rate: optax.ScalarOrSchedule,
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
    warm_start: bool = False,
) -> optax.GradientTransformationExtraArgs:
    """Large Steps in Inverse Rendering of Geometry (Nicolet et al. 2021) on vertex positions.

        x <- x - lr M^-1 AdamUniform(M^-1 g),    M = I + lambda L

    which equals optimising ``u = M x`` with ``AdamUniform`` and reading back
    ``x = M^-1 u`` (``M`` symmetric, so ``df/du = M^-1 df/dx``). In the paper's terms:
    prefilter ``A = M^-1``, postfilter ``B = M^-1``, uniform second moment.

    Args:
      learning_rate: float or optax schedule.
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian` (welded seams: see
        :func:`mesh_laplacian`).
      lambda_: smoothing weight (may be traced / injected).
      b1: ``AdamUniform``'s first-moment decay rate.
      b2: ``AdamUniform``'s second-moment decay rate.
      eps: ``AdamUniform``'s epsilon.
      solver: ``"cg"`` (Jacobi-preconditioned CG) or ``"cholesky"`` (needs ``cholespy``);
        see :func:`smoothing_solve`.
      tol: CG relative residual per column.
      maxiter: CG iteration cap.
      warm_start: keep the last solutions in the state and start the CG there.

    Returns:
      An ``optax.GradientTransformationExtraArgs``: ``weld_gradients``,
      ``laplacian_smoothing``, ``scale_by_uniform_adam``, ``laplacian_smoothing`` and
      ``optax.scale_by_learning_rate`` chained; ``update`` needs no ``params``.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> grads = jnp.zeros((6, 3)).at[4, 2].set(1.0)     # pull the top vertex up
        >>> opt = obm.large_steps(0.1, faces, lambda_=1.0)
        >>> updates, state = opt.update(grads, opt.init(verts))
        >>> # the whole mesh moves up, smoothly
        >>> print(np.round(np.asarray(updates[:, 2], float), 3))
        [-0.052 -0.052 -0.052 -0.052 -0.062 -0.049]
    """
    mesh = mesh_laplacian(faces)
    kw: dict[str, Any] = dict(solver=solver, tol=tol, maxiter=maxiter, warm_start=warm_start)
    return optax.chain(
        weld_gradients(mesh),
        laplacian_smoothing(mesh, lambda_, **kw),
        scale_by_uniform_adam(b1, b2, eps),
        laplacian_smoothing(mesh, lambda_, **kw),
        optax.scale_by_learning_rate(learning_rate),
    )


def bilateral_large_steps(
    learning_rate: optax.ScalarOrSchedule,
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: jax.typing.ArrayLike = DEFAULT_SIGMA_D,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    sigma_phi: jax.typing.ArrayLike = DEFAULT_SIGMA_PHI,
    prefilter: Prefilter = "smooth",
    postfilter_v: PostfilterV = "uniform",
    directions: Directions = DEFAULT_DIRECTIONS,
    normals: Normals = "area",
    solver: Solver = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = DEFAULT_MAXITER,
    warm_start: bool = False,
) -> optax.GradientTransformationExtraArgs:
    """The paper's mesh optimizer: Large Steps with a cross-bilateral postfilter on normals.

        g~ = M^-1 g,   m, v = EMAs of g~
        x <- x - lr B m^ / (sqrt(max v^) + eps)            (postfilter_v="uniform", default)
        x <- x - lr B m^ / (sqrt(B v^) + eps)              ("bilateral")
        x <- x - lr B m^ / (sqrt(M^-1 v^) + eps)           ("smooth")

    ``B`` diffuses with ``M^-1 = (I + lambda L)^-1`` but not across normals that
    differ (von Mises-Fisher splat of width ``sigma_d`` and slice of width
    ``sigma_phi``, see :func:`bilateral_normal_filter`). ``sigma_d -> inf`` gives
    :func:`large_steps`. ``prefilter``: ``"smooth"`` (``M^-1 g``, default),
    ``"bilateral"`` (``B g``) or ``"off"``. ``update`` needs ``params`` (the vertex
    positions give the normals).

    With ``optax.inject_hyperparams`` (to schedule ``lambda_``, ``sigma_d``,
    ``sigma_phi`` or the learning rate) pass a :class:`MeshLaplacian` as ``faces``, or
    list ``"faces"`` (and ``"directions"`` if it is an array) in ``static_args``.
    docs/triangle_mesh.md has the method, the authors' parameterisation and measured results.

    Args:
      learning_rate: a number or an optax schedule.
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian` (welded seams: see
        :func:`mesh_laplacian`).
      lambda_: smoothing weight ``>= 0`` of ``M = I + lambda L`` (default 19, the
        authors'; may be traced).
      sigma_d: splat width on normals (``> 0``, default 0.5, the paper's; ``inf`` gives
        :func:`large_steps`; may be traced).
      b1: first-moment decay rate (default 0.9, Large Steps').
      b2: second-moment decay rate (default 0.999).
      eps: added to the denominator (default 1e-8).
      sigma_phi: slice width (``> 0``, default 0.4, the authors'; may be traced).
      prefilter: ``"smooth"`` (``A = M^-1``, default), ``"bilateral"`` (``A = B``) or
        ``"off"``.
      postfilter_v: ``"uniform"`` (default), ``"bilateral"`` or ``"smooth"``, as above
        (see :func:`mesh_postfilter`).
      directions: int number of Sobol sphere directions (default 32; needs SciPy) or a
        ``(K, 3)`` array of unit vectors.
      normals: ``"area"`` (default), ``"uniform"`` (the authors'), ``"angle"`` (see
        :func:`vertex_normals`) or a callable ``positions -> (V, 3) unit normals``.
      solver: ``"cg"`` or ``"cholesky"`` (needs ``cholespy``); see
        :func:`smoothing_solve`.
      tol: CG relative residual per column (default 1e-4).
      maxiter: CG iteration cap (default 2000).
      warm_start: keep the last solutions in the state and start the CG there.

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (``weld_gradients``, the prefilter,
      :func:`mesh_postfilter` and ``optax.scale_by_learning_rate`` chained);
      ``update(updates, state, params)`` needs ``params``, the ``(V, 3)`` positions.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> grads = jnp.zeros((6, 3)).at[4, 2].set(1.0)     # pull the top vertex up
        >>> opt = obm.bilateral_large_steps(0.1, faces, lambda_=1.0, directions=8)
        >>> updates, state = opt.update(grads, opt.init(verts), verts)
        >>> print(np.round(np.asarray(updates[:, 2], float), 3))
        [-0.047 -0.047 -0.047 -0.046 -0.051 -0.044]
    """
    mesh = mesh_laplacian(faces)
    _check_choice(prefilter, "prefilter", PREFILTERS)
    kw: dict[str, Any] = dict(solver=solver, tol=tol, maxiter=maxiter, warm_start=warm_start)
    bil: dict[str, Any] = dict(sigma_phi=sigma_phi, directions=directions, normals=normals)
    parts = [weld_gradients(mesh)]
    if prefilter == "smooth":
        parts.append(laplacian_smoothing(mesh, lambda_, **kw))
    elif prefilter == "bilateral":
        parts.append(bilateral_smoothing(mesh, lambda_, sigma_d, **bil, **kw))
    parts += [
        mesh_postfilter(
            mesh, lambda_, sigma_d, b1, b2, eps, postfilter_v=postfilter_v, **bil, **kw
        ),
        optax.scale_by_learning_rate(learning_rate),
    ]
    return optax.chain(*parts)
