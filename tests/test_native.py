"""The native kernel (csrc/, an XLA FFI call): built by the install, equal to the float64
reference on drawn grids and to the pure-JAX kernels at the extremes, differentiable and
batchable through them, and absent without harm. (test_atrous.py's float64-reference tests
take it too, parametrised by kernel; `make sanitize` runs its C++ test under AddressSanitizer
and UBSan.)"""

import dataclasses
import functools
import math
import os
import re
import subprocess
import sys
import textwrap

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jax_compat
import jaxprs
from optax_bilateral import atrous_bilateral
from optax_bilateral._src import numerics
from optax_bilateral._src.filter import native
from optax_bilateral._src.filter.bilateral import Deeper
from reference import atrous_reference

# float32 sums of <= 125 taps over a few levels, in another order than the JAX kernels'.
RTOL, ATOL = 1e-5, 1e-6
F32 = dict(width=32, allow_subnormal=False)


def test_the_install_built_the_extension():
    status = native.status()
    assert status.available, status.reason
    assert status.reason in ("avx512", "avx2", "baseline")
    assert status.threads >= 1


def _both(x, g, **kw):
    return [atrous_bilateral(x, g, kernel=k, **kw) for k in ("native", "plain")]


@pytest.mark.parametrize(
    "shape, axes", [((40, 36, 3), (0, 1)), ((300, 2), (0,))], ids=["fields-2d", "planes-1d"]
)
def test_a_continued_cascade_is_the_whole_cascade_bit_for_bit(shape, axes):
    # "auto"'s correlated-noise way runs F + k levels in one call where the native kernel runs
    # and continues the F levels' output elsewhere (rules/auto.py, Auto._cascade): the two
    # must agree to the bit (the fields' target in 2-D, the planar one in 1-D).
    rng = np.random.default_rng(11)
    m, v = (jnp.asarray(rng.normal(size=shape), jnp.float32) for _ in range(2))
    g = jnp.asarray(rng.normal(size=shape[: len(axes)] + (2,)), jnp.float32)
    g = g.at[3, 1].set(jnp.nan) if len(axes) == 2 else g.at[3].set(jnp.nan)
    run = functools.partial(
        atrous_bilateral, guide=g, sigma_d=0.4, spatial_axes=axes, guide_axes=axes, kernel="native"
    )
    whole = run((m, v), levels=5)
    continued = run(run((m, v), levels=3), levels=5, first_level=3)
    for a, b in zip(whole, continued):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _deeper_case(shape, axes, masked, dtype=jnp.float32):
    rng = np.random.default_rng(5)
    m, v = (jnp.asarray(rng.normal(size=shape), dtype) for _ in range(2))
    spatial = tuple(shape[a] for a in axes)
    if masked:  # a guide that cannot hold NaN: the filter's own mask
        g = jnp.asarray(rng.integers(0, 4, size=spatial), jnp.int32)
        mask = jnp.asarray(rng.random(spatial) > 0.2)
    else:
        lead = shape[: len(axes)]  # the guide's axes are the fields' (spatial_axes)
        g = jnp.asarray(rng.normal(size=lead + (2,)), dtype).at[(1,) * len(axes)].set(jnp.nan)
        mask = None
    return (m, v), g, mask


@pytest.mark.parametrize(
    "shape, axes, separable, masked, dtype",
    [
        ((40, 36, 3), (0, 1), True, False, jnp.float32),  # the fields' target
        ((40, 36, 3), (0, 1), True, True, jnp.float32),
        ((9, 10, 2), (1, 0), True, False, jnp.float32),  # planes: axes not in order
        ((12, 11, 2), (0, 1), False, False, jnp.float32),  # planes: full
        ((300, 2), (0,), True, True, jnp.float64),
    ],
    ids=["fields", "fields-masked", "planes-reordered", "planes-full", "planes-1d-float64"],
)
@pytest.mark.parametrize("flag", [0.0, 1.0, jnp.nan, True])
def test_a_deeper_cascade_is_one_call_equal_to_either_cascade_bit_for_bit(
    shape, axes, separable, masked, dtype, flag
):
    # "auto"'s heavier filter on the native kernel: one call reads the stored flag (> 0: two
    # more levels at 1.5 sigma_d) where a conditional chose between two calls.
    from optax_bilateral._src.filter.front import atrous_bilateral_deeper

    with jax_compat.enable_x64(dtype == jnp.float64):
        fields, g, mask = _deeper_case(shape, axes, masked, dtype)
        kw = dict(spatial_axes=axes, separable=separable, mask=mask)
        vector = jnp.asarray([0.0, flag], jnp.bool_ if flag is True else dtype)
        deeper = Deeper(2, 1.5, numerics.Entry(vector, 1, vector.dtype))
        sigma = jnp.asarray(0.4, dtype)
        got = jax.jit(
            lambda f, g, s: atrous_bilateral_deeper(f, g, deeper, sigma_d=s, levels=3, **kw)
        )(fields, g, sigma)
        deep = bool(flag > 0)
        want = atrous_bilateral(
            fields,
            g,
            sigma_d=sigma * 1.5 if deep else sigma,
            levels=5 if deep else 3,
            kernel="native",
            **kw,
        )
        for a, b in zip(got, want):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        hlo = (
            jax.jit(lambda f, s: atrous_bilateral_deeper(f, g, deeper, sigma_d=s, levels=3, **kw))
            .lower(fields, sigma)
            .as_text()
        )
        assert hlo.count("optax_bilateral_atrous") == 1 and "case" not in hlo


@pytest.mark.parametrize("flag", [0.0, 1.0])
def test_a_deeper_cascade_takes_the_other_kernels_derivatives_and_batches(flag, monkeypatch):
    # Its derivative is the plain kernel's in a conditional, and on the pure-JAX kernels the
    # cascade itself is that conditional.
    from optax_bilateral._src.filter.front import atrous_bilateral_deeper

    fields, g, _ = _deeper_case((10, 9, 2), (0, 1), False)
    deeper = Deeper(1, 2.0, numerics.Entry.of(jnp.asarray(flag, jnp.float32)))

    def loss(m, g, s, kernel="native"):
        monkeypatch.setenv("OPTAX_BILATERAL_KERNEL", kernel)
        out = atrous_bilateral_deeper(
            (m, fields[1]), g, deeper, sigma_d=s, levels=2, spatial_axes=(0, 1)
        )
        return jnp.sum(out[0] ** 2) + jnp.sum(jnp.sin(out[1]))

    args = (fields[0], jnp.nan_to_num(g), jnp.asarray(0.3))
    try:
        np.testing.assert_allclose(loss(*args), loss(*args, kernel="plain"), rtol=1e-5)
        got = jax.grad(loss, argnums=(0, 1, 2))(*args)
        want = jax.grad(functools.partial(loss, kernel="plain"), argnums=(0, 1, 2))(*args)
        for a, b in zip(got, want):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
        assert float(jnp.abs(got[2])) > 0
        batched = jax.vmap(lambda m: loss(m, *args[1:]))(jnp.stack([args[0], -args[0]]))
        unbatched = [loss(s * args[0], *args[1:]) for s in (1, -1)]
        np.testing.assert_allclose(np.asarray(batched), unbatched, rtol=1e-6)
    finally:
        monkeypatch.delenv("OPTAX_BILATERAL_KERNEL")
        jax.clear_caches()


def test_a_deeper_cascade_refuses_a_flag_it_cannot_read():
    from optax_bilateral._src.filter.front import atrous_bilateral_deeper

    x = jnp.ones((2, 8, 8))
    g = jnp.ones((1, 8, 8))
    flag = Deeper(1, 1.5, numerics.Entry.of(jnp.float32(1)))
    with pytest.raises(ValueError, match="sigma_d"):
        atrous_bilateral_deeper(x, g[0], flag, sigma_d=-1.0, levels=2, spatial_axes=(1, 2))
    with pytest.raises(ValueError, match=r"deeper\.levels must be"):
        atrous_bilateral_deeper(
            x, g[0], flag._replace(levels=-1), sigma_d=0.4, levels=2, spatial_axes=(1, 2)
        )
    bad = Deeper(1, 1.5, numerics.Entry(jnp.ones((1,)), 3, jnp.float32))
    with pytest.raises(Exception, match="deeper must be a bool or float vector"):
        jax.block_until_ready(native.filter_planes(x, g, None, jnp.float32(0.4), 2, True, 0, bad))
    too_deep = Deeper(61, 1.5, numerics.Entry.of(jnp.float32(1)))
    with pytest.raises(Exception, match="levels \\+ deeper_levels <= 62"):
        jax.block_until_ready(
            native.filter_planes(x, g, None, jnp.float32(0.4), 2, True, 0, too_deep)
        )


# Shapes from a small set (each compiles a program), data drawn freely.
SHAPES = [(23,), (6, 7), (17, 5), (4, 3, 5)]


@given(
    shape=st.sampled_from(SHAPES),
    levels=st.just(3),  # strides 1, 2, 4: beyond some axes; each static setting compiles
    separable=st.booleans(),
    sigma=st.sampled_from([0.0, 1e-3, 0.4, 3.0, np.inf]),
    gch=st.sampled_from([1, 2]),
    masked=st.booleans(),
    seed=st.integers(0, 2**31 - 1),
)
def test_equals_the_float64_reference_on_drawn_grids(
    shape, levels, separable, sigma, gch, masked, seed
):
    # Against tests/reference.py's float64 loop (no compiled reference: each static setting
    # drawn compiles the native call only).
    rng = np.random.default_rng(seed)
    x = rng.normal(size=shape + (2,)).astype(np.float32)
    # Quantised guides: equal values exercise "equal guides weigh 1" (and sigma_d = 0).
    g = (rng.integers(0, 3, size=shape + (gch,)) * 0.5).astype(np.float32)
    mask = rng.random(shape) > 0.25 if masked else None
    axes = tuple(range(len(shape)))
    out = atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(g),
        sigma_d=sigma,
        levels=levels,
        spatial_axes=axes,
        separable=separable,
        mask=None if mask is None else jnp.asarray(mask),
        kernel="native",
    )
    want = atrous_reference(x, g, sigma, levels, separable, mask)
    np.testing.assert_allclose(np.asarray(out), want, rtol=RTOL, atol=ATOL)


def _extreme_arrays(shape):
    return st.tuples(
        hnp.arrays(
            np.float32,
            shape,
            elements=st.floats(np.float32(-1e30), np.float32(1e30), **F32)
            | st.sampled_from([np.nan, np.inf, -np.inf]),
        ),
        hnp.arrays(
            np.float32,
            shape,
            elements=st.floats(np.float32(-3e38), np.float32(3e38), **F32) | st.just(np.nan),
        ),
    )


# 2-D, and 3-D, whose slabs' last-axis passes run their rows as one (a NaN or an infinity at a
# row's end must not reach the next row).
@pytest.mark.parametrize("shape", [(9, 8, 2), (3, 5, 6, 2)], ids=["2d", "3d"])
@given(data=st.data())
def test_extreme_values_decided_as_the_plain_kernel(shape, data):
    # Non-finite and huge fields, NaN and huge guides: same NaN places, same values.
    x, g = data.draw(_extreme_arrays(shape))
    axes = tuple(range(len(shape) - 1))
    a, b = _both(jnp.asarray(x), jnp.asarray(g), sigma_d=0.5, levels=2, spatial_axes=axes)
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_fields_filter_in_float32(dtype):
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(12, 10, 3)), dtype)
    g = jnp.asarray(rng.random((12, 10)), jnp.float32)
    a, b = _both(x, g, sigma_d=0.2, levels=3, spatial_axes=(0, 1))
    assert a.dtype == dtype
    # Float32 results one rounding apart may round to neighbouring half-precision values.
    eps = float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(
        np.asarray(a, np.float32), np.asarray(b, np.float32), rtol=eps, atol=eps
    )


def test_gradients_are_the_plain_kernels():
    # With respect to the fields, the guide and sigma_d (the rule differentiates "plain").
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(10, 9, 2)), jnp.float32)
    g = jnp.asarray(rng.random((10, 9, 2)), jnp.float32)

    def loss(kernel):
        def f(x, g, s):
            y = atrous_bilateral(x, g, sigma_d=s, levels=2, spatial_axes=(0, 1), kernel=kernel)
            return jnp.sum(y**2)

        return jax.grad(f, argnums=(0, 1, 2))(x, g, jnp.float32(0.3))

    for a, b in zip(loss("native"), loss("plain")):
        assert np.all(np.isfinite(b)) and np.any(np.asarray(b) != 0)
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_vmap_filters_each_batch_element():
    rng = np.random.default_rng(2)
    xs = jnp.asarray(rng.normal(size=(3, 11, 7)), jnp.float32)
    g = jnp.asarray(rng.random((11, 7)), jnp.float32)
    f = lambda x: atrous_bilateral(
        x, g, sigma_d=0.3, levels=3, spatial_axes=(0, 1), kernel="native"
    )
    batched = jax.vmap(f)(xs)
    for i in range(3):
        np.testing.assert_array_equal(np.asarray(batched[i]), np.asarray(f(xs[i])))


def test_a_long_line_runs_in_blocks_as_the_plain_kernel(monkeypatch):
    # A 1-D grid's passes run in blocks of columns (csrc/atrous.cc, cut_blocks; ~21845 points
    # of two channels), each with the weights of the points before it whose partner lies in
    # it: NaN guides and masked points on the blocks' edges, and on any thread count.
    n, edge = 70_000, 21_845
    rng = np.random.default_rng(5)
    x = jnp.asarray(rng.normal(size=(n, 2)), jnp.float32)
    g = rng.random((n, 1)).astype(np.float32)
    g[[edge - 1, edge, 2 * edge + 3]] = np.nan
    mask = rng.random(n) > 0.2
    mask[[edge - 2, edge + 1, 2 * edge]] = False
    run = lambda kernel: atrous_bilateral(
        x,
        jnp.asarray(g),
        sigma_d=0.3,
        levels=7,
        spatial_axes=(0,),
        mask=jnp.asarray(mask),
        kernel=kernel,
    )
    outs = []
    for threads in ("1", "2"):
        monkeypatch.setenv(native.THREADS_ENV, threads)
        jax.clear_caches()
        outs.append(np.asarray(run("native")))
    np.testing.assert_array_equal(outs[0], outs[1])
    np.testing.assert_allclose(outs[0], np.asarray(run("plain")), rtol=RTOL, atol=ATOL)
    monkeypatch.delenv(native.THREADS_ENV)
    jax.clear_caches()


# Separable 2-D; full 3-D (chains of slabs, level 0's cut in pieces, each recomputing the
# weights before it); a 2-D grid of short rows (run in groups of rows). Each holds at least
# 2^15 point-channels, below which a call runs on one thread (csrc/atrous.h).
@pytest.mark.parametrize(
    "shape, separable",
    [((128, 96, 3), True), ((40, 24, 20, 2), False), ((2400, 7, 2), True)],
    ids=["2d", "full-3d", "short-rows"],
)
def test_thread_count_does_not_change_the_result(shape, separable, monkeypatch):
    # Each block's sums run in the same order whatever thread takes it: bit-equal outputs.
    # The count is read when a program is traced: each is traced afresh, and says its count.
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=shape), jnp.float32)
    g = jnp.asarray(rng.random(shape[:-1]), jnp.float32)
    axes = tuple(range(len(shape) - 1))
    outs = []
    for n in ("1", "3"):
        monkeypatch.setenv(native.THREADS_ENV, n)
        assert native.threads() == int(n)
        jax.clear_caches()
        f = jax.jit(
            lambda x, g: atrous_bilateral(
                x,
                g,
                sigma_d=0.2,
                levels=4,
                spatial_axes=axes,
                separable=separable,
                kernel="native",
            )
        )
        assert f"threads = {n} : i64" in f.lower(x, g).as_text()
        outs.append(f(x, g))
    np.testing.assert_array_equal(np.asarray(outs[0]), np.asarray(outs[1]))
    monkeypatch.setenv(native.THREADS_ENV, "zero")
    with pytest.raises(ValueError, match=native.THREADS_ENV):
        native.threads()
    monkeypatch.delenv(native.THREADS_ENV)
    jax.clear_caches()


def test_without_the_extension_the_pure_jax_kernels_run():
    # A process where the extension cannot load: the package imports, says why, filters on
    # the pure-JAX kernel, and a request for the native one names the reason.
    code = textwrap.dedent(
        """
        import jax.numpy as jnp, optax_bilateral as ob
        from optax_bilateral._src.filter import native
        s = native.status()
        assert not s.available and "OPTAX_BILATERAL_NATIVE=0" in s.reason, s
        for n in (8, 9):  # two programs traced: the fallback is said once
            y = ob.atrous_bilateral(jnp.ones((n, n)), jnp.ones((n, n)), sigma_d=0.1, levels=2,
                                    spatial_axes=(0, 1))
            assert float(y[3, 3]) == 1.0
        try:
            ob.atrous_bilateral(jnp.ones((8, 8)), jnp.ones((8, 8)), sigma_d=0.1, levels=2,
                                spatial_axes=(0, 1), kernel="native")
        except ValueError as e:
            assert "OPTAX_BILATERAL_NATIVE=0" in str(e), e
        else:
            raise AssertionError("kernel='native' ran without the extension")
        # The default update: the rules' local averages fall back to slices too.
        import jax
        p = jnp.ones((40, 40, 3))
        opt = ob.bilateral_adam(0.02)
        state = opt.init(p)
        for i in range(9):  # past a gate check (step 8)
            u, state = opt.update(p * 0.1 + 0.01 * i, state, p)
        assert bool(jnp.all(jnp.isfinite(u)))
        text = jax.jit(opt.update).lower(p, state, p).as_text()
        assert native.SUBGRID_TARGET not in text and "count_nonfinite" not in text
        assert native.TEXEL_MEAN_TARGET not in text and native.CORRELATION_TARGET not in text
        assert native.BLEND_TARGET not in text and native.NOISE_TEST_TARGET not in text
        assert "optax_bilateral_after" not in text  # the step's order: XLA's own
        pyramid = ob.pyramid_adam(0.01, 3)
        text = jax.jit(pyramid.update).lower(p, pyramid.init(p), p).as_text()
        assert "optax_bilateral_after" not in text  # the levels: XLA's fusion decides
        u, state = opt.update(p.at[0, 0, 0].set(jnp.nan), state, p)  # counted by jnp.sum
        assert int(state[0].nonfinite_count) == 1, state[0].nonfinite_count
        print("ok")
        """
    )
    env = dict(os.environ, OPTAX_BILATERAL_NATIVE="0")
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]
    said = [line for line in proc.stderr.splitlines() if "'xla_cpu' kernel" in line]
    assert len(said) == 1 and "OPTAX_BILATERAL_NATIVE=0" in said[0], proc.stderr[-2000:]


def test_compiles_one_custom_call_for_the_whole_cascade():
    x = jnp.ones((32, 32, 2), jnp.float32)
    f = jax.jit(
        lambda x: atrous_bilateral(
            x, x, sigma_d=0.1, levels=5, spatial_axes=(0, 1), kernel="native"
        )
    )
    text = f.lower(x).as_text()
    assert text.count(native.TARGET) == 1


@pytest.mark.parametrize("cid", __import__("goldens").covering_subset())
def test_transforms_on_the_pure_jax_kernel_match_the_goldens(cid, monkeypatch):
    # Every golden configuration (tests/goldens.py: the transforms' updates and states over
    # steps, recorded with the native kernel that "auto" takes on the CPU), run with the
    # pure-JAX xla_cpu kernel (the CPU's without the extension) in every filter. Tolerance as
    # across toolchains: kernels round differently, and a one-ulp change of a moment moves a
    # step by about as much; bfloat16/float16 round to ~1e-3.
    import goldens

    data = np.load(goldens.PATH)
    # The kernel is read when a program is traced: clear the traces before, and after, so
    # that no later test in this process reuses one made with the xla_cpu kernel.
    monkeypatch.setenv("OPTAX_BILATERAL_KERNEL", "xla_cpu")
    jax.clear_caches()
    try:
        results = goldens.run(cid)
    finally:
        monkeypatch.delenv("OPTAX_BILATERAL_KERNEL")
        jax.clear_caches()
    for variant, got in results.items():
        key = f"{cid}/{variant}"
        if key not in data.files:
            continue
        want = data[key]
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=key)
        np.testing.assert_allclose(got, want, rtol=2e-2, atol=1e-3, err_msg=key)


def test_float64_fields_match_the_float64_reference():
    # With jax_enable_x64 the kernel runs its double build: equal to the float64 loop of
    # tests/reference.py to double rounding. (A child process: x64 is set when jax starts.)
    code = textwrap.dedent(
        """
        import numpy as np, jax.numpy as jnp
        from optax_bilateral import atrous_bilateral
        from reference import atrous_reference
        rng = np.random.default_rng(5)
        for shape, sep in (((9, 7), True), ((9, 7), False), ((5, 4, 6), True), ((13,), True)):
            x = rng.normal(size=shape + (2,))
            g = rng.integers(0, 3, size=shape + (2,)) * 0.5 + rng.normal(size=shape + (2,)) * 0.05
            out = atrous_bilateral(jnp.asarray(x), jnp.asarray(g), sigma_d=0.3, levels=3,
                                   spatial_axes=tuple(range(len(shape))), separable=sep,
                                   kernel="native")
            assert out.dtype == jnp.float64, out.dtype
            np.testing.assert_allclose(np.asarray(out), atrous_reference(x, g, 0.3, 3, sep),
                                       rtol=1e-12, atol=1e-13)
        print("ok")
        """
    )
    env = dict(os.environ, JAX_ENABLE_X64="1")
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(__file__), env.get("PYTHONPATH", "")])
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


# The sigma_d rules' local averages at a sub-grid (csrc/local.h): one FFI call per field.


@settings(max_examples=8)  # each drawn shape and stride compiles two programs
@given(
    shape=st.sampled_from([(9,), (7, 5), (6, 11), (4, 5, 3)]),
    channels=st.sampled_from([1, 3]),
    stride=st.sampled_from([1, 2, 3, 4]),
    seed=st.integers(0, 2**31 - 1),
)
def test_subgrid_average_equals_the_float64_reference(shape, channels, stride, seed):
    # The filter's first level at sigma_d = inf (every weight 1) from tests/reference.py's
    # loop, read at every stride-th entry: what the rules' statistics take.
    from optax_bilateral._src.filter import local

    x = np.random.default_rng(seed).normal(size=shape + (channels,)).astype(np.float32)
    axes = tuple(range(len(shape)))
    want = atrous_reference(x, np.zeros(shape + (1,)), np.inf, levels=1, separable=True)
    want = want[tuple(slice(None, None, stride) for _ in shape)]
    got = local._native_taps(jnp.asarray(x), True, axes, stride, False)
    np.testing.assert_allclose(np.asarray(got), want, rtol=RTOL, atol=ATOL)
    # And the slices it replaces, on any order of the axes.
    for order in (axes, axes[::-1]):
        native_out = local._native_taps(jnp.asarray(x), True, order, stride, False)
        np.testing.assert_allclose(
            native_out, local._taps(jnp.asarray(x), order, stride), rtol=RTOL, atol=ATOL
        )


def test_subgrid_average_takes_axes_anywhere_and_float64():
    from optax_bilateral._src.filter import local

    x = jax.random.normal(jax.random.PRNGKey(0), (5, 2, 9, 7))
    for axes, stride in [((0, 2, 3), 2), ((3,), 3), ((2, 0), 1), ((), 2)]:
        np.testing.assert_allclose(
            local._native_taps(x, True, axes, stride, False),
            local._taps(x, axes, stride),
            rtol=RTOL,
            atol=ATOL,
        )
    code = textwrap.dedent(
        """
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        from optax_bilateral._src.filter import local
        x = jax.random.normal(jax.random.PRNGKey(0), (13, 6, 2), dtype=np.float64)
        got, want = local._native_taps(x, True, (0, 1), 2, False), local._taps(x, (0, 1), 2)
        assert got.dtype == np.float64, got.dtype
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)
        print("ok")
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


def test_subgrid_average_differentiates_and_batches_as_the_slices():
    from optax_bilateral._src.filter import local

    x = jax.random.normal(jax.random.PRNGKey(1), (16, 12, 3))
    axes = (0, 1)

    def loss(f):
        return lambda x: jnp.sum(jnp.sin(f(x, axes, 2)))

    np.testing.assert_allclose(
        jax.grad(loss(lambda x, axes, s: local._native_taps(x, True, axes, s, False)))(x),
        jax.grad(loss(local._taps))(x),
        rtol=1e-5,
        atol=1e-6,
    )
    batch = jnp.stack([x, 2 * x, -x])
    np.testing.assert_allclose(
        jax.vmap(lambda x: local._native_taps(x, True, axes, 2, False))(batch),
        jax.vmap(lambda x: local._taps(x, axes, 2))(batch),
        rtol=RTOL,
        atol=ATOL,
    )


def test_subgrid_average_reads_nan_and_infinities_as_nan_to_num():
    # The guide's contrast averages jnp.nan_to_num(guide) without making it: NaN reads as 0,
    # an infinity as the largest finite value of its sign; values and derivatives as the
    # slices' of the copy.
    from optax_bilateral._src.filter import local

    x = jax.random.normal(jax.random.PRNGKey(2), (17, 12, 3))
    x = x.at[3, 4, 0].set(jnp.nan).at[8, 0, 2].set(jnp.inf).at[16, 11, 1].set(-jnp.inf)
    x = x.at[0, 5].set(jnp.nan)
    for stride in (1, 2, 3):
        got = local._native_taps(x, True, (0, 1), stride, True)
        skipped = local._native_taps(x, jnp.asarray(False), (0, 1), stride, True)
        assert skipped.shape == got.shape and not np.any(np.asarray(skipped))  # not run
        want = local._taps(jnp.nan_to_num(x), (0, 1), stride)
        np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)
        assert np.all(np.isfinite(got))

    w = jax.random.normal(jax.random.PRNGKey(3), local._taps(x, (0, 1), 2).shape)

    def loss(f):  # linear: its gradient is the average's transpose of w, 0 where x is not finite
        return lambda x: jnp.sum(f(x) * w)

    got = jax.grad(loss(lambda x: local._native_taps(x, True, (0, 1), 2, True)))(x)
    np.testing.assert_allclose(
        got,
        jax.grad(loss(lambda x: local._taps(jnp.nan_to_num(x), (0, 1), 2)))(x),
        rtol=1e-5,
        atol=1e-6,
    )
    assert got[3, 4, 0] == 0 and got[8, 0, 2] == 0 and np.all(got[0, 5] == 0)
    assert np.count_nonzero(np.asarray(got)) > got.size // 8


def test_the_rules_statistics_call_the_native_average_where_the_filter_does(monkeypatch):
    # The default update's program: the guide's contrast, the mean distances the scale takes,
    # the step's mean norm (from the step's parts), the correlated-noise check's sums and the
    # blend (its two local averages inside) are one FFI call each; with the pure-JAX kernel
    # chosen, none.
    import optax_bilateral as ob
    from optax_bilateral._src.filter import local

    x = jnp.ones((40, 40, 3))
    opt = ob.bilateral_adam(0.02)
    state = opt.init(x)

    def text():
        return jax.jit(opt.update).lower(x, state, x).as_text()

    assert text().count(native.SUBGRID_TARGET) == 1  # the guide's contrast
    assert text().count(native.TEXEL_MEAN_TARGET) == 2  # the guide's step and its contrast
    assert text().count(native.STEP_NORM_TARGET) == 1  # AutoState.direction
    assert text().count(native.NOISE_TEST_TARGET) == 1  # the correlated-noise check
    assert native.CORRELATION_TARGET not in text()  # (its sums inside that call)
    assert text().count(native.BLEND_TARGET) == 1  # the blend, its averages inside
    monkeypatch.setenv("OPTAX_BILATERAL_KERNEL", "xla_cpu")
    jax.clear_caches()
    try:
        assert native.SUBGRID_TARGET not in text() and native.TEXEL_MEAN_TARGET not in text()
        assert native.CORRELATION_TARGET not in text() and native.BLEND_TARGET not in text()
        assert native.NOISE_TEST_TARGET not in text() and native.STEP_NORM_TARGET not in text()
        slices = local.local_average_subgrid((x,), (0, 1), 2)[0]
    finally:
        monkeypatch.delenv("OPTAX_BILATERAL_KERNEL")
        jax.clear_caches()
    np.testing.assert_allclose(
        slices, local._native_taps(x, True, (0, 1), 2, False), rtol=RTOL, atol=ATOL
    )


@pytest.mark.parametrize("shape, heavier", [((40, 40, 3), 1), ((12, 12, 12, 1), 0)])
def test_the_defaults_run_without_conditionals_where_they_are_native(shape, heavier, monkeypatch):
    # On the native kernel "auto"'s statistics (the contrast, the correlated-noise check, the
    # blend) run at every step and a select keeps what the step uses, and the correlated
    # noise's heavier filter (more levels in 2-D) is decided inside the filter's one call: the
    # update holds no conditional. The pure-JAX kernels keep a conditional around each
    # statistic, whose slices would cost full-size passes at every step, and one around the
    # heavier filter's levels.
    import optax_bilateral as ob

    x = jnp.ones(shape)
    opt = ob.bilateral_adam(0.02)
    state = opt.init(x)

    def conditionals():
        jaxpr = jax.make_jaxpr(opt.update)(x, state, x).jaxpr
        return sum(e.primitive.name == "cond" for e in jaxprs.eqns(jaxpr))

    assert conditionals() == 0
    monkeypatch.setenv("OPTAX_BILATERAL_KERNEL", "xla_cpu")
    jax.clear_caches()
    try:
        assert conditionals() == 3 + heavier
    finally:
        monkeypatch.delenv("OPTAX_BILATERAL_KERNEL")
        jax.clear_caches()


# The sigma_d rules' texel statistics (csrc/stats.h): the guide's step and contrast, one call.


def _texel_distance_float64(a, b, axes, stride):
    """The definition in float64: every texel of the sub-grid, its norm over the other axes."""
    a = np.asarray(a, np.float64)[
        tuple(slice(None, None, stride) if d in axes else slice(None) for d in range(np.ndim(a)))
    ]
    x = a if b is None else a - np.asarray(b, np.float64)
    channels = tuple(d for d in range(x.ndim) if d not in axes)
    norms = np.sqrt(np.sum(x * x, axis=channels))
    kept = norms[~np.isnan(norms)]
    return kept.mean() if kept.size else 0.0


@settings(max_examples=12)  # each drawn shape and stride compiles two programs
@given(
    case=st.sampled_from(
        [((9,), (0,)), ((7, 5, 3), (0, 1)), ((3, 6, 11), (1, 2)), ((4, 5, 3, 2), (2, 0, 1))]
    ),
    stride=st.sampled_from([1, 2, 3]),
    with_b=st.booleans(),
    special=st.sampled_from([None, np.nan, np.inf, 3e38]),
    seed=st.integers(0, 2**31 - 1),
)
def test_texel_distance_equals_the_float64_definition(case, stride, with_b, special, seed):
    from optax_bilateral._src.filter import local

    shape, axes = case
    rng = np.random.default_rng(seed)
    a = rng.normal(size=shape).astype(np.float32)
    if special is not None:
        a.flat[rng.integers(a.size)] = special
    sub = a[tuple(slice(None, None, stride) if d in axes else slice(None) for d in range(a.ndim))]
    b = rng.normal(size=sub.shape).astype(np.float32) if with_b else None
    a_, b_ = jnp.asarray(a), None if b is None else jnp.asarray(b)
    got = local._native_distance(a_, b_, True, None, axes, stride, False, 1.0)
    assert (
        float(local._native_distance(a_, b_, jnp.asarray(False), None, axes, stride, False, 1.0))
        == 0
    )  # not run
    want = _texel_distance_float64(a, b, axes, stride)
    assert got.dtype == jnp.float32 and got.shape == ()
    # Sums in double: finite wherever the norms are (3e38 squared overflows float32 only).
    np.testing.assert_allclose(float(got), want, rtol=1e-6)
    if special != 3e38:  # the slices agree to float32 rounding
        slices = local._distance(
            jnp.asarray(a), None if b is None else jnp.asarray(b), axes, stride
        )
        np.testing.assert_allclose(float(got), float(slices), rtol=1e-5)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_texel_distance_keeps_the_subgrid_it_read(dtype):
    # keep=True: the mean and a's sub-grid from one call, the sub-grid equal to the slices'
    # (NaN and all), as is its derivative.
    from optax_bilateral._src.filter import local

    rng = np.random.default_rng(1)
    raw = rng.normal(size=(11, 9, 3))
    raw[3, 4, 1] = np.nan
    with jax_compat.enable_x64(dtype == jnp.float64):
        a = jnp.asarray(raw, dtype)
        for stride in (1, 2, 4):
            b = local.every(a, (0, 1), stride) * 0.5
            mean, kept = local.texel_distance_mean(a, b, (0, 1), stride, keep=True)
            assert kept.dtype == dtype
            np.testing.assert_array_equal(kept, local.every(a, (0, 1), stride))
            assert mean == local.texel_distance_mean(a, b, (0, 1), stride)
        grad = jax.grad(
            lambda x: jnp.sum(local.texel_distance_mean(x, None, (0,), 2, keep=True)[1])
        )
        np.testing.assert_array_equal(grad(a), jax.grad(lambda x: jnp.sum(x[::2]))(a))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_texel_distance_scales_itself_or_gives_its_fallback_without_work(dtype):
    # "auto"'s sigma_d on the native kernel: the contrast's call gives contrast_factor times
    # the mean where the guide is at rest, else the step's scale, an entry of the vector the
    # flag is read from (one call, no select kernel after it); bit-equal to the product and
    # the select, and differentiable in both.
    from optax_bilateral._src.filter import local

    with jax_compat.enable_x64(dtype == jnp.float64):
        a = jax.random.normal(jax.random.PRNGKey(4), (12, 10, 3), dtype)
        plain_mean = local.texel_distance_mean(a, None, (0, 1), 2)

        def chosen(a, at_rest, fallback):
            at_rest, fallback = numerics.one_kernel((at_rest, fallback))
            return local.texel_distance_mean(
                a, None, (0, 1), 2, at_rest, otherwise=fallback, scale=1.7
            )

        f = jax.jit(chosen)
        fallback = jnp.asarray(0.123, dtype)
        assert f(a, True, fallback) == jnp.asarray(1.7, dtype) * plain_mean
        assert f(a, False, fallback) == fallback
        for at_rest in (True, False):
            got = jax.grad(lambda a, s, r=at_rest: f(a, r, s * a[0, 0, 0]), argnums=(0, 1))(a, 2.0)
            want = jax.grad(
                lambda a, s, r=at_rest: jnp.where(
                    r, 1.7 * local._distance(a, None, (0, 1), 2), s * a[0, 0, 0]
                ),
                argnums=(0, 1),
            )(a, 2.0)
            for x, y in zip(got, want):
                np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-7)
    with pytest.raises(Exception, match="otherwise must be a float vector"):
        bad = numerics.Entry(jnp.zeros((1,)), 2, jnp.float32)
        jax.block_until_ready(native.texel_distance_mean(a, None, (0, 1), 2, False, otherwise=bad))


def test_texel_distance_differentiates_batches_and_leaves_none_out():
    from optax_bilateral._src.filter import local

    a = jax.random.normal(jax.random.PRNGKey(2), (12, 10, 3))
    b = jax.random.normal(jax.random.PRNGKey(3), (6, 5, 3))

    def native_distance(a, b, axes, stride):
        return local._native_distance(a, b, True, None, axes, stride, False, 1.0)

    for f in (native_distance, local._distance):
        assert float(f(jnp.full((4, 4), jnp.nan), None, (0, 1), 1)) == 0.0  # every texel NaN
    grads = [
        jax.grad(functools.partial(f, axes=(0, 1), stride=2), argnums=(0, 1))(a, b)
        for f in (native_distance, local._distance)
    ]
    for got, want in zip(*grads):
        assert np.any(np.asarray(want) != 0)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    batch = jnp.stack([a, 2 * a])
    np.testing.assert_allclose(
        jax.vmap(lambda a: native_distance(a, b, (0, 1), 2))(batch),
        [float(local._distance(x, b, (0, 1), 2)) for x in batch],
        rtol=1e-5,
    )


@settings(max_examples=25, deadline=None)
@given(
    case=st.sampled_from([((23, 1), (0,)), ((9, 8, 2), (0, 1)), ((5, 6, 7, 1), (0, 1, 2))]),
    smooth=st.integers(0, 3),
    correlated=st.floats(-1, 1),
    noisy=st.floats(0, 4),
    due=st.booleans(),
    stored=st.sampled_from([0.0, 1.0]),
    dtype=st.sampled_from([jnp.float32, jnp.float64]),
    seed=st.integers(0, 2**31 - 1),
)
def test_the_correlated_noise_test_answers_as_its_jax_form(
    case, smooth, correlated, noisy, due, stored, dtype, seed
):
    # "auto"'s correlated-noise test as one native call: its sums' test in the float
    # arithmetic of the JAX form (rules/auto.py, Auto._correlated_noise), the stored answer
    # where it is not due; equal to the bit (an answer, 1 or 0, at any threshold).
    from optax_bilateral._src.filter import local

    shape, axes = case
    rng = np.random.default_rng(seed)
    raw = rng.normal(size=shape)
    for a in axes[:1] * smooth:  # correlated along the first axis, more with each pass
        raw = raw + np.roll(raw, 1, axis=a)
    with jax_compat.enable_x64(dtype == jnp.float64):
        g = jnp.asarray(raw, dtype)
        m = jnp.asarray(0.3 * rng.normal(size=shape), dtype)
        observed = jnp.asarray(
            rng.random(shape[: len(axes)] + (1,) * (len(shape) - len(axes))) > 0.1
        )
        c1, lag = numerics.one_kernel((jnp.asarray(0.6, dtype), jnp.asarray(0.3, dtype)))
        stored_entry = numerics.Entry.of(jnp.asarray(stored, dtype))
        test = local.NoiseTest(correlated, noisy, lag, stored_entry)
        run = numerics.Entry.flag(jnp.asarray(due))
        got = local.correlated_noise(g, m, observed, c1, axes, 1, run, math.inf, test)
        lags, (noise, signal) = local.correlation_sums(g, m, observed, c1, axes, 1)
        den = jnp.sqrt(lags[:, 0] * lags[:, 1])
        corr = jnp.where(den > 0, lags[:, 2] / jnp.where(den > 0, den, 1), 0)
        x = lag.value.astype(dtype)
        answer = (jnp.mean(corr) >= correlated) & (noise > noisy * x * x * signal)
        want = jnp.where(due, answer.astype(dtype), stored)
        assert got.dtype == dtype and got.shape == ()
        assert float(got) == float(want), (float(jnp.mean(corr)), float(noise), float(signal))
        # At the threshold's edge: the mean itself, and the next float above it.
        mean = np.asarray(jnp.mean(corr))
        for edge in (mean, np.nextafter(mean, np.inf)):
            at_edge = test._replace(correlated=float(edge), noisy=0.0)
            got = local.correlated_noise(g, m, observed, c1, axes, 1, run, math.inf, at_edge)
            answer = (jnp.mean(corr) >= float(edge)) & (noise > 0.0 * x * x * signal)
            assert float(got) == float(jnp.where(due, answer.astype(dtype), stored))


def test_the_correlated_noise_test_refuses_what_it_cannot_read():
    from optax_bilateral._src.filter import local

    g = jnp.ones((6, 5, 1))
    c1, lag = numerics.one_kernel((jnp.float32(0.5), jnp.float32(0.2)))
    run = numerics.Entry.flag(True)
    stored = numerics.Entry.of(jnp.float32(0))
    test = local.NoiseTest(0.5, 0.25, lag, stored)
    with pytest.raises(ValueError, match="one vector"):
        other = numerics.Entry.of(jnp.float32(0.2))
        local.correlated_noise(g, g, g > 0, c1, (0, 1), 1, run, math.inf, test._replace(lag=other))
    with pytest.raises(ValueError, match="at least one pair axis"):
        local.correlated_noise(
            jnp.ones((1, 1, 2)), jnp.ones((1, 1, 2)), True, c1, (0, 1), 1, run, math.inf, test
        )
    bad = test._replace(stored=numerics.Entry(stored.vector, 4, jnp.float32))
    with pytest.raises(Exception, match="lag and stored must be float vectors"):
        jax.block_until_ready(
            local.correlated_noise(g, g, g > 0, c1, (0, 1), 1, run, math.inf, bad)
        )


def _correlation_float64(z, y, axes, stride):
    """The sums by their definition in float64: the pairs (q k, q k + 1) along each axis."""
    z, y = np.asarray(z, np.float64), np.asarray(y, np.float64)
    q, lags = max(stride, 2), []
    for a in (a for a in axes if z.shape[a] > 1):
        x = z[
            tuple(
                slice(None, None, stride) if d in axes and d != a else slice(None)
                for d in range(z.ndim)
            )
        ]
        n = x.shape[a] // q
        x0 = np.take(x, np.arange(n) * q, axis=a)
        x1 = np.take(x, np.arange(n) * q + 1, axis=a)
        lags.append([np.sum(x0 * x0), np.sum(x1 * x1), np.sum(x0 * x1)])
    sub = tuple(slice(None, None, stride) if d in axes else slice(None) for d in range(z.ndim))
    return np.reshape(lags, (-1, 3)), np.array([np.sum(z[sub] ** 2), np.sum(y[sub] ** 2)])


@settings(max_examples=12)
@given(
    case=st.sampled_from(
        [((9,), (0,)), ((7, 5, 3), (0, 1)), ((3, 6, 11), (1, 2)), ((4, 1, 5, 2), (2, 0, 1))]
    ),
    stride=st.sampled_from([1, 2, 3, 4]),
    seed=st.integers(0, 2**31 - 1),
)
def test_correlation_sums_equal_the_float64_definition(case, stride, seed):
    # z = g - m / c1 and y = m / c1 where observed (a mask broadcast along the last axis),
    # else 0: computed in float32 as the rule does, summed in float64 by the definition.
    from optax_bilateral._src.filter import local

    shape, axes = case
    rng = np.random.default_rng(seed)
    g, m = (jnp.asarray(rng.normal(size=shape), jnp.float32) for _ in range(2))
    observed = jnp.asarray(rng.random(shape[:-1] + (1,)) < 0.8)
    c1 = jnp.float32(0.3)
    y = np.where(observed, m / c1, 0)
    z = np.where(observed, g - m / c1, 0)
    lags, energies = local.correlation_sums(g, m, observed, c1, axes, stride)
    want_lags, want_energies = _correlation_float64(z, y, axes, stride)
    assert lags.shape == want_lags.shape  # an axis of length 1 has no pairs
    # z from float32 operations (C++ here, XLA in the test: an ulp apart at most); a cross
    # sum that cancels is then off by about float32 rounding of its terms, not of itself.
    scale = float(np.max(want_lags)) if want_lags.size else 1.0
    np.testing.assert_allclose(lags, want_lags, rtol=1e-6, atol=1e-6 * scale)
    np.testing.assert_allclose(energies, want_energies, rtol=1e-6)
    skipped = local.correlation_sums(g, m, observed, c1, axes, stride, run=jnp.asarray(False))
    assert not np.any(np.asarray(skipped[0])) and not np.any(np.asarray(skipped[1]))
    with pytest.MonkeyPatch.context() as patch:  # the slices' sums
        patch.setattr(native, "takes_subgrid", lambda x: False)
        slices = local.correlation_sums(g, m, observed, c1, axes, stride)
    np.testing.assert_allclose(lags, slices[0], rtol=1e-5, atol=1e-6 * scale)
    np.testing.assert_allclose(energies, slices[1], rtol=1e-5)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_correlation_sums_clip_the_given_gradient_where_they_read_it(dtype):
    # The gradient as given (NaN and inf where unobserved, huge where observed) with the
    # step's limit: the same sums as of the observed, clipped gradient, to the bit.
    from optax_bilateral._src.filter import local

    rng = np.random.default_rng(0)
    shape, axes, limit = (12, 10, 3), (0, 1), 2.5
    raw = rng.normal(size=shape) * 3
    raw[rng.random(shape) < 0.2] = 1e30
    observed = rng.random(shape[:-1] + (1,)) < 0.8
    raw = np.where(observed, raw, np.where(rng.random(shape) < 0.5, np.nan, -np.inf))
    with jax_compat.enable_x64(dtype == jnp.float64):
        g = jnp.asarray(raw, dtype)
        m = jnp.asarray(rng.normal(size=shape), dtype)
        mask, c1 = jnp.asarray(observed), jnp.asarray(0.3, dtype)
        clipped = jnp.clip(jnp.where(mask, g, 0), -limit, limit)
        for stride in (1, 2, 3):
            got = local.correlation_sums(g, m, mask, c1, axes, stride, limit=limit)
            want = local.correlation_sums(clipped, m, mask, c1, axes, stride)
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
                assert np.all(np.isfinite(np.asarray(a)))
            with pytest.MonkeyPatch.context() as patch:  # the slices' sums clip alike
                patch.setattr(native, "takes_subgrid", lambda x: False)
                slices = local.correlation_sums(g, m, mask, c1, axes, stride, limit=limit)
            np.testing.assert_allclose(got[0], slices[0], rtol=1e-5)
            np.testing.assert_allclose(got[1], slices[1], rtol=1e-5)


@pytest.mark.parametrize("drop_zero", [False, True])
@pytest.mark.parametrize(
    "shape, axes",
    [((12, 10, 3), (0, 1)), ((3, 9, 8), (1, 2)), ((16, 11, 1), (0, 1)), ((40,), (0,))],
)
def test_the_noise_calls_make_the_texels_mask_from_the_given_gradient(shape, axes, drop_zero):
    # native.FromGradient: each texel observed where all its channels of the gradient as given
    # are finite and, with drop_zero, not all 0 (as observe makes the mask): the same sums and
    # answer, to the bit, as with that mask passed in; drop_zero changes them.
    rng = np.random.default_rng(1)
    channels = tuple(a for a in range(len(shape)) if a not in axes)
    texel_shape = tuple(1 if a in channels else n for a, n in enumerate(shape))
    raw = rng.normal(size=shape) * 3
    pick = rng.random(shape)
    raw[pick < 0.05], raw[(pick >= 0.05) & (pick < 0.08)] = np.nan, -np.inf
    raw[(pick >= 0.08) & (pick < 0.2)] = 0.0
    raw = np.where(rng.random(texel_shape) < 0.2, 0.0, raw)  # whole texels of 0
    finite = np.all(np.isfinite(raw), axis=channels, keepdims=True)
    zero = np.all(raw == 0, axis=channels, keepdims=True)
    g = jnp.asarray(raw, jnp.float32)
    m = jnp.asarray(rng.normal(size=shape), jnp.float32)
    c1, lag = numerics.one_kernel((jnp.float32(0.6), jnp.float32(0.3)))
    pairs = tuple(a for a in axes if shape[a] > 1)
    mask = jnp.asarray(finite & ~(drop_zero & zero))
    for stride in (1, 2):
        sums = functools.partial(
            native.correlation_sums,
            g,
            m,
            c1=c1,
            axes=axes,
            pair_axes=pairs,
            stride=stride,
            limit=2.0,
        )
        got, want = sums(native.FromGradient(drop_zero)), sums(mask)
        np.testing.assert_array_equal(got, want)
        assert np.all(np.isfinite(np.asarray(got)))
        if drop_zero:  # all-0 texels left out: y's energy changes
            assert not np.array_equal(got, sums(native.FromGradient(False)))
    test = native.NoiseTest(0.0, 0.0, lag, numerics.Entry.of(jnp.float32(0.5)))
    answers = [
        native.correlated_noise(g, m, obs, c1, axes, pairs, 1, numerics.Entry.flag(True), 2.0, test)
        for obs in (native.FromGradient(drop_zero), mask)
    ]
    assert float(answers[0]) == float(answers[1]) in (0.0, 1.0)


def test_the_defaults_write_no_texel_mask_for_a_one_channel_leaf():
    # The correlated-noise call makes the texels' mask from the gradient where it reads it: on
    # a one-channel leaf (where the moments' selects fuse the mask into their kernels) the
    # compiled update writes no bool array of the leaf's shape.
    import optax_bilateral as ob

    x = jnp.linspace(0.0, 1.0, 32 * 32).reshape(32, 32, 1)
    opt = ob.bilateral_adam(0.02)
    state = opt.init(x)
    compiled = jax.jit(opt.update).lower(x, state, x).compile().as_text()
    entry = compiled[compiled.index("\nENTRY") :]
    assert native.NOISE_TEST_TARGET in entry
    assert "pred[32,32,1]" not in entry and "pred[32,32]" not in entry


@pytest.mark.parametrize("limit", [0.0, -1.0, float("nan")])
def test_correlation_sums_refuse_a_limit_that_is_not_positive(limit):
    g = jnp.ones((6, 5, 2))
    with pytest.raises(ValueError, match="limit must be > 0"):
        native.correlation_sums(
            g, g, jnp.ones((6, 5, 1), bool), 1.0, (0, 1), (0, 1), 1, limit=limit
        )


def test_correlation_sums_refuse_a_mask_that_does_not_broadcast():
    g = jnp.ones((6, 5, 2))
    with pytest.raises(Exception, match="observed mask"):
        native.correlation_sums(g, g, jnp.ones((6, 4, 1), bool), 1.0, (0, 1), (0, 1), 1)


def test_native_statistics_read_their_flags_and_c1_from_one_vector_of_scalars():
    # numerics.one_kernel's vector: each call reads its `run` flag (nonzero: run) and the
    # correlation sums their c1 at an entry of it, as from scalars of their own.
    from optax_bilateral._src.filter import local
    from optax_bilateral._src.numerics import Entry
    from optax_bilateral._src.rules import auto

    rng = np.random.default_rng(0)
    shape, axes = (12, 10, 3), (0, 1)
    g, m = (jnp.asarray(rng.normal(size=shape), jnp.float32) for _ in range(2))
    observed = jnp.asarray(rng.random(shape[:-1] + (1,)) < 0.8)
    vector = jnp.asarray([0.3, 0.0, 1.0], jnp.float32)
    on, off = Entry(vector, 2, jnp.dtype(bool)), Entry(vector, 1, jnp.dtype(bool))
    c1 = Entry(vector, 0, jnp.dtype(jnp.float32))
    want = local.correlation_sums(g, m, observed, jnp.float32(0.3), axes, 2)
    got = local.correlation_sums(g, m, observed, c1, axes, 2, run=on)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    skipped = local.correlation_sums(g, m, observed, c1, axes, 2, run=off)
    assert not any(np.any(np.asarray(x)) for x in skipped)
    assert float(local.texel_distance_mean(g, None, axes, 2, run=off)) == 0
    assert float(local.texel_distance_mean(g, None, axes, 2, run=jnp.int32(0))) == 0  # a bool
    np.testing.assert_array_equal(
        local.texel_distance_mean(g, None, axes, 2, run=on),
        local.texel_distance_mean(g, None, axes, 2),
    )
    (average,) = local.local_average_subgrid((g,), axes, 2, run=off)
    assert not np.any(np.asarray(average))
    rule, bm, v, residual, scalars = _blend_case(0, stride=1)  # the rule's stride at 24x20
    blend = functools.partial(auto.blend_weights, rule, auto.Moments(bm, v, bm, True), residual)
    lam, gate = blend(scalars, axes, run=off)
    assert not np.any(np.asarray(lam)) and float(gate) == 0
    for a, b in zip(blend(scalars, axes, run=on), blend(scalars, axes), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(Exception, match="run must be a bool or float vector"):
        past = Entry(vector, 3, jnp.dtype(bool))  # past the vector's end
        jax.block_until_ready(local.texel_distance_mean(g, None, axes, 2, run=past))


def test_one_kernel_computes_the_steps_scalars_in_one_xla_kernel():
    # Powers, quotients and comparisons of the step count, read by one full-size kernel: XLA
    # computes each that an expensive operation produces in a kernel of its own, unless they
    # come as one_kernel's vector.
    import re

    def program(pack):
        def f(count, x):
            t = count.astype(jnp.float32)
            c1, c2 = 1 - 0.9**t, 1 - 0.999**t
            xs = (c1, c2, 1 / c1, 1 / c2, (count % 8 == 0) | (count == 2), count > 1)
            if pack:
                xs = tuple(e.value for e in numerics.one_kernel(xs))
            a, b, ia, ib, due, usable = xs
            return jnp.where(due & usable, x * ia + b, x * ib - a)

        return f

    x = jnp.linspace(0.0, 1.0, 64)
    kernels, outs = [], []
    for pack in (False, True):
        compiled = jax.jit(program(pack)).lower(jnp.int32(8), x).compile()
        kernels.append(len(re.findall(r"= \S+ fusion\(", compiled.as_text())))
        outs.append(compiled(jnp.int32(8), x))
    # The same formulas; XLA may simplify them otherwise around the vector (an ulp).
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-6)
    assert kernels[1] == 2 < kernels[0]  # the vector, and the kernel that reads it


@pytest.mark.parametrize(
    "xs, error",
    [
        ((jnp.int32(1), jnp.float32(1)), TypeError),
        ((jnp.zeros(2), jnp.float32(1)), TypeError),
        (tuple(jnp.float32(k) for k in range(9)), ValueError),
        ((), ValueError),
    ],
)
def test_one_kernel_refuses_what_it_cannot_hold(xs, error):
    with pytest.raises(error, match="one_kernel takes"):
        numerics.one_kernel(xs)


def _blend_case(seed, shape=(24, 20, 3), stride=2, count=9, scale=3.0):
    """A postfilter leaf's moments and residual (of size ``scale``) at step ``count``, and
    the rule's scalars: at scale 3 most weights lie inside (0, 1), some are 0."""
    import optax_bilateral as ob
    from optax_bilateral._src.rules.sigma import StepContext

    rng = np.random.default_rng(seed)
    m = jnp.asarray(rng.normal(size=shape), jnp.float32)
    v = jnp.asarray(rng.random(shape) + np.asarray(m) ** 2 * rng.random(shape), jnp.float32)
    sub = tuple(slice(None, None, stride) if d < 2 else slice(None) for d in range(len(shape)))
    residual = jnp.asarray(rng.normal(size=np.asarray(m)[sub].shape) * scale, jnp.float32)
    rule = ob.Auto()
    b1, t = 0.9, jnp.asarray(count)
    ctx = StepContext(t, b1, 1 - b1 ** t.astype(jnp.float32), 1 - 0.999 ** t.astype(jnp.float32))
    return rule, m, v, residual, rule._blend_scalars(ctx, jnp.float32)


@pytest.mark.parametrize("count", [1, 2, 9, 40])  # 1: no memory yet, every weight 0
def test_blend_equals_the_rules_formula_in_jax(count):
    import functools

    from optax_bilateral._src.filter import local
    from optax_bilateral._src.rules import auto

    opened = []
    for seed in range(3):
        rule, m, v, residual, scalars = _blend_case(seed, count=count)
        reference = functools.partial(auto._blend_reference, rule, axes=(0, 1), stride=2)
        low, high = rule.gate_bounds
        constants = (rule.gain, rule.power, low, high - low)
        how = local.BlendCall((0, 1), 2, constants, reference)
        lam, gate = local._native_blend(m, v, residual, scalars, True, how)
        want_lam, want_gate = reference(m, v, residual, scalars)
        # run=False: zeros, not computed (the rule selects its own zeros there).
        skipped = local._native_blend(m, v, residual, scalars, jnp.asarray(False), how)
        assert not np.any(np.asarray(skipped[0])) and float(skipped[1]) == 0
        assert lam.shape == residual.shape and gate.shape == ()
        np.testing.assert_allclose(float(gate), float(want_gate), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(lam, want_lam, rtol=1e-5, atol=1e-6)
        opened.append(float(want_gate) > 0 and bool(np.any(np.asarray(want_lam) > 0)))
        if count == 1:
            assert not np.any(np.asarray(lam))
    if count == 40:  # the gate open: the weights themselves are compared
        assert any(opened)


def test_blend_differentiates_and_batches_as_the_rules_formula():
    import functools

    from optax_bilateral._src.filter import local
    from optax_bilateral._src.rules import auto

    rule, m, v, residual, scalars = _blend_case(0, shape=(12, 10, 2), scale=10.0)
    rule = type(rule)(gate_bounds=(0.0, 1.0))  # a gate that opens with any weight
    reference = functools.partial(auto._blend_reference, rule, axes=(0, 1), stride=2)
    constants = (rule.gain, rule.power, 0.0, 1.0)

    def loss(f):
        return lambda m, v: jnp.sum(f(m, v, residual, scalars)[0] ** 2)

    def native_blend(m, v, residual, scalars):
        how = local.BlendCall((0, 1), 2, constants, reference)
        return local._native_blend(m, v, residual, scalars, True, how)

    got = jax.grad(loss(native_blend), argnums=(0, 1))(m, v)
    want = jax.grad(loss(reference), argnums=(0, 1))(m, v)
    for a, b in zip(got, want):
        assert np.any(np.asarray(b) != 0)
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    batched = jax.vmap(lambda m: native_blend(m, v, residual, scalars)[1])(jnp.stack([m, 2 * m]))
    np.testing.assert_allclose(
        batched, [float(reference(x, v, residual, scalars)[1]) for x in (m, 2 * m)], rtol=1e-5
    )


def _step_parts(seed, shape, axes, stride, dtype, computed=True, gate=0.5, drop_zero=False):
    """A postfilter step's parts (sigma_d="auto"'s direction reads them, native.step_norm):
    moments and their filtered ones, the blend's weight at the sub-grid, and the observed mask
    with the gradient it comes from (a tenth of the texels with a NaN or an infinite entry,
    a tenth all 0: unobserved with drop_zero, as mask_unobserved); the step's flags; the call's
    fixed part with the rule's JAX form (auto._step_norm_reference) as its derivative."""
    from optax_bilateral._src.filter import layout
    from optax_bilateral._src.rules import auto

    rng = np.random.default_rng(seed)
    m = rng.normal(size=shape)
    v = rng.random(shape) + m**2 * rng.random(shape)
    bm, bv = m * rng.random(shape), v * (0.5 + rng.random(shape))
    sub = tuple(slice(None, None, stride) if d in axes else slice(None) for d in range(len(shape)))
    lam = rng.random(m[sub].shape)
    grad = rng.normal(size=shape)
    texel = tuple(n if d in axes else 1 for d, n in enumerate(shape))
    which = np.broadcast_to(rng.random(texel), shape)
    grad = np.where(which < 0.1, 0.0, grad)  # whole texels of 0
    grad[rng.random(shape) < 0.1 / max(1, grad.size // np.prod(texel))] = np.nan
    grad[(which > 0.95) & (rng.random(shape) < 0.5)] = -np.inf
    given = jnp.asarray(grad, dtype)
    spatial = tuple(sorted(axes))
    texels = layout.texel_mask(jnp.isfinite(given), spatial)
    if drop_zero:
        texels = texels & ~layout.texel_mask(given == 0, spatial)
    observed = layout.expand_mask(texels, len(shape), spatial)
    parts = [jnp.asarray(x, dtype) for x in (m, v, bm, bv, lam)] + [observed]
    inv_c1, inv_c2, done = numerics.one_kernel(
        (jnp.asarray(1 / 0.271, dtype), jnp.asarray(1 / 0.0199, dtype), jnp.asarray(computed))
    )
    flags = native.StepFlags.of(inv_c1, inv_c2, done, jnp.asarray(gate, dtype))
    where = auto._SubgridStep(tuple(axes), stride, 1e-8, 0.0)
    reference = functools.partial(auto._step_norm_reference, where=where)
    return parts, given, flags, native.StepCall(*where, drop_zero, reference)


STEP_GRIDS = [
    ((24, 20, 3), (0, 1), 2),
    ((16, 12, 2), (0, 1), 1),
    ((9, 7, 5, 1), (0, 1, 2), 2),
    ((33,), (0,), 4),  # 1-D, no channel axis
    ((3, 10, 11), (1, 2), 3),  # channels first
]


@pytest.mark.parametrize("shape, axes, stride", STEP_GRIDS)
@pytest.mark.parametrize("computed, gate", [(True, 0.5), (True, 0.0), (False, 0.5)])
def test_step_norm_equals_the_step_at_the_subgrid_in_jax(shape, axes, stride, computed, gate):
    # The blend taken (computed, the gate open), its statistics computed with the gate still
    # shut (a CHECK step), and neither; all-zero texels observed or not (mask_unobserved):
    # equal to the postfilter's step computed at the sub-grid and its mean texel norm, which
    # the update took before (the goldens hold the update's bits).
    from optax_bilateral._src.filter import local

    for seed, drop_zero in ((0, False), (1, True)):
        case = _step_parts(seed, shape, axes, stride, jnp.float32, computed, gate, drop_zero)
        parts, given, flags, how = case
        got = local.step_norm(tuple(parts), given, flags, how)
        want = how.reference(*parts, flags)
        assert got.dtype == jnp.float32 and got.shape == ()
        assert float(want) > 0
        np.testing.assert_allclose(float(got), float(want), rtol=1e-6)
    # Without a blend's weight (the rule's blend off): B m and B v as they are.
    parts[4] = None
    np.testing.assert_allclose(
        float(local.step_norm(tuple(parts), given, flags, how)),
        float(how.reference(*parts, flags)),
        rtol=1e-6,
    )


@pytest.mark.parametrize("eps_root", [0.0, 1e-4])
def test_step_norm_in_float64_and_at_its_edges(eps_root):
    # float64, eps_root > 0; a NaN in B m leaves its texel out (NaN norm), v~ = 0 with eps = 0
    # gives d = 0 (no 0/0), a grid of NaN texels alone gives 0, and a gradient of no finite
    # texel (none observed) gives 0.
    from optax_bilateral._src.filter import local
    from optax_bilateral._src.rules import auto

    def with_eps(how, eps, eps_root):
        where = auto._SubgridStep(how.axes, how.stride, eps, eps_root)
        return how._replace(
            eps=eps,
            eps_root=eps_root,
            reference=functools.partial(auto._step_norm_reference, where=where),
        )

    with jax_compat.enable_x64():
        parts, given, flags, how = _step_parts(3, (12, 10, 2), (0, 1), 2, jnp.float64)
        how = with_eps(how, 1e-8, eps_root)
        parts[2] = parts[2].at[2, 4, 1].set(jnp.nan)
        got = local.step_norm(tuple(parts), given, flags, how)
        assert got.dtype == jnp.float64
        np.testing.assert_allclose(float(got), float(how.reference(*parts, flags)), rtol=1e-13)
        zero = with_eps(how, 0.0, 0.0)
        m, v, bm, bv, _, observed = parts
        flat = (m, jnp.zeros_like(v), bm, jnp.zeros_like(bv), None, observed)
        assert float(local.step_norm(flat, given, flags, zero)) == 0.0
        assert float(zero.reference(*flat, flags)) == 0.0
        nan = (m, v, jnp.full_like(bm, jnp.nan), bv, None, observed)
        assert float(local.step_norm(nan, given, flags, how)) == 0.0
        none = jnp.full_like(given, jnp.inf)
        assert float(local.step_norm(tuple(parts), none, flags, how)) == 0.0


def test_step_norm_differentiates_and_batches_as_its_jax_form():
    from optax_bilateral._src.filter import local

    parts, given, flags, how = _step_parts(1, (12, 10, 2), (0, 1), 2, jnp.float32)
    m, v, bm, bv, lam, observed = parts

    def loss(f):
        return lambda m, bm, lam: f(m, v, bm, bv, lam, observed, flags) ** 2

    native_norm = lambda *a: local.step_norm(a[:6], given, a[6], how)
    got = jax.grad(loss(native_norm), argnums=(0, 1, 2))(m, bm, lam)
    want = jax.grad(loss(how.reference), argnums=(0, 1, 2))(m, bm, lam)
    for a, b in zip(got, want):
        assert np.any(np.asarray(b) != 0)
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    batched = jax.vmap(lambda m: native_norm(m, v, bm, bv, lam, observed, flags))(
        jnp.stack([m, 2 * m])
    )
    want = [float(how.reference(x, v, bm, bv, lam, observed, flags)) for x in (m, 2 * m)]
    np.testing.assert_allclose(batched, want, rtol=1e-6)


def test_step_norm_refuses_operands_it_cannot_read():
    parts, given, flags, how = _step_parts(0, (8, 6, 2), (0, 1), 2, jnp.float32)
    m, v, bm, bv, lam, _ = parts
    call = lambda *a, flags=flags: native.step_norm(*a, flags, how)
    with pytest.raises(Exception, match="lam must have the sub-grid's shape"):
        call(m, v, bm, bv, given, lam[:-1])
    with pytest.raises(Exception, match="m, v, B m, B v and the gradient must share"):
        call(m, v, bm[:, :-1], bv, given, lam)
    with pytest.raises(Exception, match="m, v, B m, B v and the gradient must share"):
        call(m, v, bm, bv, given.astype(jnp.bfloat16), lam)
    with pytest.raises(Exception, match="scalars must be a float vector"):
        call(m, v, bm, bv, given, lam, flags=dataclasses.replace(flags, inv_c2_at=3))
    with pytest.raises(ValueError, match="entries of one vector"):
        one, two = numerics.one_kernel((jnp.float32(1),)), numerics.one_kernel((jnp.float32(2),))
        native.StepFlags.of(one[0], two[0], one[0], jnp.float32(0))


@pytest.mark.parametrize(
    "make",
    [
        lambda ob, optax: ob.sparse_adam(0.02),  # B m boosted: from the step at the sub-grid
        lambda ob, optax: optax.chain(
            ob.postfilter(second_moment="uniform"), optax.scale_by_learning_rate(0.02)
        ),
        lambda ob, optax: optax.inject_hyperparams(ob.bilateral_adam)(0.02, eps=1e-8),
    ],
)
def test_the_step_norm_reads_the_parts_only_where_they_are_the_steps(make):
    # The native norm reads B m, B v and the sub-grid's weight as buffers; where the step's
    # B m is a product (sparse_adam's boost), its second moment one for the leaf, or Adam's
    # eps traced, "auto"'s direction comes from the step computed at the sub-grid.
    import optax

    import optax_bilateral as ob

    x = jnp.ones((40, 40, 3))
    opt = make(ob, optax)
    state = opt.init(x)
    text = jax.jit(opt.update).lower(x, state, x).as_text()
    assert native.STEP_NORM_TARGET not in text
    assert native.TEXEL_MEAN_TARGET in text


# The optimizers' non-finite counts (numerics.count_nonfinite): one FFI call for every leaf.
COUNT_SHAPES = [(), (7,), (3, 5, 2), (0, 4)]
SPECIALS = [np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-45, 3e38, -2.0]


@settings(max_examples=15, deadline=None)
@given(
    dtype=st.sampled_from([jnp.float16, jnp.bfloat16, jnp.float32, jnp.complex64]),
    seed=st.integers(0, 2**31 - 1),
)
def test_nonfinite_counts_equal_jnp_on_drawn_arrays(dtype, seed):
    # Real parts and imaginary parts drawn apart: a complex entry counts once.
    rng = np.random.default_rng(seed)

    def draw(shape):
        x = rng.choice(SPECIALS, size=shape) * rng.choice([1.0, 7.5], size=shape)
        if dtype == jnp.complex64:
            x = x + 1j * rng.choice(SPECIALS, size=shape)
        return jnp.asarray(x).astype(dtype)  # 3e38 overflows the half formats to inf

    xs = [draw(s) for s in COUNT_SHAPES]
    got = jax.jit(numerics.count_nonfinite)(xs)
    assert jax.jit(numerics.count_nonfinite).lower(xs).as_text().count(numerics.COUNT_TARGET) == 1
    for x, n in zip(xs, got):
        assert n.dtype == jnp.int32 and n.shape == ()
        assert int(n) == int(np.sum(~np.isfinite(np.asarray(x, np.complex128)))), x


@pytest.mark.parametrize("native", [True, False])
def test_nonfinite_counts_add_to_their_totals_saturating(native, monkeypatch):
    # The optimizers' running counts: the same FFI call adds each count to its total, at most
    # int32's maximum, as the jnp form does where the call does not run.
    if not native:
        monkeypatch.setattr(numerics, "_counts_natively", lambda x: False)
    top = np.iinfo(np.int32).max
    xs = [jnp.asarray([np.nan, 1.0, np.inf]), jnp.asarray([1.0, 2.0]), jnp.asarray([np.nan] * 4)]
    totals = [jnp.int32(5), jnp.int32(top - 1), jnp.int32(top - 4)]
    program = jax.jit(lambda xs, totals: numerics.count_nonfinite(xs, totals))  # traced here
    got = program(xs, totals)
    assert [int(n) for n in got] == [7, top - 1, top]
    assert all(n.dtype == jnp.int32 for n in got)
    assert (program.lower(xs, totals).as_text().count(numerics.COUNT_TARGET) == 1) == native
    # Batched: one total per batch element, unbatched totals broadcast.
    batched = jax.vmap(lambda x, t: numerics.count_nonfinite([x], [t])[0])
    got = batched(jnp.stack([xs[0], xs[0] * 0]), jnp.asarray([1, top], jnp.int32))
    np.testing.assert_array_equal(got, [3, top])
    with pytest.raises(ValueError, match="one total per array"):
        numerics.count_nonfinite(xs, totals[:2])


def test_nonfinite_counts_batch_and_are_not_differentiated():
    x = jnp.asarray([[1.0, np.nan, 2.0], [np.inf, -np.inf, np.nan]])
    count = lambda a, b: numerics.count_nonfinite([a, b])
    # Nested batches, one operand unbatched: a count per batch element.
    a, b = jax.vmap(jax.vmap(count, (0, None)), (0, None))(jnp.stack([x, x * 0]), x[0])
    np.testing.assert_array_equal(a, [[1, 3], [1, 3]])
    np.testing.assert_array_equal(b, [[1, 1], [1, 1]])
    # A meta-gradient through an update that counts: the count has no derivative.
    import optax_bilateral as ob

    opt = ob.bilateral_adam(0.1, sigma_d=0.2, spatial_axes=(0,))
    p = jnp.linspace(0.0, 1.0, 16)
    state = opt.init(p)

    def loss(g):
        u, s = opt.update(g, state, p)
        return jnp.sum(u) + jnp.sum(s[0].nonfinite_count)

    grad = jax.grad(loss)(jnp.sin(p).at[3].set(np.nan))
    assert bool(jnp.all(jnp.isfinite(grad)))


# The postfilter's order (numerics.after): one FFI call passes arrays through after a token.
def test_after_passes_arrays_through_unchanged_after_its_tokens():
    xs = (
        jnp.asarray([np.nan, -0.0, np.inf, 1e-45, -3e38], jnp.float32),
        jnp.arange(6.0, dtype=jnp.float64 if jax.config.jax_enable_x64 else jnp.float32),
        jnp.asarray([[1, -2], [3, 4]], jnp.int32),
        jnp.zeros((0, 3), jnp.float16),
    )
    tokens = {"direction": jnp.float32(0.5), "count": jnp.int32(3)}
    program = jax.jit(numerics.after)
    got = program(xs, tokens)
    for x, y in zip(xs, got, strict=True):
        assert y.dtype == x.dtype and y.shape == x.shape
        np.testing.assert_array_equal(np.asarray(y).view(np.uint8), np.asarray(x).view(np.uint8))
    compiled = program.lower(xs, tokens).compile().as_text()
    assert compiled.count(numerics.AFTER_TARGET) == 1
    assert "output_to_operand_aliasing" in compiled  # no copies: the outputs are the operands
    # Nothing to wait for (no array among the tokens), or nothing to pass: no call.
    assert numerics.after(xs, None) is xs and numerics.after((), tokens) == ()
    assert numerics.after(xs, (0.5, "a name", None)) is xs
    lowered = jax.jit(lambda x, t: numerics.after((x,), (t, 2.0, "a name"))).lower(xs[0], 1.0)
    assert lowered.as_text().count(numerics.AFTER_TARGET) == 1  # the traced token alone


def test_after_is_the_identity_under_grad_and_vmap():
    x = jnp.linspace(-1.0, 2.0, 12).reshape(3, 4)
    square_after_sum = lambda x: numerics.after((x * x,), jnp.sum(x))[0]
    np.testing.assert_allclose(jax.grad(lambda x: jnp.sum(square_after_sum(x)))(x), 2 * x)
    np.testing.assert_array_equal(jax.vmap(square_after_sum)(x), x * x)
    # A batched array after an unbatched token, and the reverse.
    a, b = jax.vmap(lambda r, t: numerics.after((r, x[0]), t), (0, None))(x, jnp.float32(1))
    np.testing.assert_array_equal(a, x)
    np.testing.assert_array_equal(b, jnp.broadcast_to(x[0], x.shape))
    (c,) = jax.vmap(lambda t: numerics.after((x,), t))(jnp.arange(3.0))
    np.testing.assert_array_equal(c, jnp.broadcast_to(x, (3, *x.shape)))


def test_the_after_target_copies_where_not_aliased_and_checks_sizes():
    # Called without aliases (XLA gives the output its own buffer), it copies its operand.
    x, token = jnp.arange(5.0), jnp.float32(0)
    copy = jax.ffi.ffi_call(numerics.AFTER_TARGET, jax.ShapeDtypeStruct(x.shape, x.dtype))
    np.testing.assert_array_equal(jax.jit(copy)(x, token), x)
    wrong = jax.ffi.ffi_call(numerics.AFTER_TARGET, jax.ShapeDtypeStruct((4,), x.dtype))
    with pytest.raises(Exception, match="each output must have its operand's dtype and size"):
        jax.block_until_ready(jax.jit(wrong)(x, token))
    several = jax.ffi.ffi_call(numerics.AFTER_TARGET, (jax.ShapeDtypeStruct(x.shape, x.dtype),) * 2)
    with pytest.raises(Exception, match="one operand per output, then the tokens"):
        jax.block_until_ready(jax.jit(several)(x))


def test_materialize_passes_arrays_through_in_one_call_without_tokens():
    xs = (jnp.asarray([np.nan, -0.0, np.inf, 1e-45], jnp.float32), jnp.arange(6, dtype=jnp.int32))
    program = jax.jit(numerics.materialize)
    for x, y in zip(xs, program(xs), strict=True):
        assert y.dtype == x.dtype and y.shape == x.shape
        np.testing.assert_array_equal(np.asarray(y).view(np.uint8), np.asarray(x).view(np.uint8))
    compiled = program.lower(xs).compile().as_text()
    assert compiled.count(numerics.AFTER_TARGET) == 1 and "output_to_operand_aliasing" in compiled
    assert numerics.materialize(()) == ()
    x = jnp.linspace(-1.0, 2.0, 12).reshape(3, 4)
    twice = lambda x: numerics.materialize((x * x,))[0]
    np.testing.assert_allclose(jax.grad(lambda x: jnp.sum(twice(x)))(x), 2 * x)
    np.testing.assert_array_equal(jax.vmap(twice)(x), x * x)


def _kernels_reading(compiled: str, parameter: int) -> list[str]:
    """The result shapes of the compiled program's kernels (fusions) that read its entry's
    ``parameter``-th parameter (found by number: JAX versions name them differently)."""
    entry = compiled[compiled.index("ENTRY") :].splitlines()
    (name,) = [line.split("=")[0].strip() for line in entry if f" parameter({parameter})" in line]
    return [
        line.split("=")[1].split("{")[0].strip()
        for line in entry
        if " fusion(" in line
        and name in re.findall(r"%[\w.\-]+", line.split(" fusion(")[1].split(")")[0])
    ]


def test_a_pyramids_levels_are_computed_once_each():
    # XLA's CPU fusion had recomputed every finer level inside each coarser one and inside
    # each of Adam's reads (docs/research/camera_distance.md, cost): each level now reads
    # the one before it (each axis's pass written once), and the grid is read by the first
    # level's first pass alone.
    import optax

    from optax_bilateral._src.optimizer.pyramid import pyramid_reconstruct, pyramid_transpose

    g = jnp.ones((64, 64, 3), jnp.float32)
    adam = optax.scale_by_adam()
    state = adam.init(pyramid_transpose(g, 4, (0, 1))[1:])
    down = jax.jit(lambda g, s: adam.update(pyramid_transpose(g, 4, (0, 1))[1:], s)[0])
    compiled = down.lower(g, state).compile().as_text()
    assert compiled.count(numerics.AFTER_TARGET) == 6  # 3 levels, 2 axes
    assert set(_kernels_reading(compiled, 0)) == {"f32[32,64,3]"}
    coefficients = tuple(pyramid_transpose(g, 4, (0, 1)))
    up = jax.jit(lambda c: pyramid_reconstruct(c, (0, 1)))
    compiled = up.lower(coefficients).compile().as_text()
    assert compiled.count(numerics.AFTER_TARGET) == 2
    assert len(_kernels_reading(compiled, 3)) == 1  # the coarsest level: one upsampling


def test_the_pyramids_vjp_passes_its_boundaries():
    # jax.vjp of the reconstruction, through its pass-through calls, is its transpose.
    from optax_bilateral._src.optimizer.pyramid import pyramid_reconstruct, pyramid_transpose

    g = jax.random.normal(jax.random.PRNGKey(0), (17, 12, 2))
    coefficients = pyramid_transpose(g, 3, (0, 1))
    _, vjp = jax.vjp(lambda c: pyramid_reconstruct(c, (0, 1)), coefficients)
    for got, want in zip(vjp(g)[0], coefficients, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    "make, ordered",
    [
        (lambda ob: ob.bilateral_adam(0.02), True),  # "auto" reads its parts, not the step
        (lambda ob: ob.bilateral_adam(0.02, sigma_d=0.2), False),  # a rule that reads it
    ],
)
def test_the_step_runs_after_a_read_that_did_not_need_it(make, ordered):
    # The postfilter computes the whole step after the rule's read where the read computed its
    # own (then its last kernel may write over B m or B v, docs/performance.md); where the
    # read took the whole step, that one step, unordered.
    import optax_bilateral as ob

    params = jnp.linspace(0.0, 1.0, 48 * 48 * 2).reshape(48, 48, 2)
    opt = make(ob)
    state = opt.init(params)
    text = jax.jit(opt.update).lower(params, state, params).as_text()
    assert (numerics.AFTER_TARGET in text) == ordered
