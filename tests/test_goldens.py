"""The grid transforms' outputs equal the recorded goldens bit for bit (tests/goldens.py).

A restructuring of the library must not change a single bit of an update or a state.
Under another toolchain than the recorded one (XLA may fuse and round differently) the
comparison is to a tolerance instead, and the message says so.
"""

import os

import numpy as np
import pytest

import goldens

DATA = np.load(goldens.PATH)
SAME_TOOLCHAIN = str(DATA["toolchain"]) == goldens.toolchain()
ALL = os.environ.get("OPTAX_BILATERAL_GOLDENS") == "all"
DIGESTS = dict(line.split(" ") for line in DATA["digests"].tolist())


def test_the_file_holds_every_configuration_and_the_covering_subset():
    assert len(goldens.ALL) == 4 * 2 * 3 * 2 * 3
    assert set(DIGESTS) == {f"{c}/{v}" for c in goldens.ALL for v in goldens.VARIANTS}
    subset = goldens.covering_subset()
    assert {k for k in DATA.files if "/" in k} == {
        f"{c}/{v}" for c in subset for v in goldens.VARIANTS
    }
    # Every pair of factor levels occurs in the subset.
    rows = [goldens.parse_id(c) for c in subset]
    levels = [goldens.KINDS, goldens.SEPARABLE, goldens.GUIDES, goldens.MASKS, goldens.DTYPES]
    for i in range(5):
        for j in range(i + 1, 5):
            assert {(r[i], r[j]) for r in rows} == {(a, b) for a in levels[i] for b in levels[j]}


def _compare(cid, variant, got):
    want = DATA[f"{cid}/{variant}"]
    assert got.shape == want.shape
    np.testing.assert_array_equal(
        np.isnan(got), np.isnan(want), err_msg=f"{cid}/{variant}: NaN places"
    )
    if SAME_TOOLCHAIN:
        same = (got.view(np.uint32) == want.view(np.uint32)) | np.isnan(want)
        assert same.all(), (
            f"{cid}/{variant}: {np.sum(~same)} of {same.size} values differ in their "
            f"bits; largest difference {np.nanmax(np.abs(got - want))}"
        )
    else:
        # Another XLA: same formulas, other fusion. bfloat16 and float16 round to ~1e-3, and a
        # one-ulp change of a moment moves a step by about as much.
        np.testing.assert_allclose(
            got,
            want,
            rtol=2e-2,
            atol=1e-3,
            err_msg=f"{cid}/{variant} (recorded with {DATA['toolchain']}, "
            f"running {goldens.toolchain()}: tolerance, not bits)",
        )


@pytest.mark.parametrize("cid", goldens.ALL if ALL else goldens.covering_subset())
def test_transform_outputs_equal_the_goldens(cid):
    res = goldens.run(cid)
    for variant, got in res.items():
        if f"{cid}/{variant}" in DATA.files:
            _compare(cid, variant, got)
        if SAME_TOOLCHAIN:
            assert goldens.digest(got) == DIGESTS[f"{cid}/{variant}"], f"{cid}/{variant}"


TRAJECTORIES = np.load(goldens.TRAJECTORY_PATH)
SAME_TRAJECTORY_TOOLCHAIN = str(TRAJECTORIES["toolchain"]) == goldens.toolchain()


def _covered(kind, states):
    """What the trajectory exercised: the rule's branches it must keep covering."""
    post = [s[1] if kind == "auto-both" else s for s in states]
    if kind == "sure":
        chosen = {int(s.sigma_state[k].levels) for s in post for k in ("tex", "vol")}
        return {
            "several F chosen": len(chosen) > 1,
            "opened": float(post[-1].sigma_state["tex"].opened) > 0,
        }
    gates = [float(s.sigma_state["tex"].gate) for s in post]
    covered = {"heavier filter": any(float(s.sigma_state["vol"].correlated) > 0 for s in post)}
    if kind == "auto":
        covered["gate opened"] = max(gates) > 0.5
        covered["gate closed again"] = gates[-1] == 0
    return covered


@pytest.mark.parametrize("kind", goldens.TRAJECTORIES)
def test_sigma_rule_trajectories_equal_the_goldens(kind):
    record, states = goldens._trajectory(kind)
    assert all(_covered(kind, states).values()), _covered(kind, states)
    want = {
        k.split("/", 1)[1]: TRAJECTORIES[k] for k in TRAJECTORIES.files if k.startswith(f"{kind}/")
    }
    if SAME_TRAJECTORY_TOOLCHAIN:
        bad = [t + 1 for t, (a, b) in enumerate(zip(record["digests"], want["digests"])) if a != b]
        assert not bad, f"{kind}: the update differs in its bits from step {bad[0]} on"
        assert record["state"] == want["state"], f"{kind}: the final state differs"
    else:
        # Another XLA rounds differently, and 30 steps of a data-driven rule amplify it: the
        # first steps agree to rounding, the run as a whole to a few per cent.
        np.testing.assert_allclose(record["sums"][:3], want["sums"][:3], rtol=1e-3)
        np.testing.assert_allclose(record["sums"].sum(0), want["sums"].sum(0), rtol=5e-2)
