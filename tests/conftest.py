import os

import hypothesis

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
