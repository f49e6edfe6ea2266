"""Deprecated alias of :mod:`optax_bilateral.triangle_mesh`, the module's former name.

Kept for one release so that code written as ``import optax_bilateral.mesh`` keeps working,
with a ``DeprecationWarning`` at its first import: every name here is the very object of
:mod:`optax_bilateral.triangle_mesh` ("mesh" alone also means a JAX device mesh, hence the
new name).
"""

import warnings as _warnings

from optax_bilateral import triangle_mesh as _triangle_mesh
from optax_bilateral._src.mesh import deprecated as _deprecated
from optax_bilateral.triangle_mesh import *

_warnings.warn(
    "optax_bilateral.mesh is deprecated and will be removed in a future release: import "
    "optax_bilateral.triangle_mesh (the same objects)",
    DeprecationWarning,
    stacklevel=2,
)

__all__: tuple[str, ...] = ()
__all__ += _triangle_mesh.__all__


def __getattr__(name: str):
    """The names deprecated after 0.1.0 (``scale_by_uniform_adam``), with a warning."""
    return _deprecated.lookup(__name__, name)
