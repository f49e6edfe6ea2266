"""Grids sharded across devices: same numbers as one device, shardings kept, halos only.

The suite runs with one CPU device, and the device count is fixed when jax starts,
so the checks run in a child process (this file, run as a script) with
``XLA_FLAGS=--xla_force_host_platform_device_count=8``, on meshes 8x1 and 4x2. The
child prints one JSON record per check; the tests below assert on them.

Two routes are checked:

* explicit meshes (``jax.make_mesh``'s default): the filter runs per device with
  explicit halo exchange (``optax_bilateral/_src/filter/sharded.py``);
* auto meshes: the single-device filter, split by XLA's SPMD partitioner.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

# Filtered values are O(1) means of O(1) inputs, computed in float32 with the same terms
# in the same order; only XLA's fusion (FMA contraction) differs: a few ulps, far below 1e-5.
TOL = 1e-5

ROOT = pathlib.Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------------------
# The child: runs with 8 virtual CPU devices.


def _child() -> None:  # pragma: no cover - runs in the subprocess
    import functools
    import math
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax
    from jax.sharding import AxisType, Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    import optax_bilateral as ob
    from experiments.benchmarks import collectives

    assert jax.device_count() == 8, jax.device_count()
    records = []

    clock = [time.process_time()]

    def emit(**rec):
        rec["cpu_s"] = round(time.process_time() - clock[0], 1)  # CPU seconds of this check
        clock[0] = time.process_time()
        records.append(rec)
        print(json.dumps(rec), flush=True)

    def device_mesh_of(shape, axis_type):
        devs = np.array(jax.devices()[: math.prod(shape)]).reshape(shape)
        return Mesh(devs, ("x", "y"), axis_types=(axis_type,) * 2)

    def max_diff(a, b):
        """Largest |a - b|; inf if NaNs (a passed-through bad gradient) differ in place."""
        worst = 0.0
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
            if not np.array_equal(np.isnan(x), np.isnan(y)):
                return math.inf
            if x.size:
                worst = max(worst, float(np.max(np.abs(np.where(np.isnan(x), 0, x - y)))))
        return worst

    def stats(compiled):
        return collectives.collective_stats(compiled.as_text(), branch=None)  # worst branch

    def filter_pair(m, v, g, mk, **kw):
        return ob.atrous_bilateral((m, v), g, mask=mk, **kw)

    def halo_of(shape, spec, device_mesh, levels, separable):
        """collectives.halo_bytes of a filter case: 5 field channels, a 3-channel guide."""
        blocks = [1] * len(shape)
        for a, e in enumerate(tuple(spec)[: len(shape)]):
            if e is not None:
                blocks[a] = device_mesh.shape[e]
        return collectives.halo_bytes(shape, blocks, levels, 5, 3, separable=separable)

    key = jax.random.PRNGKey(0)

    # --- The filter itself, explicit meshes: every spatial split, multi-hop halos, masks.
    filter_cases = [
        # (grid, mesh shape, spec over (x, y), levels, separable, mask). 16 rows in 8 blocks of 2
        # with offsets up to 8: halos of 4 hops.
        ((16, 12), (8, 1), P("x", "y"), 3, False, True),
        ((16, 16), (4, 2), P("y", "x"), 2, False, False),
        ((8, 8, 4), (4, 2), P("x", "y"), 2, True, True),
        ((8, 8, 4), (4, 2), P(None, "x", "y"), 1, False, False),
        # Guide and sigma_d scaled by 2^100: squared distances would overflow float32; each
        # block rescales its own guide (a power of two: same weights, no all-reduce).
        ((16, 16), (4, 2), P("x", "y"), 2, True, False, 2.0**100),
    ]

    def case_arrays(i, shape, use_mask):
        """(m, v, guide, mask) of filter case ``i``."""
        k = jax.random.fold_in(key, i)
        m = jax.random.normal(k, shape + (2,))
        v = jax.random.uniform(jax.random.fold_in(k, 1), shape + (3,))
        guide = jax.random.uniform(jax.random.fold_in(k, 2), shape + (3,))
        mask = (jax.random.uniform(jax.random.fold_in(k, 3), shape) > 0.2) if use_mask else None
        return m, v, guide, mask

    for i, (shape, mesh_shape, spec, levels, sep, use_mask, *scale) in enumerate(filter_cases):
        scale = scale[0] if scale else 1.0
        device_mesh = device_mesh_of(mesh_shape, AxisType.Explicit)
        m, v, guide, mask = case_arrays(i, shape, use_mask)
        axes = tuple(range(len(shape)))
        # The pure-JAX per-block kernel, which exchanges each pass's halo (the native one,
        # which takes each level's box at once, is checked below).
        kw = dict(sigma_d=0.3, levels=levels, spatial_axes=axes, separable=sep, kernel="xla_cpu")
        ref = ob.atrous_bilateral((m, v), guide, mask=mask, **kw)
        sh = NamedSharding(device_mesh, spec)
        args = [jax.device_put(a, sh) for a in (m, v, guide)]
        margs = (
            [jax.device_put(mask, NamedSharding(device_mesh, P(*tuple(spec)[: len(shape)])))]
            if use_mask
            else [None]
        )
        kw_s = dict(kw, sigma_d=kw["sigma_d"] * scale)
        args[2] = args[2] * scale
        fn = jax.jit(functools.partial(filter_pair, **kw_s))
        compiled = fn.lower(*args, *margs).compile()
        out = compiled(*args, *margs)
        st = stats(compiled)
        # Fields per level plus the guide once at the widest radius: what must move.
        halo = halo_of(shape, spec, device_mesh, levels, separable=sep)
        emit(
            check="filter",
            case=f"{shape} {mesh_shape} {spec} F={levels} "
            f"{'sep' if sep else 'full'}{' mask' if use_mask else ''}"
            f"{f' guide x{scale:g}' if scale != 1 else ''}",
            separable=sep,
            max_diff=max_diff(out, ref),
            sharding_kept=all(o.sharding.is_equivalent_to(sh, len(shape) + 1) for o in out),
            kinds=sorted(k for k, s in st.items() if s["count"]),
            permute_bytes=st["collective-permute"]["bytes"],
            minimum=halo["minimum"],
            box=halo["box"],
        )

    # --- The same cases with the native kernel on every block (each level on the block and
    # its reach): equal to the single-device native filter, shardings kept.
    for i, (shape, mesh_shape, spec, levels, sep, use_mask, *scale) in enumerate(filter_cases):
        scale = scale[0] if scale else 1.0
        device_mesh = device_mesh_of(mesh_shape, AxisType.Explicit)
        m, v, guide, mask = case_arrays(i, shape, use_mask)
        guide = guide * scale
        axes = tuple(range(len(shape)))
        kw = dict(
            sigma_d=0.3 * scale, levels=levels, spatial_axes=axes, separable=sep, kernel="native"
        )
        ref = ob.atrous_bilateral((m, v), guide, mask=mask, **kw)
        sh = NamedSharding(device_mesh, spec)
        args = [jax.device_put(a, sh) for a in (m, v, guide)]
        mk = None
        if use_mask:
            mk = jax.device_put(mask, NamedSharding(device_mesh, P(*tuple(spec)[: len(shape)])))
        compiled = jax.jit(functools.partial(filter_pair, **kw)).lower(*args, mk).compile()
        out = compiled(*args, mk)
        st = stats(compiled)
        # Each level's box at once, corners included, in either mode.
        halo = halo_of(shape, spec, device_mesh, levels, separable=False)
        emit(
            check="filter_native",
            case=f"{shape} {mesh_shape} {spec} F={levels} {'sep' if sep else 'full'}",
            max_diff=max_diff(out, ref),
            sharding_kept=all(o.sharding.is_equivalent_to(sh, len(shape) + 1) for o in out),
            kinds=sorted(k for k, s in st.items() if s["count"]),
            permute_bytes=st["collective-permute"]["bytes"],
            minimum=halo["minimum"],
            box=halo["box"],
        )

    # --- guide="self": every level guided by its own input; a field whose channels are split
    # too (they are gathered per block for the guide's norm, and split again after).
    device_mesh = device_mesh_of((4, 2), AxisType.Explicit)
    x = jax.random.normal(jax.random.fold_in(key, 99), (16, 12, 4))
    mask = jax.random.uniform(jax.random.fold_in(key, 98), (16, 12)) > 0.2
    # Separable only: full mode's halos are checked above, its self-guiding in test_atrous.
    kw = dict(sigma_d=0.3, levels=3, spatial_axes=(0, 1), separable=True, log_guide=True)
    ref = ob.atrous_bilateral((x, x * x), "self", mask=mask, **kw)
    sh = NamedSharding(device_mesh, P("x", None, "y"))
    xs = jax.device_put(x, sh)
    ms = jax.device_put(mask, NamedSharding(device_mesh, P("x", None)))
    out = jax.jit(lambda a, mk: ob.atrous_bilateral((a, a * a), "self", mask=mk, **kw))(xs, ms)
    emit(
        check="filter_self",
        case="(16, 12, 4) 4x2 P('x', None, 'y') F=3 sep mask log",
        max_diff=max_diff(out, ref),
        sharding_kept=all(o.sharding.is_equivalent_to(sh, 3) for o in out),
    )

    # --- The transforms and bilateral_adam, explicit and auto meshes.
    params = {
        "tex": jax.random.uniform(key, (16, 16, 3), minval=0.05, maxval=1.0),
        "vol": jax.random.uniform(jax.random.fold_in(key, 1), (8, 8, 4, 2), minval=0.05),
        "bias": jnp.ones((5,)),
    }
    grads = jax.tree.map(lambda p: jax.random.normal(jax.random.fold_in(key, 10), p.shape), params)
    grads["tex"] = grads["tex"].at[3, 5, 1].set(jnp.nan)  # a non-finite texel: the masked path

    def make(names, sep, levels, masked):
        # masked: mask_unobserved=True, one code path (no lax.cond): halves the compile.
        kw = dict(sigma_d=0.2, levels=levels, separable=sep)

        def filtered(learning_rate, sigma_d, levels, separable, mask_unobserved):
            """bilateral_adam's chain with the postfilter's knobs, prefilter + postfilter."""
            knobs = dict(levels=levels, separable=separable, mask_unobserved=mask_unobserved)
            return optax.chain(
                ob.prefilter(sigma_d, **knobs),
                ob.postfilter(0.2, sigma_d=sigma_d, **knobs),
                optax.scale_by_learning_rate(learning_rate),
            )

        adam = optax.inject_hyperparams(
            filtered, static_args=("levels", "separable", "mask_unobserved")
        )
        txs = {
            "prefilter": lambda: ob.prefilter(mask_unobserved=masked, **kw),
            "postfilter": lambda: ob.postfilter(mask_unobserved=masked, **kw),
            "scale_by_adam": ob.scale_by_adam,
            # sigma_d traced (a hyperparameter in the state), prefilter + postfilter.
            "bilateral_adam": lambda: adam(learning_rate=0.1, mask_unobserved=masked, **kw),
        }
        return {n: txs[n]() for n in names}

    def one_step(txs, g, p):
        return {name: tx.update(g, tx.init(p), p) for name, tx in txs.items()}

    def subset(tree, keys):
        return {k: tree[k] for k in keys}

    def put(tree, device_mesh, keys):
        shard = lambda a, s: jax.device_put(a, NamedSharding(device_mesh, s))
        return jax.tree.map(shard, subset(tree, keys), subset(specs, keys))

    every = ("prefilter", "postfilter", "scale_by_adam", "bilateral_adam")
    specs = {"tex": P("x", "y"), "vol": P("x", "y"), "bias": P()}
    grids = ("tex", "vol", "bias")
    configs = [  # (route, mesh shape, transforms, separable, levels, masked, leaves)
        # 8x1 meshes are covered by the filter checks above; unmasked (the non-finite fast
        # path's lax.cond) here, masked in full mode below.
        ("shard_map", (4, 2), every, True, 2, False, grids),
        # Full 3-D (62 offset pairs per level) compiles slowly: the filter checks cover it.
        ("shard_map", (4, 2), every, False, 1, True, ("tex", "bias")),
        # XLA's partitioner compiles the filter slowly: one small configuration.
        ("xla_auto", (4, 2), ("postfilter",), True, 1, False, ("tex", "bias")),
    ]
    refs = {}
    for route, mesh_shape, names, sep, levels, masked, keys in configs:
        txs = make(names, sep, levels, masked)
        fn = jax.jit(lambda g, p, txs=txs: one_step(txs, g, p))
        cfg = (names, sep, levels, masked, keys)
        if cfg not in refs:
            refs[cfg] = fn(subset(grads, keys), subset(params, keys))
        atype = AxisType.Explicit if route == "shard_map" else AxisType.Auto
        device_mesh = device_mesh_of(mesh_shape, atype)
        g_s, p_s = put(grads, device_mesh, keys), put(params, device_mesh, keys)
        t0 = time.perf_counter()
        compiled = fn.lower(g_s, p_s).compile()
        compile_s = time.perf_counter() - t0
        out = compiled(g_s, p_s)
        kept = True
        by_shape = {p.shape: p.sharding for p in p_s.values() if p.ndim >= 2}
        for u, s in out.values():
            for leaf, p in zip(jax.tree.leaves(u), jax.tree.leaves(p_s)):
                kept &= leaf.sharding.is_equivalent_to(p.sharding, p.ndim)
            for leaf in jax.tree.leaves(s):  # grid-shaped state: m, v
                if leaf.shape in by_shape:
                    kept &= leaf.sharding.is_equivalent_to(by_shape[leaf.shape], leaf.ndim)
        st = stats(compiled)
        emit(
            check="transforms",
            route=route,
            mesh="x".join(map(str, mesh_shape)),
            transforms=list(names),
            leaves=list(keys),
            separable=sep,
            levels=levels,
            max_diff=max_diff(out, refs[cfg]),
            sharding_kept=bool(kept),
            compile_s=round(compile_s, 1),
            kinds=sorted(k for k, v in st.items() if v["count"]),
            all_reduce_max_bytes=st["all-reduce"]["max_bytes"],
            largest_all_gather_vs_tex=st["all-gather"]["max_bytes"] / (16 * 16 * 3 * 4),
        )

    # --- sigma_d chosen from the data ("auto", "sure"): its statistics are means and filter
    # passes of the sharded grid. Two steps: the second has a moved guide and a noise sample.
    is_sure = lambda x: isinstance(x, ob.SureState)

    def two_steps(tx, g, p):
        state = tx.init(p)
        _, state = tx.update(g, state, p)
        p = jax.tree.map(lambda a, b: a - 0.01 * jnp.nan_to_num(b), p, g)
        g = jax.tree.map(lambda b, a: 0.5 * b + jnp.sin(7 * a), g, p)
        u, state = tx.update(g, state, p)
        autos = jax.tree.leaves(state, is_leaf=is_sure)
        return u, [a.sigma_d for a in autos if is_sure(a)]

    def kept_guide(tx, p):
        state = optax.tree.get(jax.eval_shape(tx.init, p), "PostfilterState")
        return list(state.sigma_state["tex"].previous_guide.shape)

    def init_sharding_kept(tx, p):
        # A full-size state array (auto's residual) starts split like its leaf, not whole
        # on one device.
        state = optax.tree.get(tx.init(p), "PostfilterState").sigma_state["tex"]
        full = [a for a in jax.tree.leaves(state) if a.shape == p["tex"].shape]
        return all(a.sharding.is_equivalent_to(p["tex"].sharding, 3) for a in full)

    device_mesh = device_mesh_of((4, 2), AxisType.Explicit)
    keys = ("tex", "bias")
    subgrid = ob.auto_sigma(min_texels=16)  # the 16x16 texture as a large leaf: stride 4
    rules = {"auto": "auto", "sure": "sure", "auto, sub-grid": subgrid}
    for sigma_d, rule in rules.items():
        tx = ob.bilateral_adam(0.01, sigma_d=rule, levels=2)
        fn = jax.jit(functools.partial(two_steps, tx))
        ref = fn(subset(grads, keys), subset(params, keys))
        g_s, p_s = put(grads, device_mesh, keys), put(params, device_mesh, keys)
        out = fn(g_s, p_s)
        emit(
            check="sigma_from_data",
            sigma_d=sigma_d,
            max_diff=max_diff(out[0], ref[0]),
            sigma_diff=max_diff(out[1], ref[1]),
            sigma=[float(x) for x in out[1]],
            sharding_kept=out[0]["tex"].sharding.is_equivalent_to(p_s["tex"].sharding, 3),
            kept_shape=kept_guide(tx, p_s),
            init_sharding_kept=init_sharding_kept(tx, p_s),
        )

    # A closed gate's check on the sub-grid (stride 4 here), sharded and on one device: the
    # gate a check step (8) writes, its moments m_hat = m, v_hat = m^2 + 0.1.
    def gate_of(m):
        b, c = 0.9, 1 - 0.9**8
        tx = ob.postfilter(b, b, sigma_d=subgrid, levels=2)
        state = tx.init(m)
        mu, nu = c * m, c * (m * m + 0.1 - (1 - b) * c * m * m) / b
        # The residual is kept on the sub-grid: every 4th texel.
        rule = state.sigma_state._replace(residual=0.2 * jnp.sin(9 * m[::4, ::4]))
        state = state._replace(count=jnp.asarray(7, jnp.int32), mu=mu, nu=nu, sigma_state=rule)
        return tx.update(c * m, state, m)[1].sigma_state.gate

    gate = jax.jit(gate_of)
    gates = [float(gate(m)) for m in (params["tex"], p_s["tex"])]  # half open
    emit(check="subgrid_gate", gates=gates)

    # --- save_state / load_state: each device's block restored, under another mesh too.
    import tempfile

    grids = ("tex", "vol")
    saved = put(params, device_mesh_of((4, 2), AxisType.Explicit), grids)
    path = os.path.join(tempfile.mkdtemp(), "state.npz")
    ob.save_state(path, saved)
    likes = {"4x2": saved, "8x1": put(params, device_mesh_of((8, 1), AxisType.Explicit), grids)}
    for mesh_name, like in likes.items():
        back = ob.load_state(path, like)
        emit(
            check="checkpoint",
            mesh=mesh_name,
            max_diff=max_diff(back, subset(params, grids)),
            sharding_kept=all(
                b.sharding.is_equivalent_to(x.sharding, x.ndim)
                for b, x in zip(jax.tree.leaves(back), jax.tree.leaves(like))
            ),
        )


# ----------------------------------------------------------------------------------------
# The tests (parent process, one device).

_RESULTS = None


def _results() -> list[dict]:
    global _RESULTS
    if _RESULTS is None:
        env = dict(os.environ)
        env["XLA_FLAGS"] = env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8"
        env["OPTAX_BILATERAL_QUICK"] = "1"
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
        proc = subprocess.run(
            [sys.executable, __file__],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        recs = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
        # Kept when the child fails too: every test then reports it without running it again.
        _RESULTS = (proc, recs)
    proc, recs = _RESULTS
    assert proc.returncode == 0, f"child failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    return recs


def _checks(kind):
    recs = [r for r in _results() if r["check"] == kind]
    assert recs, f"the child reported no {kind!r} checks"
    return recs


def test_sharded_filter_equals_single_device():
    for r in _checks("filter"):
        assert r["max_diff"] <= TOL, r


def test_sharded_native_filter_equals_single_device_and_keeps_sharding():
    for r in _checks("filter_native"):
        assert r["max_diff"] <= TOL and r["sharding_kept"], r


def test_sharded_native_filter_moves_only_halo_boxes():
    for r in _checks("filter_native"):
        # Each level takes its box at once (corners included, so that a separable level's
        # later passes read filtered values in the halo): at most the unclipped boxes.
        assert r["kinds"] == ["collective-permute"], r
        assert r["minimum"] <= r["permute_bytes"] <= r["box"], r


def test_sharded_filter_keeps_sharding():
    for r in _checks("filter"):
        assert r["sharding_kept"], r


def test_sharded_filter_moves_only_halos():
    for r in _checks("filter"):
        # Only neighbour exchanges: no all-gather, all-to-all or reduction of grid data.
        assert r["kinds"] == ["collective-permute"], r
        # Separable: exactly what must move (fields per level, guide once). Full mode on
        # 2-axis splits also forwards the off-grid zeros of edge blocks' corners: at most
        # the unclipped halo boxes.
        assert (
            r["minimum"] <= r["permute_bytes"] <= (r["minimum"] if r["separable"] else r["box"])
        ), r


def test_sharded_self_guided_filter_equals_single_device_and_keeps_sharding():
    recs = _checks("filter_self")
    assert len(recs) == 1
    for r in recs:
        assert r["max_diff"] <= TOL and r["sharding_kept"], r


def test_transforms_equal_single_device():
    recs = _checks("transforms")
    # Separable and full mode on 4x2 (8x1: the filter checks).
    assert {(r["route"], r["mesh"], r["separable"]) for r in recs if r["route"] == "shard_map"} == {
        ("shard_map", "4x2", True),
        ("shard_map", "4x2", False),
    }
    assert any(r["route"] == "xla_auto" for r in recs)
    for r in recs:
        assert r["max_diff"] <= TOL, r


def test_transforms_keep_parameter_sharding():
    for r in _checks("transforms"):
        assert r["sharding_kept"], r


def test_shard_map_route_gathers_nothing():
    for r in _checks("transforms"):
        if r["route"] == "shard_map":
            # Halos by collective-permute; all-reduces only of scalars: the "all texels
            # observed?" predicate of the non-finite fast path and the state's count of
            # non-finite entries (XLA may combine a few into one all-reduce).
            assert set(r["kinds"]) <= {"collective-permute", "all-reduce"}, r
            assert "collective-permute" in r["kinds"], r
            assert r["all_reduce_max_bytes"] <= 32, r


def test_auto_and_sure_sigma_equal_single_device():
    recs = _checks("sigma_from_data")
    assert [r["sigma_d"] for r in recs] == ["auto", "sure", "auto, sub-grid"]
    for r in recs:
        assert r["max_diff"] <= TOL and r["sharding_kept"] and r["init_sharding_kept"], r
    assert [r["kept_shape"] for r in recs] == [[16, 16, 3], [16, 16, 3], [4, 4, 3]]
    ((gate, gate_sharded),) = [r["gates"] for r in _checks("subgrid_gate")]
    assert abs(gate_sharded - gate) <= TOL and 0 < gate < 1, (gate, gate_sharded)
    (sure,) = [r for r in recs if r["sigma_d"] == "sure"]
    assert sure["sigma_diff"] <= TOL * max(sure["sigma"]) and len(sure["sigma"]) == 1, sure


def test_sharded_checkpoint_restores_each_device_block():
    recs = _checks("checkpoint")
    assert [r["mesh"] for r in recs] == ["4x2", "8x1"]
    for r in recs:
        assert r["max_diff"] == 0 and r["sharding_kept"], r


if __name__ == "__main__":
    _child()
