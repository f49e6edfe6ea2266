// The sigma_d rules' grid-wide statistics at a sub-grid (rules/auto.py), each one call:
//
// * texel_distance_mean: the mean over the sub-grid's texels p of ||a[s p] - b[p]||, the norm
//   over the texel's channels, texels whose norm is NaN left out (0 when none is left): the
//   guide's step from its last sub-grid, and its distance from its local average.
//
// `shape` is a's row-major shape, `axes` its spatial axes (each once), `stride` s >= 1 along
// them; b (optional) has the sub-grid's shape: each spatial axis cut to (n - 1) / s + 1. Sums
// are accumulated in double in index order: deterministic, and finite wherever the norms are.
#pragma once

#include <cstdint>
#include <string>

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

}  // namespace optax_bilateral
