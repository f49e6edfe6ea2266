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

// y[0..w) -= sum_t l[t] x_t[0..w), x_t = x + t * w: one row below a supernode (forward).
template <typename T, int W>
inline void subtract_combination(T* __restrict y, const T* l, const T* __restrict x, int64_t s,
                                 int64_t w) {
  const int64_t width = W > 0 ? W : w;
  int64_t c0 = 0;
  for (; c0 + kChunk <= width; c0 += kChunk) {
    T acc[kChunk];
    for (int64_t c = 0; c < kChunk; ++c) acc[c] = y[c0 + c];
    for (int64_t t = 0; t < s; ++t) {
      const T lt = l[t];
      const T* xt = x + t * width + c0;
      for (int64_t c = 0; c < kChunk; ++c) acc[c] -= lt * xt[c];
    }
    for (int64_t c = 0; c < kChunk; ++c) y[c0 + c] = acc[c];
  }
  for (int64_t t = 0; t < s; ++t) {
    const T lt = l[t];
    const T* xt = x + t * width;
    for (int64_t c = c0; c < width; ++c) y[c] -= lt * xt[c];
  }
}

// The sweeps over z (n, W): W a constant for the narrow blocks (padded to 4), or 0 for any w.
template <typename T, int W>
void ldl_sweeps(const LdlFactor<T>& f, T* __restrict z, int64_t w) {
  const int64_t width = W > 0 ? W : w;
  // (I + L) y = z, supernode by supernode: its triangle, then the rows below it.
  for (int64_t k = 0; k < f.supernodes; ++k) {
    const int64_t j0 = f.first[k], s = f.first[k + 1] - j0;
    const int32_t* below = f.rows + f.row_ptr[k];
    const int64_t r = f.row_ptr[k + 1] - f.row_ptr[k];
    const T* block = f.values + f.block_ptr[k];
    T* zs = z + j0 * width;
    for (int64_t u = 1; u < s; ++u)
      subtract_combination<T, W>(zs + u * width, block + u * s, zs, u, width);
    for (int64_t i = 0; i < r; ++i)
      subtract_combination<T, W>(z + static_cast<int64_t>(below[i]) * width,
                                 block + (s + i) * s, zs, s, width);
  }
  // D^-1, then (I + L)^T x = y, last supernode first: the rows below (final already), then
  // the triangle from its last column back.
  for (int64_t k = f.supernodes - 1; k >= 0; --k) {
    const int64_t j0 = f.first[k], s = f.first[k + 1] - j0;
    const int32_t* below = f.rows + f.row_ptr[k];
    const int64_t r = f.row_ptr[k + 1] - f.row_ptr[k];
    const T* block = f.values + f.block_ptr[k];
    T* __restrict zs = z + j0 * width;
    for (int64_t t = 0; t < s; ++t) {
      const T d = f.dinv[j0 + t];
      for (int64_t c = 0; c < width; ++c) zs[t * width + c] *= d;
    }
    for (int64_t i = 0; i < r; ++i) {
      const T* __restrict zr = z + static_cast<int64_t>(below[i]) * width;
      const T* li = block + (s + i) * s;
      for (int64_t t = 0; t < s; ++t) {
        const T lt = li[t];
        T* zt = zs + t * width;
        for (int64_t c = 0; c < width; ++c) zt[c] -= lt * zr[c];
      }
    }
    for (int64_t u = s - 1; u >= 1; --u) {
      const T* __restrict zu = zs + u * width;
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
