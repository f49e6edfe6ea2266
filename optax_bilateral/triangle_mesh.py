"""Triangle meshes: Large Steps (Nicolet et al. 2021) and its bilateral variant.

The vertex positions of a mesh are not a grid, so the a-trous filter does not apply;
these transforms filter Adam's moments with the mesh's Laplacian instead (see
docs/triangle_mesh.md for the method and the measured results)::

    import optax_bilateral.triangle_mesh as obm
    opt = obm.bilateral_large_steps(1e-2, faces, lambda_=19.0, sigma_d=0.5, sigma_phi=0.4)
"""

from optax_bilateral._src.mesh.triangle_mesh import (
    DEFAULT_DIRECTIONS,
    DEFAULT_LAMBDA,
    DEFAULT_MAXITER,
    DEFAULT_SIGMA_D,
    DEFAULT_SIGMA_PHI,
    DEFAULT_TOL,
    NORMALS,
    POSTFILTERS_V,
    PREFILTERS,
    SOLVERS,
    MeshLaplacian,
    MeshPostfilterState,
    ScaleByUniformAdamState,
    SmoothingState,
    bilateral_large_steps,
    bilateral_normal_filter,
    bilateral_smoothing,
    laplacian_smoothing,
    large_steps,
    mesh_laplacian,
    mesh_postfilter,
    scale_by_uniform_adam,
    smoothing_solve,
    sphere_directions,
    vertex_normals,
    weld_gradients,
)

__all__ = (
    "DEFAULT_DIRECTIONS",
    "DEFAULT_LAMBDA",
    "DEFAULT_MAXITER",
    "DEFAULT_SIGMA_D",
    "DEFAULT_SIGMA_PHI",
    "DEFAULT_TOL",
    "NORMALS",
    "POSTFILTERS_V",
    "PREFILTERS",
    "SOLVERS",
    "MeshLaplacian",
    "MeshPostfilterState",
    "ScaleByUniformAdamState",
    "SmoothingState",
    "bilateral_large_steps",
    "bilateral_normal_filter",
    "bilateral_smoothing",
    "laplacian_smoothing",
    "large_steps",
    "mesh_laplacian",
    "mesh_postfilter",
    "scale_by_uniform_adam",
    "smoothing_solve",
    "sphere_directions",
    "vertex_normals",
    "weld_gradients",
)
