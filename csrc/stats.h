// The sigma_d rules' grid-wide statistics at a sub-grid (rules/auto.py), each one call:
//
// * texel_distance_mean: the mean over the sub-grid's texels p of ||a[s p] - b[p]||, the norm
//   over the texel's channels, texels whose norm is NaN left out (0 when none is left): the
//   guide's step from its last sub-grid, and its distance from its local average.
// * correlation_sums: the sums behind the lag-1 correlation of z between neighbours along each
//   of `pair_axes` (spatial axes of length > 1): over the positions p with p_d = s i on the
//   other spatial axes, p_a = q k along the axis (k < n_a / q, q = max(s, 2)) and every
//   channel, sum z[p]^2, z[p + e_a]^2 and z[p] z[p + e_a]; then the sums of z^2 and y^2 over
//   the sub-grid: the correlated-noise check's statistics, z and y computed from the gradient,
//   the first moment and the observed entries at the points read (Noise).
// * blend_weights: the blend's weight of the unfiltered moments at the sub-grid (auto.py's
//   _blend_weight and _gate). With m, v read at the sub-grid and r the residual there,
//     n = ((max(v / c2 - (m / c1)^2, 0) k) ema) corr_num / corr_den,   e = (r / bias)^2,
//     f = A n,  S = A e  (A: local.h's average at stride 1 over the sub-grid),
//     lam = usable and S > 0 ? clamp(1 - f / (gain S), 0, 1)^power : 0,
//     gate = clamp((mean lam - low) / span, 0, 1);   out = lam gate,
//   each operation in T, in that order (the mean's sum in double).
// * step_norm: the mean over the sub-grid's texels p of ||d[s p]||, as texel_distance_mean's,
//   of the postfilter's step before its learning rate (optimizer/step.py), computed from its
//   parts where the mean reads it (Step): sigma_d="auto"'s direction, with no XLA kernel
//   computing the step a second time at the sub-grid.
//
// `shape` is a's row-major shape, `axes` its spatial axes (each once), `stride` s >= 1 along
// them; b (optional) has the sub-grid's shape: each spatial axis cut to (n - 1) / s + 1. Sums
// are accumulated in double in index order: deterministic, and finite wherever the norms are.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "local.h"

namespace optax_bilateral {

// The first problem with a call's shapes (local.h's Subgrid, with no empty dimension), or ""
// when every read stays in bounds.
std::string check_texel_grid(const Subgrid& g);
// The sub-grid's element count (b's).
int64_t texel_subgrid_size(const Subgrid& g);

// The mean above; `b` may be null (then the mean of ||a[s p]||). `kept`, unless null, receives
// a's sub-grid (b's shape): the values the mean read, for the rule to keep as the next b.
double texel_distance_mean(const Subgrid& g, const float* a, const float* b,
                           float* kept = nullptr);
double texel_distance_mean(const Subgrid& g, const double* a, const double* b,
                           double* kept = nullptr);

// The blend's scalars: the step's (computed by the rule) and the rule's constants.
template <typename T>
struct Blend {
  T c1, c2, k, ema, corr_num, corr_den, bias, usable;
  T gain, power, low, span;
};

// out (the sub-grid's shape) <- lam gate for m, v (g.shape) and r (the sub-grid's shape);
// returns gate.
float blend_weights(const Subgrid& g, const float* m, const float* v, const float* r,
                    const Blend<float>& b, float* out);
double blend_weights(const Subgrid& g, const double* m, const double* v, const double* r,
                     const Blend<double>& b, double* out);

// The step's parts: the updated moments m, v, the filtered B m, B v and the gradient as the
// leaf received it (g.shape), and the blend's weight lam (the sub-grid's shape; null: none). A
// texel is observed where all its channels of the gradient are finite (with drop_zero, and
// not all 0: mask_unobserved), as optimizer/step.py's observe. Per entry, in T, as XLA
// evaluates the JAX form (numerics.masked_step of sigma.blend's, the blend's product and sum
// one fused multiply-add):
//   m~ = blend ? fma(lam, m, (1 - lam) B m) : B m,   v~ alike,
//   h = fma(v~, inv_c2, eps_root),   den = (h > 0 ? sqrt(h) : 0) + eps,
//   d = observed and den > 0 ? (m~ inv_c1) / den : 0.
template <typename T>
struct Step {
  const T *m, *v, *bm, *bv, *grad;
  const T* lam;
  bool drop_zero, blend;
  T inv_c1, inv_c2, eps, eps_root;
};

// A Step from its arrays (m, v, B m, B v, the gradient), lam (read only with blend) and the
// scalars (inv_c1, inv_c2, eps, eps_root), each rounded to T.
template <typename T>
Step<T> step_of(const T* const arrays[5], const T* lam, bool drop_zero, bool blend,
                const double scalars[4]) {
  return {arrays[0], arrays[1], arrays[2], arrays[3], arrays[4], blend ? lam : nullptr,
          drop_zero, blend, static_cast<T>(scalars[0]), static_cast<T>(scalars[1]),
          static_cast<T>(scalars[2]), static_cast<T>(scalars[3])};
}

// The mean above of the step's texel norms (each norm in double from d in T).
double step_norm(const Subgrid& g, const Step<float>& s);
double step_norm(const Subgrid& g, const Step<double>& s);

// The correlated-noise check's fields, computed where the sums read them (no full-size copy):
// y = m / c1 and z = clip(grad, -limit, limit) - y where `observed`, else 0, each operation in
// T (auto.py's order; the clip is the step's, so grad may be the gradient as given). grad and
// m have g.shape; observed has its rank, each dimension g.shape's or 1 (broadcast), or is null:
// then a texel is observed where all its channels of grad (the gradient as given) are finite
// and, with drop_zero, not all 0, as Step's (no mask for XLA to write out).
template <typename T>
struct Noise {
  const T* grad;
  const T* m;
  const bool* observed;
  std::vector<int64_t> observed_shape;
  T c1;
  T limit = std::numeric_limits<T>::infinity();
  bool drop_zero = false;
};

// The first problem with a Noise's mask shape for the grid g, or "".
std::string check_noise_mask(const Subgrid& g, const std::vector<int64_t>& observed_shape);

// out (3 pair_axes.size() + 2) <- the sums above, of z and y; each pair axis must be one of
// g.axes.
void correlation_sums(const Subgrid& g, const std::vector<int64_t>& pair_axes,
                      const Noise<float>& noise, double* out);
void correlation_sums(const Subgrid& g, const std::vector<int64_t>& pair_axes,
                      const Noise<double>& noise, double* out);

// sigma_d="auto"'s correlated-noise test from correlation_sums' sums (each already rounded to
// T), in T's arithmetic in the order XLA evaluates its JAX form (rules/auto.py,
// _correlated_noise): the lag-1 correlations' mean (times 1 / n: XLA divides by a constant so)
// at least `correlated`, and the noise's energy above noisy lag^2 times the signal's. 1 or 0.
template <typename T>
T noise_test(const double* sums, size_t pairs, T lag, double correlated, double noisy) {
  T total = 0;
  for (size_t k = 0; k < pairs; ++k) {
    const T s00 = static_cast<T>(sums[3 * k]), s11 = static_cast<T>(sums[3 * k + 1]);
    const T den = std::sqrt(s00 * s11);
    total = total + (den > 0 ? static_cast<T>(sums[3 * k + 2]) / den : T(0));
  }
  const T mean = total * (T(1) / static_cast<T>(pairs));
  const T noise = static_cast<T>(sums[3 * pairs]), signal = static_cast<T>(sums[3 * pairs + 1]);
  const bool correlated_now = mean >= static_cast<T>(correlated);
  const bool noisy_now = noise > static_cast<T>(noisy) * lag * lag * signal;
  return correlated_now && noisy_now ? T(1) : T(0);
}

}  // namespace optax_bilateral
