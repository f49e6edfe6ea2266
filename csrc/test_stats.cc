// The texel statistics (stats.h) against their definition written out in double with unravelled
// indices: ranks 1 to 4, every subset of spatial axes, strides 1 to 5, with and without b,
// NaN and infinite entries, float and double; and check_texel_grid's verdicts on bad shapes.
// Built and run by `make sanitize` under AddressSanitizer and UndefinedBehaviorSanitizer;
// exits non-zero on a mismatch.
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <vector>

#include "stats.h"

namespace ob = optax_bilateral;

namespace {

int failures = 0, cases = 0;

std::vector<int64_t> unravel(int64_t p, const std::vector<int64_t>& shape) {
  std::vector<int64_t> idx(shape.size());
  for (size_t k = shape.size(); k-- > 0; p /= shape[k]) idx[k] = p % shape[k];
  return idx;
}

int64_t ravel(const std::vector<int64_t>& idx, const std::vector<int64_t>& shape) {
  int64_t p = 0;
  for (size_t k = 0; k < shape.size(); ++k) p = p * shape[k] + idx[k];
  return p;
}

// Every entry of the sub-grid visited in order, its squared difference added to its texel's
// sum (found by zeroing the channel coordinates), then the mean of the finite norms.
double reference(const ob::Subgrid& g, const std::vector<double>& a, const std::vector<double>* b) {
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[ax] = true;
  std::vector<int64_t> sub = g.shape, texel_shape = g.shape;
  for (size_t d = 0; d < sub.size(); ++d) {
    if (spatial[d]) sub[d] = (g.shape[d] - 1) / g.stride + 1;
    texel_shape[d] = spatial[d] ? sub[d] : 1;
  }
  int64_t n = 1, texels = 1;
  for (size_t d = 0; d < sub.size(); ++d) n *= sub[d], texels *= texel_shape[d];
  std::vector<double> sums(texels, 0.0);
  for (int64_t i = 0; i < n; ++i) {
    auto idx = unravel(i, sub), at = idx, t = idx;
    for (size_t d = 0; d < idx.size(); ++d) {
      if (spatial[d]) at[d] *= g.stride;
      if (!spatial[d]) t[d] = 0;
    }
    const double x = a[ravel(at, g.shape)] - (b ? (*b)[i] : 0.0);
    sums[ravel(t, texel_shape)] += x * x;
  }
  double total = 0;
  int64_t counted = 0;
  for (double s : sums)
    if (!std::isnan(s)) total += std::sqrt(s), ++counted;
  return counted ? total / counted : 0.0;
}

template <typename T>
void check(const ob::Subgrid& g, std::mt19937& rng) {
  std::normal_distribution<double> normal(0.0, 3.0);
  int64_t size = 1;
  for (int64_t d : g.shape) size *= d;
  const int64_t sub = ob::texel_subgrid_size(g);
  std::vector<T> a(size), b(sub);
  std::vector<double> a64(size), b64(sub);
  for (int64_t i = 0; i < size; ++i) {
    const unsigned r = rng() % 40;
    a[i] = r == 0 ? std::numeric_limits<T>::quiet_NaN()
                  : r == 1 ? std::numeric_limits<T>::infinity() : static_cast<T>(normal(rng));
    a64[i] = a[i];
  }
  for (int64_t i = 0; i < sub; ++i) b[i] = static_cast<T>(normal(rng)), b64[i] = b[i];
  for (bool with_b : {false, true}) {
    ++cases;
    const double want = reference(g, a64, with_b ? &b64 : nullptr);
    const double got = ob::texel_distance_mean(g, a.data(), with_b ? b.data() : nullptr);
    const bool same = std::isinf(want) ? got == want : std::fabs(got - want) <= 1e-12 * (1 + std::fabs(want));
    if (!same && failures++ < 10)
      std::printf("FAIL rank %zu stride %lld b %d: %.17g != %.17g\n", g.shape.size(),
                  static_cast<long long>(g.stride), with_b, got, want);
  }
}

void refused(const ob::Subgrid& g, const char* why) {
  ++cases;
  if (ob::check_texel_grid(g).empty() && failures++ < 10) std::printf("FAIL not refused: %s\n", why);
}

}  // namespace

int main() {
  std::mt19937 rng(3);
  for (int rank = 1; rank <= 4; ++rank) {
    for (int mask = 1; mask < (1 << rank); ++mask) {
      for (int64_t stride = 1; stride <= 5; ++stride) {
        ob::Subgrid g;
        for (int d = 0; d < rank; ++d) g.shape.push_back(1 + static_cast<int64_t>(rng() % 7));
        for (int d = 0; d < rank; ++d)
          if (mask & (1 << d)) g.axes.push_back(d);
        if (rng() % 2 && g.axes.size() > 1) std::swap(g.axes.front(), g.axes.back());
        g.stride = stride;
        if (!ob::check_texel_grid(g).empty()) {
          std::printf("FAIL a sound grid was refused\n");
          return 1;
        }
        check<float>(g, rng);
        check<double>(g, rng);
      }
    }
  }
  refused({{4, 4}, {0}, 0}, "stride 0");
  refused({{4, 4}, {2}, 1}, "axis out of range");
  refused({{4, 4}, {0, 0}, 1}, "axis twice");
  refused({{4, 0}, {0}, 1}, "empty dimension");
  if (failures) {
    std::printf("%d of %d texel-statistics cases failed\n", failures, cases);
    return 1;
  }
  std::printf("0 of %d texel-statistics cases failed\n", cases);
  return 0;
}
