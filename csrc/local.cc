// csrc/local.h's passes: plain loops (the sub-grid is small: at most ~2^17 texels per field).
#include "local.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <set>

namespace optax_bilateral {

namespace {

constexpr int kRadius = 2;
// Below this many entries per step along the axis, a pass sums entry by entry (a loop over so
// few would cost more than its arithmetic); from it on, whole rows at once, vectorised.
constexpr int64_t kShortRows = 8;
constexpr double kTaps[2 * kRadius + 1] = {1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16};

int64_t kept(int64_t n, int64_t stride) { return (n - 1) / stride + 1; }

// The shape after each pass, the input's first.
std::vector<std::vector<int64_t>> shapes_of(const Subgrid& s) {
  std::vector<std::vector<int64_t>> out{s.shape};
  for (int64_t a : s.axes) {
    auto next = out.back();
    next[static_cast<size_t>(a)] = kept(next[static_cast<size_t>(a)], s.stride);
    out.push_back(next);
  }
  return out;
}

int64_t count(const std::vector<int64_t>& shape) {
  int64_t n = 1;
  for (int64_t d : shape) n *= d;
  return n;
}

// x as numpy.nan_to_num reads it: NaN as 0, an infinity as the largest finite value of its sign
// (selects, not branches, so that the loops reading through it still vectorise).
template <typename T>
T finite(T v) {
  constexpr T big = std::numeric_limits<T>::max();
  const T clamped = v > big ? big : v < -big ? -big : v;  // NaN compares false: stays NaN
  return clamped == clamped ? clamped : T(0);
}

// Entry i's taps on the grid, k in [lo, hi), and their sum.
struct Taps {
  int lo, hi;
  double norm;
};

Taps taps_at(int64_t centre, int64_t n) {
  Taps t{static_cast<int>(std::max<int64_t>(0, kRadius - centre)),
         static_cast<int>(std::min<int64_t>(2 * kRadius + 1, n - centre + kRadius)), 0.0};
  for (int k = t.lo; k < t.hi; ++k) t.norm += kTaps[k];
  return t;
}

// One pass along the middle axis of x (outer, n, inner) into out (outer, kept, inner); each
// entry's sum in the same order (k ascending) either way.
template <typename T, bool Finite>
void pass(const T* x, T* out, int64_t outer, int64_t n, int64_t inner, int64_t stride) {
  const auto load = [x](int64_t i) { return Finite ? finite(x[i]) : x[i]; };
  const int64_t m = kept(n, stride);
  if (inner < kShortRows) {  // the last axes: one sum per entry, row by row
    std::vector<Taps> at(static_cast<size_t>(m));
    for (int64_t i = 0; i < m; ++i) at[static_cast<size_t>(i)] = taps_at(stride * i, n);
    T h[2 * kRadius + 1];
    for (int k = 0; k <= 2 * kRadius; ++k) h[k] = static_cast<T>(kTaps[k]);
    // With stride 1 the entries whose taps all fall on the grid are one contiguous run [lo, hi).
    const int64_t lo = stride == 1 ? std::min<int64_t>(kRadius, m) : m;
    const int64_t hi = stride == 1 ? std::max<int64_t>(lo, m - kRadius) : m;
    for (int64_t o = 0; o < outer; ++o) {
      const int64_t row = o * n * inner;
      T* dst = out + o * m * inner;
      auto entry = [&](int64_t i) {
        const Taps& t = at[static_cast<size_t>(i)];
        const int64_t first = stride * i - kRadius;  // + k >= 0 for k >= t.lo
        for (int64_t q = 0; q < inner; ++q) {
          T sum = T(0);
          for (int k = t.lo; k < t.hi; ++k) sum += h[k] * load(row + (first + k) * inner + q);
          dst[i * inner + q] = sum / static_cast<T>(t.norm);
        }
      };
      for (int64_t i = 0; i < lo; ++i) entry(i);
      if (hi > lo) {
        const T norm = static_cast<T>(at[static_cast<size_t>(lo)].norm);
        for (int64_t j = lo * inner; j < hi * inner; ++j) {
          T sum = T(0);
          for (int k = 0; k <= 2 * kRadius; ++k) sum += h[k] * load(row + j + (k - kRadius) * inner);
          dst[j] = sum / norm;
        }
      }
      for (int64_t i = hi; i < m; ++i) entry(i);
    }
    return;
  }
  for (int64_t i = 0; i < m; ++i) {
    const Taps t = taps_at(stride * i, n);
    const T scale = static_cast<T>(t.norm);
    for (int64_t o = 0; o < outer; ++o) {
      T* dst = out + (o * m + i) * inner;
      for (int64_t q = 0; q < inner; ++q) dst[q] = T(0);
      for (int k = t.lo; k < t.hi; ++k) {
        const T h = static_cast<T>(kTaps[k]);
        const int64_t row = (o * n + stride * i + k - kRadius) * inner;
        for (int64_t q = 0; q < inner; ++q) dst[q] += h * load(row + q);
      }
      for (int64_t q = 0; q < inner; ++q) dst[q] /= scale;
    }
  }
}

template <typename T>
void run(const Subgrid& s, const T* x, T* out, T* work, Read read) {
  const auto shapes = shapes_of(s);
  const size_t passes = s.axes.size();
  // Passes between the first and the last alternate between two regions of `work`.
  T* regions[2] = {work, work ? work + (passes > 1 ? count(shapes[1]) : 0) : nullptr};
  const T* src = x;
  for (size_t p = 0; p < passes; ++p) {
    const size_t a = static_cast<size_t>(s.axes[p]);
    const auto& shape = shapes[p];
    int64_t outer = 1, inner = 1;
    for (size_t d = 0; d < a; ++d) outer *= shape[d];
    for (size_t d = a + 1; d < shape.size(); ++d) inner *= shape[d];
    T* dst = p + 1 == passes ? out : regions[p % 2];
    if (p == 0 && read == Read::kFinite)
      pass<T, true>(src, dst, outer, shape[a], inner, s.stride);
    else
      pass<T, false>(src, dst, outer, shape[a], inner, s.stride);
    src = dst;
  }
  for (int64_t i = 0; passes == 0 && i < count(s.shape); ++i)
    out[i] = read == Read::kFinite ? finite(x[i]) : x[i];
}

}  // namespace

std::string check_subgrid(const Subgrid& s) {
  if (s.stride < 1) return "stride must be >= 1";
  std::set<int64_t> seen;
  for (int64_t a : s.axes) {
    if (a < 0 || a >= static_cast<int64_t>(s.shape.size())) return "an axis is out of range";
    if (!seen.insert(a).second) return "an axis is named twice";
  }
  for (int64_t d : s.shape)
    if (d < 0) return "a dimension is negative";
  for (int64_t a : s.axes)
    if (s.shape[static_cast<size_t>(a)] < 1) return "an averaged axis is empty";
  return "";
}

int64_t subgrid_size(const Subgrid& s) { return count(shapes_of(s).back()); }

int64_t subgrid_work_size(const Subgrid& s) {
  const auto shapes = shapes_of(s);
  const size_t passes = s.axes.size();
  if (passes < 2) return 0;
  return count(shapes[1]) + (passes > 2 ? count(shapes[2]) : 0);
}

void subgrid_average(const Subgrid& s, const float* x, float* out, float* work, Read read) {
  run(s, x, out, work, read);
}

void subgrid_average(const Subgrid& s, const double* x, double* out, double* work, Read read) {
  run(s, x, out, work, read);
}

}  // namespace optax_bilateral
