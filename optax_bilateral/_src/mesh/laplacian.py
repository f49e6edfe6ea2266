"""The mesh and its linear system: the Laplacian ``L``, ``M = I + lambda L`` and its solves.

Vertex positions ``x`` (``(V, 3)``, static triangle ``faces``), the combinatorial
Laplacian ``L = D - A`` (``D`` the vertex degrees, ``A`` the adjacency) and the
Large Steps system matrix ``M = I + lambda L`` (Nicolet et al. 2021). ``M`` is an
M-matrix with ``M 1 = 1``, so ``M^-1`` is non-negative and row-stochastic.

Solvers (``solver=``, :mod:`.config`): :class:`CG` (default), Jacobi-preconditioned
conjugate gradients on all right-hand sides at once (columns scaled to unit norm share one
Krylov iteration), jit-able on any backend with a traced ``lambda``; :class:`Cholesky`, a
sparse LDL^T factor of ``M`` computed once per (mesh, lambda) on the host (METIS' nested
dissection, SciPy's SuperLU: the ``cholesky`` extra), swept by the C++ extension for all
right-hand sides at once, its independent parts on threads (SciPy's triangular solves where
it does not load), and called through ``jax.pure_callback``
inside ``lax.custom_linear_solve``, so ``jit``, ``grad`` (w.r.t. the right-hand side, the
vertices and lambda) and ``vmap`` keep working. docs/triangle_mesh.md has the measured
costs of each.

Seams: a mesh with duplicated vertices (UV or normal seams) is welded by
``mesh_laplacian(faces, weld_positions=vertices)``: the Laplacian, the normals and the
filters act on the merged vertices (:func:`merge`, :func:`spread`).
"""

from __future__ import annotations

import collections
import hashlib
import heapq
import numbers
import threading
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from optax_bilateral._src import extension
from optax_bilateral._src.mesh.config import (
    CG,
    DEFAULT_MAXITER,
    DEFAULT_TOL,
    LinearSolver,
    SolverSetting,
    deprecated_keywords,
    solver_of,
)


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
    Field = Float[ArrayLike, "V *C"]
    FieldOut = Float[Array, "V *C"]
else:
    Faces = Positions = Field = FieldOut = Any


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
    f = _checked_faces(faces)
    n = _vertex_count(f, num_vertices)
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
    neighbors, degree = _one_rings(f, n)
    as_index = lambda a: None if a is None else jnp.asarray(a, jnp.int32)
    return MeshLaplacian(
        jnp.asarray(neighbors),
        jnp.asarray(degree, jnp.float32),
        jnp.asarray(f, jnp.int32),
        as_index(index),
        as_index(first),
    )


def _checked_faces(faces) -> np.ndarray:
    f = _concrete_faces(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F >= 1 (triangles), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"faces must be an integer array of vertex indices, got dtype {f.dtype}")
    if f.min() < 0:
        raise ValueError(f"faces must hold vertex indices >= 0, got {f.min()}")
    return f


def _vertex_count(f: np.ndarray, num_vertices) -> int:
    n = int(f.max()) + 1 if num_vertices is None else num_vertices
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < int(f.max()) + 1:
        raise ValueError(
            f"num_vertices must be an int > max(faces) = {int(f.max())}, got {num_vertices!r}"
        )
    return int(n)


def _one_rings(f: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``(n, D)`` neighbour table (padded with ``n``) and the degrees."""
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
    return neighbors, degree


def merge(mesh: MeshLaplacian, x):
    """A field on the input vertices -> the merged vertices (copies hold equal values)."""
    return x if mesh.first is None else x[mesh.first]


def spread(mesh: MeshLaplacian, x):
    """A field on the merged vertices -> every input vertex (copies get the same value)."""
    return x if mesh.index is None else x[mesh.index]


def check_field(x, mesh: MeshLaplacian, what: str, channels: int | None = None) -> None:
    """Raises unless ``x`` is ``(V, C)`` (``(V, channels)`` if given) on this mesh."""
    if x.ndim != 2 or x.shape[0] != mesh.num_vertices or (channels and x.shape[1] != channels):
        want = f"({mesh.num_vertices}, {channels})" if channels else f"({mesh.num_vertices}, C)"
        raise ValueError(
            f"{what}: every leaf must have shape {want} (one row per mesh vertex), got {x.shape}"
        )


def _matvec(neighbors, degree, lambda_, x):
    """``(I + lambda L) x`` for ``x`` of shape ``(U, C)``."""
    padded = jnp.concatenate([x, jnp.zeros((1, x.shape[1]), x.dtype)])
    # One row gather per neighbour slot, summed: XLA:CPU runs this 5-10x faster
    # than gathering the (U, D, C) block and reducing it.
    neighbour_sum = padded[neighbors[:, 0]]
    for j in range(1, neighbors.shape[1]):
        neighbour_sum = neighbour_sum + padded[neighbors[:, j]]
    return x + lambda_ * (degree.astype(x.dtype)[:, None] * x - neighbour_sum)


class _Supernodes(NamedTuple):
    """``L`` by supernodes, as the extension's sweeps read it (``csrc/ldl.h``): runs of
    consecutive columns whose rows below the run are the same, each an ``(s + r, s)`` block."""

    first: np.ndarray  # (S + 1,) int32 the first column of each supernode, then U
    row_ptr: np.ndarray  # (S + 1,) int32 where each one's rows below start in ``rows``
    rows: np.ndarray  # int32
    block_ptr: np.ndarray  # (S + 1,) int64 where each one's block starts in ``values``
    values: np.ndarray  # float64
    single: np.ndarray  # the same in float32

    @classmethod
    def of(cls, colptr: np.ndarray, rows: np.ndarray, values: np.ndarray, breaks=()) -> _Supernodes:
        n = len(colptr) - 1
        counts = np.diff(colptr)
        first = _supernode_starts(colptr, rows, breaks)
        widths = np.diff(first).astype(np.int64)
        last = first[1:] - 1
        below = counts[last].astype(np.int64)  # the last column's rows are all below the run
        row_ptr = np.concatenate([[0], np.cumsum(below)]).astype(np.int32)
        take = np.repeat(colptr[last].astype(np.int64) - row_ptr[:-1], below)
        take += np.arange(row_ptr[-1])
        block_ptr = np.concatenate([[0], np.cumsum((widths + below) * widths)]).astype(np.int64)
        # Entry m of column c = j0 + t is block row t + 1 + m, block column t.
        column = np.repeat(np.arange(n), counts)
        k = np.repeat(np.arange(len(widths)), widths)[column]
        t = column - first[k]
        m = np.arange(len(rows)) - colptr[column]
        blocks = np.zeros(block_ptr[-1])
        blocks[block_ptr[k] + (t + 1 + m) * widths[k] + t] = values
        rows_below = rows[take].astype(np.int32)
        return cls(first, row_ptr, rows_below, block_ptr, blocks, blocks.astype(np.float32))


def _supernode_starts(colptr: np.ndarray, rows: np.ndarray, breaks=()) -> np.ndarray:
    """The first column of each fundamental supernode, then ``n``: column ``j + 1`` continues
    ``j``'s when it is ``j``'s first row below and ``j``'s other rows are exactly its rows, and
    is not one of ``breaks`` (columns that start a supernode: the parts' bounds)."""
    n = len(colptr) - 1
    counts = np.diff(colptr)
    j = np.arange(max(n - 1, 0))
    joins = (counts[:-1] == counts[1:] + 1) & (counts[:-1] > 0)
    joins[joins] &= rows[colptr[j[joins]]] == j[joins] + 1
    cand = j[joins]
    lengths = counts[cand + 1]
    offsets = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    same = (
        rows[np.repeat(colptr[cand] + 1, lengths) + offsets]
        == rows[np.repeat(colptr[cand + 1], lengths) + offsets]
    )
    mismatch = np.bincount(np.repeat(np.arange(len(cand)), lengths)[~same], minlength=len(cand))
    joins[cand[mismatch > 0]] = False
    cuts = np.asarray(breaks, np.int64)
    joins[cuts[(cuts > 0) & (cuts < n)] - 1] = False
    first = np.flatnonzero(np.concatenate([[True], ~joins])) if n else np.zeros(0, int)
    return np.append(first, n).astype(np.int32)


class _Factor(NamedTuple):
    """``M = P (I + L) D (I + L)^T P^T`` (:func:`_ldl`, in :func:`_ordering`'s order): ``L``
    strictly lower in compressed columns (SciPy's sweeps) and by supernodes in parts and a
    top (the extension's)."""

    colptr: np.ndarray  # (U + 1,) int32
    rows: np.ndarray  # (nnz,) int32
    values: np.ndarray  # (nnz,) float64
    dinv: np.ndarray  # (U,) float64
    perm: np.ndarray  # (U,) int32
    supernodes: _Supernodes
    part_ptr: np.ndarray  # (parts + 1,) int32: the supernode each part, then the top, starts at
    dinv_single: np.ndarray  # float32, for float32 fields

    @classmethod
    def of(cls, colptr, rows, values, d, order: _Ordering) -> _Factor:
        colptr, rows = np.asarray(colptr, np.int32), np.asarray(rows, np.int32)
        values, dinv = np.asarray(values, np.float64), 1.0 / np.asarray(d, np.float64)
        supernodes = _Supernodes.of(colptr, rows, values, order.bounds)
        part_ptr = np.searchsorted(supernodes.first, order.bounds).astype(np.int32)
        single = dinv.astype(np.float32)
        return cls(colptr, rows, values, dinv, order.perm, supernodes, part_ptr, single)

    def arrays(self, single: bool) -> tuple[np.ndarray, ...]:
        """The extension's arguments (``csrc/ldl.h``), float32 or float64 values."""
        sn = self.supernodes
        values, dinv = (sn.single, self.dinv_single) if single else (sn.values, self.dinv)
        return sn.first, sn.row_ptr, sn.rows, sn.block_ptr, values, dinv, self.perm, self.part_ptr

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``M^-1 b`` for ``b`` ``(U, C)`` float32 or float64, in that dtype."""
        module, _ = extension.loaded()
        if module is None:
            return self._solve_scipy(b)
        x = np.array(b, order="C", copy=True)
        module.ldl_solve(*self.arrays(b.dtype == np.float32), x, extension.threads())
        return x

    def _solve_scipy(self, b: np.ndarray) -> np.ndarray:
        """The same sweeps by SciPy, where the extension does not load."""
        from scipy.sparse import csc_matrix
        from scipy.sparse.linalg import spsolve_triangular

        n = len(self.dinv)
        lower = csc_matrix((self.values, self.rows, self.colptr), shape=(n, n))
        y = spsolve_triangular(lower.tocsr(), b[self.perm], lower=True, unit_diagonal=True)
        y = y * self.dinv[:, None]
        y = spsolve_triangular(lower.T.tocsr(), y, lower=False, unit_diagonal=True)
        x = np.empty_like(y)
        x[self.perm] = y
        return x.astype(b.dtype)


class _Ordering(NamedTuple):
    """Where each vertex goes in the factor, and the factor's parts (``csrc/ldl.h``)."""

    perm: np.ndarray  # (U,) int32: the factor's row i is vertex perm[i]
    bounds: np.ndarray  # (parts + 1,) int64: the first column of each part, then the top's
    inverse: np.ndarray  # (U,) int32: vertex v is the factor's row inverse[v]


def _ldl(m, sparse: Any) -> tuple[Any, np.ndarray]:
    """``m = (I + L) D (I + L)^T`` in ``m``'s own order (SciPy's SuperLU, no pivoting: ``m``
    is symmetric positive definite): ``L`` strictly lower, compressed columns, sorted."""
    from scipy.sparse.linalg import splu

    n = m.shape[0]
    lu = splu(m, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    if not (np.array_equal(lu.perm_r, np.arange(n)) and np.array_equal(lu.perm_c, np.arange(n))):
        raise RuntimeError("SuperLU reordered a symmetric positive definite matrix")
    lower = sparse.tril(lu.L, -1).tocsc()
    lower.sort_indices()
    return lower, lu.U.diagonal()


def _ordering(pattern, parts: int, metis: Any, sparse: Any) -> _Ordering:
    """METIS' nested dissection of ``pattern`` (``M``'s, symmetric), its columns then regrouped
    into ``parts`` groups of whole subtrees of the factor's elimination tree and the rest (the
    top): any order that keeps each column after its descendants has the same factor, up to the
    order of its sums."""
    adjacency = sparse.csr_matrix(pattern - sparse.diags(pattern.diagonal()))
    adjacency.eliminate_zeros()
    graph = metis.CSRAdjacency(adj_starts=adjacency.indptr, adjacent=adjacency.indices)
    nd = np.asarray(metis.nested_dissection(adjacency=graph)[0], np.int64)
    lower, _ = _ldl(sparse.csc_matrix(pattern[nd][:, nd]), sparse)
    counts = np.diff(lower.indptr)
    parent = np.full(len(nd), -1, np.int64)
    parent[counts > 0] = lower.indices[lower.indptr[:-1][counts > 0]]
    # A column's sweep cost: its entries, and a few for visiting it.
    label = _split(parent, counts + 8.0, parts)
    order = np.concatenate([np.flatnonzero(label == b) for b in range(parts + 1)])
    bounds = np.concatenate([[0], np.cumsum(np.bincount(label, minlength=parts + 1))[:-1]])
    perm = nd[order].astype(np.int32)
    return _Ordering(perm, bounds.astype(np.int64), np.argsort(perm).astype(np.int32))


def _split(parent: np.ndarray, weight: np.ndarray, parts: int) -> np.ndarray:
    """Each column's part (``0 .. parts-1``) or ``parts`` (the top): the top grows from the roots
    down, the largest subtree below it first, and the subtrees under it go to the parts, largest
    first to the lightest; the split whose top plus heaviest part is least wins."""
    n = len(parent)
    total = weight.astype(np.float64).copy()
    for j in range(n):  # a parent comes after its children
        if parent[j] >= 0:
            total[parent[j]] += total[j]
    by_parent = np.argsort(parent, kind="stable")
    starts = np.searchsorted(parent[by_parent], np.arange(-1, n + 1))
    children = lambda j: by_parent[starts[j + 1] : starts[j + 2]]  # j = -1: the roots
    frontier = [(-total[r], int(r)) for r in children(-1)]
    heapq.heapify(frontier)
    top: list[int] = []
    best, best_at, top_weight = np.inf, ([], 0), 0.0
    limit = total[children(-1)].sum() / (8 * parts)
    while frontier:
        loads = np.zeros(parts)
        assigned = []
        for w, r in sorted(frontier):
            b = int(np.argmin(loads))
            loads[b] -= w
            assigned.append((r, b))
        if top_weight + loads.max() < best:
            best, best_at = top_weight + loads.max(), (assigned, len(top))
        if -frontier[0][0] <= limit or len(frontier) > 32 * parts:
            break
        # Down to the next branching: a chain's columns join the top one at a time.
        while True:
            _, j = heapq.heappop(frontier)
            top.append(j)
            top_weight += weight[j]
            below = children(j)
            if len(below) != 1:
                break
            heapq.heappush(frontier, (-total[below[0]], int(below[0])))
        for c in below:
            heapq.heappush(frontier, (-total[c], int(c)))
    assigned, tops = best_at
    label = np.full(n, -1, np.int64)
    label[top[:tops]] = parts
    for r, b in assigned:
        label[r] = b
    for j in range(n - 1, -1, -1):  # descendants take their subtree root's part
        if label[j] < 0:
            label[j] = label[parent[j]]
    return label


class _Cholesky:
    """Host-side sparse LDL^T factors of ``I + lambda L`` (SciPy's SuperLU in METIS' nested
    dissection order, :func:`_ordering`), solved by the extension's sweeps (``csrc/ldl.h``:
    every column of the right-hand side in one pass over the factor, its parts on threads).

    One per mesh (see :func:`_host_cholesky`), with the factors of the last few lambda
    values, so a schedule over a few values does not refactorise every step.
    """

    MAX_FACTORS = 4
    MAX_PARTS = 8  # each part keeps its own copy of the top's rows in every solve's buffer

    def __init__(self, neighbors: np.ndarray, degree: np.ndarray):
        try:
            import pymetis
            import scipy.sparse
        except ImportError as e:
            raise ImportError(
                "solver='cholesky' needs pymetis and SciPy: pip install "
                "'optax_bilateral[cholesky]' (or use solver='cg')"
            ) from e
        self._metis: Any = pymetis  # a compiled extension without type information
        self._sparse: Any = scipy.sparse
        u = len(degree)
        rows = np.repeat(np.arange(u), neighbors.shape[1])
        keep = neighbors.ravel() < u
        diag = np.arange(u)
        self._ii = np.concatenate([diag, rows[keep]]).astype(np.int32)
        self._jj = np.concatenate([diag, neighbors.ravel()[keep]]).astype(np.int32)
        self._degree = np.asarray(degree, np.float64)
        self._off = int(keep.sum())
        self._order: _Ordering | None = None  # one per mesh: every lambda > 0 has M's pattern
        self._factors: collections.OrderedDict[float, _Factor] = collections.OrderedDict()
        self._stored: dict[float, int] = {}  # lambda -> the extension's id of its factor
        self._lock = threading.Lock()

    def factor(self, lam: float) -> _Factor:
        with self._lock:
            if lam in self._factors:
                self._factors.move_to_end(lam)
                return self._factors[lam]
            if self._order is None:
                # Parts for the threads a solve will have (the sums' order follows them).
                parts = min(extension.threads(), self.MAX_PARTS)
                self._order = _ordering(self._matrix(1.0), parts, self._metis, self._sparse)
            perm = self._order.perm
            lower, d = _ldl(self._matrix(lam)[perm][:, perm].tocsc(), self._sparse)
            fac = _Factor.of(lower.indptr, lower.indices, lower.data, d, self._order)
            self._factors[lam] = fac
            while len(self._factors) > self.MAX_FACTORS:
                self._factors.popitem(last=False)
            return fac

    def _matrix(self, lam: float):
        """``M = I + lam L``, compressed columns."""
        u = len(self._degree)
        values = np.concatenate([1.0 + lam * self._degree, np.full(self._off, -lam)])
        return self._sparse.csc_matrix((values, (self._ii, self._jj)), shape=(u, u))

    def pinned(self, lam: float) -> _Pinned | None:
        """The factor of ``lam`` handed to the extension, for XLA to call without a host round
        trip (kept for the process's life, one per (mesh, lambda) asked for), or None where
        the extension's FFI targets did not load."""
        if not extension.registered()[0]:
            return None
        if lam not in self._stored:
            module, _ = extension.loaded()
            assert module is not None  # registered
            self._stored[lam] = module.register_factor(*self.factor(lam).arrays(single=False))
        return _Pinned(self, self._stored[lam])

    def solve(self, b: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``b``: ``(*batch, U, C)``; ``lam``: ``(*batch)`` (vmap broadcasts both). Solved in
        ``b``'s dtype where it is float32 or float64, else in float32."""
        b, lam = np.asarray(b), np.asarray(lam, np.float64)
        work = b.dtype if b.dtype in (np.float32, np.float64) else np.dtype(np.float32)
        batch = b.shape[:-2]
        if not batch:
            x = self.factor(float(lam)).solve(b.astype(work, copy=False))
            return x.astype(b.dtype, copy=False)
        flat_b = b.reshape((-1,) + b.shape[-2:])
        flat_lam = np.broadcast_to(lam, batch).reshape(-1)
        out = np.empty(flat_b.shape, b.dtype)
        for value in np.unique(flat_lam):
            which = np.nonzero(flat_lam == value)[0]
            # All batch members with this lambda as the columns of one solve.
            rhs = (
                flat_b[which[0]] if len(which) == 1 else np.concatenate(list(flat_b[which]), axis=1)
            )
            x = self.factor(float(value)).solve(rhs.astype(work, copy=False))
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


class _Pinned(NamedTuple):
    """A factor the extension holds (``_Cholesky.pinned``): solved inside XLA by its FFI
    target ``optax_bilateral_ldl``, no host round trip."""

    host: _Cholesky
    factor: int  # the extension's id

    @property
    def order(self) -> _Ordering:
        """The factor's order of the vertices (the mesh's, shared by every lambda's factor)."""
        order = self.host._order
        assert order is not None  # set by the factor the extension holds
        return order


def factor_order(host) -> _Ordering | None:
    """The factor's order of the vertices where ``host`` (a :class:`System`'s) solves inside
    XLA, whose solve then takes right-hand sides in that order (``solve_columns(...,
    ordered=True)``) without a working copy of their rows; else None."""
    return host.order if isinstance(host, _Pinned) else None


def _ffi_solve(factor: int, rhs, ordered: bool = False):
    """``M^-1 rhs`` by the extension's FFI target, in float32 for narrower floats; ``ordered``:
    ``rhs``' rows are in the factor's order."""
    dtype = rhs.dtype
    work = rhs if dtype in (jnp.float32, jnp.float64) else rhs.astype(jnp.float32)
    call = jax.ffi.ffi_call(
        "optax_bilateral_ldl",
        jax.ShapeDtypeStruct(work.shape, work.dtype),
        vmap_method="sequential",
        input_output_aliases={0: 0},
    )
    out = call(
        work, factor=np.int64(factor), threads=np.int64(extension.threads()), ordered=ordered
    )
    return out.astype(dtype)


def solve_columns(host, neighbors, degree, b, lambda_, tol, maxiter, x0, ordered=False):
    """``(I + lambda L)^-1 b`` for ``b`` of shape ``(U, C)``; ``host`` None means CG, a
    ``_Pinned`` factor the extension's FFI call, a ``_Cholesky`` a host callback.
    ``ordered``: ``b``'s rows (and the solution's) are in the pinned factor's order
    (:func:`factor_order`), so the extension sweeps them where they are."""
    matvec = lambda v: _matvec(neighbors, degree, lambda_, v)
    if ordered and not isinstance(host, _Pinned):
        raise ValueError("ordered right-hand sides need a factor the extension holds")
    if isinstance(host, _Pinned):
        if ordered:
            order = host.order
            unordered = matvec
            matvec = lambda v: unordered(v[order.inverse])[order.perm]
        solve = lambda _, rhs: _ffi_solve(host.factor, rhs, ordered)
        return lax.custom_linear_solve(matvec, b, solve, symmetric=True)
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
solve_jit = jax.jit(solve_columns, static_argnums=0)


def _concrete(x) -> float | None:
    """``x`` as a float where it is known at trace time, else None."""
    try:
        return float(x)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError, TypeError):
        return None


class System(NamedTuple):
    """``M = I + lambda L`` on a mesh and how to solve it: what every solve needs but ``b``."""

    mesh: MeshLaplacian
    host: Any  # the factorised solver: _Pinned (in XLA) or _Cholesky (on the host); None: CG
    lambda_: Any
    tol: Any
    maxiter: Any

    @classmethod
    def of(cls, mesh: MeshLaplacian, solver: LinearSolver, lambda_) -> System:
        if isinstance(solver, CG):
            return cls(mesh, None, lambda_, solver.tol, solver.maxiter)
        host = _host_cholesky(mesh)
        lam = _concrete(lambda_)
        # A known lambda: its factor is solved inside XLA; a traced one: on the host, by value.
        solver_handle = (host.pinned(lam) if lam is not None else None) or host
        return cls(mesh, solver_handle, lambda_, DEFAULT_TOL, DEFAULT_MAXITER)

    def solve(self, b, x0=None):
        """``M^-1 b`` on the merged vertices; ``b`` and ``x0`` are ``(U, C)``."""
        dtype = b.dtype
        return solve_jit(
            self.host,
            self.mesh.neighbors,
            self.mesh.degree,
            b,
            jnp.asarray(self.lambda_, dtype),
            jnp.asarray(self.tol, dtype),
            jnp.asarray(self.maxiter, jnp.int32),
            x0,
        )


def smoothing_solve(
    mesh: MeshLaplacian,
    b: Field,
    lambda_: jax.typing.ArrayLike,
    *,
    solver: SolverSetting = "cg",
    x0: Field | None = None,
    **deprecated: Any,
) -> FieldOut:
    """Solves ``(I + lambda L) x = b`` (Large Steps' "smooth").

    Args:
      mesh: a :class:`MeshLaplacian`.
      b: ``(V,)`` or ``(V, C)`` right-hand sides (one system per column). On a welded
        mesh the copies of a vertex must hold equal values (one is read).
      lambda_: smoothing weight ``>= 0``; may be traced (with :class:`Cholesky`, each new
        value is factorised on the host, the last four are kept).
      solver: ``"cg"`` or a :class:`CG` (Jacobi-preconditioned CG, columns scaled to unit
        norm share one Krylov iteration; its ``warm_start`` is for the transforms), or
        ``"cholesky"`` / :class:`Cholesky` (needs ``pymetis`` and SciPy).
      x0: optional CG starting point with the shape of ``b`` (e.g. the last solution).
      **deprecated: ``tol`` and ``maxiter``, the fields of :class:`CG` now: still applied
        for one release, with a ``DeprecationWarning``.

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
    old = deprecated_keywords("smoothing_solve", deprecated, ("tol", "maxiter"))
    system = System.of(mesh, solver_of(solver, old), lambda_)
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
        x0 = merge(mesh, x0)
    x = spread(mesh, system.solve(merge(mesh, b), x0))
    return x[:, 0] if squeeze else x
