// The passes of a cascade, each as a "view" of the grid: rows of contiguous points and the
// pairs of offsets the pass visits. Shared by the driver and every instruction-set build.
#pragma once

#include <cstdint>
#include <vector>

namespace optax_bilateral {

// One pair of opposite offsets +o / -o, o's first non-zero component positive.
struct Pair {
  std::vector<int64_t> row_offset;  // o along the view's row axes
  int64_t column_offset = 0;        // o along the row itself
  int64_t flat_rows = 0;            // the row index o adds (> 0 unless only the column moves)
  double tap = 0;                   // the product of the B3 taps of o
};

// A pass sees the grid as rows of `row_length` contiguous points, indexed by `row_shape`.
// Separable passes along the last axis: rows are the grid's rows; along an outer axis k: rows
// of n_k*..*n_{d-1} points (one per index of the axes before k), a pair moving o n_{k+1}*..
// points along the row, which stays on the grid exactly where the row does: one long row,
// not n_k short ones, so that a 3-D slab's pass runs long loops.
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

}  // namespace optax_bilateral
