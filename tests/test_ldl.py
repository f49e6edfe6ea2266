"""The mesh solves' sparse LDL^T factor (SciPy's SuperLU in METIS' nested-dissection order,
regrouped into parts and a top) and its sweeps (the extension's ``ldl_solve``, SciPy's
triangular solves where it does not load): against dense float64 solves, on the Laplacian
systems the mesh transforms build and on the extremes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from optax_bilateral import triangle_mesh as M
from optax_bilateral._src import extension
from optax_bilateral._src.mesh import laplacian
from optax_bilateral.toy import triangle_mesh as toy

pytest.importorskip("pymetis")
native, _ = extension.loaded()


def system(frequency: int, lam: float):
    """(the factor cache, the dense M = I + lam L) of an icosphere."""
    _, f = toy.icosphere(frequency)
    mesh = M.mesh_laplacian(f)
    n = mesh.num_merged
    dense = np.eye(n)
    nb = np.asarray(mesh.neighbors)
    for i in range(n):
        for j in nb[i]:
            if j < n:
                dense[i, j] -= lam
                dense[i, i] += lam
    return laplacian._host_cholesky(mesh), dense


@pytest.mark.parametrize("lam", [0.0, 0.3, 19.0, 1e4])
@pytest.mark.parametrize("columns", [1, 3, 4, 5, 64, 130])
def test_factor_solves_the_laplacian_system(lam, columns):
    host, dense = system(4, lam)
    b = np.random.default_rng(columns).normal(size=(len(dense), columns))
    want = np.linalg.solve(dense, b)
    fac = host.factor(lam)
    for solve in (fac.solve, fac._solve_scipy):
        np.testing.assert_allclose(solve(b), want, rtol=0, atol=1e-10 * np.abs(want).max())
        got32 = solve(b.astype(np.float32))
        assert got32.dtype == np.float32
        # float32 sweeps: the conditioning of M (at most 1 + 2 lam max degree) times rounding.
        cond = np.linalg.cond(dense)
        np.testing.assert_allclose(got32, want, atol=3e-7 * cond * np.abs(want).max())


@pytest.mark.skipif(native is None, reason="the extension did not load: nothing to compare")
@pytest.mark.parametrize("threads", ["1", "2", "3"])
@pytest.mark.parametrize("columns", [3, 33, 128])  # narrow, register chunks and a tail, blocks
def test_native_sweeps_equal_scipy_on_any_thread_count(monkeypatch, threads, columns):
    monkeypatch.setenv(extension.THREADS_ENV, threads)
    host, _ = system(8, 19.0)
    fac = host.factor(19.0)
    b = np.random.default_rng(0).normal(size=(fac.dinv.size, columns))
    want = fac._solve_scipy(b)
    for _ in range(10):  # each solve takes the last one's buffers: a stale or stray read shows
        np.testing.assert_allclose(fac.solve(b), want, rtol=0, atol=1e-11)
        np.testing.assert_allclose(fac.solve(b.astype(np.float32)), want, rtol=0, atol=1e-4)


def test_smoothing_solve_without_the_extension_equals_with_it(monkeypatch):
    _, f = toy.icosphere(4)
    mesh = M.mesh_laplacian(f)
    b = jnp.asarray(np.random.default_rng(1).normal(size=(mesh.num_vertices, 3)), jnp.float32)
    with_it = M.smoothing_solve(mesh, b, 7.0, solver="cholesky")
    monkeypatch.setattr(extension, "loaded", lambda: (None, "ImportError: switched off"))
    monkeypatch.setattr(extension, "registered", lambda: (False, "ImportError: switched off"))
    assert type(laplacian.System.of(mesh, M.Cholesky(), 7.0).host) is laplacian._Cholesky
    without = M.smoothing_solve(mesh, b, 7.0, solver="cholesky")
    np.testing.assert_allclose(without, with_it, rtol=1e-5, atol=1e-6)


def test_half_precision_fields_are_solved_in_float32():
    _, f = toy.icosphere(3)
    mesh = M.mesh_laplacian(f)
    b = np.random.default_rng(2).normal(size=(mesh.num_vertices, 2))
    want = M.smoothing_solve(mesh, jnp.asarray(b, jnp.float32), 3.0, solver="cholesky")
    for dtype in (jnp.bfloat16, jnp.float16):
        got = M.smoothing_solve(mesh, jnp.asarray(b, dtype), 3.0, solver="cholesky")
        assert got.dtype == dtype
        np.testing.assert_allclose(np.asarray(got, np.float32), want, atol=2e-2)


def _arrays():
    """A sound 3 x 3 factor: supernodes {0} with row 2 below it, and {1, 2}."""
    return dict(
        first=np.array([0, 1, 3], np.int32),
        row_ptr=np.array([0, 1, 1], np.int32),
        rows=np.array([2], np.int32),
        block_ptr=np.array([0, 2, 6], np.int64),
        values=np.full(6, 0.5),
        dinv=np.ones(3),
        perm=np.array([2, 0, 1], np.int32),
        part_ptr=np.array([0, 2], np.int32),
        b=np.ones((3, 2)),
    )


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_native_sweeps_take_the_sound_factor():
    args = _arrays()
    native.ldl_solve(*args.values(), 1)
    # A = P (I + L) D (I + L)^T P^T with L[2, 0] = 0.5 (block (0, 1)) and L[2, 1] = 0.5.
    lower = np.eye(3)
    lower[2, 0] = lower[2, 1] = 0.5
    p = np.zeros((3, 3))
    p[[2, 0, 1], [0, 1, 2]] = 1
    a = p @ lower @ lower.T @ p.T
    np.testing.assert_allclose(a @ args["b"], np.ones((3, 2)), atol=1e-12)


@pytest.mark.skipif(native is None, reason="the extension did not load")
@pytest.mark.parametrize(
    "change, message",
    [
        (dict(rows=np.array([0], np.int32)), "past its columns"),
        (dict(rows=np.array([3], np.int32)), "within n"),
        (dict(first=np.array([0, 1, 2], np.int32)), "from 0 to n"),
        (dict(first=np.array([0, 0, 3], np.int32)), "at least one column"),
        (dict(row_ptr=np.array([0, 1, 2], np.int32)), "from 0 to the rows"),
        (dict(block_ptr=np.array([0, 2, 7], np.int64)), "from 0 to the values"),
        (dict(block_ptr=np.array([0, 1, 6], np.int64)), r"rows below\) x columns"),
        (dict(first=np.array([0, 3], np.int32)), "one entry per supernode"),
        (dict(perm=np.array([0, 0, 1], np.int32)), "permutation"),
        (dict(perm=np.array([0, 1, 3], np.int32)), "permutation"),
        (dict(perm=np.array([0, 1, 2], np.int64)), "perm must be int32"),
        (dict(block_ptr=np.array([0, 2, 6], np.int32)), "block_ptr must be int64"),
        (dict(values=np.full(6, 0.5, np.float32)), "b's dtype"),
        (dict(b=np.ones((3, 2), np.int32)), "float32 or float64"),
        (dict(b=np.ones(7)), "\\(n, k\\)"),
        (dict(perm=np.array([0, 1], np.int32)), "perm must have n entries"),
        # {0}'s row 2 is {1, 2}'s: the two cannot be parts swept at once.
        (dict(part_ptr=np.array([0, 1, 2], np.int32)), "its own or the top's"),
        (dict(part_ptr=np.array([0, 3], np.int32)), "at most the supernodes"),
        (dict(part_ptr=np.array([0, 2, 1], np.int32)), "must not decrease"),
        (dict(part_ptr=np.array([0], np.int32)), "one entry per part"),
        (dict(part_ptr=np.array([0, 2], np.int64)), "part_ptr must be int32"),
    ],
)
def test_native_sweeps_refuse_a_broken_factor(change, message):
    args = _arrays() | change
    with pytest.raises(ValueError, match=message):
        native.ldl_solve(*args.values(), 1)


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_native_sweeps_refuse_bad_buffers():
    args = _arrays()
    with pytest.raises(ValueError, match="threads"):
        native.ldl_solve(*args.values(), 0)
    frozen = args["b"].copy()
    frozen.flags.writeable = False
    with pytest.raises((ValueError, BufferError), match=r"[Ww]ritable|read-only"):
        native.ldl_solve(*(args | dict(b=frozen)).values(), 1)
    with pytest.raises(TypeError):
        native.ldl_solve(*(args | dict(b=[1.0, 2.0])).values(), 1)
    strided = np.ones((3, 4))[:, ::2]
    with pytest.raises((ValueError, BufferError)):
        native.ldl_solve(*(args | dict(b=strided)).values(), 1)


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_native_sweeps_take_empty_systems():
    empty = dict(
        first=np.zeros(1, np.int32),
        row_ptr=np.zeros(1, np.int32),
        rows=np.zeros(0, np.int32),
        block_ptr=np.zeros(1, np.int64),
        values=np.zeros(0),
        dinv=np.zeros(0),
        perm=np.zeros(0, np.int32),
        part_ptr=np.zeros(2, np.int32),
        b=np.zeros((0, 3)),
    )
    native.ldl_solve(*empty.values(), 2)
    args = _arrays() | dict(b=np.zeros((3, 0)))
    native.ldl_solve(*args.values(), 2)


@pytest.mark.parametrize("frequency", [1, 4, 12])
def test_supernodes_hold_the_factor_exactly(frequency):
    """The blocks, read as the sweeps read them, rebuild L's compressed columns; each
    supernode's columns share their rows below it; a mesh's factor has wide supernodes."""
    host, _ = system(frequency, 19.0)
    fac = host.factor(19.0)
    n, sn = len(fac.dinv), fac.supernodes
    want = np.zeros((n, n))
    cols = np.repeat(np.arange(n), np.diff(fac.colptr))
    want[fac.rows, cols] = fac.values
    got = np.zeros((n, n))
    for k in range(len(sn.first) - 1):
        j0, j1 = sn.first[k], sn.first[k + 1]
        s = j1 - j0
        below = sn.rows[sn.row_ptr[k] : sn.row_ptr[k + 1]]
        block = sn.values[sn.block_ptr[k] : sn.block_ptr[k + 1]].reshape(s + len(below), s)
        rows = np.concatenate([np.arange(j0, j1), below])
        for t in range(s):
            keep = rows > j0 + t
            got[rows[keep], j0 + t] = block[keep, t]
            # every column of the run has exactly the rows below the run, and the run below it
            col = fac.rows[fac.colptr[j0 + t] : fac.colptr[j0 + t + 1]]
            np.testing.assert_array_equal(col, rows[keep])
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(sn.single, sn.values.astype(np.float32))
    wide = np.diff(sn.first) >= 4
    in_wide = (fac.colptr[sn.first[1:]] - fac.colptr[sn.first[:-1]])[wide].sum()
    assert in_wide > (0.5 if frequency >= 12 else 0) * len(fac.values)


# ----------------------------------------------------------------------------- inside XLA


def _fixed_and_traced(mesh, b, lam):
    """The solve with lambda known when traced (the extension's FFI call) and traced (the
    host callback)."""
    fixed = jax.jit(lambda b: M.smoothing_solve(mesh, b, lam, solver="cholesky"))(b)
    traced = jax.jit(lambda b, lam: M.smoothing_solve(mesh, b, lam, solver="cholesky"))(b, lam)
    return fixed, traced


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_a_known_lambda_is_solved_inside_xla_as_on_the_host():
    _, f = toy.icosphere(6)
    mesh = M.mesh_laplacian(f)
    system = laplacian.System.of(mesh, M.Cholesky(), 19.0)
    assert isinstance(system.host, laplacian._Pinned)
    assert system.host is not laplacian.System.of(mesh, M.Cholesky(), 7.0).host
    rng = np.random.default_rng(3)
    for dtype, tol in ((jnp.float32, 1e-6), (jnp.float64, 1e-13), (jnp.bfloat16, 0)):
        with jax.enable_x64(dtype == jnp.float64):
            b = jnp.asarray(rng.normal(size=(mesh.num_vertices, 5)), dtype)
            fixed, traced = _fixed_and_traced(mesh, b, 19.0)
            assert fixed.dtype == traced.dtype == dtype
            np.testing.assert_allclose(
                np.asarray(fixed, np.float64), np.asarray(traced, np.float64), atol=tol
            )


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_the_ffi_solve_keeps_grad_and_vmap():
    _, f = toy.icosphere(4)
    mesh = M.mesh_laplacian(f)
    rng = np.random.default_rng(4)
    b = jnp.asarray(rng.normal(size=(mesh.num_vertices, 3)), jnp.float32)
    r = jnp.asarray(rng.normal(size=(mesh.num_vertices, 3)), jnp.float32)

    def loss(b, lam):
        return jnp.sum(M.smoothing_solve(mesh, b, lam, solver="cholesky") * r)

    # M is symmetric: d/db <M^-1 b, r> = M^-1 r, through the FFI call and the host's alike.
    g_fixed = jax.jit(jax.grad(lambda b: loss(b, 19.0)))(b)
    g_traced = jax.jit(jax.grad(loss))(b, jnp.float32(19.0))
    np.testing.assert_allclose(g_fixed, g_traced, atol=1e-6)
    np.testing.assert_allclose(
        g_fixed, M.smoothing_solve(mesh, r, 19.0, solver="cholesky"), atol=1e-6
    )
    batch = jnp.stack([b, 2 * b, -b])
    batched = jax.jit(jax.vmap(lambda b: M.smoothing_solve(mesh, b, 19.0, solver="cholesky")))(
        batch
    )
    for x, y in zip(batched, batch):
        np.testing.assert_allclose(
            x, M.smoothing_solve(mesh, y, 19.0, solver="cholesky"), atol=1e-6
        )


@pytest.mark.skipif(native is None, reason="the extension did not load")
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("columns", [1, 3, 4, 16, 64, 65, 130])
def test_a_right_hand_side_in_the_factors_order_gives_the_same_bits(dtype, columns):
    # 4 to 64 columns are swept where XLA wrote them (no working copy), the others through one;
    # either way the sums are those of the caller's order, row for row.
    _, f = toy.icosphere(6)
    mesh = M.mesh_laplacian(f)
    host = laplacian.System.of(mesh, M.Cholesky(), 19.0).host
    order = laplacian.factor_order(host)
    assert order is not None
    np.testing.assert_array_equal(order.perm[order.inverse], np.arange(mesh.num_merged))
    with jax.enable_x64(dtype == jnp.float64):
        b = jnp.asarray(
            np.random.default_rng(columns).normal(size=(mesh.num_merged, columns)), dtype
        )
        solve = jax.jit(
            lambda b, ordered: laplacian._ffi_solve(host.factor, b, ordered), static_argnums=1
        )
        want = np.asarray(solve(b, False))
        got = np.asarray(solve(b[order.perm], True))
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want[order.perm])


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_an_ordered_solve_keeps_grad_and_needs_a_pinned_factor():
    _, f = toy.icosphere(4)
    mesh = M.mesh_laplacian(f)
    system = laplacian.System.of(mesh, M.Cholesky(), 19.0)
    order = laplacian.factor_order(system.host)
    rng = np.random.default_rng(5)
    b, r = (jnp.asarray(rng.normal(size=(mesh.num_merged, 4)), jnp.float32) for _ in range(2))
    args = (mesh.neighbors, mesh.degree)

    def loss(b, ordered):
        rows = order.perm if ordered else slice(None)
        x = laplacian.solve_columns(
            system.host, *args, b[rows], jnp.float32(19.0), 0.0, 0, None, ordered=ordered
        )
        return jnp.sum(x * r[rows])

    # The transposed solve goes through the matvec in the factor's order: the same gradient.
    g_ordered = jax.jit(jax.grad(lambda b: loss(b, True)))(b)
    g_caller = jax.jit(jax.grad(lambda b: loss(b, False)))(b)
    np.testing.assert_allclose(g_ordered, g_caller, atol=1e-6)
    _, tangent = jax.jvp(lambda b: loss(b, True), (b,), (r,))
    _, want = jax.jvp(lambda b: loss(b, False), (b,), (r,))
    np.testing.assert_allclose(tangent, want, rtol=1e-5)
    assert laplacian.factor_order(laplacian.System.of(mesh, M.CG(), 19.0).host) is None
    with pytest.raises(ValueError, match="ordered right-hand sides need a factor"):
        laplacian.solve_columns(None, *args, b, jnp.float32(19.0), 1e-5, 10, None, ordered=True)


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_the_ffi_solve_names_a_missing_factor_and_register_refuses_a_broken_one():
    with pytest.raises(Exception, match="no factor is stored under id"):
        jax.block_until_ready(laplacian._ffi_solve(2**40, jnp.ones((3, 2))))
    args = _arrays()
    del args["b"]
    with pytest.raises(ValueError, match="permutation"):
        native.register_factor(*(args | dict(perm=np.array([0, 0, 1], np.int32))).values())
    with pytest.raises(ValueError, match="float64"):
        native.register_factor(*(args | dict(values=np.full(6, 0.5, np.float32))).values())
    assert native.register_factor(*args.values()) >= 1


def test_supernodes_join_only_columns_with_the_same_rows_below():
    # Column 0's rows {1, 3}: its first is column 1, but its other row (3) is not column 1's
    # (2), so 0 stands alone; column 1's rows {2} are column 2's and nothing else: {1, 2}.
    colptr = np.array([0, 2, 3, 3, 3], np.int32)
    rows = np.array([1, 3, 2], np.int32)
    np.testing.assert_array_equal(laplacian._supernode_starts(colptr, rows), [0, 1, 3, 4])
    sn = laplacian._Supernodes.of(colptr, rows, np.array([0.1, 0.2, 0.3]))
    np.testing.assert_array_equal(sn.rows, [1, 3])  # below {0}: 1, 3; below {1, 2}: none
    np.testing.assert_array_equal(sn.block_ptr, [0, 3, 7, 8])
    assert laplacian._supernode_starts(np.zeros(1, np.int32), np.zeros(0, np.int32)).tolist() == [0]
    # A part's bound starts a supernode, whatever the rows say.
    np.testing.assert_array_equal(laplacian._supernode_starts(colptr, rows, [2]), [0, 1, 2, 3, 4])


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_native_sweeps_keep_the_first_bad_buffer_error():
    # The first argument that is no buffer raises; the others are not asked for theirs.
    args = _arrays() | dict(first=[0, 1, 3], perm="not a buffer")
    with pytest.raises(TypeError):
        native.ldl_solve(*args.values(), 1)
    del args["b"]
    with pytest.raises(TypeError):
        native.register_factor(*args.values())


def test_split_gives_the_parts_whole_subtrees_and_the_top_the_rest():
    # Two chains of 4 columns (0-3, 4-7) under a root 8, and a lone column 9 under it.
    parent = np.array([1, 2, 3, 8, 5, 6, 7, 8, -1, 8])
    weight = np.ones(10)
    np.testing.assert_array_equal(laplacian._split(parent, weight, 1), np.zeros(10))
    label = laplacian._split(parent, weight, 2)
    assert label[8] == 2  # the root is the top
    assert len(set(label[:4])) == 1 and len(set(label[4:8])) == 1 and label[0] != label[4]
    # a heavier second chain: the lone column goes with the first
    label = laplacian._split(parent, np.array([1, 1, 1, 1, 2, 2, 2, 2, 1, 1.0]), 2)
    assert label[9] == label[0] != label[4]


@pytest.mark.parametrize("parts", [1, 2, 3])
def test_the_ordering_splits_the_factor_into_independent_balanced_parts(monkeypatch, parts):
    """A part's rows below are its own or the top's; the parts carry most of the sweep."""
    monkeypatch.setenv(extension.THREADS_ENV, str(parts))
    _, f = toy.icosphere(12)
    mesh = M.mesh_laplacian(f)
    fac = laplacian._Cholesky(np.asarray(mesh.neighbors), np.asarray(mesh.degree)).factor(19.0)
    sn = fac.supernodes
    assert len(fac.part_ptr) == parts + 1
    starts = sn.first[fac.part_ptr]
    top = starts[-1]
    work = []
    for p in range(parts):
        cols = slice(fac.colptr[starts[p]], fac.colptr[starts[p + 1]])
        rows = fac.rows[cols]
        assert np.all((rows < starts[p + 1]) | (rows >= top))
        work.append(cols.stop - cols.start)
    top_work = len(fac.rows) - sum(work)
    assert top_work + max(work) < (0.6 if parts > 1 else 1.0001) * len(fac.rows)


@pytest.mark.skipif(native is None, reason="the extension did not load")
def test_the_solve_does_not_depend_on_the_threads(monkeypatch):
    monkeypatch.setenv(extension.THREADS_ENV, "3")
    _, f = toy.icosphere(8)
    mesh = M.mesh_laplacian(f)
    fac = laplacian._Cholesky(np.asarray(mesh.neighbors), np.asarray(mesh.degree)).factor(19.0)
    b = np.random.default_rng(5).normal(size=(fac.dinv.size, 70)).astype(np.float32)
    want = fac.solve(b)
    for threads in (1, 2, 4):
        x = b.copy()
        native.ldl_solve(*fac.arrays(single=True), x, threads)
        np.testing.assert_array_equal(x, want)


@pytest.mark.parametrize("parts", ["2", "5"])
def test_a_mesh_in_pieces_splits_and_solves(monkeypatch, parts):
    """Two spheres and a patch: the elimination tree has three roots."""
    monkeypatch.setenv(extension.THREADS_ENV, parts)
    _, f = toy.icosphere(3)
    n = int(f.max()) + 1
    mesh = M.mesh_laplacian(np.concatenate([f, f + n, f[:4] + 2 * n]))
    host = laplacian._Cholesky(np.asarray(mesh.neighbors), np.asarray(mesh.degree))
    fac = host.factor(19.0)
    assert len(fac.part_ptr) == int(parts) + 1
    b = np.random.default_rng(6).normal(size=(fac.dinv.size, 5))
    np.testing.assert_allclose(host._matrix(19.0) @ fac.solve(b), b, atol=1e-12)
