// The sigma_d rules' grid-wide statistics at a sub-grid (rules/auto.py), each one call:
//
// * texel_distance_mean: the mean over the sub-grid's texels p of ||a[s p] - b[p]||, the norm
//   over the texel's channels, texels whose norm is NaN left out (0 when none is left): the
//   guide's step from its last sub-grid, and its distance from its local average.
// * correlation_sums: the sums behind the lag-1 correlation of z between neighbours along each
//   of `pair_axes` (spatial axes of length > 1): over the positions p with p_d = s i on the
//   other spatial axes, p_a = q k along the axis (k < n_a / q, q = max(s, 2)) and every
//   channel, sum z[p]^2, z[p + e_a]^2 and z[p] z[p + e_a]; then the sums of z^2 and y^2 over
//   the sub-grid: the correlated-noise check's statistics.
//
// `shape` is a's row-major shape, `axes` its spatial axes (each once), `stride` s >= 1 along
// them; b (optional) has the sub-grid's shape: each spatial axis cut to (n - 1) / s + 1. Sums
// are accumulated in double in index order: deterministic, and finite wherever the norms are.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "local.h"

namespace optax_bilateral {

// The first problem with a call's shapes (local.h's Subgrid, with no empty dimension), or ""
// when every read stays in bounds.
std::string check_texel_grid(const Subgrid& g);
// The sub-grid's element count (b's).
int64_t texel_subgrid_size(const Subgrid& g);

// The mean above; `b` may be null (then the mean of ||a[s p]||).
double texel_distance_mean(const Subgrid& g, const float* a, const float* b);
double texel_distance_mean(const Subgrid& g, const double* a, const double* b);

// out (3 pair_axes.size() + 2) <- the sums above, of z and y (both of shape g.shape); each
// pair axis must be one of g.axes.
void correlation_sums(const Subgrid& g, const std::vector<int64_t>& pair_axes, const float* z,
                      const float* y, double* out);
void correlation_sums(const Subgrid& g, const std::vector<int64_t>& pair_axes, const double* z,
                      const double* y, double* out);

}  // namespace optax_bilateral
