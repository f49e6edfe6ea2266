"""Golden outputs of the grid transforms, and the script that records them.

    .venv/bin/python tests/goldens.py            # re-record tests/goldens.npz
    .venv/bin/python tests/goldens.py --check    # compare all configurations (slow)
    .venv/bin/python tests/goldens.py --only self  # re-record one factor level's configurations
    .venv/bin/python tests/goldens.py --trajectories  # re-record the sigma_d rules' trajectories

A *configuration* is one compiled update: transform (``prefilter``, ``postfilter``, both
chained, memoryless ``postfilter``) x ``separable`` x ``guide`` (``"params"``, ``"self"``,
a callable with ``log_guide``) x ``mask_unobserved`` x parameter dtype (float32,
bfloat16, float16): 144 in all. Each runs three *data variants* through the same
compiled program (finite gradients, one NaN texel per grid leaf, every gradient
times 1e30), three steps each, on ``{"tex": (6, 7, 2), "plane": (5, 4), "s": ()}``.

What is recorded, per configuration and variant: the updates of every step and the
final state, upcast to float32 (exact for the three dtypes) and concatenated.

* ``tests/goldens.npz`` keeps these arrays for a *covering subset* of the
  configurations (every pair of factor levels appears in at least one of them),
  which ``tests/test_goldens.py`` compares bit for bit on every run; and a SHA-256 of
  every one of the 144 configurations, which ``--check`` (or the test with
  ``OPTAX_BILATERAL_GOLDENS=all``) compares. Recording all 144 takes about 25 s on 2
  cores (0.1-2 s each), most of it compiling, which is why the suite runs the subset.
* The programs, and the random inputs they are fed, are compiled without LLVM's
  optimisations (``COMPILER_OPTIONS``), whatever ``$XLA_FLAGS`` says.
* Bit-equality holds for one toolchain (the jax and jaxlib versions recorded in the
  file): another XLA may fuse, and so round, differently. Under another toolchain the
  test compares to a tolerance instead and says so.

*Trajectories* (``tests/goldens_trajectories.npz``) guard the data-driven sigma_d rules,
whose branches (a blend gate that opens, the heavier filter for correlated noise, a risk
average over steps) only show over many steps: 30 steps of ``postfilter`` with
``sigma_d="auto"``, with ``"sure"``, and ``prefilter`` + ``postfilter`` with ``"auto"``, on a
2-D leaf large enough for the rules' sub-grid (264x256x2, i.i.d. target: the gate opens) and a
3-D leaf (16x14x12x1, noise blurred over neighbours: the heavier filter engages), beside an
unfiltered scalar; a NaN texel at two steps and huge gradients at one take the masked path.
Per step the update's digest is kept (so a failure names its step), and the final state's.

Only the public API is used, so the file survives any restructuring of the library.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import os
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob

PATH = pathlib.Path(__file__).with_name("goldens.npz")

KINDS = ("prefilter", "postfilter", "both", "memoryless")
SEPARABLE = (True, False)
GUIDES = ("params", "self", "callable")
MASKS = (False, True)
DTYPES = ("float32", "bfloat16", "float16")
VARIANTS = ("finite", "nan_texel", "huge")
STEPS = 3
SPATIAL_AXES = {"tex": (0, 1), "plane": (0, 1), "s": ()}
SIGMA_D, LEVELS = 0.3, 2
# The suite's compile options (tests/conftest.py): they halve the compile time of these
# small programs and change nothing the goldens guard: the computation is XLA's HLO,
# compiled the same way here and when recorded.
COMPILER_OPTIONS = {
    "xla_backend_optimization_level": 0,
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_parallel_codegen_split_count": 1,
}


def config_id(kind, separable, guide, mask, dtype) -> str:
    return "-".join(
        [kind, "sep" if separable else "full", guide, "mask" if mask else "nomask", dtype]
    )


ALL = [config_id(*c) for c in itertools.product(KINDS, SEPARABLE, GUIDES, MASKS, DTYPES)]


def parse_id(cid: str):
    kind, sep, guide, mask, dtype = cid.split("-")
    return kind, sep == "sep", guide, mask == "mask", dtype


def covering_subset() -> list[str]:
    """Configurations that between them contain every pair of factor levels (greedy,
    deterministic, starting from the paper's default: postfilter, separable, params)."""
    factors = [KINDS, SEPARABLE, GUIDES, MASKS, DTYPES]
    rows = list(itertools.product(*factors))

    def pairs(row):
        return {(i, row[i], j, row[j]) for i, j in itertools.combinations(range(len(row)), 2)}

    todo = set().union(*(pairs(r) for r in rows))
    chosen = [("postfilter", True, "params", False, "float32")]
    todo -= pairs(chosen[0])
    while todo:
        best = max(rows, key=lambda r: len(pairs(r) & todo))  # first best: deterministic
        chosen.append(best)
        todo -= pairs(best)
    return [config_id(*r) for r in chosen]


def _guide(p):
    """A callable guide: auxiliary features, one channel for the texture."""
    return {"tex": jnp.sum(p["tex"], axis=-1), "plane": p["plane"] * 2, "s": None}


def optimizer(kind, separable, guide, mask):
    kw = dict(
        sigma_d=SIGMA_D,
        levels=LEVELS,
        separable=separable,
        spatial_axes=SPATIAL_AXES,
        mask_unobserved=mask,
    )
    if guide == "callable":
        kw.update(guide=_guide, log_guide=True)
    else:
        kw.update(guide=guide)
    if kind == "prefilter":
        return ob.prefilter(**kw)
    if kind == "postfilter":
        return ob.postfilter(0.2, **kw)
    if kind == "both":
        return optax.chain(ob.prefilter(**kw), ob.postfilter(0.2, **kw))
    return ob.postfilter(0.0, 0.0, 1e-8, **kw)


@functools.cache
def _compiled(fn, static, dynamic=()):
    """``fn(*static, *args)`` for arguments shaped like ``dynamic``, compiled once per
    ``static`` with ``COMPILER_OPTIONS``: the inputs' bits (``jax.random.normal`` is a
    polynomial that LLVM may contract differently) do not depend on ``$XLA_FLAGS``."""
    program = jax.jit(functools.partial(fn, *static)).lower(*dynamic)
    return program.compile(compiler_options=COMPILER_OPTIONS)


def params(dtype):
    return _compiled(_params, (jnp.dtype(dtype).name,))()


def _params(dtype):
    k = jax.random.PRNGKey(20)
    return {
        "tex": (0.1 + jax.random.uniform(k, (6, 7, 2))).astype(dtype),
        "plane": jax.random.uniform(jax.random.fold_in(k, 1), (5, 4)).astype(dtype),
        "s": jnp.asarray(0.5, dtype),
    }


def gradients(variant, step, like):
    shapes = tuple((k, np.shape(v), jnp.dtype(v.dtype).name) for k, v in sorted(like.items()))
    step_spec = jax.ShapeDtypeStruct((), jnp.int32)
    return _compiled(_gradients, (variant, shapes), (step_spec,))(jnp.int32(step))


def _gradients(variant, shapes, step):
    key = jax.random.fold_in(jax.random.PRNGKey(21), step)
    g = {
        k: jax.random.normal(jax.random.fold_in(key, i), shape, jnp.float32)
        for i, (k, shape, _) in enumerate(shapes)
    }
    if variant == "nan_texel":
        g["tex"] = g["tex"].at[2, 3, 1].set(jnp.nan)
        g["plane"] = g["plane"].at[1, 2].set(jnp.nan)
    elif variant == "huge":
        g = {k: v * 1e30 for k, v in g.items()}
    return {k: g[k].astype(dtype) for k, _, dtype in shapes}


def _flat(tree) -> np.ndarray:
    leaves = [np.asarray(x, np.float32).ravel() for x in jax.tree.leaves(tree)]
    return np.concatenate(leaves) if leaves else np.zeros(0, np.float32)


def run(cid: str) -> dict[str, np.ndarray]:
    """{variant: float32 vector of every step's updates and the final state}."""
    kind, separable, guide, mask, dtype = parse_id(cid)
    opt = optimizer(kind, separable, guide, mask)
    p = params(jnp.dtype(dtype))
    state = opt.init(p)
    update = (
        jax.jit(opt.update)
        .lower(gradients("finite", 0, p), state, p)
        .compile(compiler_options=COMPILER_OPTIONS)
    )
    out = {}
    for variant in VARIANTS:
        state = opt.init(p)
        parts = []
        for step in range(STEPS):
            u, state = update(gradients(variant, step, p), state, p)
            parts.append(_flat(u))
        parts.append(_flat(state))
        out[variant] = np.concatenate(parts)
    return out


def digest(x: np.ndarray) -> str:
    """SHA-256 of the float32 bytes, NaN payloads made canonical."""
    x = np.where(np.isnan(x), np.float32(np.nan), x).astype(np.float32)
    return hashlib.sha256(x.tobytes()).hexdigest()


def toolchain() -> str:
    import jaxlib

    from optax_bilateral._src.filter import native

    # The native kernel's instruction set rounds differently (fused multiply-adds or not).
    isa = native.status().reason if native.available() else "none"
    return f"jax {jax.__version__}, jaxlib {jaxlib.__version__}, native kernel {isa}"


def record(path=PATH, only: str | None = None) -> None:
    """Records every configuration, or (``only``) those with that factor level, keeping
    the file's records of the others (for an intended change of one option's numbers)."""
    subset = set(covering_subset())
    arrays, digests = {}, []
    kept, kept_arrays = {}, {}
    if only is not None:
        with np.load(path) as data:
            kept = dict(line.split(" ") for line in data["digests"].tolist())
            kept_arrays = {k: data[k] for k in data.files if "/" in k}
    for i, cid in enumerate(ALL):
        if only is not None and only not in cid.split("-"):
            for variant in VARIANTS:
                key = f"{cid}/{variant}"
                digests.append(f"{key} {kept[key]}")
                if key in kept_arrays:
                    arrays[key] = kept_arrays[key]
            continue
        t = time.time()
        res = run(cid)
        for variant, x in res.items():
            digests.append(f"{cid}/{variant} {digest(x)}")
            if cid in subset:
                arrays[f"{cid}/{variant}"] = x
        print(f"[{i + 1}/{len(ALL)}] {cid} {time.time() - t:.1f} s", flush=True)
    np.savez_compressed(
        path, toolchain=np.asarray(toolchain()), digests=np.asarray(digests), **arrays
    )


def check(path=PATH) -> int:
    with np.load(path) as data:
        want = dict(line.split(" ") for line in data["digests"].tolist())
    bad = 0
    for i, cid in enumerate(ALL):
        res = run(cid)
        for variant, x in res.items():
            ok = digest(x) == want[f"{cid}/{variant}"]
            bad += not ok
            print(f"[{i + 1}/{len(ALL)}] {cid}/{variant}: {'ok' if ok else 'DIFFERS'}", flush=True)
    return bad


# ----------------------------------------------------------------------------- trajectories

TRAJECTORY_PATH = PATH.with_name("goldens_trajectories.npz")
TRAJECTORIES = ("auto", "sure", "auto-both")
TRAJECTORY_STEPS = 30
TRAJECTORY_SHAPES = {"tex": (264, 256, 2), "vol": (16, 14, 12, 1), "s": ()}
TRAJECTORY_AXES = {"tex": (0, 1), "vol": (0, 1, 2), "s": ()}
TRAJECTORY_LR = 0.02
NAN_STEPS, HUGE_STEP = (5, 19), 25


def trajectory_optimizer(kind):
    post = ob.postfilter(0.2, sigma_d=kind.split("-")[0], spatial_axes=TRAJECTORY_AXES)
    if kind == "auto-both":
        return optax.chain(ob.prefilter(sigma_d="auto", spatial_axes=TRAJECTORY_AXES), post)
    return post


def _trajectory_targets():
    k = jax.random.PRNGKey(30)
    i, j, k3 = jnp.meshgrid(*(jnp.arange(n) for n in TRAJECTORY_SHAPES["vol"][:3]), indexing="ij")
    vol = 0.5 + 0.3 * jnp.sin(i / 3.0) * jnp.cos(j / 4.0) * jnp.sin(k3 / 5.0 + 1)
    return {
        "tex": jax.random.uniform(k, TRAJECTORY_SHAPES["tex"], jnp.float32, 0.2, 0.8),
        "vol": vol[..., None].astype(jnp.float32),
        "s": jnp.asarray(0.3, jnp.float32),
    }


def _blur(x, axes):
    """Noise shared by neighbours: a [1, 2, 1] / 4 blur, twice, along each spatial axis."""
    for a in axes:
        for _ in range(2):
            x = 0.25 * jnp.roll(x, 1, a) + 0.5 * x + 0.25 * jnp.roll(x, -1, a)
    return x


def _trajectory_gradient(x, step):
    """The gradient at ``step``: ``x - target`` plus noise (i.i.d. on the texture, blurred on
    the volume), with a NaN texel at ``NAN_STEPS`` and everything times 1e30 at ``HUGE_STEP``."""
    target = _trajectory_targets()
    key = jax.random.fold_in(jax.random.PRNGKey(31), step)
    noise = {
        k: jax.random.normal(jax.random.fold_in(key, n), np.shape(v), jnp.float32)
        for n, (k, v) in enumerate(sorted(x.items()))
    }
    g = {
        "tex": (x["tex"] - target["tex"]) + 0.1 * noise["tex"],
        "vol": (x["vol"] - target["vol"]) + 2.0 * _blur(noise["vol"], (0, 1, 2)),
        "s": (x["s"] - target["s"]) + 0.1 * noise["s"],
    }
    nan = (step == NAN_STEPS[0]) | (step == NAN_STEPS[1])
    g["tex"] = g["tex"].at[7, 9, 1].set(jnp.where(nan, jnp.nan, g["tex"][7, 9, 1]))
    g["vol"] = g["vol"].at[3, 4, 5, 0].set(jnp.where(nan, jnp.nan, g["vol"][3, 4, 5, 0]))
    return jax.tree.map(lambda v: jnp.where(step == HUGE_STEP, v * 1e30, v), g)


def _apply(x, u):
    return jax.tree.map(lambda p, d: p - TRAJECTORY_LR * d, x, u)


def trajectory(kind: str) -> dict[str, np.ndarray]:
    """Every step's update digest (a string array), the final state's, and per step the
    float64 sum of |update| per leaf (for a tolerance check under another toolchain)."""
    return _trajectory(kind)[0]


def _trajectory(kind: str) -> tuple[dict[str, np.ndarray], list]:
    """:func:`trajectory`'s record, and every step's state (for the coverage test)."""
    opt = trajectory_optimizer(kind)
    x = {k: jnp.full(shape, 0.5, jnp.float32) for k, shape in TRAJECTORY_SHAPES.items()}
    state = opt.init(x)
    step_spec = jax.ShapeDtypeStruct((), jnp.int32)
    grad = (
        jax.jit(_trajectory_gradient).lower(x, step_spec).compile(compiler_options=COMPILER_OPTIONS)
    )
    g0 = grad(x, jnp.int32(1))
    update = jax.jit(opt.update).lower(g0, state, x).compile(compiler_options=COMPILER_OPTIONS)
    apply = jax.jit(_apply).lower(x, g0).compile(compiler_options=COMPILER_OPTIONS)
    digests, sums, states = [], [], []
    for step in range(1, TRAJECTORY_STEPS + 1):
        u, state = update(grad(x, jnp.int32(step)), state, x)
        states.append(state)
        digests.append(digest(_flat(u)))
        sums.append([np.abs(np.asarray(u[k], np.float64)).sum() for k in sorted(u)])
        x = apply(x, u)
    return {
        "digests": np.asarray(digests),
        "state": np.asarray(digest(_flat(state))),
        "sums": np.asarray(sums),
    }, states


def record_trajectories(path=TRAJECTORY_PATH) -> None:
    arrays = {}
    for kind in TRAJECTORIES:
        t = time.time()
        for key, value in trajectory(kind).items():
            arrays[f"{kind}/{key}"] = value
        print(f"{kind}: {time.time() - t:.1f} s", flush=True)
    np.savez_compressed(path, toolchain=np.asarray(toolchain()), **arrays)


if __name__ == "__main__":
    if "--trajectories" in sys.argv[1:]:
        record_trajectories()
        sys.exit(0)
    if "--check" in sys.argv[1:]:
        n = check()
        print(f"{n} differ" if n else "all equal")
        sys.exit(1 if n else 0)
    os.makedirs(PATH.parent, exist_ok=True)
    args = sys.argv[1:]
    record(only=args[args.index("--only") + 1] if "--only" in args else None)
