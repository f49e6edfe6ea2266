"""A study (issue 44): the separable a-trous filter run in place, block by block.

Each level runs as a loop over blocks of rows of one padded planar buffer: the outer axis's
pass reads its block with a halo (the rows before the block, already overwritten, come from a
carry of the originals), the inner axes' passes follow on the same block, and the block is
written back in place. Memory then holds the buffer and one block's temporaries instead of a
pass's input, padded copy and output. Run::

    python -m tools.blocked_filter_study

It prints, for the current kernel and the blocked one (a ``lax.fori_loop`` over blocks, and
the same blocks unrolled), the largest difference from the current kernel, XLA's planned
temporaries of the filter alone in field-sizes (one field: m or v, half the stacked array)
and the median time of paired rounds.
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from optax_bilateral._src import atrous as A
from optax_bilateral._src.bilateral import level_passes, rescale_guide


def one_pass(x, g, valid, sigma, pairs, h0):
    shape = g.shape[1:]
    grid = A._Grid(shape)
    lead = max(grid.halo(off) for off, _ in pairs)
    gpad = A._pad_rows(g, lead, lead, shape)
    vpad = None if valid is None else A._pad_rows(valid[None], lead, lead, shape)
    view = A._view(shape, shape[0])
    cache = {}

    def weights(offs, dep):
        new = [o for o in offs if o not in cache]
        if new:
            h = max(grid.halo(o) for o in new)
            stack = jnp.concatenate(
                [A._pair_weights(grid, gpad, vpad, lead, sigma + dep, o, h) for o in new]
            )
            for j, o in enumerate(new):
                cache[o] = (stack[j : j + 1], h)
        return {o: cache[o] for o in offs}

    c = x.shape[0]
    v = None if valid is None else valid.reshape(view)
    y = A._pass(grid, x.reshape((c,) + view), pairs, h0, v, weights)
    return y.reshape((c,) + shape)


def filter_blocked(x, g, valid, sigma, levels, *, block_elems, unroll, start=0):
    if g.shape[0] > 1:
        g, sigma = rescale_guide(g, sigma)
    shape = g.shape[1:]
    n0, inner = shape[0], tuple(shape[1:])
    row = math.prod(inner)
    B = max(1, min(n0, block_elems // row))
    x = x.reshape(x.shape[:1] + shape)
    plan = []
    for i in range(start, levels):
        passes = level_passes(shape, 2**i, True)
        outer = [p for p in passes if p[0][0][0][0] != 0]
        rest = [p for p in passes if p[0][0][0][0] == 0]
        h = max([off[0] for pairs, _ in outer for off, _ in pairs] or [0])
        plan.append((passes, outer, rest, h, B + 2 * h <= n0 and B < n0))
    hs = [p[3] for p in plan if p[4]]
    if not hs:
        for passes, *_ in plan:
            for pairs, h0 in passes:
                x = one_pass(x, g, valid, sigma, pairs, h0)
        return x
    H = max(hs)
    nb = -(-n0 // B)
    tail = nb * B - n0
    cfg = [(0, 0, 0)] * x.ndim
    cfg[1] = (H, H + tail, 0)
    zero = jnp.zeros((), x.dtype)
    xp, gp = lax.pad(x, zero, cfg), lax.pad(g, zero, cfg)
    vp = None if valid is None else lax.pad(valid[None], zero, cfg)
    dt = x.dtype

    def rows(a, lo, n):
        return lax.dynamic_slice_in_dim(a, lo, n, axis=1)

    def vrows(lo, n):
        i = lo - H + lax.broadcasted_iota(jnp.int32, (n,) + inner, 0)
        v = ((i >= 0) & (i < n0)).astype(dt)
        return v if vp is None else v * rows(vp, lo, n)[0]

    for passes, outer, rest, h, blocked in plan:
        if not blocked:
            xs = xp[:, H : H + n0]
            for pairs, h0 in passes:
                xs = one_pass(xs, g, valid, sigma, pairs, h0)
            xp = lax.dynamic_update_slice_in_dim(xp, xs, H, axis=1)
            continue

        def body(b, carry, outer=outer, rest=rest, h=h):
            xp, keep = carry
            b0 = H + b * B
            if outer:
                xw = jnp.concatenate([keep, rows(xp, b0, B + h)], axis=1)
                gw, vw = rows(gp, b0 - h, B + 2 * h), vrows(b0 - h, B + 2 * h)
                ((pairs, h0),) = outer
                y = one_pass(xw, gw, vw, sigma, pairs, h0)[:, h : h + B]
                keep = xw[:, B : B + h]
                gb, vb = gw[:, h : h + B], vw[h : h + B]
            else:
                y, gb, vb = rows(xp, b0, B), rows(gp, b0, B), vrows(b0, B)
            for pairs, h0 in rest:
                y = one_pass(y, gb, vb, sigma, pairs, h0)
            return lax.dynamic_update_slice_in_dim(xp, y, b0, axis=1), keep

        keep0 = lax.slice_in_dim(xp, H - h, H, axis=1)
        if unroll:
            carry = (xp, keep0)
            for b in range(nb):
                carry = body(b, carry)
            xp = carry[0]
        else:
            xp, _ = lax.fori_loop(0, nb, body, (xp, keep0))
    return xp[:, H : H + n0]


def measure(shape, c, g_channels, levels, block_elems, rounds):
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(c,) + shape), jnp.float32)
    g = jnp.asarray(rng.uniform(size=(g_channels,) + shape), jnp.float32)
    sigma = jnp.float32(0.3)
    plane = A.plane_shape(shape)
    fns = {
        "current": jax.jit(
            lambda x, g: A.filter_planes(x.reshape((c,) + plane), g, None, sigma, levels, True)
        ),
        "blocked, fori_loop": jax.jit(
            lambda x, g: filter_blocked(
                x, g, None, sigma, levels, block_elems=block_elems, unroll=False
            )
        ),
        "blocked, unrolled": jax.jit(
            lambda x, g: filter_blocked(
                x, g, None, sigma, levels, block_elems=block_elems, unroll=True
            )
        ),
    }
    field = x.size * 4 / 2  # one of the two stacked fields (m or v)
    ref = fns["current"](x, g)
    times = {k: [] for k in fns}
    rows = {}
    for k, f in fns.items():
        out = f(x, g).block_until_ready()
        temp = f.lower(x, g).compile().memory_analysis().temp_size_in_bytes
        rows[k] = {"max diff": float(jnp.max(jnp.abs(out - ref))), "temp": temp / field}
    for _ in range(rounds):
        for k, f in fns.items():
            t = time.perf_counter()
            f(x, g).block_until_ready()
            times[k].append(time.perf_counter() - t)
    for k, r in rows.items():
        r["ms"] = 1e3 * float(np.median(times[k]))
        r["x current (paired)"] = float(np.median(np.array(times[k]) / np.array(times["current"])))
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=15)
    a = p.parse_args(argv)
    cases = [
        ((512, 512), 6, 3, 3, 1 << 16),
        ((512, 512), 6, 3, 5, 1 << 16),
        ((128, 128, 128), 2, 1, 3, 1 << 15),
        ((128, 128, 128), 2, 1, 5, 1 << 15),
    ]
    print("| grid (C fields, G guide) | F | filter | max diff | temp / field | ms | x current |")
    print("|---|---|---|---|---|---|---|")
    for shape, c, gc, levels, block in cases:
        for k, r in measure(shape, c, gc, levels, block, a.rounds).items():
            name = "x".join(map(str, shape)) + f" (C {c}, G {gc})"
            print(
                f"| {name} | {levels} | {k} | {r['max diff']:.1e} | {r['temp']:.2f} | "
                f"{r['ms']:.1f} | {r['x current (paired)']:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
