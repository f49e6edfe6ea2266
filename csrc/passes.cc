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
    pass.pairs.push_back(pair);
  }
  return pass;
}

// Points [first, last) of a slab, clipped to [q.lo, q.hi), as holes of q, runs merged.
void add_hole(SlabPair& q, int64_t first, int64_t last) {
  first = std::max(first, q.lo);
  last = std::min(last, q.hi);
  if (first >= last) return;
  if (!q.holes.empty() && q.holes.back().first + q.holes.back().second == first) {
    q.holes.back().second += last - first;
  } else {
    q.holes.emplace_back(first, last - first);
  }
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

std::vector<SlabPass> make_slab_passes(const std::vector<int64_t>& shape, int levels, int start) {
  std::vector<SlabPass> passes;
  const size_t n = shape.size();
  // A slab's rows (axes 1 .. n-2) and its row length.
  const std::vector<int64_t> rows(shape.begin() + 1, shape.end() - 1);
  const int64_t L = shape[n - 1], R = product(rows, 0, rows.size());
  for (int i = start; i < levels; ++i) {
    const int64_t stride = int64_t{1} << i;
    const Pass full = full_pass(shape, stride);
    if (full.pairs.empty()) continue;
    SlabPass pass;
    pass.slabs = shape[0];
    pass.slab = R * L;
    pass.stride = stride;
    pass.centre = full.centre;
    for (const Pair& p : full.pairs) {
      SlabPair q;
      q.tap = p.tap;
      q.slabs = p.row_offset[0] / stride;
      const std::vector<int64_t> in_slab(p.row_offset.begin() + 1, p.row_offset.end());
      q.flat = flat(rows, in_slab) * L + p.column_offset;
      q.lo = std::max<int64_t>(0, -q.flat);
      q.hi = std::min(pass.slab, pass.slab - q.flat);
      for (int64_t r = 0; r < R; ++r) {
        bool row_on = true;  // row r of the slab moved by the pair's in-slab rows
        for (int64_t k = static_cast<int64_t>(rows.size()), t = r; k-- > 0; t /= rows[k]) {
          const int64_t j = t % rows[k] + in_slab[k];
          row_on = row_on && j >= 0 && j < rows[k];
        }
        // The row's holes: all of it, or the columns the pair moves off its end.
        const int64_t oc = p.column_offset;
        int64_t first = r * L, last = r * L + L;
        if (row_on && oc > 0) first += std::max<int64_t>(0, L - oc);
        if (row_on && oc <= 0) last = r * L + std::min(L, -oc);
        add_hole(q, first, last);
      }
      pass.pairs.push_back(std::move(q));
    }
    passes.push_back(std::move(pass));
  }
  return passes;
}

bool needs_working_copy(const std::vector<int64_t>& shape, int levels, int start, bool separable) {
  if (separable && shape.size() >= 2) return false;
  return make_passes(shape, levels, start, separable).size() > 1;
}

}  // namespace optax_bilateral
