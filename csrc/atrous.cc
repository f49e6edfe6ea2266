// The cascade's driver: separable levels in place, other passes alternating between the output
// and one working copy, threads, and the choice of instruction set.
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

// A 2-D grid's rows shorter than kShortRow points run kGroupPoints points of a chain's rows
// at a time as one run (SlabLevel::group_rows); longer rows lose more to the gathering than
// the fewer calls save.
constexpr int64_t kShortRow = 512, kGroupPoints = 2048;

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
void chunk(const PassArgs<T>& a, const SlabLevel<T>& l, const SlabPlanes<const T>& from,
           const SlabPlanes<T>& to, bool in_place, const Chunk<T>& ch, Scratch<T>& s) {
  switch (kIsa) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (std::is_same_v<T, float>) return avx512::chunk32(a, l, from, to, in_place, ch, s);
      else return avx512::chunk64(a, l, from, to, in_place, ch, s);
    case Isa::kAvx2:
      if constexpr (std::is_same_v<T, float>) return avx2::chunk32(a, l, from, to, in_place, ch, s);
      else return avx2::chunk64(a, l, from, to, in_place, ch, s);
#endif
    default:
      if constexpr (std::is_same_v<T, float>) return baseline::chunk32(a, l, from, to, in_place, ch, s);
      else return baseline::chunk64(a, l, from, to, in_place, ch, s);
  }
}

template <typename T>
void full_chunk(const PassArgs<T>& a, const SlabPass& pass, const Chunk<T>& ch, Scratch<T>& s) {
  switch (kIsa) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (std::is_same_v<T, float>) return avx512::full32(a, pass, ch, s);
      else return avx512::full64(a, pass, ch, s);
    case Isa::kAvx2:
      if constexpr (std::is_same_v<T, float>) return avx2::full32(a, pass, ch, s);
      else return avx2::full64(a, pass, ch, s);
#endif
    default:
      if constexpr (std::is_same_v<T, float>) return baseline::full32(a, pass, ch, s);
      else return baseline::full64(a, pass, ch, s);
  }
}

// A block of a pass: rows [r0, r1), columns [c0, c1) of its view.
struct Block {
  int64_t r0, r1, c0, c1;
};

template <typename T>
std::vector<Block> cut_blocks(const Pass& pass, int64_t channels) {
  const int64_t rows = pass.rows(), L = pass.row_length;
  const int64_t per_point = (channels + 1) * static_cast<int64_t>(sizeof(T));
  int64_t most = 0;
  for (const Pair& p : pass.pairs) most = std::max(most, p.column_offset);
  // Whole rows, or one row (a 1-D grid) cut in blocks that recompute at most 1/4 of their
  // weights (those of the `o` points before them).
  const int64_t width = rows == 1 ? std::min(L, std::max(kBlockBytes / per_point, 4 * most)) : L;
  const int64_t height = std::min(rows, std::max<int64_t>(1, kBlockBytes / (per_point * L)));
  std::vector<Block> blocks;
  for (int64_t r0 = 0; r0 < rows; r0 += height)
    for (int64_t c0 = 0; c0 < L; c0 += width)
      blocks.push_back({r0, std::min(rows, r0 + height), c0, std::min(L, c0 + width)});
  return blocks;
}

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

// The separable levels of a grid of rank >= 2, each swept slab by slab.
template <typename T>
std::vector<SlabLevel<T>> plan_levels(const Cascade<T>& c) {
  std::vector<SlabLevel<T>> levels;
  const std::vector<int64_t> inner_shape(c.shape.begin() + 1, c.shape.end());
  for (int i = c.start; i < c.levels; ++i) {
    SlabLevel<T> level;
    level.slabs = c.shape[0];
    level.slab = 1;
    for (int64_t k : inner_shape) level.slab *= k;
    level.stride = int64_t{1} << i;
    level.inner = make_passes(inner_shape, i + 1, i, true);
    if (inner_shape.size() == 1 && level.inner.size() == 1 && level.slab < kShortRow)
      level.group_rows = std::max<int64_t>(1, kGroupPoints / level.slab);
    if (level.stride < c.shape[0] || !level.inner.empty()) levels.push_back(std::move(level));
  }
  return levels;
}

// Runs `units` units of work, unit k as do_unit(k, scratch), on the calling thread and on
// up to threads - 1 helpers; returns when all are done.
template <typename T, typename F>
void parallel(const Cascade<T>& c, int threads, size_t units, const F& do_unit) {
  run_claimed<Scratch<T>>(units, threads, c.schedule, do_unit);
}

// The instruction set's build of kernel.h's split_planes: n points of a field of nc
// interleaved channels into the planes dst[0..nc).
template <typename T>
void split(const T* src, T* const* dst, int64_t nc, int64_t n) {
  constexpr bool f32 = std::is_same_v<T, float>;
  switch (kIsa) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (f32) return avx512::split32(src, dst, nc, n);
      else return avx512::split64(src, dst, nc, n);
    case Isa::kAvx2:
      if constexpr (f32) return avx2::split32(src, dst, nc, n);
      else return avx2::split64(src, dst, nc, n);
#endif
    default:
      if constexpr (f32) return baseline::split32(src, dst, nc, n);
      else return baseline::split64(src, dst, nc, n);
  }
}

// The fields ((points, c_k) each, interleaved) into their outputs' memory, each slab's
// channels as planes one after another (SlabPlanes): where every level then works in place.
template <typename T>
void split_fields(const Cascade<T>& c, int threads, int64_t slab) {
  const int64_t n0 = c.shape[0];
  const int64_t group = std::max<int64_t>(1, (int64_t{1} << 14) / slab);  // slabs per unit
  const size_t units = static_cast<size_t>((n0 + group - 1) / group);
  parallel(c, threads, units, [&](size_t k, Scratch<T>&) {
    const int64_t i1 = std::min(n0, (static_cast<int64_t>(k) + 1) * group);
    std::vector<T*> dst;
    for (int64_t i = static_cast<int64_t>(k) * group; i < i1; ++i) {
      for (size_t f = 0; f < c.x_fields.size(); ++f) {
        const int64_t nc = c.x_fields[f].second;
        const T* src = c.x_fields[f].first + i * slab * nc;
        T* out = c.out_fields[f].first + i * slab * nc;
        dst.resize(static_cast<size_t>(nc));
        for (int64_t q = 0; q < nc; ++q) dst[q] = out + q * slab;
        split(src, dst.data(), nc, slab);
      }
    }
  });
}

// A level's units: each chain of slabs (Chunk) whole, or cut in pieces where there are more
// threads than chains. Pieces of a level that runs in place get copies of the originals their
// neighbours overwrite, taken here, before any is written (into `copies`).
template <typename T>
std::vector<Chunk<T>> plan_chunks(const SlabLevel<T>& level, int threads, bool in_place,
                                  const SlabPlanes<const T>& from, int64_t channels,
                                  std::vector<T>& copies) {
  const int64_t n0 = level.slabs, M = level.slab, C = channels;
  const bool axis0 = level.stride < n0;
  const int64_t chains = axis0 ? level.stride : 1, step = axis0 ? level.stride : 1;
  const int64_t pieces = axis0 ? (threads + chains - 1) / chains : threads;
  std::vector<Chunk<T>> chunks;
  for (int64_t r = 0; r < chains; ++r) {
    const int64_t len = (n0 - r + step - 1) / step;
    const int64_t k = std::clamp<int64_t>(pieces, 1, len);
    for (int64_t j = 0; j < k; ++j) chunks.push_back({r, len * j / k, len * (j + 1) / k, len});
  }
  if (!(in_place && axis0) || static_cast<int64_t>(chunks.size()) == chains) return chunks;
  const int64_t block = 2 * C * M;  // two slabs' originals
  copies.assign(static_cast<size_t>(2 * block) * chunks.size(), T(0));
  for (size_t u = 0; u < chunks.size(); ++u) {
    Chunk<T>& ch = chunks[u];
    T* before = copies.data() + 2 * block * static_cast<int64_t>(u);
    T* after = before + block;
    // Slot s of `before` holds position first - 2 + s; of `after`, position last + s.
    for (int s = 0; s < 2; ++s) {
      const int64_t pb = ch.first - 2 + s, pa = ch.last + s;
      for (int64_t c = 0; c < C; ++c) {
        if (pb >= 0)
          std::copy_n(from.at(ch.residue + pb * step, static_cast<size_t>(c)), M,
                      before + (s * C + c) * M);
        if (pa < ch.length)
          std::copy_n(from.at(ch.residue + pa * step, static_cast<size_t>(c)), M,
                      after + (s * C + c) * M);
      }
    }
    ch.before = before;
    ch.after = after;
  }
  return chunks;
}

// A separable cascade on a grid of rank >= 2: every level in place in the output's memory
// (the first from the input, or from the fields split into that memory), so no working copy.
template <typename T>
void run_levels(const Cascade<T>& c, const PassArgs<T>& args, int threads, int64_t points) {
  const std::vector<SlabLevel<T>> levels = plan_levels(c);
  const int64_t M = points / c.shape[0];
  const bool interleaved = !c.x_fields.empty();
  SlabPlanes<T> out;
  SlabPlanes<const T> input;
  if (interleaved) {
    for (const auto& [field, nc] : c.out_fields)
      for (int64_t q = 0; q < nc; ++q) {
        out.base.push_back(field + q * M);
        out.stride.push_back(M * nc);
      }
    split_fields(c, threads, M);
  } else {
    for (int64_t ch = 0; ch < c.channels; ++ch) {
      out.base.push_back(c.out + ch * points);
      out.stride.push_back(M);
      input.base.push_back(c.x + ch * points);
      input.stride.push_back(M);
    }
  }
  const SlabPlanes<const T> own{{out.base.begin(), out.base.end()}, out.stride};
  if (interleaved) input = own;
  for (size_t k = 0; k < levels.size(); ++k) {
    const bool in_place = interleaved || k > 0;
    const SlabPlanes<const T>& from = k == 0 ? input : own;
    PassArgs<T> a = args;
    if (interleaved && k + 1 == levels.size()) a.interleaved = &c.out_fields;
    std::vector<T> copies;
    const std::vector<Chunk<T>> chunks =
        plan_chunks(levels[k], threads, in_place, from, c.channels, copies);
    parallel(c, threads, chunks.size(), [&](size_t u, Scratch<T>& s) {
      chunk(a, levels[k], from, out, in_place, chunks[u], s);
    });
  }
}

// Steps 0 .. n-1 of a cascade run out of place, step i as step(i, a) with a.x and a.y set:
// alternating between the output and the working copy, so that the last step writes the output.
template <typename T, typename F>
void alternate(const Cascade<T>& c, const PassArgs<T>& args, size_t n, int64_t points,
               const F& step) {
  std::vector<const T*> in_ch(static_cast<size_t>(c.channels));
  std::vector<T*> work_ch(in_ch.size()), out_ch(in_ch.size());
  for (int64_t ch = 0; ch < c.channels; ++ch) {
    in_ch[ch] = c.x + ch * points;
    work_ch[ch] = c.work + ch * points;
    out_ch[ch] = c.out + ch * points;
  }
  for (size_t i = 0; i < n; ++i) {
    PassArgs<T> a = args;
    const bool to_out = (n - 1 - i) % 2 == 0;
    a.y = to_out ? out_ch.data() : work_ch.data();
    a.x = i == 0 ? in_ch.data() : to_out ? work_ch.data() : out_ch.data();
    step(i, a);
  }
}

// A cascade on a 1-D grid: one step per pass, each cut into blocks.
template <typename T>
void run_passes(const Cascade<T>& c, const PassArgs<T>& args, const std::vector<Pass>& passes,
                int threads, int64_t points) {
  alternate(c, args, passes.size(), points, [&](size_t i, PassArgs<T>& a) {
    a.pass = &passes[i];
    const std::vector<Block> blocks = cut_blocks<T>(passes[i], c.channels);
    parallel(c, threads, blocks.size(), [&](size_t k, Scratch<T>& scratch) {
      block(a, blocks[k].r0, blocks[k].r1, blocks[k].c0, blocks[k].c1, scratch);
    });
  });
}

// The chains of a full pass's slabs, each whole, or cut in pieces where there are more threads
// than chains (each piece recomputes the weights its first slabs read from before it).
template <typename T>
std::vector<Chunk<T>> plan_slab_chunks(const SlabPass& pass, int threads) {
  const int64_t chains = std::min(pass.stride, pass.slabs);
  const int64_t pieces = (threads + chains - 1) / chains;
  std::vector<Chunk<T>> chunks;
  for (int64_t r = 0; r < chains; ++r) {
    const int64_t len = (pass.slabs - r + pass.stride - 1) / pass.stride;
    const int64_t k = std::clamp<int64_t>(pieces, 1, len);
    for (int64_t j = 0; j < k; ++j) chunks.push_back({r, len * j / k, len * (j + 1) / k, len});
  }
  return chunks;
}

// A full cascade on a grid of rank >= 2: one step per level, slab by slab.
template <typename T>
void run_full(const Cascade<T>& c, const PassArgs<T>& args, int threads, int64_t points) {
  const std::vector<SlabPass> passes = make_slab_passes(c.shape, c.levels, c.start);
  alternate(c, args, passes.size(), points, [&](size_t i, PassArgs<T>& a) {
    const std::vector<Chunk<T>> chunks = plan_slab_chunks<T>(passes[i], threads);
    parallel(c, threads, chunks.size(), [&](size_t k, Scratch<T>& scratch) {
      full_chunk(a, passes[i], chunks[k], scratch);
    });
  });
}

template <typename T>
void run(const Cascade<T>& c) {
  int64_t points = 1;
  for (int64_t n : c.shape) points *= n;
  const std::vector<Pass> passes = make_passes(c.shape, c.levels, c.start, c.separable);
  const int64_t size = c.channels * points;
  if (passes.empty() || points == 0) {
    if (c.x_fields.empty()) {
      std::copy(c.x, c.x + size, c.out);
      return;
    }
    for (size_t f = 0; f < c.x_fields.size(); ++f)
      std::copy(c.x_fields[f].first, c.x_fields[f].first + points * c.x_fields[f].second,
                c.out_fields[f].first);
    return;
  }
  int threads = std::max(1, c.threads);
  if (size < c.min_parallel_work) threads = 1;
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
  if (c.separable && c.shape.size() >= 2) return run_levels(c, args, threads, points);
  if (c.shape.size() >= 2) return run_full(c, args, threads, points);
  run_passes(c, args, passes, threads, points);
}

}  // namespace

void run_cascade(const Cascade<float>& c) { run(c); }
void run_cascade(const Cascade<double>& c) { run(c); }

std::string instruction_set() { return isa_name(kIsa); }

}  // namespace optax_bilateral
