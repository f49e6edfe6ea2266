// The sigma_d rules' local averages at a sub-grid: one level of the filter's 5-tap B-spline
// with every data weight 1, read only at every `stride`-th entry along the chosen axes.
//
// Along one axis of length n the pass keeps kept = (n - 1) / stride + 1 entries and computes
//
//   out[i] = sum_k h[k] x[stride i + k - 2] / sum_k h[k]      (k = 0..4, taps on the grid only)
//
// (h = 1/16, 1/4, 3/8, 1/4, 1/16); the axes are passed in turn, each reading the last's result.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace optax_bilateral {

// One call's shapes: `shape` the row-major input's, `axes` the axes to average (each once, in
// the order they are passed), `stride` >= 1.
struct Subgrid {
  std::vector<int64_t> shape;
  std::vector<int64_t> axes;
  int64_t stride = 1;
};

// The first problem with a call's shapes, or "" when every later read and write stays in bounds.
std::string check_subgrid(const Subgrid& s);
// The output's element count: `shape` with each averaged axis cut to its kept entries.
int64_t subgrid_size(const Subgrid& s);
// The scratch the passes between the first and the last need, in elements (0 for one axis).
int64_t subgrid_work_size(const Subgrid& s);

// How the first pass reads x: as it is, or as numpy.nan_to_num would make it (NaN as 0, an
// infinity as the largest finite value of its sign), with no copy of it.
enum class Read { kAsIs, kFinite };

// out <- the averages of x; `work` holds subgrid_work_size elements (may be null when 0).
void subgrid_average(const Subgrid& s, const float* x, float* out, float* work,
                     Read read = Read::kAsIs);
void subgrid_average(const Subgrid& s, const double* x, double* out, double* work,
                     Read read = Read::kAsIs);

}  // namespace optax_bilateral
