"""The mesh optimizers: ``large_steps`` and the paper's ``bilateral_large_steps``, each a short
``optax.chain`` of the mesh transforms, the shared uniform Adam and the learning rate."""

from __future__ import annotations

from typing import Any

import jax
import optax

from optax_bilateral._src.mesh.config import (
    DEFAULT_LAMBDA,
    DEFAULT_WIDTH,
    FILTER_FIELDS,
    PREFILTERS,
    SOLVER_FIELDS,
    FilterSetting,
    PostfilterV,
    Prefilter,
    SolverSetting,
    deprecated_keywords,
    filter_of,
    solver_of,
)
from optax_bilateral._src.mesh.laplacian import Faces, mesh_laplacian
from optax_bilateral._src.mesh.transforms import (
    bilateral_smoothing,
    laplacian_smoothing,
    mesh_postfilter,
    weld_gradients,
)
from optax_bilateral._src.optimizer.transforms import postfilter
from optax_bilateral._src.validation import check_choice


def uniform_adam(b1, b2, eps) -> optax.GradientTransformationExtraArgs:
    """Large Steps' ``AdamUniform`` (one second moment per leaf, the max over it): the shared
    :func:`~optax_bilateral.postfilter` with ``levels=0, second_moment="uniform"``."""
    return postfilter(b1, b2, eps, levels=0, second_moment="uniform")


def large_steps(
    learning_rate: optax.ScalarOrSchedule,
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    solver: SolverSetting = "cg",
    **deprecated: Any,
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
      solver: ``"cg"`` or a :class:`CG` (its ``tol``, ``maxiter``, ``warm_start``), or
        ``"cholesky"`` / :class:`Cholesky` (needs ``pymetis`` and SciPy); see
        :func:`smoothing_solve`.
      **deprecated: ``tol``, ``maxiter``, ``warm_start``, the fields of :class:`CG` now:
        still applied for one release, with a ``DeprecationWarning``.

    Returns:
      An ``optax.GradientTransformationExtraArgs``: ``weld_gradients``,
      ``laplacian_smoothing``, the uniform Adam
      (``optax_bilateral.postfilter(b1, b2, eps, levels=0, second_moment="uniform")``),
      ``laplacian_smoothing`` and ``optax.scale_by_learning_rate`` chained; ``update`` needs
      no ``params``.

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
    linear = solver_of(solver, deprecated_keywords("large_steps", deprecated, SOLVER_FIELDS))
    return optax.chain(
        weld_gradients(mesh),
        laplacian_smoothing(mesh, lambda_, solver=linear),
        uniform_adam(b1, b2, eps),
        laplacian_smoothing(mesh, lambda_, solver=linear),
        optax.scale_by_learning_rate(learning_rate),
    )


def bilateral_large_steps(
    learning_rate: optax.ScalarOrSchedule,
    faces: Faces,
    lambda_: jax.typing.ArrayLike = DEFAULT_LAMBDA,
    sigma_d: FilterSetting = DEFAULT_WIDTH,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    prefilter: Prefilter = "smooth",
    postfilter_v: PostfilterV = "uniform",
    solver: SolverSetting = "cg",
    **deprecated: Any,
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

    With ``optax.inject_hyperparams`` (to schedule ``lambda_``, ``sigma_d`` or the learning
    rate) pass a :class:`MeshLaplacian` as ``faces``, or list ``"faces"`` in
    ``static_args``; to schedule ``sigma_phi`` as well, inject a factory that builds the
    :class:`NormalFilter` from its arguments. docs/triangle_mesh.md has the method, the
    authors' parameterisation and measured results.

    Args:
      learning_rate: a number or an optax schedule.
      faces: ``(F, 3)`` int triangles or a :class:`MeshLaplacian` (welded seams: see
        :func:`mesh_laplacian`).
      lambda_: smoothing weight ``>= 0`` of ``M = I + lambda L`` (default 19, the
        authors'; may be traced).
      sigma_d: splat width on normals (``> 0``; ``inf`` gives :func:`large_steps`; may be
        traced), a :class:`DensityWidth` that picks it from the mesh's vertex count (the
        default: the paper's 0.5 up to 2562 vertices, ``0.5 sqrt(U / 2562)`` above for ``U``
        distinct vertices, at most 2), or a :class:`NormalFilter` that also sets the
        slice width ``sigma_phi`` (0.4, the authors'), the ``directions`` (32 Lloyd-relaxed
        Sobol directions; needs SciPy) and the ``normals`` (``"area"``; ``"uniform"`` is
        the authors').
      b1: first-moment decay rate (default 0.9, Large Steps').
      b2: second-moment decay rate (default 0.999).
      eps: added to the denominator (default 1e-8).
      prefilter: ``"smooth"`` (``A = M^-1``, default), ``"bilateral"`` (``A = B``) or
        ``"off"``.
      postfilter_v: ``"uniform"`` (default), ``"bilateral"`` or ``"smooth"``, as above
        (see :func:`mesh_postfilter`).
      solver: ``"cg"`` or a :class:`CG` (its ``tol``, ``maxiter``, ``warm_start``), or
        ``"cholesky"`` / :class:`Cholesky` (needs ``pymetis`` and SciPy); see
        :func:`smoothing_solve`.
      **deprecated: ``sigma_phi``, ``directions``, ``normals`` (fields of
        :class:`NormalFilter`), ``tol``, ``maxiter``, ``warm_start`` (of :class:`CG`):
        still applied for one release, with a ``DeprecationWarning`` that names the field.

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
        >>> opt = obm.bilateral_large_steps(0.1, faces, 1.0, obm.NormalFilter(directions=8))
        >>> updates, state = opt.update(grads, opt.init(verts), verts)
        >>> print(np.round(np.asarray(updates[:, 2], float), 3))
        [-0.047 -0.047 -0.047 -0.046 -0.051 -0.044]
    """
    mesh = mesh_laplacian(faces)
    check_choice(prefilter, "prefilter", PREFILTERS)
    old = deprecated_keywords("bilateral_large_steps", deprecated, FILTER_FIELDS + SOLVER_FIELDS)
    normal_filter, linear = filter_of(sigma_d, old), solver_of(solver, old)
    parts = [weld_gradients(mesh)]
    if prefilter == "smooth":
        parts.append(laplacian_smoothing(mesh, lambda_, solver=linear))
    elif prefilter == "bilateral":
        parts.append(bilateral_smoothing(mesh, lambda_, normal_filter, solver=linear))
    post = mesh_postfilter(
        mesh, lambda_, normal_filter, b1, b2, eps, postfilter_v=postfilter_v, solver=linear
    )
    return optax.chain(*parts, post, optax.scale_by_learning_rate(learning_rate))
