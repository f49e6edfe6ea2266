#include "passes.h"

#include "atrous.h"

#include <algorithm>
#include <cstdlib>

namespace optax_bilateral {
namespace {

// B3-spline taps h[d] for d = -2..2, by |d|.
constexpr double kTaps[3] = {3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0};

int64_t product(const std::vector<int64_t>& v, size_t from, size_t to) {
  int64_t p = 1;
  for (size_t k = from; k < to; ++k) p *= v[k];
  return p;
}

int64_t flat(const std::vector<int64_t>& row_shape, const std::vector<int64_t>& offset) {
  int64_t f = 0;
  for (size_t k = 0; k < offset.size(); ++k) f = f * row_shape[k] + offset[k];
  return f;
}

Pass separable_pass(const std::vector<int64_t>& shape, size_t axis, int64_t stride) {
  Pass pass;
  pass.centre = kTaps[0];
  const size_t n = shape.size();
  if (axis + 1 == n) {
    pass.row_shape.assign(shape.begin(), shape.end() - 1);
    pass.row_length = shape[n - 1];
  } else {
    pass.row_shape = {product(shape, 0, axis)};
    pass.row_length = product(shape, axis, n);
  }
  // A step along `axis` moves this many points along the row.
  const int64_t step = product(shape, axis + 1, n);
  for (int d = 1; d <= 2; ++d) {
    if (d * stride >= shape[axis]) continue;
    Pair pair;
    pair.tap = kTaps[d];
    pair.row_offset.assign(pass.row_shape.size(), 0);
    pair.column_offset = d * stride * step;
    pair.flat_rows = 0;
    pass.pairs.push_back(pair);
  }
  return pass;
}

// Every offset stride * d, d in {-2..2}^n, with its first non-zero d positive, in the
// order of bilateral.level_passes (so the sums run in the pure-JAX kernels' order).
Pass full_pass(const std::vector<int64_t>& shape, int64_t stride) {
  Pass pass;
  const size_t n = shape.size();
  pass.row_shape.assign(shape.begin(), shape.end() - 1);
  pass.row_length = shape[n - 1];
  pass.centre = 1;
  for (size_t k = 0; k < n; ++k) pass.centre *= kTaps[0];
  std::vector<int> d(n, -2);
  std::vector<std::vector<int>> kept;
  while (true) {
    int first = 0;
    for (int c : d) {
      if (c != 0) {
        first = c;
        break;
      }
    }
    bool on = first > 0;
    for (size_t k = 0; k < n && on; ++k) on = std::abs(d[k]) * stride < shape[k];
    if (on) kept.push_back(d);
    size_t k = n;
    while (k > 0 && d[k - 1] == 2) d[--k] = -2;
    if (k == 0) break;
    ++d[k - 1];
  }
  auto key = [](const std::vector<int>& v) {
    std::vector<int> a, b;
    for (size_t k = 1; k < v.size(); ++k) {
      a.push_back(std::abs(v[k]));
      b.push_back(v[k]);
    }
    a.insert(a.end(), b.begin(), b.end());
    a.push_back(v[0]);
    return a;
  };
  std::stable_sort(kept.begin(), kept.end(),
                   [&](const auto& u, const auto& v) { return key(u) < key(v); });
  for (const auto& dd : kept) {
    Pair pair;
    pair.tap = 1;
    for (size_t k = 0; k < n; ++k) {
      pair.tap *= kTaps[std::abs(dd[k])];
      if (k + 1 < n) pair.row_offset.push_back(dd[k] * stride);
    }
    pair.column_offset = dd[n - 1] * stride;
    pair.flat_rows = flat(pass.row_shape, pair.row_offset);
    pass.pairs.push_back(pair);
  }
  return pass;
}

}  // namespace

std::vector<Pass> make_passes(const std::vector<int64_t>& shape, int levels, int start,
                              bool separable) {
  std::vector<Pass> passes;
  for (int i = start; i < levels; ++i) {
    const int64_t stride = int64_t{1} << i;
    if (separable) {
      for (size_t k = 0; k < shape.size(); ++k) {
        Pass p = separable_pass(shape, k, stride);
        if (!p.pairs.empty()) passes.push_back(std::move(p));
      }
    } else {
      Pass p = full_pass(shape, stride);
      if (!p.pairs.empty()) passes.push_back(std::move(p));
    }
  }
  return passes;
}

bool needs_working_copy(const std::vector<int64_t>& shape, int levels, int start, bool separable) {
  if (separable && shape.size() >= 2) return false;
  return make_passes(shape, levels, start, separable).size() > 1;
}

}  // namespace optax_bilateral
