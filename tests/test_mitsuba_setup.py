"""Mitsuba set-up that needs no working Mitsuba: import isolation, skip/fail policy, probe.

The tests that drive Mitsuba are in tests/test_mitsuba.py; without a usable Mitsuba that
module is skipped with one line saying why, or fails under CI (tests/mitsuba_env.py).
"""

import subprocess
import sys

import pytest


def test_import_optax_bilateral_imports_no_mitsuba():
    # Runs in a fresh interpreter: this process may have imported Mitsuba already.
    code = (
        "import sys, optax_bilateral, optax_bilateral.mitsuba; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('mitsuba', 'drjit')]; "
        "assert not bad, bad"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr


def test_an_unusable_mitsuba_fails_under_ci_and_skips_otherwise(monkeypatch):
    import mitsuba_env

    monkeypatch.setattr(mitsuba_env, "unavailable", lambda: "libLLVM 15 found, 16 needed")
    monkeypatch.setenv("CI", "true")
    assert mitsuba_env.require_mitsuba() is None
    with pytest.raises(pytest.fail.Exception, match="CI must run the Mitsuba tests: libLLVM 15"):
        mitsuba_env.fail_under_ci(None)
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="libLLVM 15 found"):
        mitsuba_env.require_mitsuba()


def test_probe_reports_a_variant_that_cannot_render():
    from experiments.mitsuba import common as mc

    reason = mc.probe("llvm_ad_no_such_variant")
    assert reason is not None and "cannot render" in reason and "\n" not in reason
