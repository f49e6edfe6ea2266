"""The mesh transforms' settings: defaults, the normal filter's data term and the solvers.

A setting that is more than one number is a frozen dataclass: :class:`NormalFilter` (what
``B`` compares: its widths on normals, its sphere directions, how normals are computed) and
:class:`CG` or :class:`Cholesky` (how ``(I + lambda L) x = b`` is solved). The transforms
take them as ``sigma_d=`` (a number is ``NormalFilter(sigma_d=number)``) and ``solver=``
(``"cg"`` is ``CG()``, ``"cholesky"`` is ``Cholesky()``). The keywords these replaced
(``sigma_phi``, ``directions``, ``normals``, ``tol``, ``maxiter``, ``warm_start``) still
work for one release, with a ``DeprecationWarning`` naming the field
(:func:`deprecated_keywords`).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal, TypeAlias, get_args

import numpy as np

from optax_bilateral._src.validation import (
    check_bool,
    check_choice,
    check_integer,
    check_number,
    check_positive,
    is_concrete,
)

# Large Steps' examples use lambda around 10-100; the authors' mesh run uses 19.
DEFAULT_LAMBDA = 19.0
"""The default smoothing weight ``lambda`` of ``M = I + lambda L`` (the authors' mesh run)."""
# The paper's default data term (supplement §3: "sigma_d around 0.5"); the authors'
# code splats with sigma_d and slices with sigma_phi = 0.4.
DEFAULT_NORMAL_SIGMA_D = 0.5
"""The paper's splat width ``sigma_d`` on normals (supplement §3): the default
:class:`DensityWidth`'s up to 2562 vertices."""
# The splat width grows with the mesh from here: the paper's 0.5 at the coarsest mesh
# measured, 2 (the widest measured) at 40962 vertices (docs/triangle_mesh.md).
DENSITY_VERTICES = 2562
"""Where :class:`DensityWidth` starts widening the splat: an icosphere of frequency 16."""
DENSITY_LARGEST = 2.0
"""The widest splat :class:`DensityWidth` picks (reached at 16x ``DENSITY_VERTICES``)."""
DEFAULT_SIGMA_PHI = 0.4
"""The default slice width ``sigma_phi`` on normals (the authors' code)."""
# "A few dozen" directions (the authors' n_filter_samples); a power of two keeps Sobol's balance.
DEFAULT_DIRECTIONS = 32
"""The default number of sphere directions ``s_k`` of the filter (:func:`sphere_directions`)."""
# The directions' kernel is smooth: rank 16 (spherical harmonics to degree 3) holds the
# defaults' to 1.1%, half the solve's columns (docs/triangle_mesh.md decisions).
DEFAULT_KERNEL_TOL = 0.02
"""The default :class:`NormalFilter` ``kernel_tol``: the largest relative error of the
compressed data term ``K(n_i, n_j)`` against the directions' own."""
# Relative residual per right-hand side (docs/triangle_mesh.md: iterations against tol).
DEFAULT_TOL = 1e-4
"""The default CG tolerance: relative residual per right-hand side."""
DEFAULT_MAXITER = 2000
"""The default cap on CG iterations per solve."""


@dataclasses.dataclass(frozen=True)
class DensityWidth:
    """The splat width ``sigma_d`` chosen from the mesh (the default of :class:`NormalFilter`).

    ``clip(sigma_d * sqrt(U / vertices), sigma_d, largest)``, ``U`` the mesh's distinct
    vertices: ``sigma_d`` up to ``vertices``, then growing as the edges shrink. The same noise
    in the positions tilts a finer mesh's normals more (about the noise over the edge
    length), so a fixed width stops the smoothing at more vertices that are not on an edge;
    a sharp edge still turns the normals by its full angle. Measured on a round-edged and a
    sharp-edged target at 2562, 10242 and 40962 vertices (docs/triangle_mesh.md). Hashable.

    Attributes:
      sigma_d: the width up to ``vertices`` (``> 0``, finite; default 0.5, the paper's).
      vertices: the count where the width starts growing (an int ``>= 1``; default 2562).
      largest: the widest it gets (``>= sigma_d``, finite; default 2, the widest measured).

    Example::

        >>> from optax_bilateral import triangle_mesh as obm
        >>> rule = obm.DensityWidth()
        >>> [rule.width(v) for v in (642, 2562, 10242, 40962, 163842)]
        [0.5, 0.5, 0.99..., 1.99..., 2.0]
    """

    sigma_d: float = DEFAULT_NORMAL_SIGMA_D
    vertices: int = DENSITY_VERTICES
    largest: float = DENSITY_LARGEST

    def __post_init__(self):
        check_number(self, "sigma_d", low=0, high=math.inf, low_open=True, high_open=True)
        check_integer(self, "vertices", low=1)
        check_number(self, "largest", low=self.sigma_d, high=math.inf, high_open=True)

    def width(self, num_vertices: int) -> float:
        """The splat width on a mesh of ``num_vertices`` distinct vertices."""
        grown = self.sigma_d * math.sqrt(num_vertices / self.vertices)
        return min(max(grown, self.sigma_d), self.largest)


DEFAULT_WIDTH = DensityWidth()
"""The default ``sigma_d`` (of :class:`NormalFilter` and the transforms): the splat width
from the mesh's vertex count."""

SolverName = Literal["cg", "cholesky"]
NormalWeighting = Literal["area", "uniform", "angle"]
Prefilter = Literal["smooth", "bilateral", "off"]
PostfilterV = Literal["uniform", "bilateral", "smooth"]

SOLVERS: tuple[SolverName, ...] = get_args(SolverName)
"""The names ``solver=`` takes: ``"cg"`` (:class:`CG`) and ``"cholesky"`` (:class:`Cholesky`)."""
NORMALS: tuple[NormalWeighting, ...] = get_args(NormalWeighting)
"""The values of :class:`NormalFilter`'s ``normals`` (and :func:`vertex_normals`' ``weighting``)."""
PREFILTERS: tuple[Prefilter, ...] = get_args(Prefilter)
"""The values of :func:`bilateral_large_steps`' ``prefilter=``."""
POSTFILTERS_V: tuple[PostfilterV, ...] = get_args(PostfilterV)
"""The values of ``postfilter_v=`` (the second moment's filter, :func:`mesh_postfilter`)."""

if TYPE_CHECKING:
    import jax
    from jaxtyping import Array, ArrayLike, Float

    Directions = int | Float[ArrayLike, "K 3"]
    UnitNormals = Float[Array, "V 3"]
    Normals = NormalWeighting | Callable[[Array], UnitNormals]
else:
    Directions = UnitNormals = Normals = Any


@dataclasses.dataclass(frozen=True)
class NormalFilter:
    """The data term of the mesh's cross-bilateral operator ``B`` (supplement §3).

    ``w_k(i) = exp((max(n_i . s_k, -1) - 1) / sigma_d)`` splats, ``phi_k(i)`` (the same with
    ``sigma_phi``) slices, ``s_k`` the sphere directions and ``n_i`` the vertex normals
    (:func:`bilateral_normal_filter` has the operator). Pass it as ``sigma_d=``; a number
    there is ``NormalFilter(sigma_d=number)``. The widths may be traced (a factory under
    ``optax.inject_hyperparams`` that builds the filter from its arguments); with Python
    numbers and an int or array of directions the object is hashable.

    Attributes:
      sigma_d: splat width on normals (``> 0``; ``inf``: every weight 1, Large Steps'
        ``B = M^-1``), or a :class:`DensityWidth` that picks it from the mesh (the default:
        the paper's 0.5 up to 2562 vertices, wider on finer meshes, 2 from 40962).
      sigma_phi: slice width (``> 0``). Default 0.4, the authors'.
      directions: an int (that many Lloyd-relaxed Sobol directions,
        :func:`sphere_directions`, which needs SciPy) or a ``(K, 3)`` array of unit vectors
        (kept as a tuple). Default 32, the authors'.
      normals: how a transform computes the guide from the positions: ``"area"`` (the
        default), ``"uniform"`` (the authors'), ``"angle"`` (see :func:`vertex_normals`) or
        a callable ``positions -> (V, 3) unit normals``. :func:`bilateral_normal_filter`,
        which is given the normals, does not read it.
      kernel_tol: how far the data term ``K(n_i, n_j) = sum_k phi_k(i) w_k(j)`` may move,
        relative, when it is compressed to fewer splat/slice pairs than directions (in
        ``[0, 0.5)``; default 0.02). ``K`` is smooth on the sphere, so a few combinations
        of the ``phi_k`` and of the ``w_k`` hold it (:func:`kernel_bases`): each pair fewer is
        ``C + 1`` solve columns fewer. ``0`` keeps every direction (the authors' form).
        With traced widths every direction is kept.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> data_term = obm.NormalFilter(sigma_d=0.3, directions=8, normals="uniform")
        >>> data_term == obm.NormalFilter(0.3, 0.4, 8, "uniform"), hash(data_term) is not None
        (True, True)
        >>> opt = obm.bilateral_large_steps(1e-2, faces, lambda_=19.0, sigma_d=data_term)
    """

    sigma_d: jax.typing.ArrayLike | DensityWidth = DEFAULT_WIDTH
    sigma_phi: jax.typing.ArrayLike = DEFAULT_SIGMA_PHI
    directions: Directions = DEFAULT_DIRECTIONS
    normals: Normals = "area"
    kernel_tol: float = DEFAULT_KERNEL_TOL

    def __post_init__(self):
        if not isinstance(self.sigma_d, DensityWidth):
            check_positive(self.sigma_d, "sigma_d", "inf turns its weights off")
        check_positive(self.sigma_phi, "sigma_phi", "inf turns its weights off")
        # Below 1 the compressed kernel stays positive (B non-negative); past 1/2 it would
        # be another filter, not the directions' one.
        check_number(self, "kernel_tol", low=0, high=0.5, high_open=True)
        if not callable(self.normals):
            check_choice(self.normals, "normals", NORMALS)
        d = self.directions
        if isinstance(d, numbers.Integral) and not isinstance(d, bool):
            if d < 1:
                raise ValueError(f"directions must be a positive int, got {d!r}")
            return
        # A (K, 3) array as a tuple: equal settings compare equal and hash alike.
        rows = tuple(tuple(float(c) for c in row) for row in check_directions(d))
        object.__setattr__(self, "directions", rows)

    @property
    def is_large_steps(self) -> bool:
        """``sigma_d`` is a concrete ``inf``: ``B = M^-1``, the directions unused."""
        if isinstance(self.sigma_d, DensityWidth) or not is_concrete(self.sigma_d):
            return False
        return bool(np.isinf(np.asarray(self.sigma_d)))

    def on_mesh(self, num_vertices: int) -> NormalFilter:
        """This filter on a mesh of ``num_vertices`` distinct vertices: a
        :class:`DensityWidth` replaced by its width there."""
        if not isinstance(self.sigma_d, DensityWidth):
            return self
        return dataclasses.replace(self, sigma_d=self.sigma_d.width(num_vertices))


def check_directions(directions) -> np.ndarray:
    """A ``(K, 3)`` array of unit vectors as float64, or a ValueError."""
    expected = (
        "directions must be an int (number of Sobol directions) or a (K, 3) array of unit vectors"
    )
    try:
        d = np.asarray(directions, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{expected}, got {directions!r}") from e
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
        raise ValueError(f"{expected}, got shape {d.shape}")
    if not np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4):
        raise ValueError("directions must be unit vectors")
    return d


@dataclasses.dataclass(frozen=True)
class CG:
    """Jacobi-preconditioned conjugate gradients for ``(I + lambda L) x = b`` (the default).

    All right-hand sides at once, each column scaled to unit norm so that they share one
    Krylov iteration; jit-able on any backend, ``lambda`` may be traced.

    Attributes:
      tol: relative residual per column (``> 0``; default 1e-4).
      maxiter: iteration cap (a positive int; default 2000).
      warm_start: keep each solution in the transform's state and start the next step's CG
        there (default False; docs/triangle_mesh.md measures what it saves).

    Example::

        >>> import numpy as np
        >>> from optax_bilateral import triangle_mesh as obm
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> opt = obm.large_steps(1e-2, faces, solver=obm.CG(tol=1e-6, warm_start=True))
        >>> obm.CG() == obm.CG(1e-4, 2000, False)
        True
    """

    tol: float = DEFAULT_TOL
    maxiter: int = DEFAULT_MAXITER
    warm_start: bool = False

    def __post_init__(self):
        check_number(self, "tol", low=0, low_open=True)
        check_integer(self, "maxiter", low=1)
        check_bool(self.warm_start, "warm_start")


@dataclasses.dataclass(frozen=True)
class Cholesky:
    """A sparse Cholesky (LDL^T) factor of ``I + lambda L`` (METIS' nested dissection by
    ``pymetis`` and SciPy's SuperLU, the ``cholesky`` extra), computed on the host once per
    (mesh, lambda), the last four lambdas kept, swept by the C++ extension for every
    right-hand side in one pass, independent subtrees of the factor on threads at once
    (SciPy's triangular solves where it does not load), in the field's precision (float32
    or float64; half precisions in float32), and called through ``jax.pure_callback``
    inside ``lax.custom_linear_solve``: ``jit``, ``grad`` (right-hand side, vertices,
    lambda) and ``vmap`` keep working.

    Example::

        >>> import numpy as np
        >>> from optax_bilateral import triangle_mesh as obm
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> opt = obm.large_steps(1e-2, faces, solver=obm.Cholesky())   # or solver="cholesky"
    """


LinearSolver: TypeAlias = CG | Cholesky
SolverSetting: TypeAlias = "SolverName | LinearSolver"
"""A transform's ``solver``: ``"cg"``, ``"cholesky"``, or a :class:`CG` or :class:`Cholesky`."""
FilterSetting: TypeAlias = "float | Array | DensityWidth | NormalFilter"
"""A transform's ``sigma_d``: the splat width on normals, a rule that picks it from the mesh
(:class:`DensityWidth`), or a whole :class:`NormalFilter`."""


def as_solver(solver: SolverSetting) -> LinearSolver:
    """The solver a ``solver=`` setting names."""
    if isinstance(solver, (CG, Cholesky)):
        return solver
    check_choice(solver, "solver", SOLVERS)
    return CG() if solver == "cg" else Cholesky()


def as_filter(sigma_d: FilterSetting) -> NormalFilter:
    """The normal filter a ``sigma_d=`` setting names."""
    return sigma_d if isinstance(sigma_d, NormalFilter) else NormalFilter(sigma_d)


# ----------------------------------------------------------------------------------------
# Keywords the mesh functions took in 0.1.0, and the field each one is now.

FILTER_FIELDS = ("sigma_phi", "directions", "normals")
SOLVER_FIELDS = ("tol", "maxiter", "warm_start")


def deprecated_keywords(function: str, keywords: dict, accepted: tuple[str, ...]) -> dict:
    """The deprecated ``keywords`` of ``function`` (those in ``accepted``), each with a
    ``DeprecationWarning`` naming the field it is now. ``optax.inject_hyperparams`` binds
    them as one keyword, ``deprecated``: unpacked."""
    keywords = {**keywords.pop("deprecated", {}), **keywords}
    for name in keywords:
        if name not in accepted:
            raise TypeError(f"{function}() got an unexpected keyword argument {name!r}")
        owner, arg = ("NormalFilter", "sigma_d") if name in FILTER_FIELDS else ("CG", "solver")
        warnings.warn(
            f"{function}({name}=...) is deprecated after 0.1.0 and will be removed in a future "
            f"release: it is the field {owner}.{name}; pass "
            f"{arg}=optax_bilateral.triangle_mesh.{owner}(..., {name}=...)",
            DeprecationWarning,
            stacklevel=3,
        )
    return keywords


def filter_of(sigma_d: FilterSetting, keywords: dict) -> NormalFilter:
    """The normal filter ``sigma_d`` names, with the deprecated keywords' fields applied."""
    normal_filter = as_filter(sigma_d)
    fields = {k: keywords[k] for k in FILTER_FIELDS if k in keywords}
    return dataclasses.replace(normal_filter, **fields) if fields else normal_filter


def solver_of(solver: SolverSetting, keywords: dict) -> LinearSolver:
    """The solver ``solver`` names, with the deprecated ``tol``, ``maxiter``, ``warm_start``
    applied (checked, and ignored by a direct solve as they were, except ``warm_start``)."""
    solver = as_solver(solver)
    fields = {k: keywords[k] for k in SOLVER_FIELDS if k in keywords}
    if not fields:
        return solver
    cg = dataclasses.replace(solver if isinstance(solver, CG) else CG(), **fields)
    if isinstance(solver, CG):
        return cg
    if cg.warm_start:
        raise ValueError(
            "warm_start starts the CG from the last solution; it does not apply to "
            "solver='cholesky' (a direct solve)"
        )
    return solver
