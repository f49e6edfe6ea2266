"""The mesh's optax transforms: welding, the smoothings ``M^-1`` and ``B``, the postfilter.

Large Steps optimises ``u = M x`` with "uniform" Adam. Since ``M`` is symmetric,
``df/du = M^-1 df/dx``, and ``x = M^-1 u``; written on ``x`` the step is

    g~_t = M^-1 g_t                                   (prefilter, A = M^-1; eq. 1)
    m_t, v_t = EMAs of g~_t, g~_t^2                   (eqs. 2, 4)
    Delta_t = M^-1 m^_t / (sqrt(max_k v^_t,k) + eps)   (postfilter, B = M^-1; eqs. 6, 10)

with ``m^, v^`` bias-corrected and the max over every vertex and coordinate
(Large Steps' ``AdamUniform``). The paper keeps ``A = M^-1`` and replaces ``B`` by the
cross-bilateral filter on normals (:mod:`.normals`). :func:`mesh_postfilter` keeps the
moments with the shared Adam step (``step.adam_moments``) and divides with the shared
policy (``numerics.safe_step``); :func:`laplacian_smoothing` and :func:`bilateral_smoothing`
are ``A`` (and Large Steps' ``M^-1`` after the uniform Adam). ``CG(warm_start=True)`` keeps
each solution in the transform's state and starts the next step's CG there.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from optax_bilateral._src import numerics
from optax_bilateral._src.mesh.config import (
    CG,
    DEFAULT_LAMBDA,
    DEFAULT_WIDTH,
    FILTER_FIELDS,
    POSTFILTERS_V,
    SOLVER_FIELDS,
    FilterSetting,
    LinearSolver,
    PostfilterV,
    SolverSetting,
    deprecated_keywords,
    filter_of,
    solver_of,
)
from optax_bilateral._src.mesh.laplacian import (
    Faces,
    MeshLaplacian,
    System,
    check_field,
    merge,
    mesh_laplacian,
    spread,
)
from optax_bilateral._src.mesh.normals import Operator, bilateral_fields, normals_of
from optax_bilateral._src.optimizer.step import AdamHyper, Observed, adam_moments
from optax_bilateral._src.validation import check_choice, check_decay, check_nonnegative


def check_lambda(lambda_) -> None:
    check_nonnegative(lambda_, "lambda_ (Laplacian smoothing weight)", finite=True)


def warm(solver: LinearSolver) -> bool:
    """Whether the transform keeps its solutions to start the next CG there."""
    return isinstance(solver, CG) and solver.warm_start


class SmoothingState(NamedTuple):
    """State of :func:`laplacian_smoothing` and :func:`bilateral_smoothing`.

    Attributes:
      count: the number of updates so far, an int32 scalar.
      x0: with ``solver=CG(warm_start=True)``, the last solutions (the CG's next starting
        point, ``(U, C)`` per leaf); else None.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> smooth = obm.laplacian_smoothing(faces, solver=obm.CG(warm_start=True))
        >>> state = smooth.init(verts)
        >>> type(state).__name__, int(state.count), state.x0.shape
        ('SmoothingState', 0, (6, 3))
    """

    count: jax.Array
    x0: Any


def _smoothing_init(warm_start: bool, shape: Callable[[Any], tuple[int, int]]):
    """``init`` of a smoothing: the count, and zeros of ``shape(leaf)`` per leaf if warm."""

    def init_fn(params):
        if not warm_start:
            return SmoothingState(jnp.zeros([], jnp.int32), None)
        return SmoothingState(
            jnp.zeros([], jnp.int32),
            jax.tree.map(lambda p: jnp.zeros(shape(p), p.dtype), params),
        )

    return init_fn


def _starts(state, treedef, warm_start: bool, count: int) -> list:
    """The stored solutions per leaf, or None per leaf."""
    return treedef.flatten_up_to(state.x0) if warm_start else [None] * count


def _weld(mesh: MeshLaplacian, index: jax.Array, g):
    """The copies' gradients summed on their merged vertex, and the sum given to every copy."""
    check_field(g, mesh, "weld_gradients")
    return spread(mesh, jax.ops.segment_sum(g, index, num_segments=mesh.num_merged))


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
    solver: SolverSetting = "cg",
    **deprecated: Any,
) -> optax.GradientTransformationExtraArgs:
    """Large Steps' smoothing ``g -> (I + lambda L)^-1 g`` on every ``(V, C)`` leaf.

    Used before the moments it is the prefilter ``A`` (eq. 1), the gradient of the
    reparameterisation ``u = (I + lambda L) x``; used after the uniform Adam
    (``optax_bilateral.postfilter(..., levels=0, second_moment="uniform")``) it maps the step
    on ``u`` back to ``x``.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian` (built once).
      lambda_: smoothing weight ``>= 0``; may be traced / injected.
      solver: ``"cg"`` or a :class:`CG` (``CG(tol=1e-4, maxiter=2000, warm_start=False)``
        by default), or ``"cholesky"`` / :class:`Cholesky` (needs ``pymetis`` and SciPy); see
        :func:`smoothing_solve`.
      **deprecated: ``tol``, ``maxiter``, ``warm_start``, the fields of :class:`CG` now:
        still applied for one release, with a ``DeprecationWarning``.

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
    check_lambda(lambda_)
    old = deprecated_keywords("laplacian_smoothing", deprecated, SOLVER_FIELDS)
    linear = solver_of(solver, old)
    system = System.of(mesh, linear, lambda_)
    warm_start = warm(linear)

    def update_fn(updates, state, params=None, **extra_args):
        del params, extra_args
        leaves, treedef = jax.tree.flatten(updates)
        out, sols = [], []
        for x, x0 in zip(leaves, _starts(state, treedef, warm_start, len(leaves))):
            check_field(x, mesh, "laplacian_smoothing")
            sol = system.solve(merge(mesh, x), None if x0 is None else merge(mesh, x0))
            sols.append(spread(mesh, sol))
            out.append(sols[-1].astype(x.dtype))
        new = SmoothingState(
            jnp.asarray(optax.safe_increment(state.count)),
            jax.tree.unflatten(treedef, sols) if warm_start else None,
        )
        return jax.tree.unflatten(treedef, out), new

    return optax.GradientTransformationExtraArgs(
        _smoothing_init(warm_start, lambda p: p.shape), update_fn
    )


def _needs_params(name: str) -> ValueError:
    return ValueError(
        f"{name} needs params (the vertex positions) to compute the normals that guide the "
        "filter: call update(updates, state, params)"
    )


def bilateral_smoothing(
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: FilterSetting = DEFAULT_WIDTH,
    *,
    solver: SolverSetting = "cg",
    **deprecated: Any,
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
      sigma_d: splat width on normals (``> 0``; ``inf`` = no data term; may be traced), a
        :class:`DensityWidth` that picks it from the mesh (the default: 0.5 up to 2562
        vertices, wider on finer meshes), or a :class:`NormalFilter` (with ``sigma_phi``,
        ``directions`` and ``normals``; by default 0.4, 32 Sobol directions, area-weighted
        normals).
      solver: ``"cg"``, ``"cholesky"``, a :class:`CG` or a :class:`Cholesky`; see
        :func:`smoothing_solve`.
      **deprecated: ``sigma_phi``, ``directions``, ``normals`` (fields of
        :class:`NormalFilter`), ``tol``, ``maxiter``, ``warm_start`` (of :class:`CG`):
        still applied for one release, with a ``DeprecationWarning``.

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
        >>> smooth = obm.bilateral_smoothing(faces, 1.0, obm.NormalFilter(directions=8))
        >>> updates, _ = smooth.update(grads, smooth.init(verts), verts)
        >>> print(np.round(np.asarray(updates[:, 2], float), 3))  # spreads less than M^-1 g
        [0.051 0.037 0.044 0.032 0.126 0.034]
    """
    mesh = mesh_laplacian(faces)
    check_lambda(lambda_)
    old = deprecated_keywords("bilateral_smoothing", deprecated, FILTER_FIELDS + SOLVER_FIELDS)
    normal_filter, linear = filter_of(sigma_d, old), solver_of(solver, old)
    op = Operator.of(System.of(mesh, linear, lambda_), normal_filter)
    normals = normals_of(normal_filter, mesh)
    warm_start = warm(linear)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        if params is None:
            raise _needs_params("bilateral_smoothing")
        leaves, treedef = jax.tree.flatten(updates)
        xs = treedef.flatten_up_to(params)
        out, sols = [], []
        for g, x, x0 in zip(leaves, xs, _starts(state, treedef, warm_start, len(leaves))):
            check_field(x, mesh, "bilateral_smoothing params", channels=3)
            check_field(g, mesh, "bilateral_smoothing updates")
            (gf,), flat = bilateral_fields([g], normals(x), op, x0)
            sols.append(flat)
            out.append(gf.astype(g.dtype))
        new = SmoothingState(
            jnp.asarray(optax.safe_increment(state.count)),
            jax.tree.unflatten(treedef, sols) if warm_start else None,
        )
        return jax.tree.unflatten(treedef, out), new

    # The diffused columns live on the merged vertices.
    shape = lambda p: (mesh.num_merged, op.columns(p.shape[1]))
    return optax.GradientTransformationExtraArgs(_smoothing_init(warm_start, shape), update_fn)


class MeshPostfilterState(NamedTuple):
    """State of :func:`mesh_postfilter`: the *unfiltered* moments (eqs. 2, 4).

    Attributes:
      count: the number of updates so far, an int32 scalar.
      mu: the first moment ``m_t``, like the parameters.
      nu: the second moment ``v_t``, like the parameters.
      x0: with ``solver=CG(warm_start=True)``, the last solutions of the filter's solves;
        else None.

    Example::

        >>> import numpy as np, jax.numpy as jnp
        >>> from optax_bilateral import triangle_mesh as obm
        >>> verts = jnp.array([[1., 0, 0], [-1, 0, 0], [0, 1, 0],
        ...                    [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        >>> faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
        ...                   [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])   # an octahedron
        >>> state = obm.mesh_postfilter(faces, sigma_d=obm.NormalFilter(directions=8)).init(verts)
        >>> type(state).__name__, state.mu.shape, state.x0
        ('MeshPostfilterState', (6, 3), None)
    """

    count: jax.Array
    mu: Any
    nu: Any
    x0: Any = None


def mesh_postfilter(
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: FilterSetting = DEFAULT_WIDTH,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    postfilter_v: PostfilterV = "uniform",
    solver: SolverSetting = "cg",
    **deprecated: Any,
) -> optax.GradientTransformationExtraArgs:
    """Adam moments with the bilateral normal postfilter ``B`` (supplement eqs. 6-10).

        m_t, v_t = EMAs of the incoming (prefiltered) gradient  (eqs. 2, 4; kept unfiltered)
        "uniform":   Delta_t = B m^_t / (sqrt(max_k v^_t,k) + eps)
        "bilateral": Delta_t = B m^_t / (sqrt(B v^_t) + eps)       (same B for m and v, §1.3)
        "smooth":    Delta_t = B m^_t / (sqrt(M^-1 v^_t) + eps)    (the authors'; not bounded)

    ``B`` is :func:`bilateral_normal_filter` with the guide ``n`` = the vertex
    normals of ``params`` (the current positions; "cross-bilateral"). With
    ``sigma_d = inf`` and "uniform" this is Large Steps' postfilter ``M^-1``. The moments are
    the shared Adam step's (``optax_bilateral.postfilter``'s); a zero denominator gives a
    zero step.

    Args:
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian`.
      lambda_: smoothing weight of ``M = I + lambda L`` (may be traced). The authors'
        ``compute_matrix(alpha=lambda/(1+lambda))`` is ``M / (1 + lambda)``
        (docs/triangle_mesh.md maps the two).
      sigma_d: splat width on normals (``> 0``, ``inf`` = Large Steps; may be traced), a
        :class:`DensityWidth` (the default: from the mesh's vertex count), or a
        :class:`NormalFilter` (with ``sigma_phi``, the authors' 0.4 by default,
        ``directions`` and ``normals``).
      b1: Adam's first-moment decay rate (Large Steps uses 0.9).
      b2: Adam's second-moment decay rate (Large Steps uses 0.999).
      eps: Adam's epsilon.
      postfilter_v: ``"uniform"`` (max over the leaf, as Large Steps), ``"bilateral"``
        (``B v``) or ``"smooth"`` (``M^-1 v``).
      solver: ``"cg"``, ``"cholesky"``, a :class:`CG` or a :class:`Cholesky`; see
        :func:`smoothing_solve`.
      **deprecated: ``sigma_phi``, ``directions``, ``normals`` (fields of
        :class:`NormalFilter`), ``tol``, ``maxiter``, ``warm_start`` (of :class:`CG`):
        still applied for one release, with a ``DeprecationWarning``.

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
        >>> post = obm.mesh_postfilter(faces, lambda_=1.0, sigma_d=obm.NormalFilter(directions=8))
        >>> step, state = post.update(grads, post.init(verts), verts)
        >>> # B m^ / sqrt(max v^), m^ = g at t = 1
        >>> print(np.round(np.asarray(step[:, 2], float), 3))
        [0.051 0.037 0.044 0.032 0.126 0.034]
    """
    mesh = mesh_laplacian(faces)
    check_lambda(lambda_)
    check_decay(b1, "b1")
    check_decay(b2, "b2")
    check_nonnegative(eps, "eps")
    check_choice(postfilter_v, "postfilter_v", POSTFILTERS_V)
    old = deprecated_keywords("mesh_postfilter", deprecated, FILTER_FIELDS + SOLVER_FIELDS)
    normal_filter, linear = filter_of(sigma_d, old), solver_of(solver, old)
    post = _Post(
        Operator.of(System.of(mesh, linear, lambda_), normal_filter),
        normals_of(normal_filter, mesh),
        postfilter_v,
        AdamHyper.of(b1, b2, eps, 0.0),
    )
    warm_start = warm(linear)

    def init_fn(params):
        x0 = None
        if warm_start:
            x0 = jax.tree.map(post.zero_solutions, params)
        zeros = lambda: jax.tree.map(jnp.zeros_like, params)
        return MeshPostfilterState(jnp.zeros([], jnp.int32), zeros(), zeros(), x0)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        if params is None:
            raise _needs_params("mesh_postfilter")
        count = jnp.asarray(optax.safe_increment(state.count))
        flat, treedef = jax.tree.flatten(updates)
        mus, nus, xs = (treedef.flatten_up_to(tree) for tree in (state.mu, state.nu, params))
        starts = _starts(state, treedef, warm_start, len(flat))
        outs = [
            post.leaf(g, m, v, x, x0, count) for g, m, v, x, x0 in zip(flat, mus, nus, xs, starts)
        ]
        d, mu, nu, sols = ([o[i] for o in outs] for i in range(4))
        unflatten = functools.partial(jax.tree.unflatten, treedef)
        x0 = unflatten(sols) if warm_start else None
        return unflatten(d), MeshPostfilterState(count, unflatten(mu), unflatten(nu), x0)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


class _Post(NamedTuple):
    """What :func:`mesh_postfilter` does for one leaf, once its settings are resolved."""

    op: Operator
    normals: Callable  # positions -> unit normals (the guide)
    postfilter_v: str
    adam: AdamHyper

    def zero_solutions(self, p):
        """The warm start's zeros: the columns of the solves, on the merged vertices."""
        rows = self.op.system.mesh.num_merged
        return tuple(jnp.zeros((rows, w), p.dtype) for w in self.widths(p))

    def widths(self, p) -> tuple[int, ...]:
        """Columns of the solves that a leaf needs: B on m (and v), then M^-1 v."""
        c = p.shape[1]
        if self.postfilter_v == "bilateral":
            return (self.op.columns(2 * c),)
        return (self.op.columns(c),) + ((c,) if self.postfilter_v == "smooth" else ())

    def leaf(self, g, m_old, v_old, x, x0, count):
        """``(Delta_t, m_t, v_t, solutions)`` for one leaf (eqs. 2, 4, 6-10)."""
        mesh = self.op.system.mesh
        check_field(x, mesh, "mesh_postfilter params", channels=3)
        check_field(g, mesh, "mesh_postfilter updates")
        every = Observed(None, jnp.asarray(True))
        m, v = adam_moments(g, (m_old, v_old), every, self.adam, jnp.result_type(g, m_old))
        c1 = numerics.bias_correction(self.adam.b1, count).astype(m.dtype)
        c2 = numerics.bias_correction(self.adam.b2, count).astype(v.dtype)
        out, sols = self.step(m / c1, v / c2, self.normals(x), x0)
        return out.astype(m.dtype), m, v, sols

    def step(self, m_hat, v_hat, normals, x0):
        """``B m^ / (sqrt(v~) + eps)``, ``v~`` as ``postfilter_v`` says, and the solutions (the
        next warm start): ``B`` on both moments, their max, or ``M^-1 v^``."""
        first = None if x0 is None else x0[0]
        if self.postfilter_v == "bilateral":
            (m_f, v_f), flat = bilateral_fields([m_hat, v_hat], normals, self.op, first)
            sols = (flat,)
        else:
            (m_f,), flat = bilateral_fields([m_hat], normals, self.op, first)
            sols = (flat,)
            if self.postfilter_v == "uniform":
                v_f = jnp.max(v_hat)
            else:
                system = self.op.system
                v_s = system.solve(merge(system.mesh, v_hat), None if x0 is None else x0[1])
                sols += (v_s,)
                v_f = spread(system.mesh, v_s)
        # m^ and v^ are bias-corrected already; B and M^-1 are non-negative, so v_f >= 0 up
        # to the solver, and its round-off counts as 0.
        one = jnp.ones((), m_hat.dtype)
        return numerics.safe_step(m_f, v_f, one, one, self.adam.eps, 0.0), sols
