"""Triangle meshes: Large Steps (Nicolet et al. 2021) and its bilateral variant.

The vertex positions of a mesh are not a grid, so the a-trous filter does not apply;
these transforms filter Adam's moments with the mesh's Laplacian instead (see
docs/triangle_mesh.md for the method and the measured results)::

    import optax_bilateral.triangle_mesh as obm
    opt = obm.bilateral_large_steps(1e-2, faces, lambda_=19.0, sigma_d=0.5)
    opt = obm.bilateral_large_steps(
        1e-2, faces, 19.0, obm.NormalFilter(sigma_d=0.5, sigma_phi=0.4, directions=32),
        solver=obm.CG(tol=1e-4),
    )
"""

from optax_bilateral._src.mesh import deprecated as _deprecated
from optax_bilateral._src.mesh.alias import bilateral_large_steps, large_steps
from optax_bilateral._src.mesh.config import (
    CG,
    DEFAULT_DIRECTIONS,
    DEFAULT_KERNEL_TOL,
    DEFAULT_LAMBDA,
    DEFAULT_MAXITER,
    DEFAULT_NORMAL_SIGMA_D,
    DEFAULT_SIGMA_PHI,
    DEFAULT_TOL,
    NORMALS,
    POSTFILTERS_V,
    PREFILTERS,
    SOLVERS,
    Cholesky,
    DensityWidth,
    NormalFilter,
)
from optax_bilateral._src.mesh.laplacian import MeshLaplacian, mesh_laplacian, smoothing_solve
from optax_bilateral._src.mesh.normals import (
    bilateral_normal_filter,
    kernel_bases,
    sphere_directions,
    vertex_normals,
)
from optax_bilateral._src.mesh.transforms import (
    MeshPostfilterState,
    SmoothingState,
    bilateral_smoothing,
    laplacian_smoothing,
    mesh_postfilter,
    weld_gradients,
)

__all__ = (
    "CG",
    "DEFAULT_DIRECTIONS",
    "DEFAULT_KERNEL_TOL",
    "DEFAULT_LAMBDA",
    "DEFAULT_MAXITER",
    "DEFAULT_NORMAL_SIGMA_D",
    "DEFAULT_SIGMA_PHI",
    "DEFAULT_TOL",
    "NORMALS",
    "POSTFILTERS_V",
    "PREFILTERS",
    "SOLVERS",
    "Cholesky",
    "DensityWidth",
    "MeshLaplacian",
    "MeshPostfilterState",
    "NormalFilter",
    "SmoothingState",
    "bilateral_large_steps",
    "bilateral_normal_filter",
    "bilateral_smoothing",
    "kernel_bases",
    "laplacian_smoothing",
    "large_steps",
    "mesh_laplacian",
    "mesh_postfilter",
    "smoothing_solve",
    "sphere_directions",
    "vertex_normals",
    "weld_gradients",
)


def __getattr__(name: str):
    """The names deprecated after 0.1.0 (``scale_by_uniform_adam``), with a warning."""
    return _deprecated.lookup(__name__, name)
