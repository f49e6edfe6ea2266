"""The C++ extension ``optax_bilateral._native`` (sources in ``csrc/``, built by ``setup.py``):
loading it, and how many threads its calls use.

It holds the a-trous filter's XLA FFI handlers (:mod:`optax_bilateral._src.filter.native`) and
the mesh solves' sparse LDL^T sweeps (:mod:`optax_bilateral._src.mesh.laplacian`). Where it is
missing or cannot load (no compiler at install time, another OS), the package still imports
and the pure-JAX / SciPy paths run; each user of the extension says why.
"""

from __future__ import annotations

import functools
import importlib
import os
from types import ModuleType

# The threads one call uses (default: the CPUs this process may run on). Read when a program
# is traced or a solve is called: a compiled program keeps the count it was traced with.
THREADS_ENV = "OPTAX_BILATERAL_THREADS"
# "0": do not load the extension: the pure-JAX kernels and SciPy's solves run, as where it was
# not built.
NATIVE_ENV = "OPTAX_BILATERAL_NATIVE"


def load() -> ModuleType:
    """The extension module; raises ``ImportError`` where it cannot load or is switched off."""
    if os.environ.get(NATIVE_ENV, "") == "0":
        raise ImportError(f"${NATIVE_ENV}=0")
    return importlib.import_module("optax_bilateral._native")


@functools.cache
def loaded() -> tuple[ModuleType | None, str]:
    """``(module, instruction set)`` once per process, or ``(None, why not)``."""
    try:
        module = load()
        return module, module.instruction_set()
    except Exception as e:  # any failure to load leaves the portable paths
        return None, f"{type(e).__name__}: {e}"


@functools.cache
def registered() -> tuple[bool, str]:
    """Loads the extension and registers its XLA FFI targets once per process: ``(True,
    instruction set)``, or ``(False, why not)``."""
    module, reason = loaded()
    if module is None:
        return False, reason
    try:
        import jax

        for name, capsule in module.registrations().items():
            jax.ffi.register_ffi_target(name, capsule, platform="cpu")
        return True, reason
    except Exception as e:  # any failure to register leaves the portable paths
        return False, f"{type(e).__name__}: {e}"


def threads() -> int:
    """The threads a call will use: ``$OPTAX_BILATERAL_THREADS``, else the usable CPUs."""
    env = os.environ.get(THREADS_ENV, "")
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n < 1:
            raise ValueError(f"${THREADS_ENV} must be a positive integer, got {env!r}")
        return n
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
