// The LDL^T solve's sweeps over one block of columns (ldl.h): the loops every instruction-set
// build compiles (kernel_*.cc include this file under their own target), written over a
// contiguous row of the block, which the compiler vectorises.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>

#include "ldl.h"

#if defined(OB_ISA)
namespace optax_bilateral {
namespace OB_ISA {

// The columns of a row handled at once, held in registers across a supernode: 32, or four
// vectors where they are wider (AVX-512's 32 registers hold four rows' sums of four vectors).
template <typename T>
constexpr int64_t kChunk =
    std::max<int64_t>(32, static_cast<int64_t>(4 * OB_ISA_VECTOR_BYTES / sizeof(T)));
// Rows (forward) or columns (backward) of a supernode's block taken together, so that each row
// read from z serves this many of them.
constexpr int64_t kGroup = 4;
// A single column's backward sums split into this many running sums: one sum is a chain of
// dependent multiply-adds, and most supernodes of a mesh's factor have one column.
constexpr int64_t kWays = 4;

// One supernode's block (ldl.h) and the rows of z it reads and writes: block row rho < s is
// the supernode's own row j0 + rho, a later one rows[rho - s], in z below `top` and in `ztop`
// from it (a part's own rows for the top's).
template <typename T>
struct Supernode {
  T* zs;               // z's rows j0 .. j0+s
  T* z;                // all of z
  T* ztop;             // row top of z, or of a part's rows for the top's
  const int32_t* below;
  const T* block;
  int64_t s, r, width, top;

  T* row(int64_t rho) const {
    if (rho < s) return zs + rho * width;
    const int64_t j = below[rho - s];
    return j < top ? z + j * width : ztop + (j - top) * width;
  }
  const T* l(int64_t rho) const { return block + rho * s; }
};

// Four columns of a row as one vector: a narrow block's row (padded to 4). Written out, since
// the compiler, left to vectorise G rows of 4 columns, packs them into one wide register with
// shuffles between every multiply-add.
template <typename T>
struct Quad {
  typedef T V __attribute__((vector_size(4 * sizeof(T))));
  // By reference, not by value: a 32-byte vector passed by value changes the ABI without AVX.
  static void load(V& v, const T* p) { std::memcpy(&v, p, sizeof(V)); }
  static void store(T* p, const V& v) { std::memcpy(p, &v, sizeof(V)); }
};

// forward_rows on a narrow block's row of four columns.
template <typename T, int64_t G>
inline void forward_quad(const Supernode<T>& n, int64_t rho0, int64_t t0, int64_t t1, int64_t c0) {
  using Q = Quad<T>;
  typename Q::V acc[G];
  T* y[G];
  const T* l[G];
  for (int64_t g = 0; g < G; ++g) {
    y[g] = n.row(rho0 + g) + c0;
    l[g] = n.l(rho0 + g);
    Q::load(acc[g], y[g]);
  }
  for (int64_t t = t0; t < t1; ++t) {
    typename Q::V x;
    Q::load(x, n.zs + t * n.width + c0);
    for (int64_t g = 0; g < G; ++g) acc[g] -= l[g][t] * x;
  }
  for (int64_t g = 0; g < G; ++g) Q::store(y[g], acc[g]);
}

// Forward, block rows rho0 .. rho0+G: y_rho[c0 .. c0+C) -= sum_{t0 <= t < t1} L[rho][t]
// x_t[c0 .. c0+C), x_t row t of zs. C and G constants: the G x C sums stay in registers while
// x_t streams from cache.
template <typename T, int64_t C, int64_t G>
inline void forward_rows(const Supernode<T>& n, int64_t rho0, int64_t t0, int64_t t1,
                         int64_t c0) {
  if constexpr (C == 4) {
    forward_quad<T, G>(n, rho0, t0, t1, c0);
  } else {
    T acc[G][C];
    T* y[G];
    const T* l[G];
    for (int64_t g = 0; g < G; ++g) {
      y[g] = n.row(rho0 + g) + c0;
      l[g] = n.l(rho0 + g);
      for (int64_t c = 0; c < C; ++c) acc[g][c] = y[g][c];
    }
    for (int64_t t = t0; t < t1; ++t) {
      const T* x = n.zs + t * n.width + c0;
      for (int64_t g = 0; g < G; ++g) {
        const T lt = l[g][t];
        for (int64_t c = 0; c < C; ++c) acc[g][c] -= lt * x[c];
      }
    }
    for (int64_t g = 0; g < G; ++g)
      for (int64_t c = 0; c < C; ++c) y[g][c] = acc[g][c];
  }
}

// backward_rows on a narrow block's row of four columns.
template <typename T, int64_t G>
inline void backward_quad(const Supernode<T>& n, int64_t t0, int64_t rho0, int64_t c0) {
  constexpr int64_t kW = G == 1 ? kWays : 1;
  using Q = Quad<T>;
  typename Q::V acc[kW][G] = {};
  const int64_t end = n.s + n.r;
  int64_t rho = rho0;
  for (; rho + kW <= end; rho += kW)
    for (int64_t w = 0; w < kW; ++w) {
      typename Q::V y;
      Q::load(y, n.row(rho + w) + c0);
      const T* l = n.l(rho + w) + t0;
      for (int64_t g = 0; g < G; ++g) acc[w][g] += l[g] * y;
    }
  for (; rho < end; ++rho) {
    typename Q::V y;
    Q::load(y, n.row(rho) + c0);
    const T* l = n.l(rho) + t0;
    for (int64_t g = 0; g < G; ++g) acc[0][g] += l[g] * y;
  }
  for (int64_t g = 0; g < G; ++g) {
    typename Q::V sum = acc[0][g];
    for (int64_t w = 1; w < kW; ++w) sum += acc[w][g];
    T* x = n.zs + (t0 + g) * n.width + c0;
    typename Q::V old;
    Q::load(old, x);
    Q::store(x, old - sum);
  }
}

// Backward, into columns t0 .. t0+G of zs: x_t[c0 .. c0+C) -= sum_{rho0 <= rho < s + r}
// L[rho][t] y_rho[c0 .. c0+C). With one column, kWays running sums over rho.
template <typename T, int64_t C, int64_t G>
inline void backward_rows(const Supernode<T>& n, int64_t t0, int64_t rho0, int64_t c0) {
  if constexpr (C == 4) {
    backward_quad<T, G>(n, t0, rho0, c0);
  } else {
    constexpr int64_t kW = G == 1 ? kWays : 1;
    T acc[kW][G][C] = {};
    T* x[G];
    for (int64_t g = 0; g < G; ++g) x[g] = n.zs + (t0 + g) * n.width + c0;
    const int64_t end = n.s + n.r;
    int64_t rho = rho0;
    for (; rho + kW <= end; rho += kW)
      for (int64_t w = 0; w < kW; ++w) {
        const T* y = n.row(rho + w) + c0;
        const T* l = n.l(rho + w) + t0;
        for (int64_t g = 0; g < G; ++g) {
          const T lt = l[g];
          for (int64_t c = 0; c < C; ++c) acc[w][g][c] += lt * y[c];
        }
      }
    for (; rho < end; ++rho) {
      const T* y = n.row(rho) + c0;
      const T* l = n.l(rho) + t0;
      for (int64_t g = 0; g < G; ++g) {
        const T lt = l[g];
        for (int64_t c = 0; c < C; ++c) acc[0][g][c] += lt * y[c];
      }
    }
    for (int64_t g = 0; g < G; ++g)
      for (int64_t c = 0; c < C; ++c) {
        T sum = acc[0][g][c];
        for (int64_t w = 1; w < kW; ++w) sum += acc[w][g][c];
        x[g][c] -= sum;
      }
  }
}

// Supernode n's forward step on columns c0 .. c0+C: its triangle, row groups after the columns
// before them, then the rows below; then D^-1 on its rows, final for the forward sweep and
// still in cache.
template <typename T, int64_t C>
void forward_chunk(const Supernode<T>& n, const T* dinv, int64_t c0) {
  int64_t u = 0;
  for (; u + kGroup <= n.s; u += kGroup) {
    forward_rows<T, C, kGroup>(n, u, 0, u, c0);
    for (int64_t g = 1; g < kGroup; ++g) forward_rows<T, C, 1>(n, u + g, u, u + g, c0);
  }
  for (; u < n.s; ++u) forward_rows<T, C, 1>(n, u, 0, u, c0);
  int64_t i = n.s;
  for (; i + kGroup <= n.s + n.r; i += kGroup) forward_rows<T, C, kGroup>(n, i, 0, n.s, c0);
  for (; i < n.s + n.r; ++i) forward_rows<T, C, 1>(n, i, 0, n.s, c0);
  for (int64_t t = 0; t < n.s; ++t) {
    T* x = n.zs + t * n.width + c0;
    for (int64_t c = 0; c < C; ++c) x[c] *= dinv[t];
  }
}

// Supernode n's backward step on columns c0 .. c0+C: column groups from the last, each after
// the rows past the group (its triangle's and those below), then inside the group.
template <typename T, int64_t C>
void backward_chunk(const Supernode<T>& n, int64_t c0) {
  int64_t t = n.s;
  for (; t - kGroup >= 0; t -= kGroup) {
    backward_rows<T, C, kGroup>(n, t - kGroup, t, c0);
    for (int64_t g = kGroup - 2; g >= 0; --g) {
      const int64_t col = t - kGroup + g;
      T* x = n.zs + col * n.width + c0;
      for (int64_t u = col + 1; u < t; ++u) {
        const T lu = n.l(u)[col];
        const T* y = n.zs + u * n.width + c0;
        for (int64_t c = 0; c < C; ++c) x[c] -= lu * y[c];
      }
    }
  }
  for (--t; t >= 0; --t) backward_rows<T, C, 1>(n, t, t + 1, c0);
}

// Both steps over columns c0 .. width in chunks of C, then of C / 2, ... 1 for what remains (so
// any width is done in registers but for its last few columns). dinv: the supernode's 1 / D,
// read by the forward step only.
template <typename T, int64_t C>
void supernode_step(const Supernode<T>& n, const T* dinv, bool forward, int64_t c0 = 0) {
  for (; c0 + C <= n.width; c0 += C) {
    if (forward)
      forward_chunk<T, C>(n, dinv, c0);
    else
      backward_chunk<T, C>(n, c0);
  }
  if constexpr (C > 1) {
    if (c0 < n.width) supernode_step<T, C / 2>(n, dinv, forward, c0);
  }
}

// The sweeps of supernodes k0 .. k1-1, their rows of the top in `ztop`; W the block's width
// where it is a constant (the narrow blocks, padded to 4), else 0. Forward: (I + L) y = z, then
// D^-1, supernode by supernode; backward: (I + L)^T x = y, the last supernode first.
template <typename T, int W>
void ldl_sweep(const LdlFactor<T>& f, const LdlBlock<T>& blk, T* ztop, int64_t top, int64_t k0,
               int64_t k1, bool forward) {
  constexpr int64_t kC = W > 0 ? W : kChunk<T>;
  const int64_t width = blk.stride;
  T* z = blk.z;
  auto node = [&](int64_t k) {
    const int64_t j0 = f.first[k];
    return Supernode<T>{z + j0 * width, z, ztop, f.rows + f.row_ptr[k], f.values + f.block_ptr[k],
                        f.first[k + 1] - j0, f.row_ptr[k + 1] - f.row_ptr[k], width, top};
  };
  if (forward) {
    for (int64_t k = k0; k < k1; ++k) supernode_step<T, kC>(node(k), f.dinv + f.first[k], true);
  } else {
    for (int64_t k = k1 - 1; k >= k0; --k) supernode_step<T, kC>(node(k), nullptr, false);
  }
}

template <typename T>
void sweep_range(const LdlFactor<T>& f, const LdlBlock<T>& blk, T* ztop, int64_t top,
                 int64_t k0, int64_t k1, bool forward) {
  if (blk.stride == 4)
    ldl_sweep<T, 4>(f, blk, ztop, top, k0, k1, forward);
  else
    ldl_sweep<T, 0>(f, blk, ztop, top, k0, k1, forward);
}

// Row i of b: perm[i], or i where b is in the factor's order (perm null).
template <typename T>
int64_t caller_row(const LdlFactor<T>& f, int64_t i) {
  return f.perm == nullptr ? i : static_cast<int64_t>(f.perm[i]);
}

// Rows j0 .. j1-1 of z from the block's columns of b (permuted; padding columns zero), or back;
// nothing where the block is swept in b itself.
template <typename T>
void gather_rows(const LdlFactor<T>& f, const LdlBlock<T>& blk, int64_t j0, int64_t j1) {
  if (blk.in_place()) return;
  const int64_t w = blk.c1 - blk.c0;
  for (int64_t i = j0; i < j1; ++i) {
    const T* from = blk.b + caller_row(f, i) * blk.k + blk.c0;
    T* to = blk.z + i * blk.stride;
    for (int64_t c = 0; c < w; ++c) to[c] = from[c];
    for (int64_t c = w; c < blk.stride; ++c) to[c] = T(0);
  }
}

template <typename T>
void scatter_rows(const LdlFactor<T>& f, const LdlBlock<T>& blk, int64_t j0, int64_t j1) {
  if (blk.in_place()) return;
  const int64_t w = blk.c1 - blk.c0;
  for (int64_t i = j0; i < j1; ++i) {
    const T* from = blk.z + i * blk.stride;
    T* to = blk.b + caller_row(f, i) * blk.k + blk.c0;
    for (int64_t c = 0; c < w; ++c) to[c] = from[c];
  }
}

// Part p's forward step: its rows gathered, its rows of the top zeroed, its supernodes swept.
template <typename T>
void ldl_part_forward(const LdlFactor<T>& f, const LdlBlock<T>& blk, int64_t p) {
  const int64_t top = f.top();
  gather_rows(f, blk, f.first[f.part_ptr[p]], f.first[f.part_ptr[p + 1]]);
  T* own = blk.part_rows(f, p);
  std::fill(own, own + (f.n - top) * blk.stride, T(0));
  sweep_range(f, blk, own, top, f.part_ptr[p], f.part_ptr[p + 1], true);
}

// The top's steps: its rows gathered and the parts' sums added (in the parts' order), swept
// forward and backward, scattered, and copied to every part's rows for the parts' backward.
template <typename T>
void ldl_top(const LdlFactor<T>& f, const LdlBlock<T>& blk) {
  const int64_t top = f.top(), count = (f.n - top) * blk.stride;
  gather_rows(f, blk, top, f.n);
  T* rows = blk.z + top * blk.stride;
  for (int64_t p = 0; p < f.parts; ++p) {
    const T* own = blk.part_rows(f, p);
    for (int64_t i = 0; i < count; ++i) rows[i] += own[i];
  }
  sweep_range(f, blk, rows, top, f.part_ptr[f.parts], f.supernodes, true);
  sweep_range(f, blk, rows, top, f.part_ptr[f.parts], f.supernodes, false);
  scatter_rows(f, blk, top, f.n);
  for (int64_t p = 0; p < f.parts; ++p) std::copy(rows, rows + count, blk.part_rows(f, p));
}

// Part p's backward step: its supernodes swept, reading the top's final rows from its copy;
// its rows scattered.
template <typename T>
void ldl_part_backward(const LdlFactor<T>& f, const LdlBlock<T>& blk, int64_t p) {
  sweep_range(f, blk, blk.part_rows(f, p), f.top(), f.part_ptr[p], f.part_ptr[p + 1], false);
  scatter_rows(f, blk, f.first[f.part_ptr[p]], f.first[f.part_ptr[p + 1]]);
}

// Part p's step of a block, or the top's (p unread).
template <typename T>
void ldl_step(const LdlFactor<T>& f, const LdlBlock<T>& blk, LdlStep step, int64_t p) {
  switch (step) {
    case LdlStep::kPartForward:
      return ldl_part_forward(f, blk, p);
    case LdlStep::kTop:
      return ldl_top(f, blk);
    case LdlStep::kPartBackward:
      return ldl_part_backward(f, blk, p);
  }
}

}  // namespace OB_ISA
}  // namespace optax_bilateral
#endif
