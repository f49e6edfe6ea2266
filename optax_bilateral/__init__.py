"""optax_bilateral: spatiotemporal bilateral gradient filtering as Optax transforms.

Chang, Yang, Belhe, Ramamoorthi, Li. "Spatiotemporal Bilateral Gradient Filtering
for Inverse Rendering". SIGGRAPH Asia 2024.
"""

from optax_bilateral._src.alias import bilateral_adam
from optax_bilateral._src.sharded import atrous_bilateral
from optax_bilateral._src.leaves import default_spatial_axes
from optax_bilateral._src.pyramid import LaplacianPyramidState, laplacian_pyramid, pyramid_adam
from optax_bilateral._src.state_io import load_state, save_state
from optax_bilateral._src.transforms import (
    DEFAULT_SIGMA_D,
    PostfilterState,
    PrefilterState,
    ScaleByAdamState,
    postfilter,
    prefilter,
    scale_by_adam,
)

from optax_bilateral import mesh  # noqa: E402  (triangle meshes: optax_bilateral.mesh)

__version__ = "0.1.0"

__all__ = (
    "DEFAULT_SIGMA_D",
    "LaplacianPyramidState",
    "PostfilterState",
    "PrefilterState",
    "ScaleByAdamState",
    "atrous_bilateral",
    "bilateral_adam",
    "default_spatial_axes",
    "laplacian_pyramid",
    "load_state",
    "mesh",
    "postfilter",
    "prefilter",
    "pyramid_adam",
    "save_state",
    "scale_by_adam",
)
