"""The a-trous cross-bilateral filter against docs/method.md's definition and its properties."""

import functools
import math

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jax_compat
import optax_bilateral as ob
from optax_bilateral import atrous_bilateral
from optax_bilateral._src.filter import atrous
from reference import atrous_reference

RTOL = 1e-5  # float32 accumulation of <= 125-tap sums over a few levels: ~1e-7 per op


def _quantised_guide(rng, shape, channels):
    # Guides with repeated values exercise the "equal guides weigh 1" rule (and sigma_d=0).
    return rng.integers(0, 3, size=shape + (channels,)).astype(np.float32) * 0.4


CASES = [
    # shape, channels, guide channels, levels
    ((9,), 2, 1, 3),
    ((7, 6), 3, 3, 2),
    ((5, 9), 1, 2, 3),
    ((4, 3, 5), 2, 1, 2),
]


@functools.cache
def _reference_case(shape, channels, gch, levels, sigma_d, separable):
    """(x, guide, float64 reference output), computed once for both kernels."""
    rng = np.random.default_rng(abs(hash((shape, sigma_d, separable))) % 2**32)
    x = rng.normal(size=shape + (channels,)).astype(np.float32)
    g = _quantised_guide(rng, shape, gch) + rng.normal(size=shape + (gch,)).astype(np.float32) * 0.1
    return x, g, atrous_reference(x, g, sigma_d, levels, separable)


@pytest.mark.parametrize("kernel", ["native", "xla_cpu", "plain"])
@pytest.mark.parametrize("separable", [True, False])
@pytest.mark.parametrize("sigma_d", [0.0, 0.35, 2.0, np.inf])
@pytest.mark.parametrize("shape,channels,gch,levels", CASES)
def test_matches_float64_reference(shape, channels, gch, levels, sigma_d, separable, kernel):
    x, g, ref = _reference_case(shape, channels, gch, levels, sigma_d, separable)
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(g),
        sigma_d=sigma_d,
        levels=levels,
        spatial_axes=tuple(range(len(shape))),
        separable=separable,
        kernel=kernel,
    )
    np.testing.assert_allclose(np.asarray(out), ref, rtol=RTOL, atol=RTOL * np.abs(ref).max())


@pytest.mark.parametrize("kernel", ["native", "xla_cpu", "plain"])
@pytest.mark.parametrize("separable", [True, False])
def test_mask_matches_reference(separable, kernel):
    rng = np.random.default_rng(1)
    shape = (6, 7)
    x = rng.normal(size=shape + (2,)).astype(np.float32)
    g = rng.normal(size=shape + (1,)).astype(np.float32)
    mask = rng.random(shape) > 0.3
    x[~mask] = np.nan  # masked entries must not be read at all
    ref = atrous_reference(np.where(mask[..., None], x, 0), g, 0.5, 3, separable, mask)
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(g),
        sigma_d=0.5,
        levels=3,
        spatial_axes=(0, 1),
        separable=separable,
        mask=jnp.asarray(mask),
        kernel=kernel,
    )
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(np.asarray(out), ref, rtol=RTOL, atol=1e-6)


def test_channels_first_and_axis_order():
    """Spatial axes anywhere, in any order: same as the channels-last layout (the order of the
    separable passes follows ``spatial_axes``)."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(6, 5, 3)).astype(np.float32)
    g = rng.normal(size=(6, 5)).astype(np.float32)
    ref = atrous_reference(x, g[..., None], 0.7, 2, True)
    chw = atrous_bilateral(jnp.moveaxis(x, -1, 0), g, sigma_d=0.7, levels=2, spatial_axes=(1, 2))
    np.testing.assert_allclose(np.moveaxis(np.asarray(chw), 0, -1), ref, rtol=RTOL, atol=1e-6)
    # Passing the axes as (1, 0) runs the W pass first; the reference on the transposed grid.
    ref_t = atrous_reference(np.swapaxes(x, 0, 1), np.swapaxes(g, 0, 1)[..., None], 0.7, 2, True)
    out_t = atrous_bilateral(x, g.T, sigma_d=0.7, levels=2, spatial_axes=(1, 0))
    np.testing.assert_allclose(np.swapaxes(np.asarray(out_t), 0, 1), ref_t, rtol=RTOL, atol=1e-6)


def test_tuple_of_fields_share_weights_and_keep_dtypes():
    rng = np.random.default_rng(3)
    m = rng.normal(size=(8, 8, 2)).astype(np.float32)
    v = (rng.normal(size=(8, 8, 2)) ** 2).astype(np.float64)
    g = rng.normal(size=(8, 8, 2)).astype(np.float32)
    fm, fv = atrous_bilateral(
        (jnp.asarray(m), jnp.asarray(v, jnp.float32).astype(jnp.bfloat16)),
        g,
        sigma_d=0.3,
        levels=2,
        spatial_axes=(0, 1),
    )
    assert fm.dtype == jnp.float32 and fv.dtype == jnp.bfloat16
    alone = atrous_bilateral(jnp.asarray(m), g, sigma_d=0.3, levels=2, spatial_axes=(0, 1))
    # Same weights; only the fused program differs, so agreement is to float32 rounding.
    np.testing.assert_allclose(np.asarray(fm), np.asarray(alone), rtol=1e-6, atol=1e-6)


def test_levels_zero_is_identity_and_sigma_inf_is_lowpass():
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.normal(size=(10, 3)), jnp.float32)
    g = jnp.asarray(rng.normal(size=(10, 1)), jnp.float32)
    assert atrous_bilateral(x, g, sigma_d=0.1, levels=0, spatial_axes=(0,)) is x
    # sigma_d = inf ignores the guide entirely.
    a = atrous_bilateral(x, g, sigma_d=np.inf, levels=3, spatial_axes=(0,))
    b = atrous_bilateral(x, 100 * g, sigma_d=np.inf, levels=3, spatial_axes=(0,))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize(
    "guided,separable,kernel",
    [
        (True, True, "xla_cpu"),
        (True, False, "xla_cpu"),
        (False, True, "xla_cpu"),
        (False, False, "xla_cpu"),
        (True, False, "plain"),  # the other kernel's levels' start (one case: it compiles slowly)
    ],
    ids=["guide-sep", "guide-full", "self-sep", "self-full", "guide-full-plain"],
)
def test_first_level_continues_a_cascade(guided, separable, kernel):
    # Levels 0..1 then 2..3 are levels 0..3, with a guide and self-guided, masked or not.
    rng = np.random.default_rng(5)
    x = jnp.asarray(rng.normal(size=(12, 9, 2)), jnp.float32)
    guide = jnp.asarray(rng.normal(size=(12, 9)), jnp.float32) if guided else "self"
    for mask in (None, jnp.asarray(rng.random((12, 9)) > 0.3)):
        run = functools.partial(
            atrous_bilateral,
            guide=guide,
            sigma_d=0.7,
            spatial_axes=(0, 1),
            mask=mask,
            separable=separable,
            kernel=kernel,
        )
        half = run(x, levels=2)
        np.testing.assert_allclose(run(half, levels=4, first_level=2), run(x, levels=4), atol=1e-6)
    half = run(x, levels=2, mask=None)
    assert run(half, levels=2, first_level=2, mask=None) is half  # nothing left to run


def test_sigma_zero_keeps_only_equal_guide_neighbours():
    guide = jnp.asarray([0.0, 0.0, 1.0, 1.0, 1.0, 0.0])
    x = jnp.asarray([1.0, 3.0, 10.0, 20.0, 30.0, 5.0])
    out = atrous_bilateral(x, guide, sigma_d=0.0, levels=1, spatial_axes=(0,))
    # Index 3 sees 10, 20, 30 with taps 1/4, 3/8, 1/4 (index 1 and 5 have another guide).
    np.testing.assert_allclose(
        float(out[3]), (10 / 4 + 20 * 3 / 8 + 30 / 4) / (1 / 4 + 3 / 8 + 1 / 4), rtol=1e-6
    )
    # Index 5 has no equal-guide neighbour within reach: it keeps its value.
    np.testing.assert_allclose(float(out[5]), 5.0, rtol=1e-6)


def test_strides_longer_than_grid_and_tiny_grids():
    rng = np.random.default_rng(5)
    for shape in [(1, 1), (1, 7), (2, 2, 2), (3,)]:
        x = rng.normal(size=shape + (2,)).astype(np.float32)
        g = rng.normal(size=shape + (1,)).astype(np.float32)
        for sep in (True, False):
            out = atrous_bilateral(
                jnp.asarray(x),
                jnp.asarray(g),
                sigma_d=0.5,
                levels=6,
                spatial_axes=tuple(range(len(shape))),
                separable=sep,
            )
            ref = atrous_reference(x, g, 0.5, 6, sep)
            np.testing.assert_allclose(np.asarray(out), ref, rtol=RTOL, atol=1e-6)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16, jnp.float32])
def test_low_precision_inputs_keep_dtype(dtype):
    rng = np.random.default_rng(6)
    x = rng.normal(size=(12, 12, 3)).astype(np.float32)
    g = rng.normal(size=(12, 12, 3)).astype(np.float32)
    out = atrous_bilateral(
        jnp.asarray(x, dtype), jnp.asarray(g, dtype), sigma_d=0.5, levels=3, spatial_axes=(0, 1)
    )
    assert out.dtype == dtype
    ref = atrous_reference(
        np.asarray(jnp.asarray(x, dtype), np.float64),
        np.asarray(jnp.asarray(g, dtype), np.float64),
        0.5,
        3,
        True,
    )
    # Accumulation is float32: the error is the final rounding to `dtype`, or float32 sums.
    tol = max(float(jnp.finfo(dtype).eps), RTOL)
    np.testing.assert_allclose(
        np.asarray(out, np.float64), ref, rtol=tol, atol=tol * np.abs(ref).max()
    )


def test_float64_when_enabled():
    with jax_compat.enable_x64(True):
        rng = np.random.default_rng(7)
        x = rng.normal(size=(6, 6, 1))
        g = rng.normal(size=(6, 6, 1))
        out = atrous_bilateral(
            jnp.asarray(x),
            jnp.asarray(g),
            sigma_d=0.3,
            levels=2,
            spatial_axes=(0, 1),
            separable=False,
        )
        assert out.dtype == jnp.float64
        np.testing.assert_allclose(
            np.asarray(out), atrous_reference(x, g, 0.3, 2, False), rtol=1e-12
        )


def test_jit_vmap_and_grads():
    rng = np.random.default_rng(8)
    x = jnp.asarray(rng.normal(size=(4, 8, 8, 2)), jnp.float32)
    g = jnp.asarray(rng.normal(size=(4, 8, 8, 1)), jnp.float32)
    f = jax.jit(lambda x, g, s: atrous_bilateral(x, g, sigma_d=s, levels=2, spatial_axes=(0, 1)))
    batched = jax.vmap(f, in_axes=(0, 0, None))(x, g, 0.5)
    for i in range(4):
        np.testing.assert_allclose(
            np.asarray(batched[i]), np.asarray(f(x[i], g[i], 0.5)), rtol=1e-6, atol=1e-6
        )

    def loss(x, g, s):
        return jnp.sum(f(x, g, s) ** 2)

    gx, gg, gs = jax.grad(loss, argnums=(0, 1, 2))(x[0], g[0], 0.5)
    assert all(np.all(np.isfinite(a)) for a in (gx, gg, gs))
    # Finite differences on sigma_d (float32 central difference: ~1e-3 relative agreement).
    h = 1e-2
    fd = (loss(x[0], g[0], 0.5 + h) - loss(x[0], g[0], 0.5 - h)) / (2 * h)
    np.testing.assert_allclose(float(gs), float(fd), rtol=2e-2)
    # Guides with equal values (distance 0) and sigma_d at 0 or inf still give finite grads.
    for s in (0.0, np.inf):
        grads = jax.grad(loss, argnums=(0, 1))(x[0], jnp.zeros_like(g[0]), s)
        assert all(np.all(np.isfinite(a)) for a in grads)


def _operator(shape, guide, sigma_d, levels, separable, extra=None):
    """The filter's matrix, by filtering every one-hot input at once (one channel each);
    with ``extra`` (*shape, k), also the filtered ``extra`` from the same program."""
    n = math.prod(shape)
    fields = jnp.eye(n, dtype=jnp.float32).reshape(shape + (n,))
    if extra is not None:
        fields = jnp.concatenate([fields, jnp.asarray(extra)], axis=-1)
    out = atrous_bilateral(
        fields,
        guide,
        sigma_d=sigma_d,
        levels=levels,
        spatial_axes=tuple(range(len(shape))),
        separable=separable,
    )
    out = np.asarray(out, np.float64).reshape(n, -1)
    return out[:, :n] if extra is None else (out[:, :n], out[:, n:])


shapes = st.sampled_from([(1,), (2,), (5,), (1, 1), (1, 4), (3, 2), (4, 5), (2, 2, 2), (3, 1, 2)])
sigmas = st.one_of(st.sampled_from([0.0, 1e-30, 1e30, np.inf]), st.floats(1e-3, 1e3))


@given(
    shape=shapes,
    sigma_d=sigmas,
    levels=st.sampled_from([0, 1, 2, 4]),
    separable=st.booleans(),
    seed=st.integers(0, 2**31 - 1),
)
def test_operator_is_nonnegative_row_stochastic_and_linear(shape, sigma_d, levels, separable, seed):
    rng = np.random.default_rng(seed)
    guide = jnp.asarray(rng.integers(0, 3, size=shape) * rng.random(), jnp.float32)
    # Linear in the fields: filtering a random field (alongside, same weights) equals B @ it.
    x = rng.normal(size=shape + (1,)).astype(np.float32)
    B, y = _operator(shape, guide, sigma_d, levels, separable, extra=x)
    assert np.all(B >= 0)
    np.testing.assert_allclose(B.sum(axis=1), 1.0, rtol=1e-5)  # float32 sums of <= 125 terms
    if levels == 0:
        np.testing.assert_array_equal(B, np.eye(B.shape[0]))
    np.testing.assert_allclose(y.ravel(), B @ x.ravel(), rtol=1e-4, atol=1e-5)


# Guide values on a 2^-20 grid: a multi-channel distance is sqrt of a float32 sum of squares,
# so differences below ~1e-19 (whose squares underflow) count as equal guides, which the
# float64 reference does not do (docs/robustness.md; the extremes are in test_properties).
QUANTISED_GUIDES = st.integers(-3 * 2**20, 3 * 2**20).map(lambda i: np.float32(i / 2**20))


@given(
    data=hnp.arrays(np.float32, (5, 4, 2), elements=QUANTISED_GUIDES),
    sigma_d=sigmas,
    levels=st.integers(1, 3),
)
def test_guide_with_channels_matches_reference(data, sigma_d, levels):
    x = np.cos(np.arange(40, dtype=np.float32)).reshape(5, 4, 2)
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(data),
        sigma_d=sigma_d,
        levels=levels,
        spatial_axes=(0, 1),
        separable=False,
    )
    np.testing.assert_allclose(
        np.asarray(out), atrous_reference(x, data, sigma_d, levels, False), rtol=RTOL, atol=1e-5
    )


def test_bad_input_errors_name_the_argument():
    x = jnp.zeros((4, 4, 2))
    g = jnp.zeros((4, 4))
    with pytest.raises(ValueError, match="sigma_d"):
        atrous_bilateral(x, g, sigma_d=-1.0, levels=1, spatial_axes=(0, 1))
    with pytest.raises(ValueError, match="sigma_d"):
        atrous_bilateral(x, g, sigma_d=float("nan"), levels=1, spatial_axes=(0, 1))
    with pytest.raises(ValueError, match="levels"):
        atrous_bilateral(x, g, sigma_d=1.0, levels=-1, spatial_axes=(0, 1))
    with pytest.raises(TypeError, match="levels"):
        atrous_bilateral(x, g, sigma_d=1.0, levels=1.5, spatial_axes=(0, 1))
    with pytest.raises(ValueError, match="spatial_axes"):
        atrous_bilateral(x, g, sigma_d=1.0, levels=1, spatial_axes=(0, 3))
    with pytest.raises(ValueError, match="repeats"):
        atrous_bilateral(x, g, sigma_d=1.0, levels=1, spatial_axes=(0, 0))
    with pytest.raises(ValueError, match="guide"):
        atrous_bilateral(x, jnp.zeros((4, 5)), sigma_d=1.0, levels=1, spatial_axes=(0, 1))
    with pytest.raises(ValueError, match="fields"):
        atrous_bilateral((x, jnp.zeros((4, 3, 2))), g, sigma_d=1.0, levels=1, spatial_axes=(0, 1))
    with pytest.raises(TypeError, match="floating"):
        atrous_bilateral(
            jnp.zeros((4, 4), jnp.int32), g, sigma_d=1.0, levels=1, spatial_axes=(0, 1)
        )
    with pytest.raises(ValueError, match="mask"):
        atrous_bilateral(
            x, g, sigma_d=1.0, levels=1, spatial_axes=(0, 1), mask=jnp.ones((4,), bool)
        )
    with pytest.raises(ValueError, match=r"first_level must be <= levels \(2\), got 3"):
        atrous_bilateral(x, g, sigma_d=1.0, levels=2, spatial_axes=(0, 1), first_level=3)
    with pytest.raises(ValueError, match="first_level"):
        atrous_bilateral(x, g, sigma_d=1.0, levels=2, spatial_axes=(0, 1), first_level=-1)


@pytest.mark.parametrize("shape", [(3, 4, 128), (3, 512)])
def test_full_mode_pitch_column_is_off_the_grid(shape):
    # Outer strides of 2 KiB and 4 KiB (powers of two) get a zero column appended in
    # full mode (atrous.pitch_columns); it must change nothing: same result as the reference,
    # with and without a mask, and (2-D) finite guide gradients along the last column.
    assert atrous.pitch_columns(shape, separable=False) == 1
    rng = np.random.default_rng(12)
    x = rng.normal(size=shape + (2,)).astype(np.float32)
    g = _quantised_guide(rng, shape, 1)
    axes = tuple(range(len(shape)))
    levels = 3 if len(shape) == 2 else 1  # full 3-D compiles slowly
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(g),
        sigma_d=0.35,
        levels=levels,
        spatial_axes=axes,
        separable=False,
    )
    np.testing.assert_allclose(
        np.asarray(out), atrous_reference(x, g, 0.35, levels, False), rtol=RTOL, atol=1e-6
    )
    mask = rng.random(shape) > 0.3
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(g),
        sigma_d=0.35,
        levels=1,
        spatial_axes=axes,
        separable=False,
        mask=jnp.asarray(mask),
    )
    np.testing.assert_allclose(
        np.asarray(out), atrous_reference(x, g, 0.35, 1, False, mask), rtol=RTOL, atol=1e-6
    )
    if len(shape) == 2:  # 3-D reverse mode compiles slowly
        gg = jax.grad(
            lambda g: jnp.sum(
                atrous_bilateral(
                    jnp.asarray(x), g, sigma_d=0.35, levels=1, spatial_axes=axes, separable=False
                )
                ** 2
            )
        )(jnp.asarray(g, jnp.float32))
        assert np.all(np.isfinite(np.asarray(gg))) and np.any(np.asarray(gg)[..., -1, :] != 0)


def test_pitch_rule():
    p = atrous.pitch_columns
    assert p((64, 64, 64), False) == 1 and p((512, 512), False) == 1
    assert p((64, 64, 64), True) == 0  # separable: not measured faster
    assert p((48, 48, 48), False) == 0 and p((96, 96, 96), False) == 0  # 9 KiB, 36 KiB
    assert p((256, 256), False) == 0 and p((4096,), False) == 0  # 1 KiB; 1-D
    assert p((32, 32, 32), False, itemsize=8) == 1 and p((512, 3), False) == 0


def test_full_3d_pairs_handed_over_between_levels_match_reference():
    # Full 3-D mode computes the weights of offsets shared by consecutive levels once
    # (atrous's handover order): three levels, so a level both takes over and hands over.
    rng = np.random.default_rng(11)
    x = rng.normal(size=(9, 6, 7, 2)).astype(np.float32)
    g = _quantised_guide(rng, (9, 6, 7), 2)  # two guide channels (one: the other tests)
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(g),
        sigma_d=0.35,
        levels=3,
        spatial_axes=(0, 1, 2),
        separable=False,
    )
    np.testing.assert_allclose(
        np.asarray(out), atrous_reference(x, g, 0.35, 3, False), rtol=RTOL, atol=1e-6
    )


def test_atrous_bilateral_is_defined_once_and_help_shows_its_docstring():
    import pathlib
    import pydoc

    root = pathlib.Path(ob.__file__).parent
    defs = [p for p in root.rglob("*.py") if "def atrous_bilateral(" in p.read_text()]
    assert [p.relative_to(root).as_posix() for p in defs] == ["_src/filter/front.py"]
    text = pydoc.render_doc(ob.atrous_bilateral, renderer=pydoc.plaintext)
    for part in (
        "A-trous cross-bilateral filter",
        "Args:",
        "guide_axes:",
        "Returns:",
        "Raises:",
        "explicit* mesh axes",
        "Example::",
    ):
        assert part in text, part
