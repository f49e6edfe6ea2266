"""The library against a float64 port of the authors' code (tests/authors_reference.py).

Everything here runs with ``jax_enable_x64`` (a module-scoped fixture that restores
the previous setting), so the comparisons are float64 against float64: 1e-12 leaves
room for the different summation orders (the port sums taps in its own order, the
library in its own) and nothing else.

Mapping (docs/triangle_mesh.md and the ``levels`` docstrings state it): their
``stride_levels = L`` is ``levels = L - 1`` here; their kernel divides by
``sigma_d + eps`` (:func:`authors_reference.kernel_sigma`), so the library gets that
value as ``sigma_d``; their mesh ``M`` for ``alpha = lambda / (1 + lambda)`` is
``(I + lambda L) / (1 + lambda)``, tested below against the library's ``I + lambda L``.

The authors' grid options are checked against the library too: ``cross_term_off``
(``guide="self"``: every level guided by its own input), ``mtfilter`` / ``vtfilter``
(``filter_m`` / ``filter_v``), the uniform second moment (``second_moment="uniform"``);
their coupled ``weight_decay`` against a chain with ``optax.add_decayed_weights``, and
the library's decoupled one against ``optax.adamw``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import authors_reference as ref
import optax_bilateral as ob

TOL = 1e-12


@pytest.fixture(scope="module", autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


def close(a, b, tol=TOL):
    """|a - b| <= tol relative to the larger of 1 and max |b|."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(1.0, float(np.abs(b).max()))
    err = float(np.abs(a - b).max())
    assert err <= tol * scale, f"max |diff| {err:.3g} > {tol:g} * {scale:.3g}"


def rand(shape, seed, lo=None, hi=None):
    rng = np.random.default_rng(seed)
    if lo is None:
        return rng.standard_normal(shape)
    return rng.uniform(lo, hi, shape)


def edged(shape, seed):
    """A field in (0.05, 1) with a sharp step across the grid: weights that matter."""
    x = rand(shape, seed, 0.05, 0.5)
    sl = (slice(None), slice(shape[1] // 2, None))
    x[sl] += 0.5
    return x


# --- the kernels ------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(9, 7, 1), (9, 7, 3)])
def test_filter_chain_matches_full_mode(shape):
    """Their kernels chained over strides 0, 1, 2 = the library's full mode, levels 2.
    (3-D: through the volume optimizer below; each 3-D full-mode program takes tens of
    seconds to compile.)"""
    x, p = rand(shape, 1), edged(shape, 2)
    n = len(shape) - 1
    sigma = 0.3
    theirs = ref.filter_chain(x, p, 3, sigma)
    ours = ob.atrous_bilateral(
        jnp.asarray(x),
        jnp.asarray(p),
        sigma_d=ref.kernel_sigma(sigma, n, shape[-1]),
        levels=2,
        spatial_axes=tuple(range(n)),
        separable=False,
    )
    close(ours, theirs)


def test_stride_zero_level_is_the_identity():
    x, p = rand((7, 6, 3), 3), edged((7, 6, 3), 4)
    close(ref.filter_level(x, p, 0, 0.2), x, 1e-15)
    close(ref.filter_chain(x, p, 1, 0.2), x, 1e-15)


# --- the grid optimizers ------------------------------------------------------------


def run_library(opt, params, grads):
    state = opt.init(params)
    update = jax.jit(opt.update)
    out = []
    for g in grads:
        u, state = update(g, state, params)
        params = optax.apply_updates(params, u)
        out.append(params)
    return out


def assert_follows_reference(opt, p0, grads, **step):
    """The library's iterates from ``p0`` equal the authors' ``spatiotemporal_adam_step``
    with the keyword arguments ``step``, after every step."""
    ours = run_library(opt, jnp.asarray(p0), [jnp.asarray(g) for g in grads])
    p, state = p0, ref.adam_init(p0)
    for g, o in zip(grads, ours):
        p, state = ref.spatiotemporal_adam_step(p, g, state, **step)
        close(o, p)


@pytest.mark.parametrize(
    "channels,log,mode", [(3, True, "both"), (1, True, "post"), (3, False, "pre")]
)
def test_texture_optimizer_matches(channels, log, mode):
    """SpatioTemporalAdam (texture runs: b2 = 1 - (1 - b1)^2, log guide) over 3 steps."""
    shape, stride_levels, sigma, lr, b1 = (9, 7, channels), 3, 0.4, 0.05, 0.2
    b2 = 1 - (1 - b1) ** 2
    pre, post = mode in ("pre", "both"), mode in ("post", "both")
    p0 = edged(shape, 5)
    grads = [rand(shape, 10 + i) for i in range(3)]
    opt = ob.bilateral_adam(
        lr,
        b1,
        b2,
        1e-8,
        sigma_d=ref.kernel_sigma(sigma, 2, channels),
        levels=stride_levels - 1,
        prefilter=pre,
        postfilter=post,
        separable=False,
        log_guide=log,
    )
    assert_follows_reference(
        opt,
        p0,
        grads,
        lr=lr,
        betas=(b1, b2),
        sigma_d=sigma,
        prefilter=pre,
        postfilter=post,
        log_primal=log,
        stride_levels=stride_levels,
    )


def test_volume_optimizer_two_grids_matches():
    """SpatioTemporalAdamVol: density (1 channel, sigma_d_1d) and albedo (3, sigma_d_3d),
    their stride_levels = 2 (levels = 1: one 3-D full-mode compilation is costly)."""
    s1, s3, lr, b1 = 0.05, 0.3, 0.02, 0.2
    b2 = 1 - (1 - b1) ** 2
    p0 = {"density": edged((5, 4, 4, 1), 6), "albedo": edged((5, 4, 4, 3), 7)}
    grads = [{k: rand(v.shape, 20 + i) for k, v in p0.items()} for i in range(3)]
    opt = ob.bilateral_adam(
        lr,
        b1,
        b2,
        1e-8,
        levels=1,
        separable=False,
        sigma_d={"density": ref.kernel_sigma(s1, 3, 1), "albedo": ref.kernel_sigma(s3, 3, 3)},
        spatial_axes=(0, 1, 2),
    )
    ours = run_library(opt, jax.tree.map(jnp.asarray, p0), jax.tree.map(jnp.asarray, grads))
    for k in p0:
        p, state = p0[k], ref.adam_init(p0[k])
        for g, o in zip(grads, ours):
            p, state = ref.spatiotemporal_adam_step(
                p, g[k], state, lr=lr, betas=(b1, b2), sigma_d_1d=s1, sigma_d_3d=s3, stride_levels=2
            )
            close(o[k], p)


def test_volume_refuses_other_channel_counts():
    with pytest.raises(ValueError, match="1 or 3 channels"):
        ref.volume_sigma(2, 0.1, 0.1)


# --- their options: the bilateral baseline, mtfilter / vtfilter, weight decay, uniform ---


def self_guided_by_cosets(x, stride_levels, sigma, log=False, separable=False):
    """cross_term_off built from the library's one-level filter: a stride-s level is a
    stride-1 level on each of the s^n interleaved sub-grids (off-grid taps are skipped),
    each guided by its own current values."""
    x = np.array(x, np.float64)
    n = x.ndim - 1
    for s in ref.strides(stride_levels):
        if s == 0:
            continue
        out = np.empty_like(x)
        for start in np.ndindex(*([s] * n)):
            sl = tuple(slice(a, None, s) for a in start)
            sub = jnp.asarray(x[sl])
            guide = jnp.log(jnp.abs(sub) + ref.LOG_PRIMAL_EPS) if log else sub
            out[sl] = np.asarray(
                ob.atrous_bilateral(
                    sub,
                    guide,
                    sigma_d=ref.kernel_sigma(sigma, n, x.shape[-1]),
                    levels=1,
                    spatial_axes=tuple(range(n)),
                    separable=separable,
                )
            )
        x = out
    return x


@pytest.mark.parametrize("shape,log", [((8, 8, 3), True), ((8, 8, 1), False)])
def test_cross_term_off_reguides_every_level(shape, log):
    """Strides 0, 1, 2, 4 on 8 x 8: every sub-grid of a level has one shape (few compilations)."""
    x = edged(shape, 8) * np.sign(rand(shape, 9))
    theirs = ref.filter_chain(x, None, 4, 0.3, cross_term_off=True, log=log)
    close(theirs, self_guided_by_cosets(x, 4, 0.3, log))
    # ... and it is not a filter guided by the unfiltered field at every level.
    fixed = ref.filter_chain(x, x, 4, 0.3, log=log)
    assert np.abs(fixed - theirs).max() > 1e-3
    # The library's separable mode, re-guided per level, against the same construction.
    n = len(shape) - 1
    ours = ob.atrous_bilateral(
        jnp.asarray(x),
        "self",
        sigma_d=ref.kernel_sigma(0.3, n, shape[-1]),
        levels=3,
        spatial_axes=(0, 1),
        separable=True,
        log_guide=log,
    )
    close(ours, self_guided_by_cosets(x, 4, 0.3, log, separable=True))


@pytest.mark.parametrize(
    "shape,log",
    [((9, 7, 3), True), ((9, 7, 1), False), ((5, 4, 4, 1), False), ((5, 4, 4, 3), True)],
)
def test_self_guide_is_cross_term_off(shape, log):
    """guide="self" is their bilateral baseline (full mode): 2-D and 3-D, 1 and 3 channels."""
    x = edged(shape, 17) * np.sign(rand(shape, 18))
    n = len(shape) - 1
    theirs = ref.filter_chain(x, None, 3, 0.3, cross_term_off=True, log=log)
    ours = ob.atrous_bilateral(
        jnp.asarray(x),
        "self",
        sigma_d=ref.kernel_sigma(0.3, n, shape[-1]),
        levels=2,
        spatial_axes=tuple(range(n)),
        separable=False,
        log_guide=log,
    )
    close(ours, theirs)


@pytest.mark.parametrize("channels,log,mode", [(3, True, "both"), (1, False, "post")])
def test_self_guided_texture_optimizer_matches_cross_term_off(channels, log, mode):
    shape, sl, sigma, lr, b1, b2 = (9, 7, channels), 3, 0.4, 0.05, 0.2, 0.36
    pre = mode == "both"
    p0 = edged(shape, 19)
    grads = [rand(shape, 90 + i) for i in range(3)]
    opt = ob.bilateral_adam(
        lr,
        b1,
        b2,
        1e-8,
        sigma_d=ref.kernel_sigma(sigma, 2, channels),
        levels=sl - 1,
        prefilter=pre,
        separable=False,
        guide="self",
        log_guide=log,
    )
    assert_follows_reference(
        opt,
        p0,
        grads,
        lr=lr,
        betas=(b1, b2),
        sigma_d=sigma,
        prefilter=pre,
        log_primal=log,
        cross_term_off=True,
        stride_levels=sl,
    )


def test_self_guided_volume_optimizer_matches_cross_term_off():
    """Their volume class with cross_term_off, the density grid, 2 steps (the 3-channel
    3-D filter is checked above: every 3-D full-mode level compiles for seconds)."""
    s1, s3, lr, b1, b2 = 0.05, 0.3, 0.02, 0.2, 0.36
    p0 = {"density": edged((5, 4, 4, 1), 21)}
    grads = [{k: rand(v.shape, 100 + i) for k, v in p0.items()} for i in range(2)]
    opt = ob.bilateral_adam(
        lr,
        b1,
        b2,
        1e-8,
        levels=2,
        separable=False,
        guide="self",
        sigma_d={"density": ref.kernel_sigma(s1, 3, 1)},
        spatial_axes=(0, 1, 2),
    )
    ours = run_library(opt, jax.tree.map(jnp.asarray, p0), jax.tree.map(jnp.asarray, grads))
    for k in p0:
        p, state = p0[k], ref.adam_init(p0[k])
        for g, o in zip(grads, ours):
            p, state = ref.spatiotemporal_adam_step(
                p,
                g[k],
                state,
                lr=lr,
                betas=(b1, b2),
                sigma_d_1d=s1,
                sigma_d_3d=s3,
                stride_levels=3,
                cross_term_off=True,
            )
            close(o[k], p)


def test_cross_term_off_step_guides_m_by_m_and_v_by_v():
    shape, sl, sigma, lr, b1, b2 = (8, 8, 3), 4, 0.3, 0.05, 0.2, 0.36
    p0, g = edged(shape, 11), rand(shape, 12)
    p1, _ = ref.spatiotemporal_adam_step(
        p0,
        g,
        ref.adam_init(p0),
        lr=lr,
        betas=(b1, b2),
        sigma_d=sigma,
        cross_term_off=True,
        stride_levels=sl,
    )
    m, v = (1 - b1) * g, (1 - b2) * g * g
    mf, vf = self_guided_by_cosets(m, sl, sigma), self_guided_by_cosets(v, sl, sigma)
    close(p1, p0 - lr * (mf / (1 - b1)) / (np.sqrt(vf / (1 - b2)) + 1e-8))


def test_no_filters_and_weight_decay_is_torch_adam():
    """postfilter off (or mtfilter = vtfilter = False): torch.optim.Adam with L2 weight
    decay = optax's add_decayed_weights before scale_by_adam."""
    shape, lr, wd = (6, 5, 3), 0.05, 0.1
    p0 = edged(shape, 13)
    grads = [rand(shape, 30 + i) for i in range(3)]
    ours = run_library(
        optax.chain(
            optax.add_decayed_weights(wd), optax.scale_by_adam(0.8, 0.9, 1e-8), optax.scale(-lr)
        ),
        jnp.asarray(p0),
        [jnp.asarray(g) for g in grads],
    )
    for kw in (dict(postfilter=False), dict(mtfilter=False, vtfilter=False)):
        p, state = p0, ref.adam_init(p0)
        for g, o in zip(grads, ours):
            p, state = ref.spatiotemporal_adam_step(
                p, g, state, lr=lr, betas=(0.8, 0.9), weight_decay=wd, **kw
            )
            close(o, p)


def test_weight_decay_is_added_after_the_prefilter_and_then_postfiltered():
    """Their weight decay is coupled (torch Adam's), added to the prefiltered gradient:
    = chain(prefilter, add_decayed_weights, postfilter) of the library."""
    shape, lr, wd, sigma = (9, 7, 3), 0.05, 0.3, 0.4
    p0 = edged(shape, 14)
    grads = [rand(shape, 40 + i) for i in range(3)]
    common = dict(sigma_d=ref.kernel_sigma(sigma, 2, 3), levels=2, separable=False)
    opt = optax.chain(
        ob.prefilter(**common),
        optax.add_decayed_weights(wd),
        ob.postfilter(0.2, 0.36, 1e-8, **common),
        optax.scale(-lr),
    )
    assert_follows_reference(
        opt,
        p0,
        grads,
        lr=lr,
        betas=(0.2, 0.36),
        sigma_d=sigma,
        weight_decay=wd,
        prefilter=True,
        stride_levels=3,
    )


@pytest.mark.parametrize("which", ["m", "v"])
def test_mtfilter_vtfilter_filter_one_moment(which):
    shape, sl, sigma, lr, b1, b2 = (9, 7, 3), 3, 0.4, 0.05, 0.2, 0.36
    p0, g = edged(shape, 15), rand(shape, 16)
    p1, _ = ref.spatiotemporal_adam_step(
        p0,
        g,
        ref.adam_init(p0),
        lr=lr,
        betas=(b1, b2),
        sigma_d=sigma,
        mtfilter=which == "m",
        vtfilter=which == "v",
        stride_levels=sl,
    )
    m, v = (1 - b1) * g, (1 - b2) * g * g

    def lib(x):
        return np.asarray(
            ob.atrous_bilateral(
                jnp.asarray(x),
                jnp.asarray(p0),
                sigma_d=ref.kernel_sigma(sigma, 2, 3),
                levels=sl - 1,
                spatial_axes=(0, 1),
                separable=False,
            )
        )

    if which == "m":
        m = lib(m)
    else:
        v = lib(v)
    close(p1, p0 - lr * (m / (1 - b1)) / (np.sqrt(v / (1 - b2)) + 1e-8))


@pytest.mark.parametrize("filter_m,filter_v", [(True, False), (False, True), (False, False)])
def test_filter_m_filter_v_match_mtfilter_vtfilter(filter_m, filter_v):
    """bilateral_adam(filter_m=, filter_v=) = their mtfilter / vtfilter, over 3 steps."""
    shape, sl, sigma, lr, b1, b2 = (9, 7, 3), 3, 0.4, 0.05, 0.2, 0.36
    p0 = edged(shape, 23)
    grads = [rand(shape, 110 + i) for i in range(3)]
    opt = ob.bilateral_adam(
        lr,
        b1,
        b2,
        1e-8,
        sigma_d=ref.kernel_sigma(sigma, 2, 3),
        levels=sl - 1,
        separable=False,
        log_guide=True,
        filter_m=filter_m,
        filter_v=filter_v,
    )
    assert_follows_reference(
        opt,
        p0,
        grads,
        lr=lr,
        betas=(b1, b2),
        sigma_d=sigma,
        mtfilter=filter_m,
        vtfilter=filter_v,
        log_primal=True,
        stride_levels=sl,
    )


def test_uniform_second_moment_matches_the_mesh_adam_uniform():
    """The uniform step (max of v over the whole leaf) = the mesh AdamUniform (Large Steps'
    optimizer, the shared postfilter unfiltered); the Dr.Jit port's version puts eps on the
    uncorrected root: eps / sqrt(1 - b2^t)."""
    b1, b2, eps = 0.2, 0.36, 1e-3
    g = [rand((7, 6, 3), 50 + i) * 1e-3 for i in range(3)]
    tx = ob.postfilter(b1, b2, eps, levels=0, second_moment="uniform")
    state = tx.init(jnp.zeros((7, 6, 3)))
    m = v = 0.0
    for t, gt in enumerate(g, 1):
        out, state = tx.update(jnp.asarray(gt), state)
        m, v = b1 * m + (1 - b1) * gt, b2 * v + (1 - b2) * gt * gt
        close(out, ref.uniform_adam_step(m, v, t, b1, b2, eps))
        close(
            ref.drjit_uniform_step(m, v, t, b1, b2, eps),
            ref.uniform_adam_step(m, v, t, b1, b2, eps / np.sqrt(1 - b2**t)),
        )


@pytest.mark.parametrize("levels", [0, 2])
def test_postfilter_uniform_second_moment(levels):
    """second_moment="uniform": B m^ / (sqrt(max B v^) + eps), the max over the leaf
    (levels 0: the mesh AdamUniform's formula on a grid)."""
    b1, b2, eps, sigma = 0.2, 0.36, 1e-3, 0.3
    p0 = edged((9, 7, 3), 24)
    grads = [rand((9, 7, 3), 120 + i) * 1e-3 for i in range(3)]
    tx = ob.postfilter(
        b1,
        b2,
        eps,
        sigma_d=ref.kernel_sigma(sigma, 2, 3),
        levels=levels,
        separable=False,
        second_moment="uniform",
    )
    state = tx.init(jnp.asarray(p0))
    m = v = 0.0
    for t, g in enumerate(grads, 1):
        out, state = tx.update(jnp.asarray(g), state, jnp.asarray(p0))
        m, v = b1 * m + (1 - b1) * g, b2 * v + (1 - b2) * g * g
        mf, vf = (
            ref.filter_chain(m, p0, levels + 1, sigma),
            ref.filter_chain(v, p0, levels + 1, sigma),
        )
        close(out, ref.uniform_adam_step(mf, vf, t, b1, b2, eps))
        ratio = np.abs(np.asarray(out)) / np.abs(mf)  # one denominator for the whole leaf
        assert np.ptp(ratio) <= 1e-12 * ratio.mean()


@pytest.mark.parametrize("masked", [False, True])
def test_weight_decay_is_optax_adamw(masked):
    """Decoupled weight decay: with no filter, bilateral_adam(weight_decay=) = optax.adamw;
    filtered, the same decay is added to the filtered step."""
    lr, b1, b2, wd = 0.05, 0.8, 0.9, 0.3
    p0 = {"tex": jnp.asarray(edged((6, 5, 3), 25)), "b": jnp.asarray(rand((4,), 26))}
    grads = [jax.tree.map(lambda p, i=i: jnp.asarray(rand(p.shape, 130 + i)), p0) for i in range(3)]
    mask = {"tex": True, "b": False} if masked else None
    ours = run_library(
        ob.bilateral_adam(lr, b1, b2, 1e-8, levels=0, weight_decay=wd, weight_decay_mask=mask),
        p0,
        grads,
    )
    theirs = run_library(optax.adamw(lr, b1, b2, 1e-8, weight_decay=wd, mask=mask), p0, grads)
    for o, t in zip(ours, theirs):
        for k in p0:
            close(o[k], t[k])
    kw = dict(sigma_d=0.3, levels=2, spatial_axes={"tex": (0, 1), "b": ()})
    filtered = ob.bilateral_adam(lr, b1, b2, 1e-8, weight_decay=wd, weight_decay_mask=mask, **kw)
    chained = optax.chain(
        ob.postfilter(b1, b2, 1e-8, **kw), optax.add_decayed_weights(wd, mask), optax.scale(-lr)
    )
    for o, t in zip(run_library(filtered, p0, grads), run_library(chained, p0, grads)):
        for k in p0:
            close(o[k], t[k])


# --- meshes ---------------------------------------------------------------------------

LAM = 7.0


@pytest.fixture(scope="module")
def cube():
    """A 42-vertex icosphere pushed onto a cube: sharp normal edges, few compilations."""
    from optax_bilateral.toy import triangle_mesh as toy

    v, f = toy.icosphere(2)
    v = v.astype(np.float64) / np.abs(v).max(1, keepdims=True) * 0.5
    return dict(
        v=v, f=f, mesh=ob.triangle_mesh.mesh_laplacian(f), M=ref.compute_matrix(f, len(v), LAM)
    )


def test_directions_are_the_authors():
    close(ob.triangle_mesh.sphere_directions(32), ref.sobol_directions(32))


@pytest.mark.parametrize(
    "weighting,theirs",
    [
        ("uniform", ref.unweighted_vertex_normals),
        ("area", ref.area_vertex_normals),
        ("angle", ref.angle_vertex_normals),
    ],
)
def test_vertex_normals_match(cube, weighting, theirs):
    close(
        ob.triangle_mesh.vertex_normals(jnp.asarray(cube["v"]), cube["f"], weighting),
        theirs(cube["v"], cube["f"]),
    )


def test_authors_normals_are_the_unweighted_mean_up_to_one_over_faces(cube):
    """Their torch.norm without dim makes every corner weight pi/2 - O(1/F)."""
    from optax_bilateral.toy import triangle_mesh as toy

    for v, f in ((cube["v"], cube["f"]), toy.icosphere(16)):
        a, u = ref.authors_vertex_normals(v, f), ref.unweighted_vertex_normals(v, f)
        angle = np.arccos(np.clip(np.sum(a * u, 1), -1, 1)).max()
        assert 0 < angle < 4.0 / len(f), (angle, len(f))


@pytest.mark.parametrize("solver", ["cg", "cholesky"])
def test_bilateral_filter_splat_sigma_d_slice_sigma_phi(cube, solver):
    x = rand((42, 3), 60)
    normals = ref.unweighted_vertex_normals(cube["v"], cube["f"])
    dirs = ref.sobol_directions(32)
    theirs = ref.mesh_filter(x, "bilateral", normals, cube["M"], dirs, 0.5, 0.4)
    (ours,) = ob.triangle_mesh.bilateral_normal_filter(
        [jnp.asarray(x)],
        jnp.asarray(normals),
        cube["mesh"],
        lambda_=LAM,
        # kernel_tol=0: every direction its own term, as theirs.
        sigma_d=ob.triangle_mesh.NormalFilter(0.5, sigma_phi=0.4, directions=dirs, kernel_tol=0.0),
        solver=ob.triangle_mesh.CG(tol=1e-15, maxiter=400) if solver == "cg" else solver,
    )
    close(ours, theirs)
    # sigma_phi is not sigma_d: slicing with 0.5 gives another operator.
    assert (
        np.abs(ref.mesh_filter(x, "bilateral", normals, cube["M"], dirs, 0.5, 0.5) - theirs).max()
        > 1e-3
    )


MESH_CASES = [
    ("smooth", "uniform"),
    ("smooth", "bilateral"),
    ("bilateral", "smooth"),
    ("off", "uniform"),
]


@pytest.mark.parametrize("prefilter,postfilter_v", MESH_CASES)
def test_mesh_optimizer_matches(cube, prefilter, postfilter_v):
    """SpatioTemporalAdamMesh over 3 steps, normals recomputed from the moving positions."""
    lr, betas, eps = 0.02, (0.9, 0.99), 1e-8
    dirs = ref.sobol_directions(32)
    grads = [rand((42, 3), 70 + i) for i in range(3)]
    opt = ob.triangle_mesh.bilateral_large_steps(
        lr,
        cube["mesh"],
        LAM,
        ob.triangle_mesh.NormalFilter(
            0.5, sigma_phi=0.4, directions=dirs, normals="uniform", kernel_tol=0.0
        ),
        *betas,
        eps,
        prefilter=prefilter,
        postfilter_v=postfilter_v,
        solver="cholesky",
    )
    ours = run_library(opt, jnp.asarray(cube["v"]), [jnp.asarray(g) for g in grads])
    p, state = cube["v"], ref.uniform_init(cube["v"])
    for g, o in zip(grads, ours):
        n = ref.unweighted_vertex_normals(p, cube["f"])
        p, state = ref.mesh_adam_step(
            p,
            g,
            state,
            n,
            cube["M"],
            dirs,
            lr=lr,
            betas=betas,
            eps=eps,
            prefilter=prefilter,
            postfilter_v=postfilter_v,
        )
        close(o, p)


def test_large_steps_matches_adam_uniform_on_u(cube):
    lr, betas = 0.05, (0.9, 0.999)
    grads = [rand((42, 3), 80 + i) for i in range(3)]
    ours = run_library(
        ob.triangle_mesh.large_steps(lr, cube["mesh"], LAM, *betas, solver="cholesky"),
        jnp.asarray(cube["v"]),
        [jnp.asarray(g) for g in grads],
    )
    x, state = cube["v"], ref.uniform_init(cube["v"])
    for g, o in zip(grads, ours):
        x, state = ref.large_steps_step(x, g, state, cube["M"], lr=lr, betas=betas)
        close(o, x)


@pytest.mark.parametrize("postfilter_v", ["uniform", "smooth"])
def test_their_alpha_matrix_is_a_rescaled_lr_and_eps(cube, postfilter_v):
    """compute_matrix(alpha = lam/(1+lam)) = (I + lam L)/(1+lam): their "smooth" is
    (1+lam) M^-1. Uniform: the library's step with eps/(1+lam). Smooth v: lr/sqrt(1+lam)
    and eps/(1+lam)^1.5 (docs/triangle_mesh.md)."""
    m_alpha = ref.compute_matrix(cube["f"], 42, LAM, alpha=LAM / (1 + LAM))
    close(m_alpha, cube["M"] / (1 + LAM), 1e-15)
    dirs, betas, eps, lr = ref.sobol_directions(32), (0.9, 0.99), 1e-3, 0.02
    n = ref.unweighted_vertex_normals(cube["v"], cube["f"])
    g = rand((42, 3), 90)
    if postfilter_v == "uniform":
        lr_ours, eps_ours = lr, eps / (1 + LAM)
    else:
        lr_ours, eps_ours = lr / np.sqrt(1 + LAM), eps / (1 + LAM) ** 1.5
    theirs, _ = ref.mesh_adam_step(
        cube["v"],
        g,
        ref.uniform_init(cube["v"]),
        n,
        m_alpha,
        dirs,
        lr=lr,
        betas=betas,
        eps=eps,
        postfilter_v=postfilter_v,
    )
    ours, _ = ref.mesh_adam_step(
        cube["v"],
        g,
        ref.uniform_init(cube["v"]),
        n,
        cube["M"],
        dirs,
        lr=lr_ours,
        betas=betas,
        eps=eps_ours,
        postfilter_v=postfilter_v,
    )
    close(theirs, ours)
