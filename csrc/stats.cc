// csrc/stats.h's statistics: plain loops over the sub-grid (at most ~2^17 texels per leaf).
#include "stats.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace optax_bilateral {

namespace {

int64_t kept(int64_t n, int64_t stride) { return (n - 1) / stride + 1; }

// A row-major walk over `sizes` that keeps an offset into a, one into b and one into c, each
// with its own step per axis.
struct Walk {
  std::vector<int64_t> sizes, step_a, step_b, step_c, idx;
  int64_t a = 0, b = 0, c = 0;

  void add(int64_t size, int64_t sa, int64_t sb, int64_t sc = 0) {
    sizes.push_back(size);
    step_a.push_back(sa);
    step_b.push_back(sb);
    step_c.push_back(sc);
    idx.push_back(0);
  }
  int64_t count() const {
    int64_t n = 1;
    for (int64_t s : sizes) n *= s;
    return n;
  }
  void next() {
    for (size_t d = sizes.size(); d-- > 0;) {
      a += step_a[d];
      b += step_b[d];
      c += step_c[d];
      if (++idx[d] < sizes[d]) return;
      a -= step_a[d] * sizes[d];
      b -= step_b[d] * sizes[d];
      c -= step_c[d] * sizes[d];
      idx[d] = 0;
    }
  }
};

// The walk over the sub-grid's texels and the one over a texel's channels.
void walks(const Subgrid& g, Walk& texels, Walk& channels) {
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[static_cast<size_t>(ax)] = true;
  std::vector<int64_t> sa(g.shape.size()), sb(g.shape.size());
  int64_t na = 1, nb = 1;
  for (size_t d = g.shape.size(); d-- > 0;) {
    const int64_t kept_d = spatial[d] ? kept(g.shape[d], g.stride) : g.shape[d];
    sa[d] = na * (spatial[d] ? g.stride : 1);
    sb[d] = nb;
    na *= g.shape[d];
    nb *= kept_d;
  }
  for (size_t d = 0; d < g.shape.size(); ++d) {
    if (spatial[d])
      texels.add(kept(g.shape[d], g.stride), sa[d], sb[d]);
    else
      channels.add(g.shape[d], sa[d], sb[d]);
  }
}

template <typename T>
double run(const Subgrid& g, const T* a, const T* b, T* kept) {
  Walk texels, channels;
  walks(g, texels, channels);
  const int64_t n_texels = texels.count(), n_channels = channels.count();
  double total = 0;
  int64_t counted = 0;
  for (int64_t t = 0; t < n_texels; ++t, texels.next()) {
    double sum = 0;
    channels.a = channels.b = 0;
    for (int64_t c = 0; c < n_channels; ++c, channels.next()) {
      const T value = a[texels.a + channels.a];
      if (kept) kept[texels.b + channels.b] = value;
      const double x =
          static_cast<double>(value) - (b ? static_cast<double>(b[texels.b + channels.b]) : 0.0);
      sum += x * x;
    }
    if (std::isnan(sum)) continue;
    total += std::sqrt(sum);
    ++counted;
  }
  return counted ? total / static_cast<double>(counted) : 0.0;
}

// Row-major strides of `shape`.
std::vector<int64_t> strides_of(const std::vector<int64_t>& shape) {
  std::vector<int64_t> out(shape.size());
  int64_t n = 1;
  for (size_t d = shape.size(); d-- > 0;) out[d] = n, n *= shape[d];
  return out;
}

// The walk over the sub-grid of g's spatial axes, with its offset into an array of g.shape.
Walk subgrid_walk(const Subgrid& g) {
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[static_cast<size_t>(ax)] = true;
  const auto step = strides_of(g.shape);
  Walk sub;
  for (size_t d = 0; d < g.shape.size(); ++d)
    sub.add(spatial[d] ? kept(g.shape[d], g.stride) : g.shape[d],
            (spatial[d] ? g.stride : 1) * step[d], 0);
  return sub;
}

// Row-major strides of a mask of `shape` read at the indices of a grid of its rank: 0 along
// its broadcast (length-1) dimensions.
std::vector<int64_t> broadcast_strides(const std::vector<int64_t>& shape) {
  auto out = strides_of(shape);
  for (size_t d = 0; d < shape.size(); ++d)
    if (shape[d] == 1) out[d] = 0;
  return out;
}

// Where a Noise reads whether an entry is observed: its mask at offset b, or (no mask) the
// texel whose first channel is at offset c of grad, from its channels at c + `channels`.
template <typename T>
struct Observed {
  const Noise<T>& noise;
  std::vector<int64_t> channels;

  bool operator()(int64_t b, int64_t c) const {
    if (noise.observed) return noise.observed[b];
    bool finite = true, zero = true;
    for (int64_t o : channels) {
      const T x = noise.grad[c + o];
      finite = finite && std::isfinite(x);
      zero = zero && x == T(0);
    }
    return finite && !(noise.drop_zero && zero);
  }
};

template <typename T>
T noise_y(const Noise<T>& n, int64_t a, bool observed) {
  return observed ? n.m[a] / n.c1 : T(0);
}

template <typename T>
T noise_z(const Noise<T>& n, int64_t a, bool observed) {
  if (!observed) return T(0);
  const T g = std::min(std::max(n.grad[a], -n.limit), n.limit);  // jnp.clip's order
  return g - n.m[a] / n.c1;
}

template <typename T>
void correlation(const Subgrid& g, const std::vector<int64_t>& pair_axes, const Noise<T>& noise,
                 double* out) {
  std::vector<bool> spatial(g.shape.size(), false);
  for (int64_t ax : g.axes) spatial[static_cast<size_t>(ax)] = true;
  const auto step = strides_of(g.shape);
  const auto mask = noise.observed ? broadcast_strides(noise.observed_shape)
                                   : std::vector<int64_t>(g.shape.size(), 0);
  // texel(d): grad's step along a spatial axis d, 0 along the channels (offset c of a Walk).
  std::vector<int64_t> texel(g.shape.size(), 0);
  Walk channel_walk;
  for (size_t d = 0; d < g.shape.size(); ++d) {
    if (spatial[d])
      texel[d] = step[d];
    else
      channel_walk.add(g.shape[d], step[d], 0);
  }
  Observed<T> seen{noise, {}};
  for (int64_t i = 0, n = channel_walk.count(); i < n; ++i, channel_walk.next())
    seen.channels.push_back(channel_walk.a);
  const int64_t q = g.stride > 2 ? g.stride : 2;
  for (size_t k = 0; k < pair_axes.size(); ++k) {
    const size_t along = static_cast<size_t>(pair_axes[k]);
    Walk pairs;
    for (size_t d = 0; d < g.shape.size(); ++d) {
      if (d == along)
        pairs.add(g.shape[d] / q, q * step[d], q * mask[d], q * texel[d]);
      else if (spatial[d])
        pairs.add(kept(g.shape[d], g.stride), g.stride * step[d], g.stride * mask[d],
                  g.stride * texel[d]);
      else
        pairs.add(g.shape[d], step[d], mask[d], 0);
    }
    double s00 = 0, s11 = 0, s01 = 0;
    const int64_t n = pairs.count();
    for (int64_t i = 0; i < n; ++i, pairs.next()) {
      const double x0 = static_cast<double>(noise_z(noise, pairs.a, seen(pairs.b, pairs.c)));
      const bool on1 = seen(pairs.b + mask[along], pairs.c + step[along]);
      const double x1 = static_cast<double>(noise_z(noise, pairs.a + step[along], on1));
      s00 += x0 * x0;
      s11 += x1 * x1;
      s01 += x0 * x1;
    }
    out[3 * k] = s00, out[3 * k + 1] = s11, out[3 * k + 2] = s01;
  }
  Walk sub;
  for (size_t d = 0; d < g.shape.size(); ++d) {
    const int64_t s = spatial[d] ? g.stride : 1;
    sub.add(spatial[d] ? kept(g.shape[d], g.stride) : g.shape[d], s * step[d], s * mask[d],
            s * texel[d]);
  }
  double zz = 0, yy = 0;
  const int64_t n = sub.count();
  for (int64_t i = 0; i < n; ++i, sub.next()) {
    const bool on = seen(sub.b, sub.c);
    const double a = static_cast<double>(noise_z(noise, sub.a, on));
    const double b = static_cast<double>(noise_y(noise, sub.a, on));
    zz += a * a;
    yy += b * b;
  }
  out[3 * pair_axes.size()] = zz, out[3 * pair_axes.size() + 1] = yy;
}

// The step at one entry (Step) of an observed texel: a, its offset in g.shape's arrays; b,
// in lam's (the sub-grid's).
template <typename T>
T step_at(const Step<T>& s, int64_t a, int64_t b) {
  const auto blended = [&](const T* x, const T* bx) {
    if (!s.blend) return bx[a];
    const T lam = s.lam[b];
    return std::fma(lam, x[a], (T(1) - lam) * bx[a]);
  };
  const T m = blended(s.m, s.bm), v = blended(s.v, s.bv);
  const T h = std::fma(v, s.inv_c2, s.eps_root);
  const T den = (h > T(0) ? std::sqrt(h) : T(0)) + s.eps;
  return den > T(0) ? (m * s.inv_c1) / den : T(0);
}

template <typename T>
double mean_step_norm(const Subgrid& g, const Step<T>& s) {
  Walk texels, channels;  // offsets into g.shape's arrays (a) and into the sub-grid's (b)
  walks(g, texels, channels);
  const int64_t n_texels = texels.count(), n_channels = channels.count();
  double total = 0;
  int64_t counted = 0;
  for (int64_t t = 0; t < n_texels; ++t, texels.next()) {
    bool finite = true, zero = true;
    channels.a = channels.b = 0;
    for (int64_t c = 0; c < n_channels; ++c, channels.next()) {
      const T x = s.grad[texels.a + channels.a];
      finite = finite && std::isfinite(x);
      zero = zero && x == T(0);
    }
    const bool observed = finite && !(s.drop_zero && zero);
    double sum = 0;
    channels.a = channels.b = 0;
    for (int64_t c = 0; c < n_channels; ++c, channels.next()) {
      const double d = observed ? static_cast<double>(step_at(s, texels.a + channels.a,
                                                              texels.b + channels.b))
                                : 0.0;
      sum += d * d;
    }
    if (std::isnan(sum)) continue;
    total += std::sqrt(sum);
    ++counted;
  }
  return counted ? total / static_cast<double>(counted) : 0.0;
}

template <typename T>
T blend(const Subgrid& g, const T* m, const T* v, const T* r, const Blend<T>& b, T* out) {
  Walk walk = subgrid_walk(g);
  const int64_t n = walk.count();
  std::vector<T> noise(static_cast<size_t>(n)), energy(noise), floor(noise), signal(noise);
  for (int64_t i = 0; i < n; ++i, walk.next()) {
    const T mm = m[walk.a] / b.c1;
    const T x = v[walk.a] / b.c2 - mm * mm;
    noise[i] = (((x < T(0) ? T(0) : x) * b.k) * b.ema) * b.corr_num / b.corr_den;
    const T rh = r[i] / b.bias;
    energy[i] = rh * rh;
  }
  Subgrid at_sub{walk.sizes, g.axes, 1};
  std::vector<T> work(static_cast<size_t>(subgrid_work_size(at_sub)));
  subgrid_average(at_sub, noise.data(), floor.data(), work.data());
  subgrid_average(at_sub, energy.data(), signal.data(), work.data());
  double total = 0;
  for (int64_t i = 0; i < n; ++i) {
    const bool on = b.usable > T(0) && signal[i] > T(0);
    T lam = T(1) - floor[i] / (b.gain * (signal[i] > T(0) ? signal[i] : T(1)));
    lam = on ? (lam < T(0) ? T(0) : lam > T(1) ? T(1) : lam) : T(0);  // NaN stays NaN
    lam = b.power == T(2) ? lam * lam : std::pow(lam, b.power);
    out[i] = lam;
    total += static_cast<double>(lam);
  }
  const T mean = static_cast<T>(total / static_cast<double>(n));
  const T open = (mean - b.low) / b.span;
  const T gate = open < T(0) ? T(0) : open > T(1) ? T(1) : open;
  for (int64_t i = 0; i < n; ++i) out[i] *= gate;
  return gate;
}

}  // namespace

std::string check_texel_grid(const Subgrid& g) {
  const std::string problem = check_subgrid(g);
  if (!problem.empty()) return problem;
  for (int64_t d : g.shape)
    if (d < 1) return "every dimension must be >= 1";
  return "";
}

int64_t texel_subgrid_size(const Subgrid& g) {
  Walk texels, channels;
  walks(g, texels, channels);
  return texels.count() * channels.count();
}

double texel_distance_mean(const Subgrid& g, const float* a, const float* b, float* kept) {
  return run(g, a, b, kept);
}

double texel_distance_mean(const Subgrid& g, const double* a, const double* b, double* kept) {
  return run(g, a, b, kept);
}

std::string check_noise_mask(const Subgrid& g, const std::vector<int64_t>& observed_shape) {
  if (observed_shape.size() != g.shape.size())
    return "the observed mask must have the gradient's rank";
  for (size_t d = 0; d < g.shape.size(); ++d)
    if (observed_shape[d] != g.shape[d] && observed_shape[d] != 1)
      return "each dimension of the observed mask must be the gradient's or 1";
  return "";
}

void correlation_sums(const Subgrid& g, const std::vector<int64_t>& pair_axes,
                      const Noise<float>& noise, double* out) {
  correlation(g, pair_axes, noise, out);
}

void correlation_sums(const Subgrid& g, const std::vector<int64_t>& pair_axes,
                      const Noise<double>& noise, double* out) {
  correlation(g, pair_axes, noise, out);
}

double step_norm(const Subgrid& g, const Step<float>& s) { return mean_step_norm(g, s); }

double step_norm(const Subgrid& g, const Step<double>& s) { return mean_step_norm(g, s); }

float blend_weights(const Subgrid& g, const float* m, const float* v, const float* r,
                    const Blend<float>& b, float* out) {
  return blend(g, m, v, r, b, out);
}

double blend_weights(const Subgrid& g, const double* m, const double* v, const double* r,
                     const Blend<double>& b, double* out) {
  return blend(g, m, v, r, b, out);
}

}  // namespace optax_bilateral
