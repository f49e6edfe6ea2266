"""Where the mesh update's time goes: ``bilateral_large_steps`` against ``large_steps``, and
their parts, jitted, on the mesh experiment's vertex counts (issue #55, "profile first").

    python -m tools.mesh_update_parts [--quick] [--out DIR]

For icosphere meshes pushed onto the mesh experiment's rounded cube (10 f^2 + 2 vertices,
f = 16, 32 and 64: 2562, 10242 and 40962 vertices) and each solver, the median milliseconds
of: the whole jitted update of ``bilateral_large_steps`` (the defaults: 32 directions, the
prefilter ``M^-1 g``, ``postfilter_v="uniform"``) and of ``large_steps``; and of their parts,
``smoothing_solve`` (``M^-1`` on 3 columns) and ``bilateral_normal_filter`` (``B`` on one
3-channel field: a solve of 32 x 4 columns). Then the solves alone, on the host, float32, with
3 and 128 columns: ``solver="cholesky"``'s factor (qdldl) swept by the extension, and CHOLMOD
through cholespy (Mitsuba's Large Steps' solver, float64), with the seconds each takes to
factorise. Writes ``mesh_update_parts.json`` and ``.md``.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.mitsuba.mesh import rounded_cube
from optax_bilateral import triangle_mesh as obm

LAMBDA = 19.0  # the mesh experiment's


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
    for columns in (3, 128):
        b = rng.normal(size=(u, columns)).astype(np.float32)
        out = np.empty_like(b)
        row[f"sweeps {columns} ms"] = median_ms(lambda b=b: factor.solve(b), repeats)
        row[f"cholespy {columns} ms"] = median_ms(lambda b=b, out=out: chol.solve(b, out), repeats)
    return row


def main(argv=None) -> list[dict]:
    args = common.parse_args("the mesh update's parts", "results/mesh_update_parts", argv)
    frequencies, repeats = ((3,), 2) if args.quick else ((16, 32, 64), 7)
    rows = [parts(f, s, repeats) for f in frequencies for s in ("cholesky", "cg")]
    host = [solves(f, repeats) for f in frequencies]
    md = (
        "Jitted, medians; `python -m tools.mesh_update_parts`.\n\n"
        + common.markdown_table(rows)
        + "\n\nThe host solves alone (float32, medians):\n\n"
        + common.markdown_table(host)
    )
    print(md)
    common.write_results(
        args.out, "mesh_update_parts", {"rows": rows, "solves": host, "quick": args.quick}, md
    )
    return rows + host


if __name__ == "__main__":
    main()
