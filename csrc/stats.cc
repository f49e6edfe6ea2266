// csrc/stats.h's statistics: plain loops over the sub-grid (at most ~2^17 texels per leaf).
#include "stats.h"

#include <cmath>
#include <vector>

namespace optax_bilateral {

namespace {

int64_t kept(int64_t n, int64_t stride) { return (n - 1) / stride + 1; }

// A row-major walk over `sizes` that keeps an offset into a and one into b, each with its own
// step per axis.
struct Walk {
  std::vector<int64_t> sizes, step_a, step_b, idx;
  int64_t a = 0, b = 0;

  void add(int64_t size, int64_t sa, int64_t sb) {
    sizes.push_back(size);
    step_a.push_back(sa);
    step_b.push_back(sb);
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
      if (++idx[d] < sizes[d]) return;
      a -= step_a[d] * sizes[d];
      b -= step_b[d] * sizes[d];
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
double run(const Subgrid& g, const T* a, const T* b) {
  Walk texels, channels;
  walks(g, texels, channels);
  const int64_t n_texels = texels.count(), n_channels = channels.count();
  double total = 0;
  int64_t counted = 0;
  for (int64_t t = 0; t < n_texels; ++t, texels.next()) {
    double sum = 0;
    channels.a = channels.b = 0;
    for (int64_t c = 0; c < n_channels; ++c, channels.next()) {
      const double x = static_cast<double>(a[texels.a + channels.a]) -
                       (b ? static_cast<double>(b[texels.b + channels.b]) : 0.0);
      sum += x * x;
    }
    if (std::isnan(sum)) continue;
    total += std::sqrt(sum);
    ++counted;
  }
  return counted ? total / static_cast<double>(counted) : 0.0;
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

double texel_distance_mean(const Subgrid& g, const float* a, const float* b) {
  return run(g, a, b);
}

double texel_distance_mean(const Subgrid& g, const double* a, const double* b) {
  return run(g, a, b);
}

}  // namespace optax_bilateral
