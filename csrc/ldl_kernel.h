// The LDL^T solve's sweeps over one block of columns (ldl.h): the loops every instruction-set
// build compiles (kernel_*.cc include this file under their own target), written over a
// contiguous row of the block, which the compiler vectorises.
#pragma once

#include <cstdint>

#include "ldl.h"

#if defined(OB_ISA)
namespace optax_bilateral {
namespace OB_ISA {

// The columns of a row handled at once: a few vectors, held in registers across a supernode.
constexpr int64_t kChunk = 32;
// Rows (forward) or columns (backward) of a supernode's block taken together, so that each row
// read from z serves this many of them.
constexpr int64_t kGroup = 4;

// Forward, the rows below a supernode: y_i[c0 .. c0+C) -= sum_t l_i[t] x_t[c0 .. c0+C) for
// rows i0 .. i0+G, with y_i = z + below[i] * width, l_i = block + (s + i) * s, x_t = zs + t *
// width. C and G constants: the G x C sums stay in registers while x_t streams from cache.
template <typename T, int64_t C, int64_t G>
inline void forward_rows(T* __restrict z, const int32_t* below, const T* block, const T* zs,
                         int64_t s, int64_t width, int64_t i0, int64_t c0) {
  T acc[G][C];
  T* y[G];
  const T* l[G];
  for (int64_t g = 0; g < G; ++g) {
    y[g] = z + static_cast<int64_t>(below[i0 + g]) * width + c0;
    l[g] = block + (s + i0 + g) * s;
    for (int64_t c = 0; c < C; ++c) acc[g][c] = y[g][c];
  }
  for (int64_t t = 0; t < s; ++t) {
    const T* x = zs + t * width + c0;
    for (int64_t g = 0; g < G; ++g) {
      const T lt = l[g][t];
      for (int64_t c = 0; c < C; ++c) acc[g][c] -= lt * x[c];
    }
  }
  for (int64_t g = 0; g < G; ++g)
    for (int64_t c = 0; c < C; ++c) y[g][c] = acc[g][c];
}

// Backward, the rows below a supernode into its columns t0 .. t0+G: x_t[c0 .. c0+C) -=
// sum_i l_i[t] y_i[c0 .. c0+C).
template <typename T, int64_t C, int64_t G>
inline void backward_rows(const T* __restrict z, const int32_t* below, const T* block, T* zs,
                          int64_t s, int64_t r, int64_t width, int64_t t0, int64_t c0) {
  T acc[G][C];
  for (int64_t g = 0; g < G; ++g)
    for (int64_t c = 0; c < C; ++c) acc[g][c] = zs[(t0 + g) * width + c0 + c];
  for (int64_t i = 0; i < r; ++i) {
    const T* y = z + static_cast<int64_t>(below[i]) * width + c0;
    const T* l = block + (s + i) * s + t0;
    for (int64_t g = 0; g < G; ++g) {
      const T lt = l[g];
      for (int64_t c = 0; c < C; ++c) acc[g][c] -= lt * y[c];
    }
  }
  for (int64_t g = 0; g < G; ++g)
    for (int64_t c = 0; c < C; ++c) zs[(t0 + g) * width + c0 + c] = acc[g][c];
}

// Both over every row group, for columns c0 .. width in chunks of C, then of C / 2, ... 1 for
// what remains (so any width is done in registers but for its last few columns).
template <typename T, int64_t C>
void rows_below(T* z, const int32_t* below, const T* block, T* zs, int64_t s, int64_t r,
                int64_t width, bool forward, int64_t c0 = 0) {
  for (; c0 + C <= width; c0 += C) {
    if (forward) {
      int64_t i = 0;
      for (; i + kGroup <= r; i += kGroup)
        forward_rows<T, C, kGroup>(z, below, block, zs, s, width, i, c0);
      for (; i < r; ++i) forward_rows<T, C, 1>(z, below, block, zs, s, width, i, c0);
    } else {
      int64_t t = 0;
      for (; t + kGroup <= s; t += kGroup)
        backward_rows<T, C, kGroup>(z, below, block, zs, s, r, width, t, c0);
      for (; t < s; ++t) backward_rows<T, C, 1>(z, below, block, zs, s, r, width, t, c0);
    }
  }
  if constexpr (C > 1) {
    if (c0 < width) rows_below<T, C / 2>(z, below, block, zs, s, r, width, forward, c0);
  }
}

// The sweeps over z (n, W): W a constant for the narrow blocks (padded to 4), or 0 for any w.
template <typename T, int W>
void ldl_sweeps(const LdlFactor<T>& f, T* __restrict z, int64_t w) {
  constexpr int64_t kC = W > 0 ? W : kChunk;
  const int64_t width = W > 0 ? W : w;
  // (I + L) y = z, supernode by supernode: its triangle, then the rows below it.
  for (int64_t k = 0; k < f.supernodes; ++k) {
    const int64_t j0 = f.first[k], s = f.first[k + 1] - j0;
    const int32_t* below = f.rows + f.row_ptr[k];
    const int64_t r = f.row_ptr[k + 1] - f.row_ptr[k];
    const T* block = f.values + f.block_ptr[k];
    T* zs = z + j0 * width;
    for (int64_t u = 1; u < s; ++u) {
      T* zu = zs + u * width;
      const T* lu = block + u * s;
      for (int64_t t = 0; t < u; ++t) {
        const T lt = lu[t];
        const T* zt = zs + t * width;
        for (int64_t c = 0; c < width; ++c) zu[c] -= lt * zt[c];
      }
    }
    rows_below<T, kC>(z, below, block, zs, s, r, width, true);
  }
  // D^-1, then (I + L)^T x = y, last supernode first: the rows below (final already), then
  // the triangle from its last column back.
  for (int64_t k = f.supernodes - 1; k >= 0; --k) {
    const int64_t j0 = f.first[k], s = f.first[k + 1] - j0;
    const int32_t* below = f.rows + f.row_ptr[k];
    const int64_t r = f.row_ptr[k + 1] - f.row_ptr[k];
    const T* block = f.values + f.block_ptr[k];
    T* zs = z + j0 * width;
    for (int64_t t = 0; t < s; ++t) {
      const T d = f.dinv[j0 + t];
      for (int64_t c = 0; c < width; ++c) zs[t * width + c] *= d;
    }
    rows_below<T, kC>(z, below, block, zs, s, r, width, false);
    for (int64_t u = s - 1; u >= 1; --u) {
      const T* zu = zs + u * width;
      const T* lu = block + u * s;
      for (int64_t t = 0; t < u; ++t) {
        const T lt = lu[t];
        T* zt = zs + t * width;
        for (int64_t c = 0; c < width; ++c) zt[c] -= lt * zu[c];
      }
    }
  }
}

// Columns c0 .. c1-1 of b (n, k): gathered permuted into z (n, stride), swept, scattered back.
// Narrow blocks are padded to a width of 4 (one vector of the row per entry of L); z must hold
// n * max(4, c1 - c0) values.
template <typename T>
void ldl_block(const LdlFactor<T>& f, T* b, int64_t k, int64_t c0, int64_t c1, T* z) {
  const int64_t n = f.n, w = c1 - c0, stride = w < 4 ? 4 : w;
  for (int64_t i = 0; i < n; ++i) {
    const T* from = b + static_cast<int64_t>(f.perm[i]) * k + c0;
    T* to = z + i * stride;
    for (int64_t c = 0; c < w; ++c) to[c] = from[c];
    for (int64_t c = w; c < stride; ++c) to[c] = T(0);
  }
  if (stride == 4)
    ldl_sweeps<T, 4>(f, z, stride);
  else
    ldl_sweeps<T, 0>(f, z, stride);
  for (int64_t i = 0; i < n; ++i) {
    const T* from = z + i * stride;
    T* to = b + static_cast<int64_t>(f.perm[i]) * k + c0;
    for (int64_t c = 0; c < w; ++c) to[c] = from[c];
  }
}

}  // namespace OB_ISA
}  // namespace optax_bilateral
#endif
