"""Triangle-mesh transforms (Large Steps, bilateral normal filter) and the toy mesh scene."""

import dataclasses
import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given
from hypothesis import strategies as st

import optax_bilateral as ob
from optax_bilateral import triangle_mesh as M
from optax_bilateral._src.mesh import laplacian
from optax_bilateral.toy import triangle_mesh as toy

LAM = 7.0


@pytest.fixture(scope="module")
def small():
    """162-vertex icosphere, its Laplacian, the dense reference (I + LAM L)^-1."""
    v, f = toy.icosphere(4)
    n = len(v)
    adj = np.zeros((n, n))
    for a, b in ((0, 1), (1, 2), (2, 0)):  # independent of mesh_laplacian's edge table
        adj[f[:, a], f[:, b]] = adj[f[:, b], f[:, a]] = 1
    lap = np.diag(adj.sum(1)) - adj
    return dict(
        v=v, f=f, mesh=M.mesh_laplacian(f), lap=lap, minv=np.linalg.inv(np.eye(n) + LAM * lap)
    )


def cubified(v):
    """The sphere's vertices pushed radially onto a cube: sharp edges, flat faces."""
    return (v / np.abs(v).max(1, keepdims=True) * 0.5).astype(np.float32)


def dense_bilateral(minv, normals, sigma_d, dirs, sigma_phi):
    """Reference: B_ij = Minv_ij K(n_i, n_j) / row sum, K(n_i, n_j) = sum_k phi_k(i) w_k(j)."""
    cos = normals.astype(np.float64) @ dirs.T.astype(np.float64)
    w, phi = np.exp(cos / sigma_d), np.exp(cos / sigma_phi)
    b = minv * (phi @ w.T)
    return b / b.sum(1, keepdims=True)


def filter_matrix(small, normals, sigma_d, **kw):
    n = len(small["v"])
    (b,) = M.bilateral_normal_filter(
        [jnp.eye(n, dtype=jnp.float32)],
        normals,
        small["mesh"],
        lambda_=LAM,
        sigma_d=M.NormalFilter(sigma_d, **kw),
        solver=M.CG(tol=1e-7),
    )
    return np.asarray(b, np.float64)


# --- the mesh and the solve -----------------------------------------------------


def test_laplacian_degrees_of_icosphere(small):
    deg = np.asarray(small["mesh"].degree)
    # An icosphere keeps the 12 icosahedron vertices at degree 5; all others have 6.
    assert (deg == 5).sum() == 12 and (deg == 6).sum() == len(deg) - 12
    np.testing.assert_array_equal(deg, small["lap"].diagonal())


@pytest.mark.parametrize("lam", [0.0, 1.0, LAM, 99.0])
def test_solve_agrees_with_dense_solve(small, lam):
    n = len(small["v"])
    b = np.random.default_rng(0).standard_normal((n, 4)).astype(np.float32)
    b[:, 3] *= 1e-4  # a tiny column must be solved as accurately (columns are normalised)
    x = np.asarray(M.smoothing_solve(small["mesh"], b, lam, solver=M.CG(tol=1e-6)))
    ref = np.linalg.solve(np.eye(n) + lam * small["lap"], b.astype(np.float64))
    # tol=1e-6 relative residual, times cond(M) <= 1 + 12 lam would be loose;
    # 2e-5 of each column's scale is float32 accuracy with margin.
    scale = np.abs(ref).max(0)
    np.testing.assert_allclose(x / scale, ref / scale, atol=2e-5)


def test_solve_1d_and_traced_lambda(small):
    b = np.asarray(small["v"][:, 0])
    solve = jax.jit(lambda b, lam: M.smoothing_solve(small["mesh"], b, lam, solver=M.CG(tol=1e-6)))
    np.testing.assert_allclose(solve(b, LAM), small["minv"] @ b, atol=1e-5)


def test_vertex_normals_of_sphere_point_outwards(small):
    n = np.asarray(M.vertex_normals(small["v"], small["f"]))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    # On a unit icosphere the area-weighted normal is the position up to facet error.
    assert np.min(np.sum(n * small["v"], 1)) > 0.99


def test_sphere_directions_unit_and_spread():
    d = M.sphere_directions(32, seed=0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(d, M.sphere_directions(32, seed=0))
    # Uniform on the sphere has mean 0; 32 scrambled Sobol points stay within 0.1
    # (i.i.d. points would scatter about 1/sqrt(3*32) = 0.1 per axis).
    assert np.linalg.norm(d.mean(0)) < 0.1


# --- the bilateral operator -----------------------------------------------------


@pytest.mark.parametrize("sigma_d", [0.2, 0.5, 2.0])
def test_bilateral_operator_row_stochastic_nonnegative_and_matches_dense(small, sigma_d):
    normals = np.asarray(M.vertex_normals(cubified(small["v"]), small["f"]))
    dirs = M.sphere_directions(32)
    b = filter_matrix(small, normals, sigma_d, directions=dirs, sigma_phi=0.4, kernel_tol=0.0)
    # Rows sum to one up to float32 and the CG tolerance (1e-7 relative per column).
    np.testing.assert_allclose(b.sum(1), 1.0, atol=1e-5)
    # M^-1 >= 0 and w >= 0, so B >= 0; CG round-off may dip below by ~1e-7.
    assert b.min() > -1e-6
    np.testing.assert_allclose(
        b, dense_bilateral(small["minv"], normals, sigma_d, dirs, 0.4), atol=2e-6
    )


@pytest.mark.parametrize("sigma_d,tol", [(0.2, 0.02), (0.5, 0.02), (0.5, 0.1), (2.0, 0.3)])
def test_compressed_kernel_stays_within_its_tolerance(small, sigma_d, tol):
    """K_r within tol of K (relative) puts each B_ij within (1 + tol) / (1 - tol) of the
    directions' own, both ways, and B stays non-negative and row-stochastic."""
    normals = np.asarray(M.vertex_normals(cubified(small["v"]), small["f"]))
    dirs = M.sphere_directions(32)
    bases = M.kernel_bases(dirs, sigma_d, 0.4, tol)
    assert bases is not None and bases[0].shape[1] < 32  # fewer terms than directions
    b = filter_matrix(small, normals, sigma_d, directions=dirs, sigma_phi=0.4, kernel_tol=tol)
    exact = dense_bilateral(small["minv"], normals, sigma_d, dirs, 0.4)
    np.testing.assert_allclose(b.sum(1), 1.0, atol=1e-5)
    assert b.min() > -1e-6
    bound = (1 + tol) / (1 - tol) - 1
    assert np.all(np.abs(b - exact) <= bound * exact + 2e-6)
    # The tolerance is spent: the compressed filter is another operator, not the same one.
    assert np.abs(b - exact).max() > 1e-5


def test_kernel_bases_keep_every_direction_where_the_kernel_is_sharp():
    dirs = M.sphere_directions(32)
    assert M.kernel_bases(dirs, 0.5, 0.4, 0.0) is None  # tol 0: the authors' form
    assert M.kernel_bases(dirs, 0.02, 0.02, 0.02) is None  # narrow lobes need every direction
    # Lobes so narrow that the kernel underflows to 0 between them: no relative error exists
    # there, so no rank holds (and nothing warns of a division by zero).
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert M.kernel_bases(M.sphere_directions(8), 1e-3, 1e-3, 0.02) is None
    a_w, a_phi = M.kernel_bases(dirs, 0.5, 0.4, 0.02)
    # The defaults' kernel: spherical harmonics to degree 3, 1 + 3 + 5 + 7 terms.
    assert a_w.shape == a_phi.shape == (32, 16)
    # A repeated direction leaves the same kernel twice over, and the same rank.
    twice = M.kernel_bases(np.concatenate([dirs, dirs]), 0.5, 0.4, 0.02)
    assert twice is not None and twice[0].shape == (64, 16)


@given(
    sigma_d=st.sampled_from([0.05, 0.2, 0.5, 2.0, 5.0]),
    sigma_phi=st.sampled_from([0.05, 0.4, 1.0]),
    tol=st.sampled_from([0.005, 0.02, 0.1, 0.45]),
    seed=st.integers(0, 2**16),
)
def test_kernel_bases_hold_the_tolerance_off_their_samples(sigma_d, sigma_phi, tol, seed):
    """Chosen on a Fibonacci sphere, the compressed kernel holds its tolerance within 1.25x
    (1.05x measured at worst on a grid of widths) on normals it never saw, and stays
    positive; where no rank below the directions' holds it, no tighter one does either."""
    dirs = M.sphere_directions(32)
    bases = M.kernel_bases(dirs, sigma_d, sigma_phi, tol)
    if bases is None:
        assert M.kernel_bases(dirs, sigma_d, sigma_phi, tol / 2) is None
        return
    n = np.random.default_rng(seed).normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)

    def vmf(sigma):
        return np.exp((np.maximum(n @ dirs.T, -1.0) - 1.0) / sigma)

    exact = vmf(sigma_phi) @ vmf(sigma_d).T
    compressed = (vmf(sigma_phi) @ bases[1]) @ (vmf(sigma_d) @ bases[0]).T
    assert compressed.min() > 0
    assert np.max(np.abs(compressed - exact) / exact) <= 1.25 * tol


def test_kernel_bases_reject_bad_arguments():
    dirs = M.sphere_directions(8)
    with pytest.raises(ValueError, match="directions"):
        M.kernel_bases(dirs[:, :2], 0.5, 0.4, 0.02)
    for name, args in (("sigma_d", (0.0, 0.4)), ("sigma_phi", (0.5, -1.0))):
        with pytest.raises(ValueError, match=f"{name} must be > 0"):
            M.kernel_bases(dirs, *args, 0.02)
    with pytest.raises(TypeError, match="sigma_d must be a concrete number"):
        jax.jit(lambda s: M.kernel_bases(dirs, s, 0.4, 0.02))(0.5)
    for bad in (-0.1, 0.5, "0.1", True, float("nan")):
        with pytest.raises(ValueError, match=r"tol must be a real number >= 0 and < 0\.5"):
            M.kernel_bases(dirs, 0.5, 0.4, bad)
    with pytest.raises(ValueError, match="samples must be an int >= 16"):
        M.kernel_bases(dirs, 0.5, 0.4, 0.02, samples=8)
    # inf: every weight 1, one term holds the kernel exactly.
    a_w, a_phi = M.kernel_bases(dirs, np.inf, 0.4, 0.02)
    assert a_w.shape == a_phi.shape == (8, 1)


def test_traced_widths_keep_every_direction(small):
    normals = M.vertex_normals(cubified(small["v"]), small["f"])
    x = jnp.asarray(np.random.default_rng(3).normal(size=(len(small["v"]), 2)), jnp.float32)

    def filtered(sigma_d, tol):
        data_term = M.NormalFilter(sigma_d, directions=8, kernel_tol=tol)
        return M.bilateral_normal_filter(
            [x], normals, small["mesh"], lambda_=LAM, sigma_d=data_term, solver="cholesky"
        )[0]

    traced = jax.jit(lambda s: filtered(s, 0.3))(jnp.float32(0.5))
    np.testing.assert_allclose(traced, filtered(0.5, 0.0), rtol=1e-5, atol=1e-6)
    assert np.abs(np.asarray(filtered(0.5, 0.3) - filtered(0.5, 0.0))).max() > 1e-6


def test_bilateral_reduces_to_large_steps_as_sigma_grows(small):
    normals = np.asarray(M.vertex_normals(cubified(small["v"]), small["f"]))
    b_inf = filter_matrix(small, normals, np.inf)
    np.testing.assert_allclose(b_inf, small["minv"], atol=2e-6)  # exact path: B = M^-1
    errs = [np.abs(filter_matrix(small, normals, s) - small["minv"]).max() for s in (0.5, 5.0, 1e5)]
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 2e-6  # at sigma_d = 1e5 every weight is 1 to float32 precision


def test_bilateral_weights_less_across_cube_edges(small):
    """Row mass on neighbours whose normal differs by > 45 degrees shrinks as sigma_d falls."""
    normals = np.asarray(M.vertex_normals(cubified(small["v"]), small["f"]))
    other = (normals @ normals.T) < np.cos(np.pi / 4)
    # Splat and slice widths shrink together (the slice width alone also narrows B).
    mass = [
        float(
            (filter_matrix(small, normals, s, sigma_phi=s if np.isfinite(s) else 0.4) * other)
            .sum(1)
            .mean()
        )
        for s in (np.inf, 1.0, 0.2)
    ]
    assert mass[0] > mass[1] > mass[2]
    assert mass[2] < 0.5 * mass[0]


def test_filtered_moments_keep_step_bounded(small):
    """Supplement §1.3: |m| <= sqrt(v) entrywise implies |B m| <= sqrt(B v) (same B)."""
    rng = np.random.default_rng(1)
    n = len(small["v"])
    v = rng.uniform(0.0, 2.0, (n, 3)).astype(np.float32) ** 4
    m = (np.sqrt(v) * rng.uniform(-1, 1, (n, 3))).astype(np.float32)
    normals = M.vertex_normals(cubified(small["v"]), small["f"])
    bm, bv = M.bilateral_normal_filter(
        [m, v], normals, small["mesh"], lambda_=LAM, sigma_d=0.3, solver=M.CG(tol=1e-7)
    )
    # 1e-5 relative slack: float32 and CG tolerance on a bound that holds exactly.
    assert np.all(np.abs(bm) <= np.sqrt(np.maximum(bv, 0)) * (1 + 1e-5) + 1e-7)


# --- the transforms -------------------------------------------------------------


def _grads(v, steps, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.standard_normal(v.shape).astype(np.float32) * 0.1 for _ in range(steps)]


def uniform_adam(b1=0.9, b2=0.999, eps=1e-8):
    """Large Steps' AdamUniform: the shared postfilter, unfiltered, with one second moment."""
    return ob.postfilter(b1, b2, eps, levels=0, second_moment="uniform")


def test_uniform_adam_matches_reference(small):
    b1, b2, eps = 0.8, 0.95, 1e-8
    tx = uniform_adam(b1, b2, eps)
    g = _grads(small["v"], 4)
    state = tx.init(jnp.asarray(small["v"]))
    m = v = 0.0
    for t, gt in enumerate(g, 1):
        out, state = tx.update(jnp.asarray(gt), state)
        m = b1 * m + (1 - b1) * gt.astype(np.float64)
        v = b2 * v + (1 - b2) * gt.astype(np.float64) ** 2
        ref = (m / (1 - b1**t)) / (np.sqrt(np.max(v / (1 - b2**t))) + eps)
        np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6)


def test_large_steps_is_uniform_adam_on_u(small):
    """Nicolet et al.: optimise u = (I + lam L) x with AdamUniform, read x = M^-1 u."""
    lr, b1, b2 = 0.05, 0.9, 0.999
    x0 = small["v"].astype(np.float64)
    mm = np.eye(len(x0)) + LAM * small["lap"]
    tx = M.large_steps(lr, small["f"], LAM, b1, b2, solver=M.CG(tol=1e-7))
    x = jnp.asarray(small["v"])
    state = tx.init(x)
    u = mm @ x0
    m = v = 0.0
    for t, gx in enumerate(_grads(small["v"], 4), 1):
        upd, state = tx.update(jnp.asarray(gx), state, x)
        x = optax.apply_updates(x, upd)
        gu = np.linalg.solve(mm, gx.astype(np.float64))  # df/du = M^-T df/dx
        m = b1 * m + (1 - b1) * gu
        v = b2 * v + (1 - b2) * gu**2
        u = u - lr * (m / (1 - b1**t)) / (np.sqrt(np.max(v / (1 - b2**t))) + 1e-8)
        # Positions are O(1); float32 and CG tolerance give ~1e-6 differences.
        np.testing.assert_allclose(x, np.linalg.solve(mm, u), atol=1e-5)


@pytest.mark.parametrize("sigma_d", [np.inf, 1e5])
def test_bilateral_large_steps_reduces_to_large_steps(small, sigma_d):
    ls = M.large_steps(0.02, small["mesh"], LAM, solver=M.CG(tol=1e-7))
    ours = M.bilateral_large_steps(0.02, small["mesh"], LAM, sigma_d, solver=M.CG(tol=1e-7))
    xa = xb = jnp.asarray(cubified(small["v"]))
    sa, sb = ls.init(xa), ours.init(xb)
    for g in _grads(small["v"], 3):
        ua, sa = ls.update(jnp.asarray(g), sa, xa)
        ub, sb = ours.update(jnp.asarray(g), sb, xb)
        # Same math, different solve order; the step is <= lr = 0.02, compared to 1e-6.
        np.testing.assert_allclose(ua, ub, atol=1e-6)
        xa, xb = optax.apply_updates(xa, ua), optax.apply_updates(xb, ub)


def test_filtered_second_moment_step_is_bounded(small):
    data_term = M.NormalFilter(0.3, directions=M.sphere_directions(16))
    tx = M.bilateral_large_steps(1.0, small["mesh"], LAM, data_term, postfilter_v="bilateral")
    x = jnp.asarray(cubified(small["v"]))
    state = tx.init(x)
    for g in _grads(small["v"], 3):
        upd, state = tx.update(jnp.asarray(g), state, x)
        # Adam's step is bounded by lr (here 1) up to the bias-correction ratio
        # sqrt(1-b2^t)/(1-b1^t) <= 1 for these b's; B keeps the bound (§1.3).
        assert np.abs(np.asarray(upd)).max() <= 1.0 + 1e-4


def test_inject_hyperparams_jit_and_pytree_params(small):
    mesh, dirs = small["mesh"], M.sphere_directions(8)

    def factory(learning_rate, lambda_, sigma_d, sigma_phi):  # the normal filter's widths
        data_term = M.NormalFilter(sigma_d, sigma_phi, directions=dirs)
        return M.bilateral_large_steps(learning_rate, mesh, lambda_, data_term)

    tx = optax.inject_hyperparams(factory)(
        learning_rate=0.01, lambda_=LAM, sigma_d=0.5, sigma_phi=0.4
    )
    params = {"shape": jnp.asarray(cubified(small["v"]))}
    state = tx.init(params)
    step = jax.jit(tx.update)
    g = {"shape": jnp.asarray(_grads(small["v"], 1)[0])}
    upd, state = step(g, state, params)
    state.hyperparams["sigma_d"] = jnp.asarray(0.2)
    state.hyperparams["lambda_"] = jnp.asarray(2.0)
    state.hyperparams["sigma_phi"] = jnp.asarray(0.3)
    upd2, state = step(g, state, params)  # traced lambda_, sigma_d, sigma_phi: no retrace needed
    assert np.all(np.isfinite(upd["shape"])) and not np.allclose(upd["shape"], upd2["shape"])


def test_bad_arguments_raise_clear_errors(small):
    f, mesh = small["f"], small["mesh"]
    with pytest.raises(ValueError, match="faces must have shape"):
        M.mesh_laplacian(f[:, :2])
    with pytest.raises(TypeError, match="integer"):
        M.mesh_laplacian(f.astype(float))
    with pytest.raises(ValueError, match="degenerate"):
        M.mesh_laplacian(np.array([[0, 1, 1]]))
    with pytest.raises(ValueError, match="lambda_"):
        M.large_steps(0.1, mesh, -1.0)
    with pytest.raises(ValueError, match="sigma_d"):
        M.bilateral_large_steps(0.1, mesh, 1.0, 0.0)
    with pytest.raises(ValueError, match="postfilter_v"):
        M.mesh_postfilter(mesh, postfilter_v="max")
    with pytest.raises(ValueError, match="directions"):
        M.NormalFilter(directions=np.ones((4, 2)))
    for bad in ("x", [[1.0, 0.0, "y"]], {"k": 3}):  # not numbers: still named
        with pytest.raises(ValueError, match="directions must be an int"):
            M.NormalFilter(directions=bad)
    with pytest.raises(TypeError, match="sigma_d must be a real number"):
        M.NormalFilter("wide")
    with pytest.raises(TypeError, match="sigma_phi must be a real number"):
        M.NormalFilter(0.5, "wide")
    with pytest.raises(TypeError, match=r"lambda_.* must be a real number"):
        M.bilateral_large_steps(0.1, f, "19")
    with pytest.raises(TypeError, match="b1 must be a real number"):
        M.large_steps(0.1, f, 1.0, b1="0.9")
    tx = M.mesh_postfilter(mesh, sigma_d=M.NormalFilter(directions=M.sphere_directions(4)))
    x = jnp.asarray(small["v"])
    with pytest.raises(ValueError, match="needs params"):
        tx.update(x, tx.init(x))
    with pytest.raises(ValueError, match="one row per mesh vertex"):
        M.laplacian_smoothing(mesh).update(x[:10], optax.EmptyState())


# --- solvers, warm start, seams, options ------------------------------------------


def _filter_loss(small, solver):
    mesh = small["mesh"]
    r = jnp.asarray(np.random.default_rng(5).standard_normal((len(small["v"]), 3)), jnp.float32)
    dirs = M.sphere_directions(8)

    def loss(field, verts, lam):
        normals = M.vertex_normals(verts, mesh)
        (out,) = M.bilateral_normal_filter(
            [field],
            normals,
            mesh,
            lambda_=lam,
            sigma_d=M.NormalFilter(0.4, directions=dirs),
            solver=M.CG(tol=1e-7) if solver == "cg" else solver,
        )
        return jnp.sum(out * r)

    return loss


def _assert_matches_cg(grads):
    """``{"cg": (value, grads), "cholesky": (value, grads)}`` agree: float32 CG at tol 1e-7
    against a float64 factor, 1e-4 of each gradient's scale."""
    (v_cg, g_cg), (v_ch, g_ch) = grads["cg"], grads["cholesky"]
    np.testing.assert_allclose(v_ch, v_cg, rtol=1e-4)
    for a, b in zip(g_ch, g_cg):
        assert np.all(np.isfinite(a)) and np.abs(b).max() > 0
        np.testing.assert_allclose(a, b, atol=1e-4 * float(np.abs(b).max()))


def test_cholesky_keeps_jit_grad_and_vmap(small):
    """Grads w.r.t. the field, the vertices (through the normals) and lambda, under jit,
    equal the CG path's; vmap over fields and over lambdas equals a loop."""
    field = jnp.asarray(_grads(small["v"], 1, seed=3)[0] * 10)
    verts = jnp.asarray(cubified(small["v"]))
    grads = {}
    for solver in ("cg", "cholesky"):
        f = jax.jit(jax.value_and_grad(_filter_loss(small, solver), argnums=(0, 1, 2)))
        grads[solver] = f(field, verts, jnp.float32(LAM))
    _assert_matches_cg(grads)
    loss = _filter_loss(small, "cholesky")
    fields = jnp.stack([field, 2 * field + 1, -field])
    lams = jnp.asarray([1.0, LAM, 30.0], jnp.float32)
    batched = jax.jit(jax.vmap(loss, in_axes=(0, None, 0)))(fields, verts, lams)
    np.testing.assert_allclose(
        batched, [loss(a, verts, b) for a, b in zip(fields, lams)], rtol=1e-5
    )


def test_a_known_lambda_filters_in_the_factors_order_with_grad_and_vmap(small):
    """A concrete lambda pins the factor: the filter's columns are built and solved in its
    order (``solve_columns(..., ordered=True)``). Grads w.r.t. the field and the vertices equal
    the CG path's; vmap over fields equals a loop."""
    mesh = small["mesh"]
    assert laplacian.factor_order(laplacian.System.of(mesh, M.Cholesky(), LAM).host) is not None
    field = jnp.asarray(_grads(small["v"], 1, seed=4)[0] * 10)
    verts = jnp.asarray(cubified(small["v"]))
    at_lam = {s: functools.partial(_filter_loss(small, s), lam=LAM) for s in ("cg", "cholesky")}
    grads = {s: jax.jit(jax.value_and_grad(f, (0, 1)))(field, verts) for s, f in at_lam.items()}
    program = jax.jit(jax.grad(at_lam["cholesky"])).lower(field, verts).as_text()
    assert "optax_bilateral_ldl" in program and "ordered = true" in program
    _assert_matches_cg(grads)
    loss = _filter_loss(small, "cholesky")
    fields = jnp.stack([field, 2 * field + 1, -field])
    batched = jax.jit(jax.vmap(lambda f: loss(f, verts, LAM)))(fields)
    np.testing.assert_allclose(batched, [loss(f, verts, LAM) for f in fields], rtol=1e-5)


def test_cholesky_lambda_gradient_matches_finite_difference(small):
    with jax.enable_x64(True):
        b = jnp.asarray(small["v"][:, :2].astype(np.float64) + 0.3)

        def f(lam):
            return jnp.sum(M.smoothing_solve(small["mesh"], b, lam, solver="cholesky") ** 2)

        g = jax.grad(f)(jnp.float64(LAM))
        h = 1e-5
        fd = (f(jnp.float64(LAM + h)) - f(jnp.float64(LAM - h))) / (2 * h)
        # Central difference in float64: error ~h^2 f''' and 1e-16/h round-off.
        np.testing.assert_allclose(g, fd, rtol=1e-7)


@pytest.mark.parametrize("opt", ["large_steps", "bilateral_large_steps"])
def test_warm_start_changes_the_trajectory_only_within_the_tolerance(small, opt):
    make = getattr(M, opt)
    data_term = M.NormalFilter(directions=M.sphere_directions(8))
    kw = dict(sigma_d=data_term) if opt != "large_steps" else {}
    x0 = jnp.asarray(cubified(small["v"]))
    runs = []
    for warm in (False, True):
        tx = make(0.02, small["mesh"], LAM, solver=M.CG(tol=1e-6, warm_start=warm), **kw)
        x, state = x0, tx.init(x0)
        update = jax.jit(tx.update)
        for g in _grads(small["v"], 4):
            u, state = update(jnp.asarray(g), state, x)
            x = optax.apply_updates(x, u)
        runs.append((x, state))
    # 4 steps of <= lr = 0.02 with solves to 1e-6 relative: 1e-5 absolute.
    np.testing.assert_allclose(runs[1][0], runs[0][0], atol=1e-5)
    stored = [
        leaf
        for leaf in jax.tree.leaves(runs[1][1])
        if leaf.ndim == 2 and leaf.shape[0] == len(x0) and leaf.shape[1] != 3
    ]
    if opt == "large_steps":
        stored = [leaf for leaf in jax.tree.leaves(runs[1][1]) if leaf.ndim == 2]
    assert stored and all(np.abs(leaf).max() > 0 for leaf in stored)  # the solutions are kept


def seam_mesh(v, f):
    """Cuts the sphere along the loop between faces with z > 0 and the rest: the z > 0
    faces get their own copies of the loop's vertices (a UV seam)."""
    top = v[f].mean(1)[:, 2] > 0
    loop = np.intersect1d(np.unique(f[top]), np.unique(f[~top]))
    copy = np.arange(len(v))
    copy[loop] = len(v) + np.arange(len(loop))
    f2 = f.copy()
    f2[top] = copy[f[top]]
    return np.concatenate([v, v[loop]]), f2, loop


def test_welded_seam_does_not_open_and_equals_the_closed_mesh(small):
    v, f = cubified(small["v"]), small["f"]
    v2, f2, loop = seam_mesh(v, f)
    assert len(loop) > 0 and len(v2) > len(v)
    welded = M.mesh_laplacian(f2, weld_positions=v2)
    assert welded.num_vertices == len(v2) and welded.num_merged == len(v)
    data_term = M.NormalFilter(directions=M.sphere_directions(8))
    cg = M.CG(tol=1e-7)
    for make, kw in (
        (M.large_steps, {}),
        (M.bilateral_large_steps, dict(sigma_d=data_term)),
    ):
        closed = make(0.02, small["mesh"], LAM, solver=cg, **kw)
        cut = make(0.02, welded, LAM, solver=cg, **kw)
        opened = make(0.02, M.mesh_laplacian(f2), LAM, solver=cg, **kw)
        xa, xb, xc = jnp.asarray(v), jnp.asarray(v2), jnp.asarray(v2)
        sa, sb, sc = closed.init(xa), cut.init(xb), opened.init(xc)
        for g in _grads(v, 3):
            # A seam vertex's gradient is shared by its copies (they sum to it).
            g2 = np.concatenate([g, g[loop] / 2])
            g2[loop] /= 2
            ua, sa = closed.update(jnp.asarray(g), sa, xa)
            ub, sb = cut.update(jnp.asarray(g2), sb, xb)
            uc, sc = opened.update(jnp.asarray(g2), sc, xc)
            xa, xb, xc = (
                optax.apply_updates(xa, ua),
                optax.apply_updates(xb, ub),
                optax.apply_updates(xc, uc),
            )
        # Welded: the copies move together and the mesh moves as the closed one.
        np.testing.assert_array_equal(np.asarray(xb)[len(v) :], np.asarray(xb)[loop])
        np.testing.assert_allclose(np.asarray(xb)[: len(v)], xa, atol=1e-6)
        # Not welded: the two halves are separate meshes and the seam opens.
        assert np.abs(np.asarray(xc)[len(v) :] - np.asarray(xc)[loop]).max() > 1e-4


def test_density_width_grows_with_the_vertex_count_between_its_bounds():
    rule = M.DensityWidth()
    assert M.NormalFilter().sigma_d == rule and hash(M.NormalFilter()) == hash(M.NormalFilter())
    assert rule.width(1) == rule.width(2562) == 0.5
    assert rule.width(4 * 2562) == pytest.approx(1.0, rel=1e-15)
    assert rule.width(16 * 2562) == rule.width(10**9) == 2.0
    counts = np.unique(np.geomspace(1, 10**7, 300).astype(int))
    assert np.all(np.diff([rule.width(int(n)) for n in counts]) >= 0)
    fixed = M.DensityWidth(sigma_d=0.25, vertices=100, largest=0.25)
    assert {fixed.width(n) for n in (1, 100, 10**6)} == {0.25}
    for kw, error in (
        (dict(sigma_d=0.0), ValueError),
        (dict(sigma_d=math.inf), ValueError),
        (dict(sigma_d=math.nan), TypeError),
        (dict(vertices=0), ValueError),
        (dict(vertices=2562.0), TypeError),
        (dict(largest=0.4), ValueError),
        (dict(largest=math.inf), ValueError),
    ):
        with pytest.raises(error, match=next(iter(kw))):
            M.DensityWidth(**kw)


def test_the_default_width_is_the_rules_on_the_meshs_distinct_vertices():
    # A welded seam adds rows (V) but no vertices (U): the width follows U.
    v, f = toy.icosphere(20)
    v2, f2, _ = seam_mesh(cubified(v), f)
    welded = M.mesh_laplacian(f2, weld_positions=v2)
    assert welded.num_merged == len(v) == 4002 and welded.num_vertices > 4002
    normals = M.vertex_normals(jnp.asarray(v2), f2)
    x = jnp.asarray(np.random.default_rng(0).standard_normal((len(v2), 3)), jnp.float32)

    def filtered(sigma_d):
        data_term = M.NormalFilter(sigma_d, directions=8)
        (out,) = M.bilateral_normal_filter([x], normals, welded, lambda_=LAM, sigma_d=data_term)
        return np.asarray(out)

    rule = M.DensityWidth()
    by_rule = filtered(rule)
    assert rule.width(len(v)) == pytest.approx(0.625, rel=1e-3)
    np.testing.assert_array_equal(by_rule, filtered(rule.width(len(v))))
    assert np.abs(by_rule - filtered(rule.width(welded.num_vertices))).max() > 1e-6
    assert np.abs(by_rule - filtered(M.DEFAULT_NORMAL_SIGMA_D)).max() > 1e-4
    # The transforms' default is the rule.
    default = M.bilateral_large_steps(0.02, welded, LAM, solver=M.CG(tol=1e-7))
    explicit = M.bilateral_large_steps(
        0.02, welded, LAM, M.NormalFilter(rule.width(len(v))), solver=M.CG(tol=1e-7)
    )
    x0 = jnp.asarray(v2)
    updates = [tx.update(x, tx.init(x0), x0)[0] for tx in (default, explicit)]
    np.testing.assert_array_equal(*updates)


def test_update_accepts_extra_args_and_pytrees(small):
    x = {"a": jnp.asarray(cubified(small["v"]))}
    g = {"a": jnp.asarray(_grads(small["v"], 1)[0])}
    mesh = small["mesh"]
    data_term = M.NormalFilter(directions=M.sphere_directions(4))
    for tx in (
        M.large_steps(0.1, mesh),
        M.bilateral_large_steps(0.1, mesh, sigma_d=data_term, prefilter="bilateral"),
        uniform_adam(),
        M.weld_gradients(mesh),
        M.bilateral_smoothing(mesh, sigma_d=data_term),
    ):
        u, _ = tx.update(g, tx.init(x), x, value=jnp.float32(1.0), grad=g)
        assert np.all(np.isfinite(u["a"]))


def test_uniform_adam_bias_correction_for_b2_near_one():
    """b2 = 1 - 1e-9 rounds to 1 in float32; the first step must still be g / max|g|."""
    g = jnp.asarray(np.random.default_rng(2).standard_normal((10, 3)), jnp.float32)
    for b2 in (1 - 1e-9, 1 - 1e-5):
        tx = uniform_adam(0.9, b2, eps=0.0)
        u, _ = tx.update(g, tx.init(g))
        np.testing.assert_allclose(u, g / jnp.abs(g).max(), rtol=1e-4)


def test_normals_options_and_callable(small):
    v = jnp.asarray(cubified(small["v"]))
    f = small["f"]
    ns = {w: np.asarray(M.vertex_normals(v, f, w)) for w in M.NORMALS}
    for n in ns.values():
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.abs(ns["area"] - ns["uniform"]).max() > 1e-3  # they differ on a cube
    g = jnp.asarray(_grads(small["v"], 1)[0])
    dirs = M.sphere_directions(8)
    by_name = M.NormalFilter(normals="angle", directions=dirs)
    by_fn = M.NormalFilter(normals=lambda x: M.vertex_normals(x, f, "angle"), directions=dirs)
    by_name, by_fn = (M.mesh_postfilter(small["mesh"], sigma_d=d) for d in (by_name, by_fn))
    ua, _ = by_name.update(g, by_name.init(v), v)
    ub, _ = by_fn.update(g, by_fn.init(v), v)
    np.testing.assert_allclose(ua, ub, rtol=1e-6)


def test_directions_lloyd_option():
    a, b = M.sphere_directions(32), M.sphere_directions(32, lloyd=False)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    assert np.abs(a - b).max() > 1e-2

    def closest(d):  # largest cosine between two directions
        return np.sort((d @ d.T)[np.triu_indices(len(d), 1)])[-1]

    assert closest(a) < closest(b)  # Lloyd spreads the points


def test_new_options_reject_bad_values(small):
    mesh = small["mesh"]
    with pytest.raises(ValueError, match="sigma_phi"):
        M.bilateral_large_steps(0.1, mesh, sigma_d=M.NormalFilter(sigma_phi=0.0))
    with pytest.raises(ValueError, match="prefilter"):
        M.bilateral_large_steps(0.1, mesh, prefilter="gauss")
    with pytest.raises(ValueError, match="normals"):
        M.mesh_postfilter(mesh, sigma_d=M.NormalFilter(normals="cotan"))
    with pytest.raises(ValueError, match="solver"):
        M.large_steps(0.1, mesh, solver="lu")
    with pytest.raises(ValueError, match="tol"):
        M.large_steps(0.1, mesh, solver=M.CG(tol=0.0))
    with pytest.raises(ValueError, match="maxiter"):
        M.CG(maxiter=0)
    for bad in (-0.01, 0.5, 2.0):
        with pytest.raises(ValueError, match=r"kernel_tol must be >= 0 and < 0\.5"):
            M.NormalFilter(kernel_tol=bad)
    for bad in ("0.1", None, float("nan"), True):
        with pytest.raises(TypeError, match="kernel_tol must be a real number"):
            M.NormalFilter(kernel_tol=bad)
    with pytest.raises(ValueError, match="weld_positions"):
        M.mesh_laplacian(small["f"], weld_positions=np.zeros((3, 3)))


# --- settings objects and the keywords of 0.1.0 ----------------------------------


def test_settings_are_frozen_hashable_and_named_by_shorthands():
    dirs = M.sphere_directions(8)
    data_term = M.NormalFilter(0.3, directions=dirs)
    # An array of directions is kept as a tuple: equal settings compare equal, hash alike.
    assert data_term == M.NormalFilter(0.3, directions=dirs.copy())
    assert hash(data_term) == hash(M.NormalFilter(0.3, directions=dirs.copy()))
    np.testing.assert_array_equal(np.asarray(data_term.directions), dirs)
    assert M.CG() == M.CG(M.DEFAULT_TOL, M.DEFAULT_MAXITER, False) and hash(M.Cholesky())
    with pytest.raises(dataclasses.FrozenInstanceError):
        data_term.sigma_d = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="sigma_d"):
        M.NormalFilter(0.0)
    with pytest.raises(TypeError, match="warm_start"):
        M.CG(warm_start=1)


def _steps(tx, x, grads):
    state, out = tx.init(x), []
    for g in grads:
        u, state = tx.update(jnp.asarray(g), state, x)
        out.append(np.asarray(u))
    return out


OLD_KEYWORDS = dict(
    sigma_phi=0.3, directions=M.sphere_directions(8), normals="uniform", tol=1e-6, maxiter=500
)


@pytest.mark.parametrize(
    "name", ["bilateral_large_steps", "mesh_postfilter", "bilateral_smoothing"]
)
def test_old_keywords_warn_naming_their_field_and_give_the_same_steps(small, name):
    make = getattr(M, name)
    head = (0.02, small["mesh"]) if name == "bilateral_large_steps" else (small["mesh"],)
    fields = {k: OLD_KEYWORDS[k] for k in ("sigma_phi", "directions", "normals")}
    new = make(*head, LAM, M.NormalFilter(0.4, **fields), solver=M.CG(tol=1e-6, maxiter=500))
    with pytest.warns(DeprecationWarning) as caught:
        old = make(*head, LAM, 0.4, **OLD_KEYWORDS)
    said = " ".join(str(w.message) for w in caught)
    for field in ("NormalFilter.sigma_phi", "NormalFilter.directions", "NormalFilter.normals"):
        assert field in said
    assert "CG.tol" in said and "CG.maxiter" in said and f"{name}(tol=...)" in said
    x, grads = jnp.asarray(cubified(small["v"])), _grads(small["v"], 3)
    for a, b in zip(_steps(old, x, grads), _steps(new, x, grads)):
        np.testing.assert_array_equal(a, b)


def test_old_solver_keywords_of_the_other_functions_still_apply(small):
    mesh, x, grads = small["mesh"], jnp.asarray(cubified(small["v"])), _grads(small["v"], 3)
    cg = M.CG(tol=1e-6, warm_start=True)
    field = r"large_steps\((tol|warm_start)=...\).* the field CG\.(tol|warm_start);"
    with pytest.warns(DeprecationWarning, match=field):
        old = M.large_steps(0.02, mesh, LAM, tol=1e-6, warm_start=True)
    new = M.large_steps(0.02, mesh, LAM, solver=cg)
    for a, b in zip(_steps(old, x, grads), _steps(new, x, grads)):
        np.testing.assert_array_equal(a, b)
    b = jnp.asarray(grads[0])
    with pytest.warns(DeprecationWarning, match=r"CG\.(tol|maxiter)"):
        old = M.smoothing_solve(mesh, b, LAM, tol=1e-6, maxiter=50)
    new = M.smoothing_solve(mesh, b, LAM, solver=M.CG(tol=1e-6, maxiter=50))
    np.testing.assert_array_equal(old, new)
    normals = M.vertex_normals(x, mesh)
    with pytest.warns(DeprecationWarning, match=r"NormalFilter\.(directions|sigma_phi)"):
        (old,) = M.bilateral_normal_filter([b], normals, mesh, directions=8, sigma_phi=0.3)
    data_term = M.NormalFilter(directions=8, sigma_phi=0.3)
    (new,) = M.bilateral_normal_filter([b], normals, mesh, sigma_d=data_term)
    np.testing.assert_array_equal(old, new)
    # optax.inject_hyperparams binds them as one keyword, `deprecated`.
    with pytest.warns(DeprecationWarning, match="CG.tol"):
        M.laplacian_smoothing(mesh, deprecated={"tol": 1e-6})


def test_old_keywords_keep_their_checks_and_unknown_ones_raise(small):
    mesh = small["mesh"]
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="warm_start"):
        M.bilateral_large_steps(0.1, mesh, solver="cholesky", warm_start=True)
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="sigma_phi"):
        M.bilateral_large_steps(0.1, mesh, sigma_phi=0.0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'sigma_phi'"):
        M.large_steps(0.1, mesh, sigma_phi=0.3)
    with pytest.raises(TypeError, match="unexpected keyword argument 'tolerance'"):
        M.bilateral_large_steps(0.1, mesh, tolerance=1e-3)


@pytest.mark.filterwarnings("ignore:optax_bilateral.mesh is deprecated:DeprecationWarning")
def test_scale_by_uniform_adam_is_a_deprecated_alias_of_the_shared_uniform_adam():
    import optax_bilateral.mesh as old_name

    g = jnp.asarray(np.random.default_rng(4).standard_normal((10, 3)), jnp.float32)
    for module in (M, old_name):
        with pytest.warns(DeprecationWarning, match="second_moment=.uniform"):
            tx = module.scale_by_uniform_adam(0.8, 0.95, 1e-8)
        ref = uniform_adam(0.8, 0.95, 1e-8)
        np.testing.assert_array_equal(tx.update(g, tx.init(g))[0], ref.update(g, ref.init(g))[0])
        with pytest.warns(DeprecationWarning, match="PostfilterState"):
            assert module.ScaleByUniformAdamState._fields == ("count", "mu", "nu")
        assert "scale_by_uniform_adam" not in module.__all__
    with pytest.raises(AttributeError):
        M.scale_by_uniform_adams  # noqa: B018


# --- the toy scene --------------------------------------------------------------


@pytest.mark.parametrize("freq", [1, 3, 8])
def test_icosphere_is_closed_outward_and_counts(freq):
    v, f = toy.icosphere(freq)
    assert len(v) == 10 * freq**2 + 2 and len(f) == 20 * freq**2
    edges, _ = toy._edge_faces(f)  # raises unless every edge has two faces
    assert len(v) - len(edges) + len(f) == 2  # Euler characteristic of a sphere
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(np.sum(n * v[f].mean(1), 1) > 0)


def test_hausdorff_to_cube_known_values():
    v, f = toy.icosphere(8)
    # Unit sphere vs cube of half 0.55: the sphere's axis points are 0.45 from the faces.
    assert abs(toy.hausdorff_to_cube(v, f, 0.55) - 0.45) < 1e-3
    # The same mesh pushed onto the cube: only the facets bridging its edges are off
    # (by about one facet width at this resolution), far below the sphere's 0.45.
    assert toy.hausdorff_to_cube(cubified(v) * 1.1, f, 0.55) < 0.15


def test_render_target_and_gradient_are_finite():
    scene = toy.make_scene(num_views=4, resolution=24, views_per_iteration=2)
    v, f = toy.icosphere(4)
    r = toy.MeshRenderer(scene, f)
    frame = r.frame(v, np.random.default_rng(0))
    (_, loss), g = jax.value_and_grad(lambda x: r.loss(x, frame), has_aux=True)(jnp.asarray(v))
    assert np.isfinite(loss) and np.all(np.isfinite(g)) and np.abs(g).max() > 0
    img = toy.render_target(scene, 0)
    # The cube covers some pixels but not all; covered pixels have a lit colour.
    assert 0 < (img.sum(-1) > 0).mean() < 1


def test_public_module_exports_the_transforms_and_mesh_is_its_deprecated_alias():
    import importlib

    import optax_bilateral as ob
    import optax_bilateral.triangle_mesh as obtm

    with pytest.warns(DeprecationWarning, match="import optax_bilateral.triangle_mesh"):
        obm = importlib.reload(importlib.import_module("optax_bilateral.mesh"))
    from optax_bilateral.mesh import large_steps  # the former spelling keeps working

    assert "mesh" not in ob.__all__
    with pytest.warns(DeprecationWarning, match="DEFAULT_NORMAL_SIGMA_D"):
        assert obtm.DEFAULT_SIGMA_D == obtm.DEFAULT_NORMAL_SIGMA_D == 0.5

    assert ob.triangle_mesh is obtm and ob.mesh is obm
    assert obm.__all__ == obtm.__all__
    assert {n for n in vars(obm) if not n.startswith("_")} == set(obtm.__all__)
    for name in obtm.__all__:
        assert getattr(obm, name) is getattr(obtm, name) is getattr(M, name), name
    assert large_steps is M.large_steps
