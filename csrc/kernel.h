// One pass of the cascade over one block of a view's rows and columns: the loops every
// instruction-set build compiles (kernel_*.cc include this file under their own target).
// Written as plain loops over contiguous points, which the compiler vectorises.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <utility>
#include <vector>

#include "passes.h"

namespace optax_bilateral {

// What one pass reads and writes; the geometry is the pass's view of the grid.
template <typename T>
struct PassArgs {
  const T* const* x;  // channel c of the input at x[c] + x_at
  int64_t x_at;
  T* const* y;  // channel c of the output at y[c] + y_at
  int64_t y_at;
  const T* guide;  // (G, .), channel c at guide + c * guide_stride
  const T* valid;  // (.) or nullptr
  int64_t channels, guide_channels, guide_stride;
  // run_chunk only: write the result into these fields, each (points, channels) with its
  // channels interleaved, instead of into the level's output planes.
  const std::vector<std::pair<T*, int64_t>>* interleaved = nullptr;
  T guide_scale;    // the guide's multiplier: 1/2 with one channel, else a power of two
  T neg_inv_sigma;  // -1 / sigma_d (scaled like the guide); -inf for sigma_d = 0
  bool sigma_inf;   // sigma_d = inf: every kept pair weighs 1
  const Pass* pass;

  // 0 < sigma_d < inf: a pair's weight is exp_or_zero(distance * neg_inv_sigma), as
  // data_weight's without its selects (equal guides give exp(-0) = 1, a NaN distance 0).
  bool finite_sigma() const {
    return !sigma_inf && neg_inv_sigma < T(0) && neg_inv_sigma > -std::numeric_limits<T>::infinity();
  }
};

// Per-thread buffers, reused across passes.
// One term of a row's sums: weights w, read against x from flat index `from`, added at
// column `at` of the row's block, for n columns.
template <typename T>
struct Term {
  const T* w;
  int64_t from, at, n;
};

template <typename T>
struct Scratch {
  std::vector<T> den, weights, dist;
  std::vector<int64_t> offsets;
  std::vector<Term<T>> terms;
  std::vector<int64_t> bounds;       // row_sums: where the row's terms start and end
  std::vector<const Term<T>*> active;  // the terms of each cut between them, in order
  std::vector<int64_t> first_active;   // cut k's terms: active[first_active[k], [k + 1])
  std::vector<int64_t> cut_key;        // what the cuts were made for: most rows repeat it
  // run_chunk: two slabs of the fields, the axis-0 weights (5 slabs), the originals of the
  // last two slabs an in-place level overwrote (2 slabs of the fields); run_slab_chunk: each
  // pair's slots of weights in `ring`
  std::vector<T> slabs, ring, saved;
  // run_chunk's groups of rows (SlabLevel::group_rows): their fields, results, guide and mask
  // rows, one run of rows per channel, and the slab each row came from.
  std::vector<T> group_x, group_y, group_guide, group_valid;
  std::vector<int64_t> group_slabs;
  std::vector<T*> cur, other, to;  // the two slabs' channels, the output slab's
  std::vector<const T*> from;      // the input slab's channels
};

// One separable level of a grid of rank >= 2 run slab by slab (slabs along axis 0): the pass
// along axis 0 (if the stride fits), then the passes along the other axes, which stay within
// a slab, while the slab is in cache. One read and one write of the fields per level instead
// of one per axis.
template <typename T>
struct SlabLevel {
  int64_t slabs = 0, slab = 0;   // n0, and the points of one slab (n1 * ... * n_{d-1})
  int64_t stride = 0;            // 2^level
  std::vector<Pass> inner;       // the passes along axes 1.., on one slab's grid
  // A 2-D grid's slab is one row: its pass along the row runs for this many slabs of a chain
  // at once, their rows gathered into one run (short rows: a call per row costs more than it
  // computes); 1: slab by slab.
  int64_t group_rows = 1;
};

// Where a level reads or writes its slabs: channel c of slab i at base[c] + i * stride[c].
// Planar grids: stride = a slab's points. Fields in their own layout between levels: field
// k's slab i holds its c_k planes one after another, in the memory its interleaved output
// takes, so the last level writes each slab where it read it.
template <typename P>
struct SlabPlanes {
  std::vector<P*> base;
  std::vector<int64_t> stride;
  P* at(int64_t i, size_t c) const { return base[c] + i * stride[c]; }
};

// One unit of a level: positions [first, last) of the chain of slabs residue, residue + st,
// residue + 2 st, ... (length slabs in all). The axis-0 pass of a slab reads only its chain,
// so chains are independent and each is swept in order, in place: the originals of the two
// slabs before the current one are kept aside (Scratch::saved). A chain cut into several
// chunks gets the originals its neighbours overwrite as copies taken before the level starts.
template <typename T>
struct Chunk {
  int64_t residue = 0, first = 0, last = 0, length = 0;
  const T* before = nullptr;  // positions first - 2, first - 1: (2, channels, slab points)
  const T* after = nullptr;   // positions last, last + 1, alike
};

}  // namespace optax_bilateral

// Everything below is compiled once per instruction set, in namespace OB_ISA.
#if defined(OB_ISA)
namespace optax_bilateral {
namespace OB_ISA {

// exp(a) for a <= 0 (or -inf): Cody-Waite reduction and a degree-5 minimax polynomial
// (float32: ~1 ulp); exp(0) = 1 exactly, results below FLT_MIN flush to 0. Branch-free, so
// that the loops calling it vectorise.
inline float exp_nonpositive(float a) {
  const bool under = a < -87.33654f;
  const float x = under ? 0.0f : a;
  // n = round(x / ln 2) in the low bits of k (1.5 * 2^23 + n); no float-to-int conversion.
  const float k = x * 1.44269504088896341f + 12582912.0f;
  const int32_t i = __builtin_bit_cast(int32_t, k) - 0x4B400000;
  const float n = k - 12582912.0f;
  float r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const float e = p * r * r + r + 1.0f;
  const float scale = __builtin_bit_cast(float, (i + 127) * (1 << 23));  // 2^n, n >= -126
  return under ? 0.0f : e * scale;
}

inline double exp_nonpositive(double a) { return std::exp(a); }

// exp(a) for a <= 0, and 0 for a NaN a: one comparison does both (a NaN fails every one).
inline float exp_or_zero(float a) {
  const bool keep = a >= -87.33654f;
  return keep ? exp_nonpositive(keep ? a : 0.0f) : 0.0f;
}

inline double exp_or_zero(double a) { return a == a ? std::exp(a) : 0.0; }

// The data weight of a guide distance `d` (one channel: |a - b|; several: the squared
// norm), as bilateral.weight: equal guides weigh 1, a NaN distance or a dropped pair 0.
template <typename T, bool kSquared>
inline T data_weight(T d, bool keep, T neg_inv_sigma, bool sigma_inf) {
  const bool pos = d > 0;
  // Both forms select before they compute, as bilateral.weight does (and GCC's vectoriser
  // then takes the one-channel loop as it takes the other).
  T dist = pos ? d : T(1);
  if constexpr (kSquared) dist = std::sqrt(dist);
  T arg = sigma_inf ? T(0) : dist * neg_inv_sigma;
  arg = pos ? arg : T(0);
  const bool drop = (d != d) | !keep;  // bitwise: no branch, so the loop vectorises
  return drop ? T(0) : exp_nonpositive(arg);
}

// tap * w(p, p + o) for kG guide channels, the squared distance summed in registers.
template <typename T, int kG, bool kMasked, bool kScaled>
void few_channel_weights(const PassArgs<T>& a, int64_t pa, int64_t pb, int64_t n, T tap,
                         T* __restrict__ w) {
  const T gs = a.guide_scale;
  const T nis = a.neg_inv_sigma;
  const bool sinf = a.sigma_inf;
  const T* __restrict__ ga[kG];
  const T* __restrict__ gb[kG];
  for (int c = 0; c < kG; ++c) {
    ga[c] = a.guide + c * a.guide_stride + pa;
    gb[c] = a.guide + c * a.guide_stride + pb;
  }
  const T* __restrict__ va = kMasked ? a.valid + pa : nullptr;
  const T* __restrict__ vb = kMasked ? a.valid + pb : nullptr;
  const auto squared_distance = [&](int64_t j) {
    // Scaled only where the guide is large enough to overflow (bilateral.rescale_guide).
    T t = kScaled ? ga[0][j] * gs - gb[0][j] * gs : ga[0][j] - gb[0][j];
    T d2 = t * t;
    for (int c = 1; c < kG; ++c) {
      t = kScaled ? ga[c][j] * gs - gb[c][j] * gs : ga[c][j] - gb[c][j];
      d2 += t * t;
    }
    return d2;
  };
  if (a.finite_sigma()) {
    for (int64_t j = 0; j < n; ++j) {
      const T e = tap * exp_or_zero(std::sqrt(squared_distance(j)) * nis);
      if constexpr (kMasked) {
        w[j] = (va[j] > 0) & (vb[j] > 0) ? e : T(0);
      } else {
        w[j] = e;
      }
    }
    return;
  }
  for (int64_t j = 0; j < n; ++j) {
    const T d2 = squared_distance(j);
    bool keep = true;
    if constexpr (kMasked) keep = (va[j] > 0) & (vb[j] > 0);
    w[j] = tap * data_weight<T, true>(d2, keep, nis, sinf);
  }
}

// tap * w(p, p + o) for the points p = row_a[j], j in [0, n), whose partner is row_b[j].
template <typename T>
void pair_weights(const PassArgs<T>& a, int64_t pa, int64_t pb, int64_t n, T tap,
                  T* __restrict__ w, T* __restrict__ d2) {
  const T gs = a.guide_scale;
  const T nis = a.neg_inv_sigma;
  const bool sinf = a.sigma_inf;
  const T* __restrict__ va = a.valid ? a.valid + pa : nullptr;
  const T* __restrict__ vb = a.valid ? a.valid + pb : nullptr;
  if (a.guide_channels == 1) {
    const T* __restrict__ ga = a.guide + pa;
    const T* __restrict__ gb = a.guide + pb;
    if (a.finite_sigma() && va) {
      for (int64_t j = 0; j < n; ++j) {
        const T e = tap * exp_or_zero(std::fabs(ga[j] * gs - gb[j] * gs) * nis);
        w[j] = (va[j] > 0) & (vb[j] > 0) ? e : T(0);
      }
    } else if (a.finite_sigma()) {
      for (int64_t j = 0; j < n; ++j)
        w[j] = tap * exp_or_zero(std::fabs(ga[j] * gs - gb[j] * gs) * nis);
    } else if (va) {
      for (int64_t j = 0; j < n; ++j) {
        const T d = std::fabs(ga[j] * gs - gb[j] * gs);
        w[j] = tap * data_weight<T, false>(d, (va[j] > 0) & (vb[j] > 0), nis, sinf);
      }
    } else {
      for (int64_t j = 0; j < n; ++j) {
        const T d = std::fabs(ga[j] * gs - gb[j] * gs);
        w[j] = tap * data_weight<T, false>(d, true, nis, sinf);
      }
    }
    return;
  }
  if (a.guide_channels >= 2 && a.guide_channels <= 4) {  // the distance in registers
    const int64_t key = a.guide_channels * 4 + (va ? 2 : 0) + (gs != T(1) ? 1 : 0);
    switch (key) {
#define OB_FEW(g, m, sc) \
  case g * 4 + m * 2 + sc: \
    return few_channel_weights<T, g, m, sc>(a, pa, pb, n, tap, w);
      OB_FEW(2, 0, 0) OB_FEW(2, 0, 1) OB_FEW(2, 1, 0) OB_FEW(2, 1, 1)
      OB_FEW(3, 0, 0) OB_FEW(3, 0, 1) OB_FEW(3, 1, 0) OB_FEW(3, 1, 1)
      OB_FEW(4, 0, 0) OB_FEW(4, 0, 1) OB_FEW(4, 1, 0) OB_FEW(4, 1, 1)
#undef OB_FEW
      default:
        break;
    }
  }
  for (int64_t c = 0; c < a.guide_channels; ++c) {
    const T* __restrict__ ga = a.guide + c * a.guide_stride + pa;
    const T* __restrict__ gb = a.guide + c * a.guide_stride + pb;
    if (c == 0) {
      for (int64_t j = 0; j < n; ++j) {
        const T t = ga[j] * gs - gb[j] * gs;
        d2[j] = t * t;
      }
    } else {
      for (int64_t j = 0; j < n; ++j) {
        const T t = ga[j] * gs - gb[j] * gs;
        d2[j] += t * t;
      }
    }
  }
  if (a.finite_sigma() && va) {
    for (int64_t j = 0; j < n; ++j) {
      const T e = tap * exp_or_zero(std::sqrt(d2[j]) * nis);
      w[j] = (va[j] > 0) & (vb[j] > 0) ? e : T(0);
    }
  } else if (a.finite_sigma()) {
    for (int64_t j = 0; j < n; ++j) w[j] = tap * exp_or_zero(std::sqrt(d2[j]) * nis);
  } else if (va) {
    for (int64_t j = 0; j < n; ++j)
      w[j] = tap * data_weight<T, true>(d2[j], (va[j] > 0) & (vb[j] > 0), nis, sinf);
  } else {
    for (int64_t j = 0; j < n; ++j) w[j] = tap * data_weight<T, true>(d2[j], true, nis, sinf);
  }
}

// acc + w (the normaliser) and acc + w x (a channel), skipping a hole: with kHoles, a NaN
// weight marks a pair that crosses a row's end in rows run as one (run_rows_as_one), where
// the JAX kernels have no term; a real weight is never NaN (data_weight).
template <typename T, bool kHoles>
inline T plus_weight(T acc, T w) {
  if constexpr (kHoles) return w == w ? acc + w : acc;
  return acc + w;
}

template <typename T, bool kHoles>
inline T plus_product(T acc, T w, T x) {
  if constexpr (kHoles) return w == w ? acc + w * x : acc;
  return acc + w * x;
}

// o[j] += w_0[j] + ... + w_{N-1}[j] (the normaliser), terms in order as in the JAX kernels.
template <typename T, int N, bool kHoles = false>
void add_weights(T* __restrict__ o, const T* const* w, int64_t n) {
  const T* __restrict__ w0 = w[0];
  const T* __restrict__ w1 = N > 1 ? w[1] : nullptr;
  const T* __restrict__ w2 = N > 2 ? w[2] : nullptr;
  const T* __restrict__ w3 = N > 3 ? w[3] : nullptr;
  for (int64_t j = 0; j < n; ++j) {
    T acc = plus_weight<T, kHoles>(o[j], w0[j]);
    if constexpr (N > 1) acc = plus_weight<T, kHoles>(acc, w1[j]);
    if constexpr (N > 2) acc = plus_weight<T, kHoles>(acc, w2[j]);
    if constexpr (N > 3) acc = plus_weight<T, kHoles>(acc, w3[j]);
    o[j] = acc;
  }
}

// o[j] += w_0[j] x_0[j] + ... (four of a channel's many terms: strip_sums).
template <typename T, int N, bool kHoles = false>
void add_products(T* __restrict__ o, const T* const* w, const T* const* x, int64_t n) {
  const T* __restrict__ w0 = w[0];
  const T* __restrict__ w1 = N > 1 ? w[1] : nullptr;
  const T* __restrict__ w2 = N > 2 ? w[2] : nullptr;
  const T* __restrict__ w3 = N > 3 ? w[3] : nullptr;
  const T* __restrict__ x0 = x[0];
  const T* __restrict__ x1 = N > 1 ? x[1] : nullptr;
  const T* __restrict__ x2 = N > 2 ? x[2] : nullptr;
  const T* __restrict__ x3 = N > 3 ? x[3] : nullptr;
  for (int64_t j = 0; j < n; ++j) {
    T acc = plus_product<T, kHoles>(o[j], w0[j], x0[j]);
    if constexpr (N > 1) acc = plus_product<T, kHoles>(acc, w1[j], x1[j]);
    if constexpr (N > 2) acc = plus_product<T, kHoles>(acc, w2[j], x2[j]);
    if constexpr (N > 3) acc = plus_product<T, kHoles>(acc, w3[j], x3[j]);
    o[j] = acc;
  }
}

// add_weights / add_products for g (1-4) terms, g known only at run time.
template <typename T, bool kHoles = false>
void add_weight_terms(T* o, const T* const* w, size_t g, int64_t n) {
  switch (g) {
    case 1: return add_weights<T, 1, kHoles>(o, w, n);
    case 2: return add_weights<T, 2, kHoles>(o, w, n);
    case 3: return add_weights<T, 3, kHoles>(o, w, n);
    default: return add_weights<T, 4, kHoles>(o, w, n);
  }
}

template <typename T, bool kHoles = false>
void add_product_terms(T* o, const T* const* w, const T* const* x, size_t g, int64_t n) {
  switch (g) {
    case 1: return add_products<T, 1, kHoles>(o, w, x, n);
    case 2: return add_products<T, 2, kHoles>(o, w, x, n);
    case 3: return add_products<T, 3, kHoles>(o, w, x, n);
    default: return add_products<T, 4, kHoles>(o, w, x, n);
  }
}

// den[j] = h0 valid[j] (h0 where every point is valid): the centre's term of the normaliser.
template <typename T>
void start_normaliser(T* __restrict__ den, const T* __restrict__ valid, T h0, int64_t n) {
  if (valid) {
    for (int64_t j = 0; j < n; ++j) den[j] = h0 * valid[j];
  } else {
    for (int64_t j = 0; j < n; ++j) den[j] = h0;
  }
}

// o[j] = (h0 c[j] + w_0[j] x_0[j] + ...) / den, from the reciprocal inv[j]; 0 where no
// weight reaches (as the JAX kernels' where(den > 0, ..., 0): a masked point's sum may hold
// 0 * inf). Up to four terms, in one loop.
template <typename T, int N, bool kHoles = false>
void fused_channel(T* __restrict__ o, const T* __restrict__ c, T h0, const T* const* w,
                   const T* const* x, const T* __restrict__ inv, int64_t n) {
  const T* __restrict__ w0 = N > 0 ? w[0] : nullptr;
  const T* __restrict__ w1 = N > 1 ? w[1] : nullptr;
  const T* __restrict__ w2 = N > 2 ? w[2] : nullptr;
  const T* __restrict__ w3 = N > 3 ? w[3] : nullptr;
  const T* __restrict__ x0 = N > 0 ? x[0] : nullptr;
  const T* __restrict__ x1 = N > 1 ? x[1] : nullptr;
  const T* __restrict__ x2 = N > 2 ? x[2] : nullptr;
  const T* __restrict__ x3 = N > 3 ? x[3] : nullptr;
  for (int64_t j = 0; j < n; ++j) {
    T acc = h0 * c[j];
    if constexpr (N > 0) acc = plus_product<T, kHoles>(acc, w0[j], x0[j]);
    if constexpr (N > 1) acc = plus_product<T, kHoles>(acc, w1[j], x1[j]);
    if constexpr (N > 2) acc = plus_product<T, kHoles>(acc, w2[j], x2[j]);
    if constexpr (N > 3) acc = plus_product<T, kHoles>(acc, w3[j], x3[j]);
    o[j] = inv[j] > 0 ? acc * inv[j] : T(0);
  }
}

// den[j] <- 1 / den[j], and 0 where den[j] is 0 (a point no weight reaches: masked).
template <typename T>
void reciprocal(T* __restrict__ den, int64_t n) {
  for (int64_t j = 0; j < n; ++j) {
    const bool some = den[j] > 0;
    den[j] = some ? T(1) / (some ? den[j] : T(1)) : T(0);
  }
}

// A row's columns [0, width) cut where a term starts or ends (s.bounds), and for each cut the
// terms that cover it (s.active, in order; cut k's from s.first_active[k]): within a cut
// every term covers all of it or none, so its sums run in one loop.
template <typename T>
void cut_row(const Term<T>* terms, size_t nt, int64_t width, Scratch<T>& s) {
  // The cuts depend only on where the terms lie and the row's width: rows alike reuse them.
  std::vector<int64_t>& key = s.cut_key;
  const auto at = reinterpret_cast<std::uintptr_t>(terms);
  bool same = key.size() == 2 * nt + 2 && key[0] == static_cast<int64_t>(at) && key[1] == width;
  for (size_t t = 0; same && t < nt; ++t)
    same = key[2 + 2 * t] == terms[t].at && key[3 + 2 * t] == terms[t].n;
  if (same) return;
  key.assign({static_cast<int64_t>(at), width});
  for (size_t t = 0; t < nt; ++t) key.insert(key.end(), {terms[t].at, terms[t].n});
  std::vector<int64_t>& b = s.bounds;
  b.assign({0, width});
  for (size_t t = 0; t < nt; ++t) {
    b.push_back(terms[t].at);
    b.push_back(terms[t].at + terms[t].n);
  }
  std::sort(b.begin(), b.end());
  b.erase(std::unique(b.begin(), b.end()), b.end());
  s.active.clear();
  s.first_active.assign(1, 0);
  for (size_t k = 0; k + 1 < b.size(); ++k) {
    for (size_t t = 0; t < nt; ++t)
      if (terms[t].at <= b[k] && b[k + 1] <= terms[t].at + terms[t].n) s.active.push_back(terms + t);
    s.first_active.push_back(static_cast<int64_t>(s.active.size()));
  }
}

// The normaliser's terms over each cut of the row (cut_row): den[j] += sum of w.
template <typename T, bool kHoles>
void add_row_weights(T* den, const Scratch<T>& s) {
  const T* w[4];
  for (size_t k = 0; k + 1 < s.bounds.size(); ++k) {
    const int64_t j0 = s.bounds[k], n = s.bounds[k + 1] - j0;
    const auto first = static_cast<size_t>(s.first_active[k]);
    const auto last = static_cast<size_t>(s.first_active[k + 1]);
    for (size_t t = first; t < last; t += 4) {
      const size_t m = last - t < 4 ? last - t : 4;
      for (size_t u = 0; u < m; ++u) w[u] = s.active[t + u]->w + (j0 - s.active[t + u]->at);
      add_weight_terms<T, kHoles>(den + j0, w, m, n);
    }
  }
}

// One channel's output over the row (cut_row): y = (h0 centre + sum of w x) * inv, the terms'
// x read from xc + from; its up to four terms a cut in one loop with the quotient.
template <typename T, bool kHoles>
void channel_sums(const Scratch<T>& s, T h0, T* __restrict__ y, const T* __restrict__ centre,
                  const T* xc, const T* __restrict__ inv) {
  const T* w[4] = {};
  const T* x[4] = {};
  for (size_t k = 0; k + 1 < s.bounds.size(); ++k) {
    const int64_t j0 = s.bounds[k], n = s.bounds[k + 1] - j0;
    const auto first = static_cast<size_t>(s.first_active[k]);
    const auto last = static_cast<size_t>(s.first_active[k + 1]);
    auto load = [&](size_t t, size_t m) {
      for (size_t u = 0; u < m; ++u) {
        const Term<T>& term = *s.active[t + u];
        w[u] = term.w + (j0 - term.at);
        x[u] = xc + term.from + (j0 - term.at);
      }
    };
    T* o = y + j0;
    const T* c = centre + j0;
    const T* iv = inv + j0;
    switch (last - first) {
      case 0: fused_channel<T, 0, kHoles>(o, c, h0, w, x, iv, n); continue;
      case 1: load(first, 1); fused_channel<T, 1, kHoles>(o, c, h0, w, x, iv, n); continue;
      case 2: load(first, 2); fused_channel<T, 2, kHoles>(o, c, h0, w, x, iv, n); continue;
      case 3: load(first, 3); fused_channel<T, 3, kHoles>(o, c, h0, w, x, iv, n); continue;
      case 4: load(first, 4); fused_channel<T, 4, kHoles>(o, c, h0, w, x, iv, n); continue;
      default: std::abort();  // at most two pairs, +o and -o each: run_sums
    }
  }
}

// The normaliser and every channel's sums over one run of `width` points from flat index p
// (a row's, or whole rows' run as one), the terms already cut (cut_row): a pass of at most two
// pairs (separable, or a 1-D grid's full one), so at most four terms a cut, each channel's sums
// and quotient in one loop. Full passes of more pairs: strip_sums.
template <typename T, bool kHoles>
void run_sums(const PassArgs<T>& a, int64_t p, int64_t width, T h0, Scratch<T>& s) {
  T* den = s.den.data();
  start_normaliser(den, a.valid ? a.valid + p : nullptr, h0, width);
  add_row_weights<T, kHoles>(den, s);
  reciprocal(den, width);  // one divide per point, not per channel
  for (int64_t c = 0; c < a.channels; ++c) {
    const T* xc = a.x[c] + a.x_at;
    channel_sums<T, kHoles>(s, h0, a.y[c] + a.y_at + p, xc + p, xc, den);
  }
}

// run_sums over strips of kStrip points, for runs of many terms (full passes): each group of
// four terms' weights is read from memory once, by the normaliser and then every channel,
// while the strip's sums stay in L1. The same sums in the same order as run_sums.
template <typename T, bool kHoles>
void strip_sums(const PassArgs<T>& a, int64_t p, int64_t width, T h0, Scratch<T>& s) {
  constexpr int64_t kStrip = 512;
  const int64_t C = a.channels;
  s.den.resize(static_cast<size_t>(std::min(width, kStrip)));
  T* __restrict__ den = s.den.data();
  const std::vector<int64_t>& b = s.bounds;
  const T* w[4];
  const T* x[4];
  size_t first_cut = 0;
  for (int64_t j0 = 0; j0 < width; j0 += kStrip) {
    const int64_t n = std::min(width - j0, kStrip);
    start_normaliser(den, a.valid ? a.valid + p + j0 : nullptr, h0, n);
    for (int64_t c = 0; c < C; ++c) {  // each channel's sums in its output's strip
      const T* __restrict__ xc = a.x[c] + a.x_at + p + j0;
      T* __restrict__ y = a.y[c] + a.y_at + p + j0;
      for (int64_t j = 0; j < n; ++j) y[j] = h0 * xc[j];
    }
    while (b[first_cut + 1] <= j0) ++first_cut;
    for (size_t k = first_cut; k + 1 < b.size() && b[k] < j0 + n; ++k) {
      const int64_t lo = std::max(b[k], j0), m = std::min(b[k + 1], j0 + n) - lo;
      const auto last = static_cast<size_t>(s.first_active[k + 1]);
      for (auto t = static_cast<size_t>(s.first_active[k]); t < last; t += 4) {
        const size_t g = last - t < 4 ? last - t : 4;
        for (size_t u = 0; u < g; ++u) w[u] = s.active[t + u]->w + (lo - s.active[t + u]->at);
        add_weight_terms<T, kHoles>(den + (lo - j0), w, g, m);
        for (int64_t c = 0; c < C; ++c) {
          const T* xc = a.x[c] + a.x_at;
          for (size_t u = 0; u < g; ++u)
            x[u] = xc + s.active[t + u]->from + (lo - s.active[t + u]->at);
          add_product_terms<T, kHoles>(a.y[c] + a.y_at + p + lo, w, x, g, m);
        }
      }
    }
    reciprocal(den, n);
    for (int64_t c = 0; c < C; ++c) {
      T* __restrict__ y = a.y[c] + a.y_at + p + j0;
      for (int64_t j = 0; j < n; ++j) y[j] = den[j] > 0 ? y[j] * den[j] : T(0);
    }
  }
}

// Whole rows [r0, r1) of a pass whose pairs all move along the row, as one run of points:
// each pair's weights in one call, a hole (NaN) where a pair crosses from one row into the
// next, and the sums in a few long loops instead of a few short ones per row (rows of a 3-D
// slab's last axis are short).
template <typename T>
void run_rows_as_one(const PassArgs<T>& a, int64_t r0, int64_t r1, Scratch<T>& s) {
  const Pass& pass = *a.pass;
  const int64_t L = pass.row_length, width = (r1 - r0) * L, p = r0 * L;
  s.weights.resize(static_cast<size_t>(width) * pass.pairs.size());
  s.dist.resize(static_cast<size_t>(width));
  s.den.resize(static_cast<size_t>(width));
  s.terms.resize(2 * pass.pairs.size());
  size_t nt = 0;
  for (size_t k = 0; k < pass.pairs.size(); ++k) {
    const Pair& pair = pass.pairs[k];
    const int64_t ol = pair.column_offset;
    if (ol >= L) continue;  // no point of a row has its partner on it
    T* w = s.weights.data() + static_cast<int64_t>(k) * width;
    pair_weights(a, p, p + ol, width - ol, static_cast<T>(pair.tap), w, s.dist.data());
    for (int64_t r = 0; r + 1 < r1 - r0; ++r)
      std::fill_n(w + r * L + (L - ol), ol, std::numeric_limits<T>::quiet_NaN());
    // Per pair, +o then -o, as the JAX kernels: w(q, q + o) x[q + o] and w(q - o, q) x[q - o].
    s.terms[nt++] = {w, p + ol, 0, width - ol};
    s.terms[nt++] = {w, p, ol, width - ol};
  }
  cut_row(s.terms.data(), nt, width, s);
  run_sums<T, true>(a, p, width, static_cast<T>(pass.centre), s);
}

// Columns [c0, c1) of row r of a pass whose pairs all move along the row (a 1-D grid's, cut
// in blocks: atrous.cc, cut_blocks): each pair's weights for the block's points and the `o`
// points before it whose partner lies in it, then the sums.
template <typename T>
void run_columns(const PassArgs<T>& a, int64_t r, int64_t c0, int64_t c1, Scratch<T>& s) {
  const Pass& pass = *a.pass;
  const int64_t L = pass.row_length, width = c1 - c0, row = r * L;
  const size_t np = pass.pairs.size();
  s.offsets.assign(np + 1, 0);
  for (size_t k = 0; k < np; ++k) {  // pair k's weights w(p, p + o), p in [lo, hi)
    const int64_t ol = pass.pairs[k].column_offset;
    const int64_t lo = std::max<int64_t>(0, c0 - ol), hi = std::min(c1, L - ol);
    s.offsets[k + 1] = s.offsets[k] + std::max<int64_t>(0, hi - lo);
  }
  s.weights.resize(static_cast<size_t>(s.offsets[np]));
  s.dist.resize(static_cast<size_t>(s.offsets[np]));
  s.den.resize(static_cast<size_t>(width));
  s.terms.resize(2 * np);
  size_t nt = 0;
  for (size_t k = 0; k < np; ++k) {
    const Pair& pair = pass.pairs[k];
    const int64_t ol = pair.column_offset;
    const int64_t lo = std::max<int64_t>(0, c0 - ol), hi = std::min(c1, L - ol);
    if (hi <= lo) continue;
    T* w = s.weights.data() + s.offsets[k];
    pair_weights(a, row + lo, row + lo + ol, hi - lo, static_cast<T>(pair.tap), w, s.dist.data());
    // Per pair, +o then -o, as the JAX kernels: w(q, q + o) x[q + o] for q in [c0, hi),
    // w(q - o, q) x[q - o] for q in [max(c0, o), c1).
    if (hi > c0) s.terms[nt++] = {w + (c0 - lo), row + c0 + ol, 0, hi - c0};
    const int64_t q0 = std::max(c0, ol);
    if (c1 > q0) s.terms[nt++] = {w + (q0 - ol - lo), row + q0 - ol, q0 - c0, c1 - q0};
  }
  cut_row(s.terms.data(), nt, width, s);
  run_sums<T, false>(a, row + c0, width, static_cast<T>(pass.centre), s);
}

// Rows [r0, r1) and columns [c0, c1) of a pass whose pairs all move along the row (separable
// passes, a 1-D grid's full ones; a full pass of a grid of rank >= 2 runs slab by slab:
// run_slab_chunk): y = normalised sums of x's neighbours. Whole rows as one run, a block of
// columns row by row.
template <typename T>
void run_block(const PassArgs<T>& a, int64_t r0, int64_t r1, int64_t c0, int64_t c1,
               Scratch<T>& s) {
  if (c0 == 0 && c1 == a.pass->row_length && r1 - r0 > 1) return run_rows_as_one(a, r0, r1, s);
  for (int64_t r = r0; r < r1; ++r) run_columns(a, r, c0, c1, s);
}

// Positions [first, last) of one chain of slabs of a full pass (SlabPass; the chain and its
// positions as a separable level's, Chunk), out of place: each pair's weights for a slab as it
// comes (each weight once, kept for the slabs after it that read it), then the slab's sums as
// one run of points (strip_sums), a NaN hole where a pair's partner wraps to another row.
template <typename T>
void run_slab_chunk(const PassArgs<T>& a, const SlabPass& pass, const Chunk<T>& ch,
                    Scratch<T>& s) {
  const int64_t M = pass.slab, st = pass.stride, len = ch.length;
  const size_t np = pass.pairs.size();
  bool holes = false;
  // Pair k's weights at position p: slot p % (slabs + 1) of its slots, from s.offsets[k].
  s.offsets.assign(np + 1, 0);
  for (size_t k = 0; k < np; ++k) {
    s.offsets[k + 1] = s.offsets[k] + (pass.pairs[k].slabs + 1) * M;
    holes = holes || !pass.pairs[k].holes.empty();
  }
  s.ring.resize(static_cast<size_t>(s.offsets[np]));
  s.dist.resize(static_cast<size_t>(M));
  s.terms.resize(2 * np);
  const auto slab = [&](int64_t pos) { return (ch.residue + pos * st) * M; };
  const auto weights = [&](size_t k, int64_t p) {
    return s.ring.data() + s.offsets[k] + (p % (pass.pairs[k].slabs + 1)) * M;
  };
  const auto compute = [&](size_t k, int64_t p) {  // if both slabs exist
    const SlabPair& q = pass.pairs[k];
    if (p < 0 || p + q.slabs >= len || q.hi <= q.lo) return;
    T* w = weights(k, p);
    pair_weights(a, slab(p) + q.lo, slab(p + q.slabs) + q.lo + q.flat, q.hi - q.lo,
                 static_cast<T>(q.tap), w + q.lo, s.dist.data());
    for (const auto& [first, n] : q.holes)
      std::fill_n(w + first, n, std::numeric_limits<T>::quiet_NaN());
  };
  for (size_t k = 0; k < np; ++k)  // the weights the first slab's -o terms read
    for (int64_t p = ch.first - pass.pairs[k].slabs; p < ch.first; ++p) compute(k, p);
  for (int64_t pos = ch.first; pos < ch.last; ++pos) {
    size_t nt = 0;
    for (size_t k = 0; k < np; ++k) {
      const SlabPair& q = pass.pairs[k];
      compute(k, pos);
      if (q.hi <= q.lo) continue;
      // Per pair, +o then -o, as the JAX kernels: w(p, p + o) x[p + o], w(p - o, p) x[p - o].
      if (pos + q.slabs < len)
        s.terms[nt++] = {weights(k, pos) + q.lo, slab(pos + q.slabs) + q.lo + q.flat, q.lo,
                         q.hi - q.lo};
      if (pos - q.slabs >= 0)
        s.terms[nt++] = {weights(k, pos - q.slabs) + q.lo, slab(pos - q.slabs) + q.lo,
                         q.lo + q.flat, q.hi - q.lo};
    }
    cut_row(s.terms.data(), nt, M, s);
    if (holes) {
      strip_sums<T, true>(a, slab(pos), M, static_cast<T>(pass.centre), s);
    } else {
      strip_sums<T, false>(a, slab(pos), M, static_cast<T>(pass.centre), s);
    }
  }
}

// out[j * kC + q] = src[q][j]: planes into one field, each point's channels together (kC a
// constant, so that the stores vectorise; one plane at a time they were scalar).
template <typename T, int kC>
void interleave_channels(const T* const* src, T* __restrict__ out, int64_t n) {
  const T* __restrict__ s[kC];
  for (int q = 0; q < kC; ++q) s[q] = src[q];
  for (int64_t j = 0; j < n; ++j)
    for (int q = 0; q < kC; ++q) out[j * kC + q] = s[q][j];
}

// dst[q][p] = src[p * kC + q]: a field's channels into planes, each point's channels
// together (kC a constant, so that the loads vectorise).
template <typename T, int kC>
void split_channels(const T* __restrict__ src, T* const* dst, int64_t n) {
  T* __restrict__ d[kC];
  for (int q = 0; q < kC; ++q) d[q] = dst[q];
  for (int64_t p = 0; p < n; ++p)
    for (int q = 0; q < kC; ++q) d[q][p] = src[p * kC + q];
}

// n points of a field of nc interleaved channels into nc planes.
template <typename T>
void split_planes(const T* src, T* const* dst, int64_t nc, int64_t n) {
  switch (nc) {
    case 1: std::memcpy(dst[0], src, sizeof(T) * n); return;
    case 2: return split_channels<T, 2>(src, dst, n);
    case 3: return split_channels<T, 3>(src, dst, n);
    case 4: return split_channels<T, 4>(src, dst, n);
    default:
      for (int64_t q = 0; q < nc; ++q)
        for (int64_t p = 0; p < n; ++p) dst[q][p] = src[p * nc + q];
  }
}

// One chunk of a separable level (SlabLevel, Chunk): each slab's axis-0 pass into a scratch
// slab, its inner passes, and the result into `to`'s slab (or the interleaved fields). With
// `in_place` (from and to the same memory) a slab's original is kept aside before its result
// overwrites it, for the two slabs after it.
template <typename T>
void run_chunk(const PassArgs<T>& a, const SlabLevel<T>& level, const SlabPlanes<const T>& from,
               const SlabPlanes<T>& to, bool in_place, const Chunk<T>& ch, Scratch<T>& s) {
  constexpr double kTaps[3] = {3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0};
  const int64_t M = level.slab, C = a.channels, st = level.stride, len = ch.length;
  const bool axis0 = st < level.slabs;
  const T h0 = static_cast<T>(kTaps[0]);
  const int64_t step = axis0 ? st : 1;  // without an axis-0 pass every slab stands alone
  const auto slab = [&](int64_t pos) { return ch.residue + pos * step; };
  s.slabs.resize(static_cast<size_t>(2 * C * M));
  if (axis0) s.ring.resize(static_cast<size_t>(5 * M));
  if (axis0 && in_place) s.saved.resize(static_cast<size_t>(2 * C * M));
  s.dist.resize(static_cast<size_t>(M));
  s.den.resize(static_cast<size_t>(M));
  // w(p, p + d) in chain positions: d = 1 in two slots, d = 2 in three.
  const auto weights_of = [&](int d, int64_t p) {
    return s.ring.data() + (d == 1 ? p % 2 : 2 + p % 3) * M;
  };
  const auto compute = [&](int d, int64_t p) {  // if both slabs exist
    if (p < 0 || p + d >= len) return;
    pair_weights(a, slab(p) * M, slab(p + d) * M, M, static_cast<T>(kTaps[d]), weights_of(d, p),
                 s.dist.data());
  };
  // Channel c of the original of position p, read by the slab at position `pos`.
  const auto original = [&](int64_t p, int64_t pos, int64_t c) -> const T* {
    if (!in_place || (p > pos && p < ch.last)) return from.at(slab(p), static_cast<size_t>(c));
    if (p > pos) return ch.after + ((p - ch.last) * C + c) * M;
    if (p >= ch.first) return s.saved.data() + ((p % 2) * C + c) * M;
    return ch.before + ((p - ch.first + 2) * C + c) * M;
  };
  if (axis0) {
    for (int d = 1; d <= 2; ++d)
      for (int64_t p = ch.first - d; p < ch.first; ++p) compute(d, p);
  }
  s.cur.resize(static_cast<size_t>(C));
  s.other.resize(static_cast<size_t>(C));
  s.from.resize(static_cast<size_t>(C));
  s.to.resize(static_cast<size_t>(C));
  const int64_t group = level.group_rows, G = a.guide_channels;
  if (group > 1) {  // a group's rows: channel c's at cur[c] (fields) and other[c] (results)
    s.group_x.resize(static_cast<size_t>(C * group * M));
    s.group_y.resize(static_cast<size_t>(C * group * M));
    s.group_guide.resize(static_cast<size_t>(G * group * M));
    s.group_valid.resize(static_cast<size_t>(a.valid ? group * M : 0));
    s.group_slabs.clear();
  }
  for (int64_t c = 0; c < C; ++c) {
    s.cur[c] = group > 1 ? s.group_x.data() + c * group * M : s.slabs.data() + c * M;
    s.other[c] = group > 1 ? s.group_y.data() + c * group * M : s.slabs.data() + (C + c) * M;
  }
  // Slab i's result, its channels at in[c], into `to`'s slab or the interleaved fields.
  const auto write = [&](int64_t i, const T* const* in) {
    if (a.interleaved) {
      int64_t c = 0;
      for (const auto& [field, nc] : *a.interleaved) {
        T* out = field + i * M * nc;
        switch (nc) {
          case 1: std::memcpy(out, in[c], sizeof(T) * M); break;
          case 2: interleave_channels<T, 2>(in + c, out, M); break;
          case 3: interleave_channels<T, 3>(in + c, out, M); break;
          case 4: interleave_channels<T, 4>(in + c, out, M); break;
          default:
            for (int64_t q = 0; q < nc; ++q)
              for (int64_t j = 0; j < M; ++j) out[j * nc + q] = in[c + q][j];
        }
        c += nc;
      }
      return;
    }
    for (int64_t c = 0; c < C; ++c) {
      T* y = to.at(i, static_cast<size_t>(c));
      if (y != in[c]) std::memcpy(y, in[c], sizeof(T) * M);
    }
  };
  // The group's pass along its rows as one run, then each row's result to its slab. Writing
  // late is safe in place: a slab's original is read only by the slabs after it, from `saved`.
  std::vector<const T*> row(static_cast<size_t>(C));
  const auto run_group = [&] {
    const auto rows = static_cast<int64_t>(s.group_slabs.size());
    Pass pass = level.inner[0];
    pass.row_shape = {rows};
    PassArgs<T> b = a;
    b.x = s.cur.data();
    b.x_at = 0;
    b.y = s.other.data();
    b.y_at = 0;
    b.guide = s.group_guide.data();
    b.guide_stride = group * M;
    b.valid = a.valid ? s.group_valid.data() : nullptr;
    b.pass = &pass;
    run_block(b, 0, rows, 0, M, s);
    for (int64_t q = 0; q < rows; ++q) {
      for (int64_t c = 0; c < C; ++c) row[c] = s.other[c] + q * M;
      write(s.group_slabs[q], row.data());
    }
    s.group_slabs.clear();
  };
  for (int64_t pos = ch.first; pos < ch.last; ++pos) {
    const int64_t i = slab(pos);
    for (int64_t c = 0; c < C; ++c) {
      s.from[c] = from.at(i, static_cast<size_t>(c));
      s.to[c] = to.at(i, static_cast<size_t>(c));
    }
    const T* const* in = s.from.data();
    const auto slot = static_cast<int64_t>(s.group_slabs.size());  // the row in the group
    if (axis0) {
      compute(1, pos);
      compute(2, pos);
      // The terms in the pure-JAX kernels' order: per offset, +o then -o.
      const T* w[4];
      int64_t partner[4];
      int nt = 0;
      for (int d = 1; d <= 2; ++d) {
        if (pos + d < len) w[nt] = weights_of(d, pos), partner[nt++] = pos + d;
        if (pos - d >= 0) w[nt] = weights_of(d, pos - d), partner[nt++] = pos - d;
      }
      T* den = s.den.data();
      start_normaliser(den, a.valid ? a.valid + i * M : nullptr, h0, M);
      if (nt > 0) add_weight_terms<T>(den, w, static_cast<size_t>(nt), M);
      reciprocal(den, M);
      for (int64_t c = 0; c < C; ++c) {
        const T* x[4];
        for (int k = 0; k < nt; ++k) x[k] = original(partner[k], pos, c);
        T* y = s.cur[c] + (group > 1 ? slot * M : 0);
        switch (nt) {
          case 0: fused_channel<T, 0>(y, s.from[c], h0, w, x, den, M); break;
          case 1: fused_channel<T, 1>(y, s.from[c], h0, w, x, den, M); break;
          case 2: fused_channel<T, 2>(y, s.from[c], h0, w, x, den, M); break;
          case 3: fused_channel<T, 3>(y, s.from[c], h0, w, x, den, M); break;
          default: fused_channel<T, 4>(y, s.from[c], h0, w, x, den, M); break;
        }
      }
      if (in_place && pos + 1 < ch.last) {  // its original, for the next two positions
        for (int64_t c = 0; c < C; ++c)
          std::memcpy(s.saved.data() + ((pos % 2) * C + c) * M, s.from[c], sizeof(T) * M);
      }
      in = s.cur.data();
    }
    if (group > 1) {  // the slab's fields, guide and mask as the group's next row
      for (int64_t c = 0; c < C && !axis0; ++c)
        std::memcpy(s.cur[c] + slot * M, s.from[c], sizeof(T) * M);
      for (int64_t c = 0; c < G; ++c)
        std::memcpy(s.group_guide.data() + (c * group + slot) * M,
                    a.guide + c * a.guide_stride + i * M, sizeof(T) * M);
      if (a.valid)
        std::memcpy(s.group_valid.data() + slot * M, a.valid + i * M, sizeof(T) * M);
      s.group_slabs.push_back(i);
      if (slot + 1 == group || pos + 1 == ch.last) run_group();
      continue;
    }
    for (size_t k = 0; k < level.inner.size(); ++k) {
      // The last pass writes the output slab itself, unless it reads it (no axis-0 pass and
      // one inner pass, in place) or the output is interleaved.
      const bool direct = k + 1 == level.inner.size() && !a.interleaved && in != s.from.data();
      T* const* next = direct ? s.to.data() : in == s.cur.data() ? s.other.data() : s.cur.data();
      PassArgs<T> b = a;
      b.x = in;
      b.x_at = 0;
      b.y = next;
      b.y_at = 0;
      b.guide = a.guide + i * M;
      b.valid = a.valid ? a.valid + i * M : nullptr;
      b.pass = &level.inner[k];
      run_block(b, 0, level.inner[k].rows(), 0, level.inner[k].row_length, s);
      in = next;
    }
    if (in != s.to.data()) write(i, in);  // the slab's result into the fields
  }
}

}  // namespace OB_ISA
}  // namespace optax_bilateral
#endif  // OB_ISA
