"""What the tests need from JAX that moved within the supported versions (pyproject.toml),
so that ``make test-min`` runs the same tests under the oldest JAX as ``make test`` under
the newest."""

import contextlib

import jax


def enable_x64(new_val: bool = True) -> contextlib.AbstractContextManager:
    """``jax.enable_x64(new_val)``: top-level from jax 0.8, ``jax.experimental`` before."""
    if hasattr(jax, "enable_x64"):
        return jax.enable_x64(new_val)
    from jax.experimental import enable_x64 as experimental_enable_x64

    return experimental_enable_x64(new_val)
