// The sub-grid local averages (local.h) against the tensor-product sum written from its
// definition in float64: ranks 1 to 4, any subset and order of axes, strides 1 to 5, float and
// double; and check_subgrid's verdicts on bad shapes. Built and run by `make sanitize` under
// AddressSanitizer and UndefinedBehaviorSanitizer; exits non-zero on a mismatch.
#include <algorithm>
#include <cmath>
#include <limits>
#include <cstdio>
#include <memory>
#include <random>
#include <vector>

#include "local.h"

namespace ob = optax_bilateral;

namespace {

const double kH[5] = {1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16};

int64_t count(const std::vector<int64_t>& shape) {
  int64_t n = 1;
  for (int64_t d : shape) n *= d;
  return n;
}

std::vector<int64_t> unravel(int64_t p, const std::vector<int64_t>& shape) {
  std::vector<int64_t> idx(shape.size());
  for (size_t k = shape.size(); k-- > 0; p /= shape[k]) idx[k] = p % shape[k];
  return idx;
}

// Every output entry as one sum over the 5^axes taps, each tap's weight the product of the
// per-axis B-spline weights normalised over that axis's taps on the grid.
std::vector<double> reference(const std::vector<double>& x, const ob::Subgrid& s) {
  std::vector<int64_t> out_shape = s.shape;
  for (int64_t a : s.axes) out_shape[a] = (s.shape[a] - 1) / s.stride + 1;
  std::vector<double> out(static_cast<size_t>(count(out_shape)));
  const size_t n_axes = s.axes.size();
  int64_t taps = 1;
  for (size_t k = 0; k < n_axes; ++k) taps *= 5;
  for (int64_t p = 0; p < count(out_shape); ++p) {
    const auto idx = unravel(p, out_shape);
    std::vector<int64_t> centre = idx;
    std::vector<double> norm(n_axes, 0.0);
    for (size_t k = 0; k < n_axes; ++k) {
      const int64_t a = s.axes[k];
      centre[a] = idx[a] * s.stride;
      for (int d = -2; d <= 2; ++d)
        if (centre[a] + d >= 0 && centre[a] + d < s.shape[a]) norm[k] += kH[d + 2];
    }
    double sum = 0;
    for (int64_t t = 0; t < taps; ++t) {
      std::vector<int64_t> q = centre;
      double w = 1;
      bool on = true;
      int64_t r = t;
      for (size_t k = 0; k < n_axes; ++k, r /= 5) {
        const int d = static_cast<int>(r % 5) - 2;
        q[s.axes[k]] += d;
        on = on && q[s.axes[k]] >= 0 && q[s.axes[k]] < s.shape[s.axes[k]];
        w *= kH[d + 2] / norm[k];
      }
      if (!on) continue;
      int64_t flat = 0;
      for (size_t k = 0; k < q.size(); ++k) flat = flat * s.shape[k] + q[k];
      sum += w * x[static_cast<size_t>(flat)];
    }
    out[static_cast<size_t>(p)] = sum;
  }
  return out;
}

// x in T, and (kFinite) as numpy.nan_to_num makes it: what the average must read.
template <typename T>
std::vector<double> as_read(const std::vector<double>& x, ob::Read read) {
  std::vector<double> out;
  for (double v : x) {
    const T t = static_cast<T>(v);
    if (read == ob::Read::kAsIs || std::isfinite(t))
      out.push_back(t);
    else
      out.push_back(std::isnan(t) ? 0.0 : t > 0 ? std::numeric_limits<T>::max()
                                                : std::numeric_limits<T>::lowest());
  }
  return out;
}

template <typename T>
bool check(const ob::Subgrid& s, const std::vector<double>& x, double tol,
           ob::Read read = ob::Read::kAsIs) {
  std::vector<T> xt(x.begin(), x.end());
  const int64_t n_out = ob::subgrid_size(s), n_work = ob::subgrid_work_size(s);
  // Exactly sized heap buffers, so that AddressSanitizer sees any write past them.
  auto out = std::make_unique<T[]>(static_cast<size_t>(n_out));
  auto work = n_work ? std::make_unique<T[]>(static_cast<size_t>(n_work)) : nullptr;
  ob::subgrid_average(s, xt.data(), out.get(), work.get(), read);
  const auto seen = as_read<T>(x, read);
  const auto want = reference(seen, s);
  if (static_cast<int64_t>(want.size()) != n_out) {
    std::printf("size %lld, want %zu\n", static_cast<long long>(n_out), want.size());
    return false;
  }
  // Rounding relative to the inputs' scale: an average of large values of both signs cancels.
  double scale = 1;
  for (double v : seen) scale = std::max(scale, std::fabs(v));
  for (int64_t i = 0; i < n_out; ++i) {
    const double got = static_cast<double>(out[static_cast<size_t>(i)]);
    if (!(std::fabs(got - want[static_cast<size_t>(i)]) <= tol * scale)) {
      std::printf("entry %lld: %.17g, want %.17g\n", static_cast<long long>(i), got,
                  want[static_cast<size_t>(i)]);
      return false;
    }
  }
  return true;
}

}  // namespace

int main() {
  std::mt19937 rng(7);
  std::normal_distribution<double> normal;
  int failures = 0, cases = 0;
  for (int trial = 0; trial < 400; ++trial) {
    ob::Subgrid s;
    const int rank = 1 + static_cast<int>(rng() % 4);
    for (int k = 0; k < rank; ++k) s.shape.push_back(1 + static_cast<int64_t>(rng() % 9));
    for (int64_t a = 0; a < rank; ++a)
      if (rng() % 3 != 0) s.axes.push_back(a);
    std::shuffle(s.axes.begin(), s.axes.end(), rng);
    s.stride = 1 + static_cast<int64_t>(rng() % 5);
    if (!ob::check_subgrid(s).empty()) {
      std::printf("check_subgrid refused a sound call: %s\n", ob::check_subgrid(s).c_str());
      ++failures;
      continue;
    }
    std::vector<double> x(static_cast<size_t>(count(s.shape)));
    for (auto& v : x) v = trial % 7 == 0 ? 1e30 * normal(rng) : normal(rng);
    ++cases;
    if (!check<float>(s, x, 1e-6) || !check<double>(s, x, 1e-14)) {
      std::printf("  in trial %d (rank %d, %zu axes, stride %lld)\n", trial, rank, s.axes.size(),
                  static_cast<long long>(s.stride));
      ++failures;
    }
    // NaN and infinities read as numpy.nan_to_num makes them (the guide's contrast).
    for (auto& v : x) {
      const auto r = rng() % 8;
      v = r == 0 ? std::nan("") : r == 1 ? HUGE_VAL : r == 2 ? -HUGE_VAL : v;
    }
    ++cases;
    if (!check<float>(s, x, 1e-6, ob::Read::kFinite) ||
        !check<double>(s, x, 1e-14, ob::Read::kFinite)) {
      std::printf("  in trial %d (rank %d, %zu axes, stride %lld)\n", trial, rank, s.axes.size(),
                  static_cast<long long>(s.stride));
      ++failures;
    }
  }
  // Bad calls are refused before any read.
  const ob::Subgrid bad[] = {
      {{4, 4}, {0, 0}, 1}, {{4, 4}, {2}, 1}, {{4, 4}, {-1}, 1},
      {{4, 4}, {0}, 0},    {{4, 0}, {1}, 2}, {{4, -1}, {0}, 1},
  };
  for (const auto& s : bad) {
    ++cases;
    if (ob::check_subgrid(s).empty()) {
      std::printf("check_subgrid accepted a bad call\n");
      ++failures;
    }
  }
  std::printf("%d of %d local-average cases failed\n", failures, cases);
  return failures ? 1 : 0;
}
