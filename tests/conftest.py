import os

import hypothesis

# Each new shape compiles a new XLA program; keep property tests small and deadline-free.
hypothesis.settings.register_profile(
    "default", max_examples=int(os.environ.get("HYPOTHESIS_EXAMPLES", 15)), deadline=None,
    derandomize=True, print_blob=True)
hypothesis.settings.load_profile("default")
