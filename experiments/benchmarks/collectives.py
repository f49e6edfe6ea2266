"""What a compiled SPMD program moves between devices, and what a halo exchange must move.

Shared by ``experiments/benchmarks/sharding.py`` and ``tests/test_sharding.py``: the bytes of
every collective, read from the compiled HLO text (:func:`collective_stats`), and the
halo volumes a split grid needs per filter call (:func:`halo_bytes`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np

_DTYPE_BYTES = {
    "pred": 1,
    "s8": 1,
    "u8": 1,
    "s16": 2,
    "u16": 2,
    "f16": 2,
    "bf16": 2,
    "s32": 4,
    "u32": 4,
    "f32": 4,
    "s64": 8,
    "u64": 8,
    "f64": 8,
    "c64": 8,
    "c128": 16,
}
_SHAPE = re.compile(r"\b(pred|bf16|c64|c128|[suf]\d+)\[([\d,]*)\]")
_HEADER = re.compile(r"^(ENTRY\s+)?%?([\w.\-]+)\s*\(.*\)\s*->.*\{\s*$")
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s*=\s*(.*?)\s([a-z][\w\-]*)\((.*)$")
COLLECTIVES = ("collective-permute", "all-gather", "all-reduce", "all-to-all", "reduce-scatter")


def shape_bytes(text: str) -> int:
    """Bytes of every array shape in ``text`` (e.g. ``f32[3,32,2]`` or a tuple of them)."""
    total = 0
    for dtype, dims in _SHAPE.findall(text):
        total += math.prod(int(d) for d in dims.split(",") if d) * _DTYPE_BYTES[dtype]
    return total


def _computations(hlo: str):
    comps, entry, cur = {}, None, None
    for line in hlo.splitlines():
        m = _HEADER.match(line)
        if m:
            cur = m.group(2)
            comps[cur] = []
            entry = cur if m.group(1) else entry
        elif line.startswith("}"):
            cur = None
        elif cur is not None:
            mi = _INSTR.match(line)
            if mi:
                comps[cur].append((mi.group(2), mi.group(1), mi.group(3)))
    return comps, entry


def _group_size(rest: str, devices: int) -> int:
    """Devices per replica group of a collective (all of them if the text does not say)."""
    m = re.search(r"replica_groups=\{\{([\d,]*)\}", rest)
    if m:
        return len(m.group(1).split(","))
    m = re.search(r"replica_groups=\[(\d+),(\d+)\]<=", rest)
    if m:
        return int(m.group(2))
    m = re.search(r"replica_groups=mesh\[([^\]]*)\]\s*\{([^}]*)\}", rest)
    if m:
        sizes = dict((k.strip("' "), int(v)) for k, v in re.findall(r"([^,=]+)=(\d+)", m.group(1)))
        return math.prod(sizes.get(a.strip("' "), 1) for a in m.group(2).split(",") if a.strip())
    return devices


def collective_stats(hlo: str, branch: int | None = -1) -> dict:
    """Collectives of a compiled SPMD module, per kind: ``{"count", "bytes", "max_bytes"}``.

    ``bytes`` is summed over devices: a collective-permute's operand times its
    source-target pairs; an all-gather's result times ``(g-1)/g`` per device (the
    part that came from the other ``g-1`` devices of its group); an all-reduce's
    operand times ``2 (g-1)/g`` per device (a ring). ``max_bytes``: the largest
    single result on one device. Computations called by an instruction count as
    often as they are called; of a ``conditional`` only branch ``branch`` does
    (``-1``: the last, ``lax.cond``'s true branch; ``None``: the one moving most).
    """
    comps, entry = _computations(hlo)
    m = re.search(r"num_partitions=(\d+)", hlo)
    devices = int(m.group(1)) if m else 1
    memo: dict = {}

    def walk(name):
        if name in memo:
            return memo[name]
        acc = {k: {"count": 0, "bytes": 0, "max_bytes": 0} for k in COLLECTIVES}

        def add(other):
            for k in COLLECTIVES:
                acc[k]["count"] += other[k]["count"]
                acc[k]["bytes"] += other[k]["bytes"]
                acc[k]["max_bytes"] = max(acc[k]["max_bytes"], other[k]["max_bytes"])

        for op, shape, rest in comps.get(name, []):
            kind = op[: -len("-start")] if op.endswith("-start") else op
            if kind in COLLECTIVES and not op.endswith("-done"):
                b = shape_bytes(shape)
                if op.endswith("-start"):
                    b //= 2  # an async start's shape is (in, out)
                if kind == "collective-permute":
                    pairs = re.search(r"source_target_pairs=\{(.*?)\}\}", rest)
                    moved = b * (len(re.findall(r"\{\d+,\d+", pairs.group(0))) if pairs else 1)
                else:
                    g = _group_size(rest, devices)
                    share = (g - 1) / g if g else 0.0
                    moved = devices * b * share * (2 if kind == "all-reduce" else 1)
                acc[kind]["count"] += 1
                acc[kind]["bytes"] += round(moved)
                acc[kind]["max_bytes"] = max(acc[kind]["max_bytes"], b)
            for key in ("calls", "to_apply", "body", "condition"):
                for mm in re.finditer(key + r"=%?([\w.\-]+)", rest):
                    add(walk(mm.group(1)))
            mm = re.search(r"branch_computations=\{([^}]*)\}", rest)
            branches = [c.strip().lstrip("%") for c in mm.group(1).split(",")] if mm else []
            for key in ("false_computation", "true_computation"):
                mm = re.search(key + r"=%?([\w.\-]+)", rest)
                if mm:
                    branches.append(mm.group(1))
            if branches:
                stats = [walk(c) for c in branches]
                if branch is None:
                    add(max(stats, key=lambda s: sum(v["bytes"] for v in s.values())))
                else:
                    add(stats[branch])
        memo[name] = acc
        return acc

    return walk(entry)


def _radius(size: int, stride: int) -> int:
    """The widest tap of a level that lands inside an axis of ``size`` points."""
    return max([d * stride for d in (1, 2) if d * stride < size] + [0])


def _remote_points(shape, blocks, radii, clip: bool = True) -> int:
    """Points other blocks hold within ``radii[k]`` of a block along every split axis k.

    Summed over blocks: the box ``block + radii`` on each side (only along split
    axes; neighbours along an unsplit axis are local), minus the block itself.
    ``clip``: count only points on the grid (what must move); without it, the whole
    box (what an exchange that also forwards a neighbour's off-grid zeros moves).
    Along one axis with ``r <= L`` this is ``2 r`` x face area per cut.
    """
    shape, blocks = tuple(shape), tuple(blocks)
    total = 0
    for index in np.ndindex(*blocks):
        box, own = 1, 1
        for size, n, b, r in zip(shape, blocks, index, radii):
            block = size // n
            if n == 1 or r == 0:
                box, own = box * block, own * block
                continue
            lo, hi = b * block - r, (b + 1) * block + r
            box *= (min(hi, size) - max(lo, 0)) if clip else hi - lo
            own *= block
        total += box - own
    return total


def halo_bytes(
    shape: Sequence[int],
    blocks: Sequence[int],
    levels: int,
    fields: int,
    guide: int,
    separable: bool = True,
    itemsize: int = 4,
) -> dict:
    """Halo volumes (bytes, summed over devices) of one filter call on a split grid.

    A level of stride ``s`` reads up to ``r = 2 s`` points away (less on short axes):
    separable, along one axis per pass; full, in a box (with corners).

    * ``per_level``: fields and guide exchanged at every level, ``2 r`` x face area
      per cut and level (corners not counted): the bound the issue states.
    * ``minimum``: what must cross devices: the fields per level (boxes in full
      mode) and the guide once, at the widest radius (it never changes).
    * ``box``: ``minimum`` without clipping the boxes at the grid's edge: an upper
      bound for an exchange that forwards the off-grid zeros of a neighbour's halo
      when it extends a second axis (full mode on 2-axis splits).
    """
    shape, blocks = tuple(shape), tuple(blocks)
    n = len(shape)
    radii_by_level = [[_radius(shape[k], 2**i) for k in range(n)] for i in range(levels)]
    widest = [max([r[k] for r in radii_by_level] + [0]) for k in range(n)]

    def along(k, r):
        return [r if j == k else 0 for j in range(n)]

    per_level = sum(
        _remote_points(shape, blocks, along(k, r[k])) for r in radii_by_level for k in range(n)
    )
    out = {"per_level": per_level * (fields + guide) * itemsize}
    for name, clip in (("minimum", True), ("box", False)):
        if separable:
            f = sum(
                _remote_points(shape, blocks, along(k, r[k]), clip)
                for r in radii_by_level
                for k in range(n)
            )
            g = sum(_remote_points(shape, blocks, along(k, widest[k]), clip) for k in range(n))
        else:
            f = sum(_remote_points(shape, blocks, r, clip) for r in radii_by_level)
            g = _remote_points(shape, blocks, widest, clip)
        out[name] = (f * fields + g * guide) * itemsize
    return out
