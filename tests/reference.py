"""Independent, slow float64 NumPy loop implementation of the a-trous filter of docs/method.md.

Written straight from the formula, point by point, with no vectorisation and no
weight sharing, so that it shares no code or tricks with the library.
"""

import itertools

import numpy as np

H = np.array([1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16])


def data_weight(gp, gq, sigma_d):
    dist = np.sqrt(np.sum((np.asarray(gp, np.float64) - np.asarray(gq, np.float64)) ** 2))
    if dist == 0:
        return 1.0  # equal guides weigh 1 for any sigma_d (0/0 treated as 0)
    if sigma_d == 0:
        return 0.0
    return float(np.exp(-dist / sigma_d))


def atrous_reference(x, guide, sigma_d, levels, separable, mask=None):
    """x: (*S, C); guide: (*S, G); mask: (*S) bool or None. Returns (*S, C) float64."""
    x = np.asarray(x, np.float64)
    guide = np.asarray(guide, np.float64)
    shape = x.shape[:-1]
    n = len(shape)
    valid = np.ones(shape, bool) if mask is None else np.asarray(mask, bool)
    x = np.where(valid[..., None], x, 0.0)
    for level in range(levels):
        stride = 2**level
        groups = [[k] for k in range(n)] if separable else [list(range(n))]
        for axes in groups:
            out = np.zeros_like(x)
            for p in np.ndindex(*shape):
                num = np.zeros(x.shape[-1])
                den = 0.0
                for d in itertools.product(range(-2, 3), repeat=len(axes)):
                    q = list(p)
                    for a, dd in zip(axes, d):
                        q[a] += stride * dd
                    if any(c < 0 or c >= m for c, m in zip(q, shape)):
                        continue  # outside the grid: skipped, the rest renormalised
                    q = tuple(q)
                    if not valid[q]:
                        continue
                    w = np.prod([H[dd + 2] for dd in d]) * data_weight(guide[p], guide[q], sigma_d)
                    num += w * x[q]
                    den += w
                out[p] = num / den if den > 0 else 0.0
            x = np.where(valid[..., None], out, 0.0)
    return x
