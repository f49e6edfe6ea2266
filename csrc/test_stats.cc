// The texel statistics (stats.h) against their definitions written out in double with
// unravelled indices: ranks 1 to 4, every subset of spatial axes, strides 1 to 5, float and
// double; the mean distance with and without b, NaN and infinite entries; the correlation sums
// over every spatial axis of length > 1; the blend (its local averages written out as 5-tap
// sums); the step's mean norm from its parts; and check_texel_grid's verdicts on bad shapes.
// Built and run by `make sanitize` under AddressSanitizer and UndefinedBehaviorSanitizer;
// exits non-zero on a mismatch.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <random>
#include <vector>

#include "stats.h"

namespace ob = optax_bilateral;

namespace {

int failures = 0, cases = 0, open_blends = 0, blends = 0;

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

// The number of elements of an array of `shape`.
int64_t elements(const std::vector<int64_t>& shape) {
  int64_t n = 1;
  for (int64_t d : shape) n *= d;
  return n;
}

// The sub-grid's shape and its texels' (the channel dimensions cut to 1), and their sizes.
struct Shapes {
  std::vector<bool> spatial;
  std::vector<int64_t> sub, texel_shape;
  int64_t n = 1, texels = 1;

  explicit Shapes(const ob::Subgrid& g) : spatial(g.shape.size(), false), sub(g.shape) {
    for (int64_t ax : g.axes) spatial[ax] = true;
    texel_shape = g.shape;
    for (size_t d = 0; d < sub.size(); ++d) {
      if (spatial[d]) sub[d] = (g.shape[d] - 1) / g.stride + 1;
      texel_shape[d] = spatial[d] ? sub[d] : 1;
    }
    for (size_t d = 0; d < sub.size(); ++d) n *= sub[d], texels *= texel_shape[d];
  }
  // Sub-grid entry i's index in the grid (at) and its texel's (t).
  void locate(int64_t i, int64_t stride, std::vector<int64_t>& at, std::vector<int64_t>& t) const {
    at = t = unravel(i, sub);
    for (size_t d = 0; d < at.size(); ++d) {
      if (spatial[d]) at[d] *= stride;
      if (!spatial[d]) t[d] = 0;
    }
  }
};

// The mean of the texels' norms from their squared sums, NaN ones left out (0 if none is left).
double mean_norm(const std::vector<double>& sums) {
  double total = 0;
  int64_t counted = 0;
  for (double x : sums)
    if (!std::isnan(x)) total += std::sqrt(x), ++counted;
  return counted ? total / static_cast<double>(counted) : 0.0;
}

// Every entry of the sub-grid visited in order, its squared difference added to its texel's
// sum (found by zeroing the channel coordinates), then the mean of the finite norms.
double reference(const ob::Subgrid& g, const std::vector<double>& a, const std::vector<double>* b) {
  const Shapes s(g);
  std::vector<double> sums(s.texels, 0.0);
  std::vector<int64_t> at, t;
  for (int64_t i = 0; i < s.n; ++i) {
    s.locate(i, g.stride, at, t);
    const double x = a[ravel(at, g.shape)] - (b ? (*b)[i] : 0.0);
    sums[ravel(t, s.texel_shape)] += x * x;
  }
  return mean_norm(sums);
}

template <typename T>
void check(const ob::Subgrid& g, std::mt19937& rng) {
  std::normal_distribution<double> normal(0.0, 3.0);
  const int64_t size = elements(g.shape);
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
    std::vector<T> kept(sub, T(-7));
    const double got =
        ob::texel_distance_mean(g, a.data(), with_b ? b.data() : nullptr, kept.data());
    // kept: a's sub-grid, every entry written (the sub-grid of a's flat index i's point).
    for (int64_t i = 0; i < size; ++i) {
      auto idx = unravel(i, g.shape);
      bool on = true;
      int64_t at = 0;
      for (size_t d = 0; d < idx.size(); ++d) {
        const bool spatial_d = std::find(g.axes.begin(), g.axes.end(),
                                         static_cast<int64_t>(d)) != g.axes.end();
        if (spatial_d && idx[d] % g.stride) on = false;
        const int64_t n = spatial_d ? (g.shape[d] - 1) / g.stride + 1 : g.shape[d];
        at = at * n + (spatial_d ? idx[d] / g.stride : idx[d]);
      }
      const bool equal = std::isnan(a[i]) ? std::isnan(kept[at]) : kept[at] == a[i];
      if (on && !equal && failures++ < 10)
        std::printf("FAIL kept rank %zu stride %lld at %lld\n", g.shape.size(),
                    static_cast<long long>(g.stride), static_cast<long long>(at));
    }
    const bool same = std::isinf(want) ? got == want : std::fabs(got - want) <= 1e-12 * (1 + std::fabs(want));
    if (!same && failures++ < 10)
      std::printf("FAIL rank %zu stride %lld b %d: %.17g != %.17g\n", g.shape.size(),
                  static_cast<long long>(g.stride), with_b, got, want);
  }
}

// Every entry of z tested for being a pair's first point along `along` (on the sub-grid of the
// other spatial axes, at a multiple of q = max(s, 2) with a partner before the block's end).
std::vector<double> correlation_reference(const ob::Subgrid& g, const std::vector<int64_t>& pairs,
                                          const std::vector<double>& z,
                                          const std::vector<double>& y) {
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[ax] = true;
  const int64_t q = std::max<int64_t>(g.stride, 2);
  const int64_t n = elements(g.shape);
  std::vector<double> out;
  for (int64_t along : pairs) {
    double s00 = 0, s11 = 0, s01 = 0;
    for (int64_t i = 0; i < n; ++i) {
      auto idx = unravel(i, g.shape);
      bool first = idx[along] % q == 0 && idx[along] / q < g.shape[along] / q;
      for (size_t d = 0; d < idx.size(); ++d)
        if (spatial[d] && static_cast<int64_t>(d) != along && idx[d] % g.stride) first = false;
      if (!first) continue;
      auto next = idx;
      ++next[along];
      const double x0 = z[i], x1 = z[ravel(next, g.shape)];
      s00 += x0 * x0, s11 += x1 * x1, s01 += x0 * x1;
    }
    out.insert(out.end(), {s00, s11, s01});
  }
  double zz = 0, yy = 0;
  for (int64_t i = 0; i < n; ++i) {
    auto idx = unravel(i, g.shape);
    bool on = true;
    for (size_t d = 0; d < idx.size(); ++d)
      if (spatial[d] && idx[d] % g.stride) on = false;
    if (on) zz += z[i] * z[i], yy += y[i] * y[i];
  }
  out.insert(out.end(), {zz, yy});
  return out;
}

// noise_test at the edges of its thresholds: the lags' mean correlation, written out here in T
// in the test's order, passes at itself and fails at the next T above it; the noise's energy
// likewise against noisy lag^2 times the signal's (noisy chosen to land on it).
template <typename T>
void check_noise_test(std::vector<double> sums, size_t pairs, T lag) {
  for (double& x : sums) x = static_cast<T>(x);
  T total = 0;
  for (size_t k = 0; k < pairs; ++k) {
    const T den = std::sqrt(static_cast<T>(sums[3 * k]) * static_cast<T>(sums[3 * k + 1]));
    total = total + (den > 0 ? static_cast<T>(sums[3 * k + 2]) / den : T(0));
  }
  const T mean = total * (T(1) / static_cast<T>(pairs));
  const T noise = static_cast<T>(sums[3 * pairs]), signal = static_cast<T>(sums[3 * pairs + 1]);
  const T above = std::nextafter(mean, std::numeric_limits<T>::infinity());
  const bool quiet = !(noise > T(0) * lag * lag * signal);  // an all-zero z (nothing observed)
  const T at_mean = ob::noise_test<T>(sums.data(), pairs, lag, mean, 0.0);
  const T past_mean = ob::noise_test<T>(sums.data(), pairs, lag, above, 0.0);
  ++cases;
  if ((at_mean != (quiet ? T(0) : T(1)) || past_mean != T(0)) && failures++ < 10)
    std::printf("FAIL noise test at its mean %.9g: %g, above it: %g\n", double(mean),
                double(at_mean), double(past_mean));
  if (!(signal > 0) || quiet) return;
  const T ratio = noise / (lag * lag * signal);  // noise > noisy lag^2 signal iff noisy < ratio
  const T below = std::nextafter(ratio, T(0));
  const bool pass = noise > below * lag * lag * signal;
  ++cases;
  if (ob::noise_test<T>(sums.data(), pairs, lag, -2.0, below) != (pass ? T(1) : T(0)) &&
      failures++ < 10)
    std::printf("FAIL noise test at noisy %.9g\n", double(below));
}

// z and y from a gradient, a first moment and a mask broadcast along some dimensions, as Noise
// defines them (in T), for the float64 reference; then the native sums. `from_grad`: no mask,
// each texel observed or not from its gradient (every channel finite; with drop_zero, not all
// 0), some of whose entries are not finite or 0.
template <typename T>
void check_correlation(const ob::Subgrid& g, std::mt19937& rng, bool from_grad) {
  std::normal_distribution<double> normal(0.0, 2.0);
  const int64_t n = elements(g.shape);
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[static_cast<size_t>(ax)] = true;
  std::vector<int64_t> mask_shape;
  for (size_t d = 0; d < g.shape.size(); ++d)
    mask_shape.push_back((from_grad ? !spatial[d] : rng() % 3 == 0) ? 1 : g.shape[d]);
  const int64_t n_mask = elements(mask_shape);
  const auto mask_at = [&](int64_t i) {
    auto idx = unravel(i, g.shape);
    for (size_t d = 0; d < idx.size(); ++d)
      if (mask_shape[d] == 1) idx[d] = 0;
    return ravel(idx, mask_shape);
  };
  const T c1 = static_cast<T>(0.1 + 0.9 * (rng() % 1000) / 1000.0);
  // Half the cases clip the gradient (to about its spread: many entries are clipped).
  const T limit = rng() % 2 ? static_cast<T>(1.5) : std::numeric_limits<T>::infinity();
  const bool drop_zero = from_grad && rng() % 2;
  std::vector<T> grad(n), m(n);
  for (int64_t i = 0; i < n; ++i)
    grad[i] = static_cast<T>(normal(rng)), m[i] = static_cast<T>(normal(rng));
  std::unique_ptr<bool[]> observed(new bool[static_cast<size_t>(n_mask)]);
  if (from_grad) {  // the texel mask, as the native call makes it
    const T inf = std::numeric_limits<T>::infinity(), nan = std::numeric_limits<T>::quiet_NaN();
    std::vector<bool> finite(n_mask, true), zero(n_mask, true);
    for (int64_t i = 0; i < n; ++i) {
      const unsigned r = rng() % 20;
      grad[i] = r == 0 ? nan : r == 1 ? -inf : r < 6 ? T(0) : grad[i];
      finite[mask_at(i)] = finite[mask_at(i)] && std::isfinite(grad[i]);
      zero[mask_at(i)] = zero[mask_at(i)] && grad[i] == T(0);
    }
    for (int64_t t = 0; t < n_mask; ++t) observed[t] = finite[t] && !(drop_zero && zero[t]);
  } else {
    for (int64_t i = 0; i < n_mask; ++i) observed[i] = rng() % 4 != 0;
  }
  std::vector<double> z64(n), y64(n);
  for (int64_t i = 0; i < n; ++i) {
    const bool on = observed[mask_at(i)];
    if (!from_grad && !on && rng() % 2) grad[i] = std::numeric_limits<T>::quiet_NaN();  // unread
    const T y = m[i] / c1;
    const T clipped = grad[i] < -limit ? -limit : grad[i] > limit ? limit : grad[i];
    z64[i] = on ? static_cast<T>(clipped - y) : T(0);
    y64[i] = on ? y : T(0);
  }
  std::vector<int64_t> pairs;
  for (int64_t ax : g.axes)
    if (g.shape[ax] > 1) pairs.push_back(ax);
  const auto want = correlation_reference(g, pairs, z64, y64);
  std::vector<double> got(want.size(), -1.0);
  if (!ob::check_noise_mask(g, mask_shape).empty()) {
    std::printf("FAIL a sound mask shape was refused\n");
    ++failures;
    return;
  }
  const ob::Noise<T> noise{grad.data(), m.data(), from_grad ? nullptr : observed.get(),
                           from_grad ? std::vector<int64_t>{} : mask_shape, c1, limit, drop_zero};
  ob::correlation_sums(g, pairs, noise, got.data());
  ++cases;
  for (size_t k = 0; k < want.size(); ++k) {
    if (!(std::fabs(got[k] - want[k]) <= 1e-12 * (1 + std::fabs(want[k]))) && failures++ < 10) {
      std::printf("FAIL correlation rank %zu stride %lld sum %zu%s: %.17g != %.17g\n",
                  g.shape.size(), static_cast<long long>(g.stride), k,
                  from_grad ? " (mask from the gradient)" : "", got[k], want[k]);
      break;
    }
  }
  if (!pairs.empty()) check_noise_test<T>(got, pairs.size(), c1);
}

// One level of the B-spline at stride 1 along `axis` of `shape`, its taps on the grid only.
std::vector<double> average_along(const std::vector<double>& x, const std::vector<int64_t>& shape,
                                  int64_t axis) {
  const double h[5] = {1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16};
  std::vector<double> out(x.size());
  for (size_t i = 0; i < x.size(); ++i) {
    auto idx = unravel(static_cast<int64_t>(i), shape);
    double sum = 0, norm = 0;
    for (int k = 0; k < 5; ++k) {
      auto at = idx;
      at[axis] += k - 2;
      if (at[axis] < 0 || at[axis] >= shape[axis]) continue;
      sum += h[k] * x[ravel(at, shape)];
      norm += h[k];
    }
    out[i] = sum / norm;
  }
  return out;
}

// The blend (stats.h) by its formula in double, the sub-grid read through unravelled indices.
std::vector<double> blend_reference(const ob::Subgrid& g, const std::vector<double>& m,
                                    const std::vector<double>& v, const std::vector<double>& r,
                                    const ob::Blend<double>& b) {
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[ax] = true;
  std::vector<int64_t> sub = g.shape;
  for (size_t d = 0; d < sub.size(); ++d)
    if (spatial[d]) sub[d] = (g.shape[d] - 1) / g.stride + 1;
  std::vector<double> noise(r.size()), energy(r.size());
  for (size_t i = 0; i < r.size(); ++i) {
    auto at = unravel(static_cast<int64_t>(i), sub);
    for (size_t d = 0; d < at.size(); ++d)
      if (spatial[d]) at[d] *= g.stride;
    const int64_t p = ravel(at, g.shape);
    const double mm = m[p] / b.c1;
    noise[i] = std::max(v[p] / b.c2 - mm * mm, 0.0) * b.k * b.ema * b.corr_num / b.corr_den;
    energy[i] = (r[i] / b.bias) * (r[i] / b.bias);
  }
  for (int64_t ax : g.axes) {
    noise = average_along(noise, sub, ax);
    energy = average_along(energy, sub, ax);
  }
  std::vector<double> lam(r.size());
  double total = 0;
  for (size_t i = 0; i < r.size(); ++i) {
    const double l = 1 - noise[i] / (b.gain * (energy[i] > 0 ? energy[i] : 1));
    lam[i] = b.usable > 0 && energy[i] > 0 ? std::pow(std::clamp(l, 0.0, 1.0), b.power) : 0.0;
    total += lam[i];
  }
  const double gate = std::clamp((total / r.size() - b.low) / b.span, 0.0, 1.0);
  for (double& l : lam) l *= gate;
  lam.push_back(gate);
  return lam;
}

template <typename T>
void check_blend(const ob::Subgrid& g, std::mt19937& rng) {
  std::normal_distribution<double> normal(0.0, 1.0);
  const int64_t n = elements(g.shape);
  const int64_t sub = ob::texel_subgrid_size(g);
  std::vector<T> m(n), v(n), r(sub), out(sub);
  std::vector<double> m64(n), v64(n), r64(sub);
  for (int64_t i = 0; i < n; ++i) {
    m[i] = static_cast<T>(normal(rng));
    v[i] = static_cast<T>(0.05 * std::fabs(normal(rng)) + 0.01 * m[i] * m[i]);
    m64[i] = m[i], v64[i] = v[i];
  }
  for (int64_t i = 0; i < sub; ++i) r[i] = static_cast<T>(normal(rng)), r64[i] = r[i];
  // Weights inside (0, 1) and at its ends, an open gate (low 0.05, span 0.5).
  const ob::Blend<T> b{T(0.6), T(0.01), T(0.3), T(0.2), T(1.8), T(0.2), T(0.5), T(1),
                       T(0.25), T(2), T(0.05), T(0.5)};
  const ob::Blend<double> b64{0.6, 0.01, 0.3, 0.2, 1.8, 0.2, 0.5, 1, 0.25, 2, 0.05, 0.5};
  const auto want = blend_reference(g, m64, v64, r64, b64);
  const T gate = ob::blend_weights(g, m.data(), v.data(), r.data(), b, out.data());
  const double tol = sizeof(T) == 4 ? 2e-5 : 1e-12;
  ++cases;
  bool ok = std::fabs(gate - want.back()) <= tol;
  for (int64_t i = 0; i < sub && ok; ++i) ok = std::fabs(out[i] - want[i]) <= tol;
  ++blends;
  bool inside = false;
  for (int64_t i = 0; i < sub; ++i) inside |= out[i] > T(0) && out[i] < gate;
  open_blends += gate > T(0) && inside;
  if (!ok && failures++ < 10)
    std::printf("FAIL blend rank %zu stride %lld: gate %.9g != %.9g\n", g.shape.size(),
                static_cast<long long>(g.stride), static_cast<double>(gate), want.back());
}

// The step's mean texel norm (stats.h's Step) by its formula in double, through unravelled
// indices: each texel observed or not from its gradient (every channel finite; with drop_zero,
// not all 0), each sub-grid entry's step added to its texel's squared norm, then the mean of
// the norms that are not NaN.
double step_reference(const ob::Subgrid& g, const std::vector<double>* p[6], bool drop_zero,
                      bool blend, const double k[4]) {
  const Shapes s(g);
  std::vector<double> sums(s.texels, 0.0);
  std::vector<bool> finite(s.texels, true), zero(s.texels, true);
  std::vector<int64_t> at, t;
  for (int64_t i = 0; i < s.n; ++i) {
    s.locate(i, g.stride, at, t);
    const double x = (*p[4])[ravel(at, g.shape)];
    const int64_t texel = ravel(t, s.texel_shape);
    finite[texel] = finite[texel] && std::isfinite(x);
    zero[texel] = zero[texel] && x == 0;
  }
  for (int64_t i = 0; i < s.n; ++i) {
    s.locate(i, g.stride, at, t);
    const int64_t a = ravel(at, g.shape), texel = ravel(t, s.texel_shape);
    const double lam = blend ? (*p[5])[i] : 0.0;
    const auto mixed = [&](int x, int bx) {
      return blend ? lam * (*p[x])[a] + (1 - lam) * (*p[bx])[a] : (*p[bx])[a];
    };
    const double h = mixed(1, 3) * k[1] + k[3];
    const double den = (h > 0 ? std::sqrt(h) : 0.0) + k[2];
    const bool observed = finite[texel] && !(drop_zero && zero[texel]);
    const double step = observed && den > 0 ? mixed(0, 2) * k[0] / den : 0;
    sums[texel] += step * step;
  }
  return mean_norm(sums);
}

template <typename T>
void check_step(const ob::Subgrid& g, std::mt19937& rng) {
  std::normal_distribution<double> normal(0.0, 1.0);
  const int64_t n = elements(g.shape);
  const int64_t sub = ob::texel_subgrid_size(g);
  // m, v, B m, B v, the gradient (g.shape) and lam (the sub-grid's).
  std::vector<T> x[6] = {std::vector<T>(n), std::vector<T>(n), std::vector<T>(n),
                         std::vector<T>(n), std::vector<T>(n), std::vector<T>(sub)};
  std::vector<double> x64[6];
  const T inf = std::numeric_limits<T>::infinity(), nan = std::numeric_limits<T>::quiet_NaN();
  for (int64_t i = 0; i < n; ++i) {
    x[0][i] = static_cast<T>(normal(rng)), x[2][i] = static_cast<T>(normal(rng));
    x[1][i] = static_cast<T>(std::fabs(normal(rng))), x[3][i] = static_cast<T>(normal(rng));
    if (rng() % 50 == 0) x[2][i] = nan;  // its texel left out, if observed
    // The gradient: some entries not finite, some 0 (whole texels of 0 where channels are few).
    const unsigned r = rng() % 20;
    x[4][i] = r == 0 ? nan : r == 1 ? -inf : r < 6 ? T(0) : static_cast<T>(normal(rng));
  }
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int64_t i = 0; i < sub; ++i) x[5][i] = static_cast<T>(unit(rng));
  for (int j = 0; j < 6; ++j) x64[j].assign(x[j].begin(), x[j].end());
  const bool blend = rng() % 2, drop_zero = rng() % 2;
  // eps_root 0 or not; B v may be negative there (h <= 0: den = eps).
  const double k[4] = {3.7, 50.2, 1e-8, rng() % 2 ? 0.0 : 1e-3};
  const T* arrays[5] = {x[0].data(), x[1].data(), x[2].data(), x[3].data(), x[4].data()};
  const ob::Step<T> step = ob::step_of<T>(arrays, x[5].data(), drop_zero, blend, k);
  const std::vector<double>* parts[6] = {&x64[0], &x64[1], &x64[2], &x64[3], &x64[4], &x64[5]};
  const double want = step_reference(g, parts, drop_zero, blend, k);
  const double got = ob::step_norm(g, step);
  ++cases;
  const double tol = sizeof(T) == 4 ? 2e-5 : 1e-12;
  if (!(std::fabs(got - want) <= tol * (1 + std::fabs(want))) && failures++ < 10)
    std::printf("FAIL step norm rank %zu stride %lld: %.17g != %.17g\n", g.shape.size(),
                static_cast<long long>(g.stride), got, want);
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
        for (bool from_grad : {false, true}) {
          check_correlation<float>(g, rng, from_grad);
          check_correlation<double>(g, rng, from_grad);
        }
        check_blend<float>(g, rng);
        check_blend<double>(g, rng);
        check_step<float>(g, rng);
        check_step<double>(g, rng);
      }
    }
  }
  refused({{4, 4}, {0}, 0}, "stride 0");
  refused({{4, 4}, {2}, 1}, "axis out of range");
  refused({{4, 4}, {0, 0}, 1}, "axis twice");
  refused({{4, 0}, {0}, 1}, "empty dimension");
  for (const auto& mask : std::vector<std::vector<int64_t>>{{4}, {4, 3}, {2, 4}, {4, 4, 1}}) {
    ++cases;
    if (ob::check_noise_mask({{4, 4}, {0, 1}, 1}, mask).empty() && failures++ < 10)
      std::printf("FAIL a mask of rank %zu was not refused\n", mask.size());
  }
  if (2 * open_blends < blends) {  // the blend's cases must reach its weights
    std::printf("FAIL only %d of %d blends had an open gate and weights inside\n", open_blends,
                blends);
    return 1;
  }
  if (failures) {
    std::printf("%d of %d texel-statistics cases failed\n", failures, cases);
    return 1;
  }
  std::printf("0 of %d texel-statistics cases failed\n", cases);
  return 0;
}
