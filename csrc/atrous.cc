// The cascade's driver: passes, the ping-pong between the output and one working copy,
// threads, and the choice of instruction set.
#include "atrous.h"

#include <algorithm>
#include <cmath>
#include <atomic>
#include <condition_variable>
#include <memory>
#include <cstdlib>
#include <limits>
#include <mutex>
#include <string>
#include <thread>
#include <type_traits>

#include "isa.h"
#include "kernel_isa.h"
#include "passes.h"

namespace optax_bilateral {
namespace {

// The bytes a block's sums (its fields and normaliser) should take: within L2.
constexpr int64_t kBlockBytes = 256 * 1024;
// Below this many point-channels a cascade runs on the calling thread alone: starting
// threads costs more than they save.
constexpr int64_t kMinParallelWork = 1 << 15;

const Isa kIsa = cpu_isa();

// The instruction set's build of one block (kernel.h, run_block) or of one level's slabs.
template <typename T>
void block(const PassArgs<T>& a, int64_t r0, int64_t r1, int64_t c0, int64_t c1, Scratch<T>& s) {
  constexpr bool f32 = std::is_same_v<T, float>;
  switch (kIsa) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (f32) return avx512::block32(a, r0, r1, c0, c1, s);
      else return avx512::block64(a, r0, r1, c0, c1, s);
    case Isa::kAvx2:
      if constexpr (f32) return avx2::block32(a, r0, r1, c0, c1, s);
      else return avx2::block64(a, r0, r1, c0, c1, s);
#endif
    default:
      if constexpr (f32) return baseline::block32(a, r0, r1, c0, c1, s);
      else return baseline::block64(a, r0, r1, c0, c1, s);
  }
}

template <typename T>
void slabs(const PassArgs<T>& a, const SlabLevel<T>& l, int64_t i0, int64_t i1, Scratch<T>& s) {
  switch (kIsa) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (std::is_same_v<T, float>) return avx512::slabs32(a, l, i0, i1, s);
      else return avx512::slabs64(a, l, i0, i1, s);
    case Isa::kAvx2:
      if constexpr (std::is_same_v<T, float>) return avx2::slabs32(a, l, i0, i1, s);
      else return avx2::slabs64(a, l, i0, i1, s);
#endif
    default:
      if constexpr (std::is_same_v<T, float>) return baseline::slabs32(a, l, i0, i1, s);
      else return baseline::slabs64(a, l, i0, i1, s);
  }
}

// A block of a pass: rows [r0, r1), columns [c0, c1) of its view.
struct Block {
  int64_t r0, r1, c0, c1;
};

template <typename T>
std::vector<Block> cut_blocks(const Pass& pass, int64_t channels) {
  const int64_t rows = pass.rows(), L = pass.row_length;
  int64_t reach = 0;  // the most rows a pair spans: a block recomputes that many rows' weights
  for (const Pair& p : pass.pairs) reach = std::max(reach, p.flat_rows);
  const int64_t per_point = (channels + 1) * static_cast<int64_t>(sizeof(T));
  int64_t width = L;
  int64_t height = std::max<int64_t>(1, kBlockBytes / (per_point * L));
  if (reach > 0) height = std::max(height, 4 * reach);  // recompute at most 1/4 of the rows
  if (pass.column_tiles) {
    width = std::clamp<int64_t>(kBlockBytes / (per_point * height) / 16 * 16, 16, L);
  }
  height = std::min(height, rows);
  std::vector<Block> blocks;
  for (int64_t r0 = 0; r0 < rows; r0 += height)
    for (int64_t c0 = 0; c0 < L; c0 += width)
      blocks.push_back({r0, std::min(rows, r0 + height), c0, std::min(L, c0 + width)});
  return blocks;
}

// One step's units of work, claimed one at a time by the caller and its helpers. Shared,
// so that a helper that starts after the step ended only reads that nothing is left.
struct Claims {
  explicit Claims(size_t n) : total(n) {}
  const size_t total;
  std::atomic<size_t> next{0}, done{0};
  std::mutex mutex;
  std::condition_variable finished;
};

// The largest finite |x[i]|, i in [lo, hi), 0 if none: as the integer maximum of the bits
// (non-negative floats order as their bits), which vectorises where a float maximum does not.
template <typename T>
T largest_finite_magnitude(const T* __restrict__ x, int64_t lo, int64_t hi) {
  using I = std::conditional_t<sizeof(T) == 4, int32_t, int64_t>;
  const I magnitude = std::numeric_limits<I>::max();  // every bit but the sign
  const I inf = __builtin_bit_cast(I, std::numeric_limits<T>::infinity());
  I m = 0;
  for (int64_t i = lo; i < hi; ++i) {
    const I u = __builtin_bit_cast(I, x[i]) & magnitude;
    const I finite = u < inf ? u : 0;  // inf and NaN count as 0
    m = finite > m ? finite : m;
  }
  return __builtin_bit_cast(T, m);
}

template <typename T, typename F>
void parallel(const Cascade<T>& c, int threads, size_t units, const F& do_unit);

// (guide scale, sigma_d scaled alike) as bilateral.rescale_guide and the one-channel halving.
template <typename T>
std::pair<T, T> guide_scale(const Cascade<T>& c, int threads, int64_t points) {
  if (c.guide_channels == 1) return {T(0.5), c.sigma_d * T(0.5)};
  const int64_t total = c.guide_channels * points;
  const int64_t chunk = 1 << 16;
  std::vector<T> largest(static_cast<size_t>((total + chunk - 1) / chunk), T(0));
  parallel(c, threads, largest.size(), [&](size_t k, Scratch<T>&) {
    const int64_t lo = static_cast<int64_t>(k) * chunk;
    largest[k] = largest_finite_magnitude(c.guide, lo, std::min(total, lo + chunk));
  });
  const T m = largest.empty() ? T(0) : *std::max_element(largest.begin(), largest.end());
  int e = 0;
  std::frexp(m, &e);  // m < 2^e
  const int limit = std::numeric_limits<T>::max_exponent / 2 - 8;
  const int k = std::max(e - limit, 0);
  const T inv = std::ldexp(T(1), -k);
  return {inv, c.sigma_d * inv};
}

// One step of a cascade: a pass cut into blocks, or a separable level swept by slabs.
template <typename T>
struct Step {
  const Pass* pass = nullptr;
  std::vector<Block> blocks;
  SlabLevel<T> level;  // used when pass is null
};

template <typename T>
std::vector<Step<T>> plan_steps(const Cascade<T>& c, const std::vector<Pass>& passes) {
  std::vector<Step<T>> steps;
  const size_t n = c.shape.size();
  if (c.separable && n >= 2) {
    const std::vector<int64_t> inner_shape(c.shape.begin() + 1, c.shape.end());
    for (int i = c.start; i < c.levels; ++i) {
      Step<T> step;
      step.level.slabs = c.shape[0];
      step.level.slab = 1;
      for (int64_t k : inner_shape) step.level.slab *= k;
      step.level.stride = int64_t{1} << i;
      step.level.inner = make_passes(inner_shape, i + 1, i, true);
      if (step.level.stride < c.shape[0] || !step.level.inner.empty())
        steps.push_back(std::move(step));
    }
    return steps;
  }
  for (const Pass& p : passes) {
    Step<T> step;
    step.pass = &p;
    step.blocks = cut_blocks<T>(p, c.channels);
    steps.push_back(std::move(step));
  }
  return steps;
}

// Runs `units` units of work, unit k as do_unit(k, scratch), on the calling thread and on
// up to threads - 1 helpers; returns when all are done.
template <typename T, typename F>
void parallel(const Cascade<T>& c, int threads, size_t units, const F& do_unit) {
  auto claims = std::make_shared<Claims>(units);
  auto work = [claims, &do_unit, units] {
    Scratch<T> scratch;
    for (size_t k; (k = claims->next.fetch_add(1)) < units;) {
      do_unit(k, scratch);
      if (claims->done.fetch_add(1) + 1 == units) {
        std::lock_guard<std::mutex> lock(claims->mutex);
        claims->finished.notify_all();
      }
    }
  };
  const int helpers = static_cast<int>(std::min<size_t>(static_cast<size_t>(threads), units)) - 1;
  std::vector<std::thread> own;
  for (int t = 0; t < helpers; ++t) {
    if (c.schedule) {
      c.schedule(work);
    } else {
      own.emplace_back(work);
    }
  }
  work();
  {
    std::unique_lock<std::mutex> lock(claims->mutex);
    claims->finished.wait(lock, [&] { return claims->done.load() == units; });
  }
  for (auto& th : own) th.join();
}

// Points [lo, hi) of a field of kC interleaved channels into the planes dst[0..kC): one
// sweep over the field, each point's channels together (kC a constant, so it vectorises).
template <typename T, int kC>
void split_channels(const T* __restrict__ src, T* const* dst, int64_t lo, int64_t hi) {
  T* __restrict__ d[kC];
  for (int q = 0; q < kC; ++q) d[q] = dst[q];
  for (int64_t p = lo; p < hi; ++p)
    for (int q = 0; q < kC; ++q) d[q][p] = src[p * kC + q];
}

// The channels of `fields` ((points, c_k) each, interleaved) as planes `planes[c]`.
template <typename T>
void deinterleave(const Cascade<T>& c, int threads, int64_t points,
                  const std::vector<T*>& planes) {
  const int64_t chunk = 1 << 14;
  const size_t units = static_cast<size_t>((points + chunk - 1) / chunk);
  parallel(c, threads, units, [&](size_t k, Scratch<T>&) {
    const int64_t lo = static_cast<int64_t>(k) * chunk;
    const int64_t hi = std::min(points, lo + chunk);
    size_t ch = 0;
    for (const auto& [field, nc] : c.x_fields) {
      T* const* dst = planes.data() + ch;
      ch += static_cast<size_t>(nc);
      switch (nc) {
        case 1: split_channels<T, 1>(field, dst, lo, hi); continue;
        case 2: split_channels<T, 2>(field, dst, lo, hi); continue;
        case 3: split_channels<T, 3>(field, dst, lo, hi); continue;
        case 4: split_channels<T, 4>(field, dst, lo, hi); continue;
        default: break;
      }
      for (int64_t q = 0; q < nc; ++q) {
        T* __restrict__ d = dst[q];
        for (int64_t p = lo; p < hi; ++p) d[p] = field[p * nc + q];
      }
    }
  });
}

// Bounds of `threads` slab ranges of about equal cost: a range that does not start at slab 0
// first recomputes the axis-0 weights of the 3 st slabs before it (one pair each, about a
// quarter of a slab's work), so it gets fewer slabs.
template <typename T>
std::vector<int64_t> slab_ranges(const SlabLevel<T>& level, int threads) {
  const int64_t n0 = level.slabs, st = level.stride;
  const int64_t t = std::max<int64_t>(1, std::min<int64_t>(threads, n0));
  const int64_t halo = st < n0 ? (std::min(st, n0) + std::min(2 * st, n0)) / 4 : 0;
  const int64_t share = (n0 + (t - 1) * halo + t - 1) / t;  // cost per range, rounded up
  std::vector<int64_t> bounds = {0};
  for (int64_t k = 1; k < t; ++k) {
    const int64_t next = bounds.back() + share - (k > 1 ? halo : 0);
    bounds.push_back(std::clamp<int64_t>(next, bounds.back() + 1, n0 - (t - k)));
  }
  bounds.push_back(n0);
  return bounds;
}

template <typename T>
void run(const Cascade<T>& c) {
  int64_t points = 1;
  for (int64_t n : c.shape) points *= n;
  const std::vector<Pass> passes = make_passes(c.shape, c.levels, c.start, c.separable);
  const int64_t size = c.channels * points;
  const bool interleaved = !c.x_fields.empty();
  if (passes.empty() || points == 0) {
    if (!interleaved) {
      std::copy(c.x, c.x + size, c.out);
      return;
    }
    for (size_t f = 0; f < c.x_fields.size(); ++f)
      std::copy(c.x_fields[f].first, c.x_fields[f].first + points * c.x_fields[f].second,
                c.out_fields[f].first);
    return;
  }
  int threads = std::max(1, c.threads);
  if (size < kMinParallelWork) threads = 1;
  const auto [scale, sigma] = guide_scale(c, threads, points);
  PassArgs<T> args{};
  args.guide = c.guide;
  args.valid = c.valid;
  args.channels = c.channels;
  args.guide_channels = c.guide_channels;
  args.guide_stride = points;
  args.guide_scale = scale;
  args.sigma_inf = std::isinf(sigma);
  args.neg_inv_sigma = sigma > 0 ? T(-1) / sigma : -std::numeric_limits<T>::infinity();
  const std::vector<Step<T>> steps = plan_steps(c, passes);
  const size_t ns = steps.size();
  // The channels of the buffers the steps read and write: the input, the working copy and
  // the output (with interleaved outputs: their memory, as planes, for the steps before the
  // last one).
  std::vector<const T*> in_ch(static_cast<size_t>(c.channels));
  std::vector<T*> work_ch(static_cast<size_t>(c.channels)), out_ch(work_ch.size());
  for (int64_t ch = 0; ch < c.channels; ++ch) {
    work_ch[ch] = c.work + ch * points;
    if (!interleaved) {
      in_ch[ch] = c.x + ch * points;
      out_ch[ch] = c.out + ch * points;
    }
  }
  if (interleaved) {
    size_t ch = 0;
    for (const auto& [field, nc] : c.out_fields)
      for (int64_t q = 0; q < nc; ++q) out_ch[ch++] = field + q * points;
  }
  // Planar: step i writes `out` when the steps after it are even in number, so the last
  // writes `out` and the first reads the input. Interleaved: the last step reads the working
  // copy and writes the outputs; the planes of the input go first to whichever buffer the
  // steps' alternation starts from.
  auto writes_out = [&](size_t i) { return (ns - 1 - i) % 2 == 0; };
  if (interleaved) {
    const bool first_to_out = ns % 2 == 0;  // then step 0 reads out's memory
    deinterleave(c, threads, points, first_to_out ? out_ch : work_ch);
    for (int64_t ch = 0; ch < c.channels; ++ch)
      in_ch[ch] = first_to_out ? out_ch[ch] : work_ch[ch];
  }
  for (size_t i = 0; i < ns; ++i) {
    PassArgs<T> a = args;
    const bool to_out = writes_out(i);
    a.y = to_out ? out_ch.data() : work_ch.data();
    const T* const* prev = to_out ? work_ch.data() : out_ch.data();
    a.x = i == 0 ? in_ch.data() : prev;
    if (interleaved && i + 1 == ns) a.interleaved = &c.out_fields;
    const Step<T>& step = steps[i];
    a.pass = step.pass;
    // Units: a pass's blocks, or a level's slabs in one range per thread.
    const std::vector<int64_t> bounds = step.pass ? std::vector<int64_t>{}
                                                  : slab_ranges(step.level, threads);
    const size_t units = step.pass ? step.blocks.size() : bounds.size() - 1;
    parallel(c, threads, units, [&](size_t k, Scratch<T>& scratch) {
      if (step.pass) {
        const Block& b = step.blocks[k];
        block(a, b.r0, b.r1, b.c0, b.c1, scratch);
      } else {
        slabs(a, step.level, bounds[k], bounds[k + 1], scratch);
      }
    });
  }
}

}  // namespace

void run_cascade(const Cascade<float>& c) { run(c); }
void run_cascade(const Cascade<double>& c) { run(c); }

std::string instruction_set() { return isa_name(kIsa); }

}  // namespace optax_bilateral
