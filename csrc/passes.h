// The passes of a cascade, each as a "view" of the grid: rows of contiguous points and the
// pairs of offsets the pass visits. Shared by the driver and every instruction-set build.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

namespace optax_bilateral {

// One pair of opposite offsets +o / -o, o's first non-zero component positive.
struct Pair {
  std::vector<int64_t> row_offset;  // o along the view's row axes
  int64_t column_offset = 0;        // o along the row itself
  double tap = 0;                   // the product of the B3 taps of o
};

// A pass sees the grid as rows of `row_length` contiguous points, indexed by `row_shape`.
// Separable passes along the last axis: rows are the grid's rows; along an outer axis k: rows
// of n_k*..*n_{d-1} points (one per index of the axes before k), a pair moving o n_{k+1}*..
// points along the row, which stays on the grid exactly where the row does: one long row,
// not n_k short ones, so that a 3-D slab's pass runs long loops. A full pass's rows are the
// grid's rows, its pairs moving along them and the row axes; one over a grid of rank >= 2 is
// run as slabs (SlabPass), so that every Pass that runs moves its pairs along the row.
struct Pass {
  std::vector<int64_t> row_shape;
  int64_t row_length = 1;
  std::vector<Pair> pairs;
  double centre = 0;  // h0, or h0^n for a full pass

  int64_t rows() const {
    int64_t r = 1;
    for (int64_t n : row_shape) r *= n;
    return r;
  }
};

std::vector<Pass> make_passes(const std::vector<int64_t>& shape, int levels, int start,
                              bool separable);

// One pair of a full pass over a grid of rank >= 2 seen as slabs along axis 0 (SlabPass): it
// moves `slabs` strides along axis 0 and `flat` points within a slab. Points [lo, hi) of a
// slab have their partner inside the slab's memory; `holes` ((first, count) runs within them)
// are those whose partner is not their neighbour (a row or column of the slab wraps).
struct SlabPair {
  int64_t slabs = 0, flat = 0, lo = 0, hi = 0;
  double tap = 0;
  std::vector<std::pair<int64_t, int64_t>> holes;
};

// A full pass run slab by slab along chains of slabs `stride` apart (kernel.h,
// run_slab_chunk), the pairs in the pass's order.
struct SlabPass {
  int64_t slabs = 0, slab = 0, stride = 0;  // n0, the points of a slab, 2^level
  double centre = 0;
  std::vector<SlabPair> pairs;
};

// The full passes of levels start .. levels-1 of a grid of rank >= 2, as slabs.
std::vector<SlabPass> make_slab_passes(const std::vector<int64_t>& shape, int levels, int start);

}  // namespace optax_bilateral
