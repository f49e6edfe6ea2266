"""Where the mesh update's time goes: ``bilateral_large_steps`` against ``large_steps``, and
their parts, jitted, on the mesh experiment's vertex counts (issue #55, "profile first").

    python -m tools.mesh_update_parts [--quick] [--out DIR] [--after-render]

For icosphere meshes pushed onto the mesh experiment's rounded cube (10 f^2 + 2 vertices, f =
16, 32 and 64: 2562, 10242 and 40962 vertices) and each solver, the median milliseconds of: the
whole jitted update of ``bilateral_large_steps`` (the defaults: ``DensityWidth``'s splat
width, 0.5 / ~1 / 2 at the three counts, and the 32 directions' kernel in 16 / 9 / 8 terms;
the prefilter ``M^-1 g``, ``postfilter_v="uniform"``) and of ``large_steps``; and of their
parts, ``smoothing_solve`` (``M^-1`` on 3 columns) and ``bilateral_normal_filter`` (``B`` on
one 3-channel field: a solve of 4 columns a term). Then the solves alone, on the host,
float32, with 3, 64 and 128 columns (``kernel_tol=0``'s 32 x 4): ``solver="cholesky"``'s
factor (SuperLU in METIS' order) swept by the extension, and CHOLMOD through cholespy
(Mitsuba's Large Steps' solver, float64), with the seconds each takes to factorise. Writes
``mesh_update_parts.json`` and ``.md``.

``--after-render`` (needs Mitsuba 3) adds the whole jitted update at a few delays after a
render and ``dr.backward`` of the Mitsuba mesh experiment's scene, as its loop runs it, with
the CPU milliseconds Dr.Jit's worker threads (nanothread's ``nt [i]``, read from
``/proc/self/task`` on Linux) spent in the 50 ms after the render, which they spend waiting
for work, not asleep. ``OPTAX_BILATERAL_THREADS=1`` runs the update's solves on one thread.
"""

from __future__ import annotations

import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.mitsuba.mesh import rounded_cube
from optax_bilateral import triangle_mesh as obm
from optax_bilateral._src import extension

LAMBDA = 19.0  # the mesh experiment's
DELAYS_MS = (0, 5, 20, 100)  # after the render, before the update
WATCH_S = 0.05  # how long the workers' CPU time is read after a render


def median_ms(fn, repeats: int) -> float:
    """Median milliseconds of ``fn()`` after one untimed call (which compiles)."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def parts(frequency: int, solver: str, repeats: int) -> dict:
    vertices, faces = rounded_cube(frequency, 0.6, 0.08)
    x = jnp.asarray(vertices, jnp.float32)
    g = jnp.asarray(np.random.default_rng(0).normal(size=x.shape), jnp.float32)
    mesh = obm.mesh_laplacian(faces)
    row: dict = {"vertices": len(x), "solver": solver}
    for name, opt in (
        (
            "bilateral_large_steps update ms",
            obm.bilateral_large_steps(0.03, mesh, LAMBDA, solver=solver),
        ),
        ("large_steps update ms", obm.large_steps(0.03, mesh, LAMBDA, solver=solver)),
    ):
        state, update = opt.init(x), jax.jit(opt.update)
        row[name] = median_ms(lambda update=update, state=state: update(g, state, x), repeats)
    normals = obm.vertex_normals(x, faces)
    row["M^-1 g ms"] = median_ms(
        lambda: obm.smoothing_solve(mesh, g, LAMBDA, solver=solver), repeats
    )
    row["B g ms"] = median_ms(
        lambda: obm.bilateral_normal_filter([g], normals, mesh, lambda_=LAMBDA, solver=solver),
        repeats,
    )
    return row


def solves(frequency: int, repeats: int) -> dict:
    """The host solves alone: this library's factor and sweeps against cholespy's."""
    import cholespy

    from optax_bilateral._src.mesh import laplacian

    vertices, faces = rounded_cube(frequency, 0.6, 0.08)
    mesh = obm.mesh_laplacian(faces)
    # A cache of its own: the updates above factorised this mesh already.
    host = laplacian._Cholesky(np.asarray(mesh.neighbors), np.asarray(mesh.degree))
    t = time.perf_counter()
    factor = host.factor(LAMBDA)
    row: dict = {"vertices": len(vertices), "factorise s": time.perf_counter() - t}
    u = len(factor.dinv)
    values = np.concatenate([1.0 + LAMBDA * host._degree, np.full(host._off, -LAMBDA)])
    t = time.perf_counter()
    chol = cholespy.CholeskySolverF(
        u, host._ii, host._jj, values.astype(np.float32), cholespy.MatrixType.COO
    )
    row["cholespy factorise s"] = time.perf_counter() - t
    rng = np.random.default_rng(0)
    for columns in (3, 64, 128):
        b = rng.normal(size=(u, columns)).astype(np.float32)
        out = np.empty_like(b)
        row[f"sweeps {columns} ms"] = median_ms(lambda b=b: factor.solve(b), repeats)
        row[f"cholespy {columns} ms"] = median_ms(lambda b=b, out=out: chol.solve(b, out), repeats)
    return row


def worker_cpu_ms() -> float | None:
    """CPU milliseconds used so far by this process's Dr.Jit worker threads, or None where
    ``/proc`` does not list them."""
    tasks = pathlib.Path("/proc/self/task")
    if not tasks.is_dir():
        return None
    ticks = 0
    for task in tasks.iterdir():
        try:
            if not (task / "comm").read_text().startswith("nt "):
                continue
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended
            continue
        ticks += int(fields[11]) + int(fields[12])  # utime, stime
    return 1e3 * ticks / os.sysconf("SC_CLK_TCK")


def after_render(frequency: int, repeats: int, quick: bool) -> list[dict]:
    """The jitted update at ``DELAYS_MS`` after a render and ``dr.backward`` of the Mitsuba
    mesh experiment's scene, the delays interleaved; medians over ``repeats`` renders each."""
    from experiments.mitsuba import mesh as mitsuba_mesh

    problem = mitsuba_mesh.Problem(mitsuba_mesh.default_config(quick), frequency)
    run = mitsuba_mesh.BilateralRun(problem, 0.03, LAMBDA)  # the positions with gradients
    import drjit as dr  # imported by Problem, after it set Mitsuba's variant

    x = jnp.asarray(problem.init, jnp.float32)
    g = jnp.asarray(np.random.default_rng(0).normal(size=x.shape), jnp.float32)
    opt = obm.bilateral_large_steps(
        0.03, obm.mesh_laplacian(problem.faces), LAMBDA, solver="cholesky"
    )
    state, update = opt.init(x), jax.jit(opt.update)
    jax.block_until_ready(update(g, state, x))
    times: dict[int, list[float]] = {d: [] for d in DELAYS_MS}
    for i in range(repeats * len(DELAYS_MS)):
        run.write()
        problem.render_and_backward(i)
        dr.sync_thread()
        delay = DELAYS_MS[i % len(DELAYS_MS)]
        time.sleep(delay / 1e3)
        t = time.perf_counter()
        jax.block_until_ready(update(g, state, x))
        times[delay].append(time.perf_counter() - t)
    busy = []
    for i in range(repeats):
        run.write()
        problem.render_and_backward(i)
        dr.sync_thread()
        before = worker_cpu_ms()
        time.sleep(WATCH_S)
        after = worker_cpu_ms()
        if before is not None and after is not None:
            busy.append(after - before)
    row: dict = {"vertices": len(x), "threads": extension.threads()}
    for delay, ts in times.items():
        row[f"update ms, {delay} ms after"] = 1e3 * float(np.median(ts))
    row["workers' CPU ms in 50 ms after"] = float(np.median(busy)) if busy else float("nan")
    return [row]


def main(argv=None) -> list[dict]:
    args = common.parse_args(
        "the mesh update's parts",
        "results/mesh_update_parts",
        argv,
        extra=lambda p: p.add_argument(
            "--after-render",
            action="store_true",
            help="also time the update after a Mitsuba render (needs Mitsuba 3)",
        ),
    )
    frequencies, repeats = ((3,), 2) if args.quick else ((16, 32, 64), 7)
    rows = [parts(f, s, repeats) for f in frequencies for s in ("cholesky", "cg")]
    host = [solves(f, repeats) for f in frequencies]
    md = (
        "Jitted, medians; `python -m tools.mesh_update_parts`.\n\n"
        + common.markdown_table(rows)
        + "\n\nThe host solves alone (float32, medians):\n\n"
        + common.markdown_table(host)
    )
    data: dict = {"rows": rows, "solves": host, "quick": args.quick}
    rendered = []
    if args.after_render:
        rendered = [r for f in frequencies for r in after_render(f, 2 * repeats, args.quick)]
        data["after render"] = rendered
        md += (
            "\n\nThe jitted update after a Mitsuba render (medians; Dr.Jit's workers wait "
            "for work before they sleep):\n\n" + common.markdown_table(rendered)
        )
    print(md)
    common.write_results(args.out, "mesh_update_parts", data, md)
    return rows + host + rendered


if __name__ == "__main__":
    main()
