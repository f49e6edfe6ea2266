// The native kernel against a point-by-point float64 loop written from docs/method.md's
// formula: 1-, 2- and 3-D grids, separable and full, one or several guide channels, masks,
// NaN guides, sigma_d 0 and inf, one and several threads. Built and run by `make sanitize`
// under AddressSanitizer and UndefinedBehaviorSanitizer; exits non-zero on a mismatch.
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <vector>

#include "atrous.h"

namespace ob = optax_bilateral;

namespace {

const double kH[5] = {1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16};

double data_weight(const std::vector<double>& g, int64_t G, int64_t N, int64_t p, int64_t q,
                   double sigma) {
  double d2 = 0;
  for (int64_t c = 0; c < G; ++c) d2 += std::pow(g[c * N + p] - g[c * N + q], 2);
  if (std::isnan(d2)) return 0;
  if (d2 == 0) return 1;
  if (sigma == 0) return 0;
  if (std::isinf(sigma)) return 1;
  return std::exp(-std::sqrt(d2) / sigma);
}

std::vector<double> reference(std::vector<double> x, const std::vector<double>& g,
                              const std::vector<int>& valid, std::vector<int64_t> shape,
                              int64_t C, int64_t G, double sigma, int levels, bool separable) {
  const int64_t n = static_cast<int64_t>(shape.size());
  int64_t N = 1;
  for (int64_t s : shape) N *= s;
  for (int level = 0; level < levels; ++level) {
    const int64_t stride = int64_t{1} << level;
    std::vector<std::vector<int64_t>> groups;
    if (separable) {
      for (int64_t k = 0; k < n; ++k) groups.push_back({k});
    } else {
      std::vector<int64_t> all;
      for (int64_t k = 0; k < n; ++k) all.push_back(k);
      groups.push_back(all);
    }
    for (const auto& axes : groups) {
      std::vector<double> out(x.size(), 0.0);
      for (int64_t p = 0; p < N; ++p) {
        std::vector<int64_t> idx(n);
        for (int64_t k = n, r = p; k-- > 0; r /= shape[k]) idx[k] = r % shape[k];
        std::vector<double> num(C, 0.0);
        double den = 0;
        const int64_t taps = static_cast<int64_t>(std::pow(5, axes.size()));
        for (int64_t t = 0; t < taps; ++t) {
          std::vector<int64_t> qi = idx;
          double h = 1;
          bool on = true;
          for (size_t a = 0, r = t; a < axes.size(); ++a, r /= 5) {
            const int64_t d = static_cast<int64_t>(r % 5) - 2;
            qi[axes[a]] += stride * d;
            h *= kH[d + 2];
            on = on && qi[axes[a]] >= 0 && qi[axes[a]] < shape[axes[a]];
          }
          if (!on) continue;
          int64_t q = 0;
          for (int64_t k = 0; k < n; ++k) q = q * shape[k] + qi[k];
          if (!valid[q] || !valid[p]) continue;
          // The centre always counts: a NaN guide makes a point nobody's neighbour, not its own.
          const double w = q == p ? h : h * data_weight(g, G, N, p, q, sigma);
          for (int64_t c = 0; c < C; ++c) num[c] += w * x[c * N + q];
          den += w;
        }
        for (int64_t c = 0; c < C; ++c) out[c * N + p] = den > 0 ? num[c] / den : 0.0;
      }
      x = out;
    }
  }
  return x;
}

int check(std::vector<int64_t> shape, int64_t C, int64_t G, double sigma, int levels,
          bool separable, bool masked, bool nan_guide, int threads, unsigned seed,
          bool interleaved = false) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  int64_t N = 1;
  for (int64_t s : shape) N *= s;
  std::vector<double> x(C * N), g(G * N);
  std::vector<int> valid(N, 1);
  for (auto& v : x) v = normal(rng);
  // Quantised guides: equal values exercise the equal-guides rule (and sigma_d = 0).
  for (auto& v : g) v = std::floor(std::fabs(normal(rng)) * 1.5) * 0.4 + normal(rng) * 0.05;
  if (masked)
    for (auto& v : valid) v = (rng() % 5) != 0;
  if (nan_guide) g[N / 2] = std::numeric_limits<double>::quiet_NaN();
  for (int64_t p = 0; p < N; ++p)
    if (!valid[p])
      for (int64_t c = 0; c < C; ++c) x[c * N + p] = 0;
  const auto want = reference(x, g, valid, shape, C, G, sigma, levels, separable);

  std::vector<float> xf(x.begin(), x.end()), gf(g.begin(), g.end()), vf(valid.begin(), valid.end());
  // A separable cascade of rank >= 2 runs in place: no working copy, so ASan sees any use.
  const bool own_work = ob::needs_working_copy(shape, levels, 0, separable);
  std::vector<float> out(C * N, -1.0f), work(own_work ? C * N : 0, -1.0f);
  ob::Cascade<float> c;
  c.x = xf.data();
  c.guide = gf.data();
  c.valid = masked ? vf.data() : nullptr;
  c.out = out.data();
  c.work = own_work ? work.data() : nullptr;
  c.channels = C;
  c.guide_channels = G;
  c.shape = shape;
  c.sigma_d = static_cast<float>(sigma);
  c.levels = levels;
  c.separable = separable;
  c.threads = threads;
  c.min_parallel_work = 0;  // threads on these small grids too: chains cut in chunks
  // Interleaved: the channels as two fields (1 and C - 1 channels), each (N, c_k).
  std::vector<float> f0(N), f1((C - 1) * N), o0(N, -1.0f), o1((C - 1) * N, -1.0f);
  if (interleaved) {
    for (int64_t p = 0; p < N; ++p) {
      f0[p] = xf[p];
      for (int64_t k = 1; k < C; ++k) f1[p * (C - 1) + k - 1] = xf[k * N + p];
    }
    c.x = nullptr;
    c.out = nullptr;
    c.levels = levels;
    c.x_fields = {{f0.data(), 1}, {f1.data(), C - 1}};
    c.out_fields = {{o0.data(), 1}, {o1.data(), C - 1}};
  }
  ob::run_cascade(c);
  if (interleaved) {
    for (int64_t p = 0; p < N; ++p) {
      out[p] = o0[p];
      for (int64_t k = 1; k < C; ++k) out[k * N + p] = o1[p * (C - 1) + k - 1];
    }
  }
  for (int64_t i = 0; i < C * N; ++i) {
    // float32 sums of unit-scale terms: 1e-5 relative, 1e-6 absolute where they cancel.
    const double err = std::fabs(out[i] - want[i]);
    if (!(err <= 1e-6 + 1e-5 * std::fabs(want[i]))) {
      std::printf("FAIL shape[0]=%lld rank=%zu C=%lld G=%lld sigma=%g F=%d sep=%d mask=%d "
                  "nan=%d threads=%d interleaved=%d: [%lld] %g vs %g\n",
                  (long long)shape[0], shape.size(), (long long)C, (long long)G, sigma, levels,
                  separable, masked, nan_guide, threads, interleaved, (long long)i, out[i], want[i]);
      return 1;
    }
  }
  return 0;
}

}  // namespace

int main() {
  int failures = 0, cases = 0;
  const std::vector<std::vector<int64_t>> shapes = {{37}, {9, 13}, {40, 33}, {5, 7, 6}, {11, 9, 10},
                                                     {3, 17}, {300, 7}, {23, 4, 3}, {4, 5, 3, 6},
                                                     {50000}};
  const double sigmas[] = {0.0, 0.3, 2.0, std::numeric_limits<double>::infinity()};
  unsigned seed = 0;
  for (const auto& shape : shapes)
    for (bool separable : {true, false})
      for (double sigma : sigmas)
        for (int64_t G : {1, 3, 5})  // 5: the guide's distance summed in a buffer
          for (bool masked : {false, true}) {
            // Level 3 of 40 x 33 has a stride of 8: 8 chains of 5 slabs, 4 of them cut.
            // A line of 50000 points runs in blocks of columns, each with the weights before it.
            // 300 rows of 7 points run in groups of 292 rows, the last group of each piece short.
            const int levels = shape.size() == 3   ? (shape[0] == 23 ? 4 : 2)
                               : shape[0] == 40 || shape[0] == 300 ? 4
                               : shape[0] == 50000 ? 7
                                                   : 3;
            const int threads = 1 + (seed % 5);
            const bool nan_guide = seed % 4 == 1;
            failures += check(shape, 2, G, sigma, levels, separable, masked, nan_guide, threads,
                              seed++);
            ++cases;
            if (separable && shape.size() >= 2) {  // fields with their channels interleaved
              failures += check(shape, 3, G, sigma, levels, true, masked, nan_guide, threads,
                                seed++, true);
              ++cases;
            }
          }
  std::printf("%d passed, %d failed (instruction set %s)\n", cases - failures, failures,
              ob::instruction_set().c_str());
  return failures != 0;
}
