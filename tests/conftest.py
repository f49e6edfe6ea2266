import os

import hypothesis
import jax.numpy as jnp
import numpy as np
import pytest

# The suite compiles hundreds of small programs. LLVM's optimisations, XLA's MLIR fusion
# emitters (against its older elemental ones) and the split of each program for parallel
# codegen are most of their compile time while changing results by float rounding at most:
# without them a bilateral_adam update compiles in half the time (docs/research/compilation.md).
# The tests assert properties and tolerances, and the goldens compile with the same options
# (tests/goldens.py). Set before JAX starts its backend, so pytest's workers and the children
# they start inherit them; a value the caller chose wins.
FAST_COMPILE = {
    "xla_backend_optimization_level": "0",
    "xla_cpu_use_fusion_emitters": "false",
    "xla_cpu_parallel_codegen_split_count": "1",
}
_FLAGS = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join(
    [_FLAGS] + [f"--{k}={v}" for k, v in FAST_COMPILE.items() if k not in _FLAGS]
).strip()

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
