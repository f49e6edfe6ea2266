"""A float64 NumPy port of the authors' optimizers (github wchang22/stadam, commit f864a0c).

Written here from reading their code, for the tests to compare the library against;
it shares no code with the library. Every function follows the authors' control flow
(their names in brackets), in float64 throughout:

* grid kernels [``optimizers/filter{2,3}d_{rgb,scalar}.slang``]: full ``5^n`` taps,
  off-grid taps skipped, weight ``h(x) h(y) [h(z)] exp(-|gp - gq| / (sigma_d + eps))``
  with the kernel's ``eps`` (:data:`KERNEL_EPS`), the guide's norm over channels;
* the texture / volume optimizers [``optimizers/spatiotemporal_adam{,_vol}.py``]:
  strides ``[int(2**(j-1)) for j in range(stride_levels)]`` (the first is 0, the
  identity, so ``stride_levels = L`` is the library's ``levels = L - 1``), the
  prefilter, ``nan_to_num``, coupled weight decay (``torch.optim.Adam``'s
  ``grad + wd * param``), the moments, the postfilter of *clones* of ``m`` and ``v``
  (``mtfilter`` / ``vtfilter``), ``cross_term_off`` (each level guided by its own
  input) and torch's step ``p -= lr/(1-b1^t) * m / (sqrt(v)/sqrt(1-b2^t) + eps)``;
* Large Steps [rgl-epfl/large-steps-pytorch: ``laplacian_uniform``,
  ``compute_matrix``, ``AdamUniform``] and the mesh optimizer
  [``optimizers/spatiotemporal_adam_mesh.py``]: splat with ``exp(clamp(n.s, -1)/sigma_d)``,
  one solve of ``[x w | w]``, slice with ``exp(clamp(n.s, -1)/sigma_phi)``, divide;
  the 32 Lloyd-optimised Sobol directions; their vertex normals
  [``largesteps_scripts/geometry.py``].

Where the authors compute in float32 (their weights, their directions), this port
computes in float64: it is the authors' arithmetic without their rounding.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import numpy as np

# The a-trous taps [kernel[] = {3/8, 1/4, 1/16}, indexed by |offset|].
TAPS = (3.0 / 8, 1.0 / 4, 1.0 / 16)
# The eps each kernel adds to sigma_d: 1e-30 in the 2-D one-channel kernel, 1e-10 elsewhere.
KERNEL_EPS = {(2, 1): 1e-30, (2, 3): 1e-10, (3, 1): 1e-10, (3, 3): 1e-10}
LOG_PRIMAL_EPS = 1e-8


def strides(stride_levels: int) -> list[int]:
    """Their a-trous strides: 0, 1, 2, 4, ... (the stride-0 level is the identity)."""
    return [int(2 ** (j - 1)) for j in range(stride_levels)]


def kernel_sigma(sigma_d: float, ndim: int, channels: int) -> float:
    """The denominator the kernel divides the guide distance by: ``sigma_d + eps``."""
    return sigma_d + KERNEL_EPS[(ndim, channels)]


# ----------------------------------------------------------------------------
# Grid kernels


def filter_level(x, primal, stride: int, sigma_d: float):
    """One launch of their kernel on a ``(*S, C)`` grid, ``len(S)`` in (2, 3), ``C`` in (1, 3).

    ``out[p] = sum_q w(p, q) x[q] / sum_q w(p, q)``, ``q = p + stride * d`` for
    ``d`` in ``{-2..2}^n`` on the grid, ``w = prod_k TAPS[|d_k|] exp(-|primal[p] -
    primal[q]| / (sigma_d + eps))``.
    """
    x = np.asarray(x, np.float64)
    primal = np.asarray(primal, np.float64)
    shape, channels = x.shape[:-1], x.shape[-1]
    ndim = len(shape)
    if ndim not in (2, 3) or channels not in (1, 3) or primal.shape != x.shape:
        raise ValueError(
            f"their kernels take (H, W[, D], 1 or 3) grids, got {x.shape}, {primal.shape}"
        )
    sigma = kernel_sigma(sigma_d, ndim, channels)
    num = np.zeros_like(x)
    den = np.zeros(shape)
    index = np.indices(shape)
    for d in itertools.product(range(-2, 3), repeat=ndim):
        q = [index[k] + stride * d[k] for k in range(ndim)]
        inside = np.all([(qk >= 0) & (qk < n) for qk, n in zip(q, shape)], axis=0)
        qc = tuple(np.clip(qk, 0, n - 1) for qk, n in zip(q, shape))
        dist = np.sqrt(np.sum((primal - primal[qc]) ** 2, axis=-1))
        w = np.prod([TAPS[abs(dk)] for dk in d]) * np.exp(-dist / sigma)
        w = np.where(inside, w, 0.0)
        num += w[..., None] * x[qc]
        den += w
    return num / den[..., None]


def log_primal(p):
    return np.log(np.abs(np.asarray(p, np.float64)) + LOG_PRIMAL_EPS)


def filter_chain(x, param, stride_levels: int, sigma_d: float, *, cross_term_off=False, log=False):
    """Their loop over strides; each level reads its guide afresh (``cross_term_off``:
    the level's own input), through ``log(|.| + 1e-8)`` with ``log_primal``."""
    x = np.asarray(x, np.float64)
    for s in strides(stride_levels):
        primal = x if cross_term_off else np.asarray(param, np.float64)
        x = filter_level(x, log_primal(primal) if log else primal, s, sigma_d)
    return x


def volume_sigma(channels: int, sigma_d_1d: float, sigma_d_3d: float) -> float:
    """[filter3d] picks sigma_d by channel count; other counts are refused."""
    if sigma_d_1d < 0 or sigma_d_3d < 0:
        raise ValueError("sigma_d_1d and sigma_d_3d must be >= 0")
    if channels == 1:
        return sigma_d_1d
    if channels == 3:
        return sigma_d_3d
    raise ValueError(f"their volume kernels take 1 or 3 channels, got {channels}")


# ----------------------------------------------------------------------------
# The grid optimizers (SpatioTemporalAdam, SpatioTemporalAdamVol)


class AdamState(NamedTuple):
    step: int
    exp_avg: np.ndarray
    exp_avg_sq: np.ndarray


def adam_init(param) -> AdamState:
    z = np.zeros_like(np.asarray(param, np.float64))
    return AdamState(0, z, z.copy())


def spatiotemporal_adam_step(
    param,
    grad,
    state: AdamState,
    *,
    lr,
    betas,
    eps=1e-8,
    weight_decay=0.0,
    sigma_d=2e-2,
    sigma_d_1d=None,
    sigma_d_3d=None,
    postfilter=True,
    prefilter=False,
    mtfilter=True,
    vtfilter=True,
    log_primal=False,
    cross_term_off=False,
    stride_levels=5,
    maximize=False,
):
    """One step of their texture (2-D) or volume (3-D) optimizer on one parameter.

    ``param``, ``grad``: ``(H, W, C)`` (texture, ``sigma_d``, optional ``log_primal``)
    or ``(H, W, D, C)`` (volume: ``sigma_d_1d`` / ``sigma_d_3d``; their volume
    class has no ``log_primal``). Returns ``(new_param, new_state)``.
    """
    param = np.asarray(param, np.float64)
    grad = np.asarray(grad, np.float64)
    volume = param.ndim == 4
    if volume:
        if log_primal:
            raise ValueError("their volume optimizer has no log_primal")
        sigma = volume_sigma(param.shape[-1], sigma_d_1d, sigma_d_3d)
    else:
        sigma = sigma_d
    b1, b2 = betas
    if maximize:
        grad = -grad

    def chain(x):
        return filter_chain(
            x, param, stride_levels, sigma, cross_term_off=cross_term_off, log=log_primal
        )

    if prefilter:
        grad = chain(grad)
    grad = np.nan_to_num(grad)
    step = state.step + 1
    if weight_decay != 0:
        grad = grad + weight_decay * param
    exp_avg = state.exp_avg * b1 + (1 - b1) * grad
    exp_avg_sq = state.exp_avg_sq * b2 + (1 - b2) * grad * grad
    bias_correction1 = 1 - b1**step
    bias_correction2 = 1 - b2**step
    m, v = exp_avg.copy(), exp_avg_sq.copy()
    if postfilter:
        if mtfilter:
            m = np.nan_to_num(chain(m))
        if vtfilter:
            v = np.nan_to_num(chain(v))
    step_size = lr / bias_correction1
    denom = np.sqrt(v) / math.sqrt(bias_correction2) + eps
    return param - step_size * m / denom, AdamState(step, exp_avg, exp_avg_sq)


def drjit_uniform_step(m_f, v_f, t: int, b1: float, b2: float, eps: float):
    """The Dr.Jit port's ``uniform`` step, before the learning rate: one second moment,
    the max over the whole tensor, eps on the uncorrected root [FilteredAdam.step]:
    ``sqrt(1-b2^t)/(1-b1^t) * m / (sqrt(max v) + eps)``."""
    return math.sqrt(1 - b2**t) / (1 - b1**t) * np.asarray(m_f) / (np.sqrt(np.max(v_f)) + eps)


def uniform_adam_step(m, v, t: int, b1: float, b2: float, eps: float):
    """Large Steps' uniform second moment in this paper's convention:
    ``m^ / (sqrt(max v^) + eps)`` [AdamUniform, SpatioTemporalAdamMesh "uniform"]."""
    return (np.asarray(m) / (1 - b1**t)) / (np.sqrt(np.max(v) / (1 - b2**t)) + eps)


# ----------------------------------------------------------------------------
# Meshes: Large Steps


def laplacian_uniform(faces, num_vertices: int) -> np.ndarray:
    """Dense combinatorial Laplacian ``D - A`` [largesteps.geometry.laplacian_uniform]."""
    f = np.asarray(faces)
    ii = f[:, [1, 2, 0]].ravel()
    jj = f[:, [2, 0, 1]].ravel()
    adj = np.zeros((num_vertices, num_vertices))
    adj[ii, jj] = 1.0  # unique edges, both directions
    adj[jj, ii] = 1.0
    return np.diag(adj.sum(1)) - adj


def compute_matrix(faces, num_vertices: int, lambda_: float, alpha: float | None = None):
    """[largesteps.geometry.compute_matrix]: ``I + lambda L``, or ``(1 - alpha) I + alpha L``."""
    lap = laplacian_uniform(faces, num_vertices)
    eye = np.eye(num_vertices)
    if alpha is None:
        return eye + lambda_ * lap
    if not 0.0 <= alpha < 1.0:
        raise ValueError("alpha must be in [0, 1)")
    return (1 - alpha) * eye + alpha * lap


def matrix_solve(M, b):
    """[from_differential]: ``M^-1 b`` (their Cholesky; a dense solve here)."""
    return np.linalg.solve(M, np.asarray(b, np.float64))


class UniformState(NamedTuple):
    step: int
    g1: np.ndarray
    g2: np.ndarray


def uniform_init(p) -> UniformState:
    z = np.zeros_like(np.asarray(p, np.float64))
    return UniformState(0, z, z.copy())


def adam_uniform_step(u, grad_u, state: UniformState, *, lr, betas):
    """[largesteps.optimize.AdamUniform.step]: ``u -= lr m^ / (1e-8 + max sqrt(v^))``."""
    b1, b2 = betas
    step = state.step + 1
    g1 = state.g1 * b1 + (1 - b1) * grad_u
    g2 = state.g2 * b2 + (1 - b2) * np.square(grad_u)
    m1 = g1 / (1 - b1**step)
    m2 = g2 / (1 - b2**step)
    return u - lr * m1 / (1e-8 + np.sqrt(m2).max()), UniformState(step, g1, g2)


def large_steps_step(x, grad_x, state: UniformState, M, *, lr, betas):
    """Large Steps written on the positions: ``u = M x``, ``dL/du = M^-1 dL/dx``
    [to_differential / from_differential]; returns the new positions ``M^-1 u``."""
    u = M @ np.asarray(x, np.float64)
    u, state = adam_uniform_step(u, matrix_solve(M, grad_x), state, lr=lr, betas=betas)
    return matrix_solve(M, u), state


# ----------------------------------------------------------------------------
# Meshes: the bilateral normal filter and SpatioTemporalAdamMesh


def sobol_directions(n: int = 32) -> np.ndarray:
    """Their ``normal_samples``: ``Sobol(d=2, scramble=True, optimization="lloyd",
    seed=0).random(n)`` mapped by ``theta = 2 pi u0``, ``phi = acos(1 - 2 u1)``."""
    from scipy.stats.qmc import Sobol

    eta = Sobol(d=2, scramble=True, optimization="lloyd", seed=0).random(n=n)
    theta = 2 * np.pi * eta[:, 0]
    phi = np.arccos(1 - 2 * eta[:, 1])
    return np.stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)], 1)


def face_normals(v, f):
    """[compute_face_normals]: unit ``(b - a) x (c - a)`` per face, ``(F, 3)``."""
    v = np.asarray(v, np.float64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def authors_vertex_normals(v, f):
    """[compute_vertex_normals] exactly: face normals weighted by
    ``acos(e0 . e1 / (|E0| |E1|))`` where ``|E0|``, ``|E1|`` are the norms of *all*
    the faces' edge vectors together (``torch.norm`` without ``dim``), so every
    weight is ``pi/2 - O(1/F)``: nearly the unweighted mean of unit face normals."""
    v = np.asarray(v, np.float64)
    fn = face_normals(v, f)
    corners = [v[f[:, i]] for i in range(3)]
    normals = np.zeros_like(v)
    for i in range(3):
        d0 = corners[(i + 1) % 3] - corners[i]
        d0 = d0 / np.linalg.norm(d0)
        d1 = corners[(i + 2) % 3] - corners[i]
        d1 = d1 / np.linalg.norm(d1)
        angle = np.arccos(np.clip(np.sum(d0 * d1, 1), -1, 1))
        np.add.at(normals, f[:, i], fn * angle[:, None])
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def unweighted_vertex_normals(v, f):
    """The limit of :func:`authors_vertex_normals`: the normalised sum of unit face normals."""
    fn = face_normals(v, f)
    normals = np.zeros((len(v), 3))
    for i in range(3):
        np.add.at(normals, f[:, i], fn)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def angle_vertex_normals(v, f):
    """What :func:`authors_vertex_normals` meant: weights = the corner angles."""
    v = np.asarray(v, np.float64)
    fn = face_normals(v, f)
    normals = np.zeros_like(v)
    for i in range(3):
        d0 = v[f[:, (i + 1) % 3]] - v[f[:, i]]
        d1 = v[f[:, (i + 2) % 3]] - v[f[:, i]]
        cos = np.sum(d0 * d1, 1) / (np.linalg.norm(d0, axis=1) * np.linalg.norm(d1, axis=1))
        np.add.at(normals, f[:, i], fn * np.arccos(np.clip(cos, -1, 1))[:, None])
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def area_vertex_normals(v, f):
    """Face normals weighted by face area (the library's default)."""
    v = np.asarray(v, np.float64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n2 = np.cross(b - a, c - a)
    normals = np.zeros_like(v)
    for i in range(3):
        np.add.at(normals, f[:, i], n2)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def von_mises_fisher(normals, samples, sigma, clamp=-1.0):
    """[von_mises_fisher_kernel]: ``exp(clamp(n . s, min=-1) / sigma)``, ``(V, K)``."""
    return np.exp(
        np.maximum(np.asarray(normals, np.float64) @ np.asarray(samples, np.float64).T, clamp)
        / sigma
    )


def mesh_filter(x, filt_type: str, normals, M, samples, sigma_d: float, sigma_phi: float):
    """[SpatioTemporalAdamMesh.filter]: ``"smooth"`` = ``M^-1 x``; ``"bilateral"`` =
    splat with ``sigma_d``, one solve of ``[x w | w]``, slice with ``sigma_phi``, divide."""
    x = np.asarray(x, np.float64)
    if filt_type == "smooth":
        return matrix_solve(M, x)
    if filt_type != "bilateral":
        raise ValueError(filt_type)
    g_den = von_mises_fisher(normals, samples, sigma_d)[:, None, :]  # (V, 1, K)
    g_num = x[:, :, None] * g_den  # (V, C, K)
    dim = x.shape[-1]
    g = np.concatenate([g_num, g_den], axis=1).reshape(x.shape[0], -1)
    diffused = matrix_solve(M, g).reshape(x.shape[0], dim + 1, -1)
    phi = von_mises_fisher(normals, samples, sigma_phi)[:, None, :]
    weighted = diffused * phi
    return weighted[:, :dim].sum(-1) / weighted[:, dim:].sum(-1)


def mesh_adam_step(
    p,
    grad,
    state: UniformState,
    normals,
    M,
    samples,
    *,
    lr,
    betas,
    eps=1e-8,
    sigma_d=0.5,
    sigma_phi=0.4,
    prefilter="smooth",
    postfilter="bilateral",
    postfilter_v="uniform",
):
    """[SpatioTemporalAdamMesh.step] on one parameter with ``M`` and ``normals`` given.

    The state keeps the unfiltered moments (the filters rebind locals); with
    ``postfilter="off"`` the second moment is Adam's, whatever ``postfilter_v``."""
    b1, b2 = betas
    kw = dict(normals=normals, M=M, samples=samples, sigma_d=sigma_d, sigma_phi=sigma_phi)
    step = state.step + 1
    grad = np.asarray(grad, np.float64)
    if prefilter != "off":
        grad = mesh_filter(grad, prefilter, **kw)
    g1 = state.g1 * b1 + (1 - b1) * grad
    g2 = state.g2 * b2 + (1 - b2) * np.square(grad)
    new_state = UniformState(step, g1, g2)
    if postfilter != "off":
        g1 = mesh_filter(g1, postfilter, **kw)
        g2 = g2.max() if postfilter_v == "uniform" else mesh_filter(g2, postfilter_v, **kw)
    m1 = g1 / (1 - b1**step)
    m2 = g2 / (1 - b2**step)
    return np.asarray(p, np.float64) - lr * m1 / (eps + np.sqrt(m2)), new_state
