"""Grids sharded across 2 processes x 4 CPU devices: the same numbers as one device.

The parent (the suite's process) starts two children, this file run as a script with
``XLA_FLAGS=--xla_force_host_platform_device_count=4``, that join one
``jax.distributed`` run on localhost (gloo CPU collectives). Each runs a few
``bilateral_adam`` steps on grids sharded over all 8 devices (rows over processes),
compares the blocks its devices hold with a one-device run of the same steps in the same
child, and saves and restores the sharded state (``save_state`` writes one part per
process; ``load_state`` gives each device its block). The children print one JSON record
per check; the tests below assert on them. Run alone::

    python -m pytest -q tests/test_multiprocess.py
"""

from __future__ import annotations

import json
import os
import pathlib
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

TOL = 1e-5  # float32 filtering of O(1) values; only XLA's fusion differs between the runs
ROOT = pathlib.Path(__file__).resolve().parents[1]
PROCESSES, LOCAL_DEVICES = 2, 4
CHILD_TIMEOUT_S = 300  # a hung collective fails the tests instead of blocking the suite


# ----------------------------------------------------------------------------------------
# The children: one process of the distributed run each.


def _child(process_id: int, port: int, folder: str) -> None:  # pragma: no cover - subprocess
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=f"localhost:{port}",
        num_processes=PROCESSES,
        process_id=process_id,
        initialization_timeout=120,
    )
    import optax
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    import optax_bilateral as ob

    assert jax.device_count() == PROCESSES * LOCAL_DEVICES, jax.devices()
    host_params, host_grads = problem()
    specs = {"tex": P("x", "y"), "vol": P("x", "y"), "bias": P()}
    device_mesh = jax.make_mesh((4, 2), ("x", "y"))  # x: spans both processes

    def emit(**rec):
        print(json.dumps({"process": process_id, **rec}), flush=True)

    def global_array(a, spec):
        # A spec as long as the array, as jit's outputs have: the same types, one compile.
        sharding = NamedSharding(device_mesh, P(*spec, *[None] * (a.ndim - len(spec))))
        return jax.make_array_from_callback(a.shape, sharding, lambda index: a[index])

    def on_mesh(tree):
        """Single-device leaves of opt.init (counters; auto's residual, made unsharded)
        placed as a step's outputs are: grid-shaped ones split like the grid, the others
        replicated. Then every step runs one compiled program."""
        by_shape = {v.shape: specs[k] for k, v in host_params.items() if v.ndim > 1}
        one = lambda x: len(x.sharding.device_set) == 1
        put = lambda x: global_array(np.asarray(x), by_shape.get(x.shape, P()))
        return jax.tree.map(lambda x: put(x) if one(x) else x, tree)

    def same_blocks(a, b):
        """The same bits in every block this process holds, and the same shardings."""
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            if not x.sharding.is_equivalent_to(y.sharding, x.ndim):
                return False
            xs = {str(s.index): np.asarray(s.data).tobytes() for s in x.addressable_shards}
            ys = {str(s.index): np.asarray(s.data).tobytes() for s in y.addressable_shards}
            if xs != ys:
                return False
        return True

    place = lambda tree: {k: global_array(v, specs[k]) for k, v in tree.items()}
    for name, opt in optimizers().items():

        @jax.jit
        def step(params, state, grads, opt=opt):
            updates, state = opt.update(grads, state, params)
            return optax.apply_updates(params, updates), state

        t0 = time.perf_counter()
        params = place(host_params)
        state = on_mesh(opt.init(params))
        for g in host_grads[:-1]:
            params, state = step(params, state, place(g))
        path = os.path.join(folder, name)
        ob.save_state(path + ".steps", (params, state))  # each process: its blocks
        seconds = time.perf_counter() - t0

        # The sharded state saved and restored: each process reads its devices' blocks.
        ob.save_state(path, state)
        restored = on_mesh(ob.load_state(path, opt.init(params)))
        with jax.sharding.set_mesh(device_mesh):  # jax.eval_shape's shardings: abstract
            like = jax.eval_shape(opt.init, params)
            abstract = ob.load_state(path, like)
        # Each leaf placed as like says (auto's residual: replicated before the first step).
        follows_like = all(
            x.sharding.spec == y.sharding.spec
            for x, y in zip(jax.tree.leaves(abstract), jax.tree.leaves(like))
            if y.sharding is not None
        )
        abstract = jax.tree.map(lambda x, y: jax.device_put(x, y.sharding), abstract, state)
        last = place(host_grads[-1])
        after = step(params, state, last)
        resumed = step(params, restored, last)
        ob.save_state(path + ".resumed", resumed)
        leaf = params["tex"]
        emit(
            optimizer=name,
            seconds=round(seconds, 1),
            blocks=len(leaf.addressable_shards),
            process_local=not leaf.is_fully_addressable,
            steps=step._cache_size(),  # compiled programs
            parts=sorted(p.name for p in pathlib.Path(folder).glob(name + ".[0-9]*")),
            restored_equal=same_blocks(restored, state),
            restored_from_eval_shape_equal=same_blocks(abstract, state),
            restored_follows_like=follows_like,
            resumed_equal=same_blocks(resumed, after),
        )


def problem(steps: int = 3):
    """Host arrays both processes (and the one-device reference) start from: a texture and
    a volume with an edge, a vector, and ``steps`` noisy gradients."""
    rng = np.random.default_rng(0)
    edge = lambda n: np.where(np.arange(n) < n // 2, 0.3, 0.8).astype("f4")
    params = {
        "tex": np.broadcast_to(edge(32)[:, None, None], (32, 32, 3)).copy(),
        "vol": np.broadcast_to(edge(16)[:, None, None, None], (16, 16, 16, 1)).copy(),
        "bias": np.ones(5, "f4"),
    }
    grads = [
        {k: (0.5 * v + rng.normal(size=v.shape)).astype("f4") for k, v in params.items()}
        for _ in range(steps)
    ]
    return params, grads


def optimizers():
    import optax_bilateral as ob

    # The defaults ("auto"), and a fixed sigma_d through both filters (each compile of a
    # sharded step costs both processes; the postfilter alone is the second one's half).
    return {
        "defaults": ob.bilateral_adam(0.02),
        "sigma_d=0.1, prefilter": ob.bilateral_adam(0.02, sigma_d=0.1, levels=3, prefilter=True),
    }


# ----------------------------------------------------------------------------------------
# The tests (parent process, one device).


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run_children(folder: pathlib.Path) -> dict:
    """Starts the two processes; meanwhile computes the one-device reference."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={LOCAL_DEVICES}"
    )
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    port, t0 = _free_port(), time.perf_counter()
    logs = [(folder / f"stdout{i}", folder / f"stderr{i}") for i in range(PROCESSES)]
    procs = []
    for i, (out, err) in enumerate(logs):
        cmd = [sys.executable, __file__, str(i), str(port), str(folder)]
        with open(out, "w") as fo, open(err, "w") as fe:
            procs.append(subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=fo, stderr=fe))
    try:
        reference = _one_device_reference()
    finally:
        codes = []
        for p in procs:
            try:
                codes.append(p.wait(timeout=max(1.0, CHILD_TIMEOUT_S - (time.perf_counter() - t0))))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
                codes.append(f"killed after {CHILD_TIMEOUT_S} s")
    failed = [
        f"process {i}: exit {c}\n{logs[i][1].read_text()[-4000:]}"
        for i, c in enumerate(codes)
        if c != 0
    ]
    records = [
        json.loads(line)
        for out, _ in logs
        for line in out.read_text().splitlines()
        if line.startswith("{")
    ]
    return {
        "records": records,
        "reference": reference,
        "failed": failed,
        "seconds": time.perf_counter() - t0,
    }


def _one_device_reference() -> dict:
    """Each optimizer's (params, state) after the steps, and the step after that."""
    import jax
    import optax

    host_params, host_grads = problem()
    out = {}
    for name, opt in optimizers().items():
        step = jax.jit(
            lambda p, s, g, opt=opt: (lambda u, s: (optax.apply_updates(p, u), s))(
                *opt.update(g, s, p)
            )
        )
        params, state = host_params, opt.init(host_params)
        for g in host_grads[:-1]:
            params, state = step(params, state, g)
        out[name] = {"steps": (params, state), "resumed": step(params, state, host_grads[-1])}
    return out


_RUN: dict = {}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    if not _RUN:
        folder = tmp_path_factory.mktemp("multiprocess")
        _RUN.update(_run_children(folder), folder=folder)
    assert not _RUN["failed"], "children failed:\n" + "\n".join(_RUN["failed"])
    return _RUN


def _blocks(part: pathlib.Path):
    """(leaf number, index, block) for every block a process's part file holds."""
    with np.load(part) as data:
        meta = json.loads(str(data["__blocks__"]))
        for i, m in enumerate(meta):
            for j, (start, stop) in enumerate(zip(m["starts"], m["stops"])):
                index = tuple(slice(a, b) for a, b in zip(start, stop))
                yield i, index, data[f"leaf_{i:05d}_{j:05d}"]


def _max_diff_per_process(folder: pathlib.Path, name: str, reference) -> list[float]:
    """Largest |block - reference[index]| over each process's blocks of a saved tree."""
    import jax

    ref = [np.asarray(x, np.float64) for x in jax.tree.leaves(reference)]
    worst = []
    for i in range(PROCESSES):
        part = folder / f"{name}.{i}-of-{PROCESSES}"
        blocks = list(_blocks(part))
        assert blocks, part
        worst.append(max(float(np.max(np.abs(b - ref[k][index]))) for k, index, b in blocks))
    return worst


def test_both_processes_ran_every_optimizer_on_its_own_blocks(run):
    recs = run["records"]
    for process in range(PROCESSES):
        mine = [r for r in recs if r["process"] == process]
        assert [r["optimizer"] for r in mine] == list(optimizers()), recs
        for r in mine:
            # 4 of the 8 blocks of every grid; one compiled step per optimizer.
            assert r["process_local"] and r["blocks"] == LOCAL_DEVICES and r["steps"] == 1, r


def test_sharded_steps_equal_one_device(run):
    for name in optimizers():
        for key in ("steps", "resumed"):  # after the steps; after restoring and one more
            diffs = _max_diff_per_process(
                run["folder"], f"{name}.{key}", run["reference"][name][key]
            )
            assert max(diffs) <= TOL, (name, key, diffs)


def test_sharded_state_saves_a_part_per_process_and_restores_bit_for_bit(run):
    for r in run["records"]:
        assert r["parts"] == [f"{r['optimizer']}.{i}-of-{PROCESSES}" for i in range(PROCESSES)], r
        assert r["restored_equal"] and r["restored_from_eval_shape_equal"], r
        assert r["restored_follows_like"], r
        assert r["resumed_equal"], r  # the step after restoring equals the uninterrupted one


def test_multiprocess_checkpoint_restores_on_one_device(run):
    import jax

    import optax_bilateral as ob

    for name, opt in optimizers().items():
        params, state = run["reference"][name]["steps"]
        restored = ob.load_state(run["folder"] / name, jax.eval_shape(opt.init, params))
        for x, y in zip(jax.tree.leaves(restored), jax.tree.leaves(state)):
            assert x.shape == y.shape and float(np.max(np.abs(x - y), initial=0.0)) <= TOL, name


if __name__ == "__main__":
    _child(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3])
