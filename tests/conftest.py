import os

import hypothesis
import jax.numpy as jnp
import numpy as np
import pytest

# The suite compiles hundreds of small programs, and LLVM's optimisations are most of their
# compile time while changing results by float rounding at most; the tests assert properties
# and tolerances, and the goldens compile with the same option (tests/goldens.py). Set before
# JAX starts its backend, so pytest's workers and the children they start inherit it; a level
# the caller chose wins.
FAST_COMPILE = "--xla_backend_optimization_level=0"
_FLAGS = os.environ.get("XLA_FLAGS", "")
if "xla_backend_optimization_level" not in _FLAGS:
    os.environ["XLA_FLAGS"] = f"{_FLAGS} {FAST_COMPILE}".strip()

# Each new shape or static setting compiles a new XLA program, so the property tests draw
# those from small sets (shared compiled programs) and explore the data freely.
# "default": quick, reproducible local runs. "ci" (make test): explores, >= 100 examples.
hypothesis.settings.register_profile(
    "default",
    max_examples=int(os.environ.get("HYPOTHESIS_EXAMPLES", 15)),
    deadline=None,
    derandomize=True,
    print_blob=True,
)
hypothesis.settings.register_profile(
    "ci",
    max_examples=int(os.environ.get("HYPOTHESIS_EXAMPLES", 100)),
    deadline=None,
    derandomize=False,
    print_blob=True,
    suppress_health_check=[hypothesis.HealthCheck.too_slow, hypothesis.HealthCheck.data_too_large],
)
hypothesis.settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


@pytest.fixture
def iid_and_smooth_targets():
    """Two 32x32x1 targets in (0, 1): i.i.d. uniform texels (the filter's bias persists on
    every texel) and a smooth sinusoid (a filter that follows it has little bias)."""
    rng = np.random.default_rng(1)
    iid = jnp.asarray(rng.uniform(0.2, 0.8, (32, 32, 1)), jnp.float32)
    i, j = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    smooth = jnp.asarray(0.5 + 0.3 * np.sin(i / 5) * np.cos(j / 7), jnp.float32)[..., None]
    return iid, smooth
