"""optax_bilateral: spatiotemporal bilateral gradient filtering as Optax transforms.

Chang, Yang, Belhe, Ramamoorthi, Li. "Spatiotemporal Bilateral Gradient Filtering
for Inverse Rendering". SIGGRAPH Asia 2024.
"""

from importlib.metadata import PackageNotFoundError, version

from optax_bilateral import triangle_mesh
from optax_bilateral._src.filter.front import atrous_bilateral
from optax_bilateral._src.filter.native import status as native_status
from optax_bilateral._src.optimizer.alias import bilateral_adam, sparse_adam
from optax_bilateral._src.optimizer.coarse import CoarseLevelsState, coarse_levels
from optax_bilateral._src.optimizer.leaf_rule import LeafRuleWarning, default_spatial_axes
from optax_bilateral._src.optimizer.leaves import DEFAULT_LEVELS, filtered_axes
from optax_bilateral._src.optimizer.pyramid import (
    LaplacianPyramidState,
    laplacian_pyramid,
    pyramid_adam,
)
from optax_bilateral._src.optimizer.state_io import load_state, save_state
from optax_bilateral._src.optimizer.transforms import (
    PostfilterState,
    PrefilterState,
    ScaleByAdamState,
    postfilter,
    prefilter,
    scale_by_adam,
)
from optax_bilateral._src.rules.auto import Auto, AutoState
from optax_bilateral._src.rules.fixed import Fixed
from optax_bilateral._src.rules.registry import (
    DEFAULT_SIGMA_D,
    auto_sigma,
    sparse_sigma,
    sure_sigma,
)
from optax_bilateral._src.rules.sigma import SigmaRule
from optax_bilateral._src.rules.sparse import Sparse, SparseState
from optax_bilateral._src.rules.sure import SURE_LEVELS, Sure, SureState

try:
    __version__ = version("optax_bilateral")  # written once, in pyproject.toml
except PackageNotFoundError:  # a source tree that is not installed
    __version__ = "unknown"

__all__ = (
    "DEFAULT_LEVELS",
    "DEFAULT_SIGMA_D",
    "SURE_LEVELS",
    "Auto",
    "AutoState",
    "CoarseLevelsState",
    "Fixed",
    "LaplacianPyramidState",
    "LeafRuleWarning",
    "PostfilterState",
    "PrefilterState",
    "ScaleByAdamState",
    "SigmaRule",
    "Sparse",
    "SparseState",
    "Sure",
    "SureState",
    "atrous_bilateral",
    "auto_sigma",
    "bilateral_adam",
    "coarse_levels",
    "default_spatial_axes",
    "filtered_axes",
    "laplacian_pyramid",
    "load_state",
    "native_status",
    "postfilter",
    "prefilter",
    "pyramid_adam",
    "save_state",
    "scale_by_adam",
    "sparse_adam",
    "sparse_sigma",
    "sure_sigma",
    "triangle_mesh",
)


def __getattr__(name: str):
    # optax_bilateral.mesh, the deprecated former name of triangle_mesh: imported (and
    # warning) only when asked for.
    if name == "mesh":
        import importlib

        return importlib.import_module("optax_bilateral.mesh")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
