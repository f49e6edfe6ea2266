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
    from experiments.mitsuba import common as mc

    return mc.probe()


def require_mitsuba():
    """Call at module level. With a usable Mitsuba: sets the variant and returns ``mi``.
    Without: skips the calling module (one line saying why), or under CI returns ``None``;
    the module's ``mi`` fixture (:func:`fail_under_ci`) then fails every test in it while
    the other modules still run."""
    reason = unavailable()
    if reason is None:
        from experiments.mitsuba import common as mc

        mi, _ = mc.setup()
        return mi
    if os.environ.get("CI"):
        return None
    pytest.skip(reason, allow_module_level=True)


def fail_under_ci(mi):
    """``mi`` itself, or a test failure saying why Mitsuba is unusable (``mi is None``)."""
    if mi is None:
        pytest.fail(f"CI must run the Mitsuba tests: {unavailable()}", pytrace=False)
    return mi
