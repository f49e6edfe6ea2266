"""Whether the Mitsuba tests can run here, decided once per session.

Outside CI a missing or unusable Mitsuba (not installed, or a libLLVM older than 16)
skips the Mitsuba tests with one line saying why; with the environment variable
``CI`` set it fails them instead, so CI always exercises them.
"""

import functools
import os

import pytest


@functools.lru_cache(maxsize=1)
def unavailable() -> str | None:
    """``None`` when the LLVM variant renders a 16x16 scene here, else the reason (one line)."""
    try:
        import drjit  # noqa: F401
        import mitsuba  # noqa: F401
    except ImportError as e:
        return f"Mitsuba 3 is not installed ({e}); pip install -e '.[mitsuba]'"
    from experiments import mitsuba_common as mc

    return mc.probe()


def require_mitsuba():
    """Skips (fails under CI) unless Mitsuba's LLVM variant works; sets it and returns ``mi``."""
    reason = unavailable()
    if reason is not None:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the Mitsuba tests: {reason}", pytrace=False)
        pytest.skip(reason)
    from experiments import mitsuba_common as mc

    mi, _ = mc.setup()
    return mi
