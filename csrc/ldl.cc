// The LDL^T solve's driver: the factor's checks, each block's parts on threads, and the
// instruction set's build of the sweeps.
#include "ldl.h"

#include <algorithm>
#include <mutex>
#include <unordered_map>
#include <type_traits>
#include <vector>

#include "isa.h"
#include "kernel_isa.h"

namespace optax_bilateral {
namespace {

// Helpers only for at least this many multiply-adds a thread (the factor's values times the
// block's width): a smaller solve costs more to hand out than it saves.
constexpr int64_t kMinWorkPerThread = int64_t{1} << 18;
// The widest block one sweep takes: wider blocks read the factor fewer times, and beyond this
// the rows of a block no longer fit the cache (docs/triangle_mesh.md has the measurements).
constexpr int64_t kMaxWidth = 64;

template <typename T>
void step(const LdlFactor<T>& f, const LdlBlock<T>& blk, LdlStep which, int64_t p) {
  constexpr bool f32 = std::is_same_v<T, float>;
  switch (cpu_isa()) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (f32) return avx512::ldl32(f, blk, which, p);
      else return avx512::ldl64(f, blk, which, p);
    case Isa::kAvx2:
      if constexpr (f32) return avx2::ldl32(f, blk, which, p);
      else return avx2::ldl64(f, blk, which, p);
#endif
    default:
      if constexpr (f32) return baseline::ldl32(f, blk, which, p);
      else return baseline::ldl64(f, blk, which, p);
  }
}

// The working rows kept between solves, at most this many bytes in all: a buffer allocated
// afresh on every call pays its page faults each time, and an optimisation's updates solve
// the same sizes again.
constexpr size_t kKeptBytes = size_t{64} << 20;

template <typename T>
SolveBuffers<T>& buffers() {
  static auto* pool = new SolveBuffers<T>(kKeptBytes);  // never destroyed, as store() below
  return *pool;
}

struct NoState {};

template <typename T>
void solve(const LdlFactor<T>& f, T* b, int64_t k, int threads, const Schedule& schedule,
           LdlRows rows) {
  if (f.n == 0 || k == 0) return;
  const int64_t blocks = (k + kMaxWidth - 1) / kMaxWidth;
  const int64_t stride = std::max<int64_t>(4, (k + blocks - 1) / blocks);
  const bool in_place = rows == LdlRows::kFactor && blocks == 1 && stride == k;
  const int64_t own = f.parts * (f.n - f.top()) * stride;
  const int64_t work = f.block_ptr[f.supernodes] * stride;
  const int workers = static_cast<int>(
      std::max<int64_t>(1, std::min<int64_t>(threads, work / kMinWorkPerThread)));
  LdlFactor<T> g = f;
  if (rows == LdlRows::kFactor) g.perm = nullptr;
  auto buffer = buffers<T>().take(static_cast<size_t>(own + (in_place ? 0 : f.n * stride)));
  T* base = buffer.data.get();
  // A block's steps before the next block's, while its rows are in the cache.
  for (int64_t i = 0; i < blocks; ++i) {
    const LdlBlock<T> blk{b,      k, k * i / blocks, k * (i + 1) / blocks, stride,
                          in_place ? b : base + own, base};
    for (LdlStep which : {LdlStep::kPartForward, LdlStep::kTop, LdlStep::kPartBackward}) {
      const size_t units = which == LdlStep::kTop ? 1 : static_cast<size_t>(f.parts);
      run_claimed<NoState>(units, workers, schedule, [&](size_t p, NoState&) {
        step(g, blk, which, static_cast<int64_t>(p));
      });
    }
  }
  buffers<T>().give_back(std::move(buffer));
}

}  // namespace

namespace {

template <typename T>
const char* check(const LdlFactor<T>& f, int64_t num_rows, int64_t num_values) {
  const int64_t n = f.n, ns = f.supernodes;
  if (n < 0 || ns < 0 || num_rows < 0 || num_values < 0) return "sizes must be non-negative";
  if (f.first[0] != 0 || f.first[ns] != n) return "first must run from 0 to n";
  if (f.row_ptr[0] != 0 || f.row_ptr[ns] != num_rows)
    return "row_ptr must run from 0 to the rows' count";
  if (f.block_ptr[0] != 0 || f.block_ptr[ns] != num_values)
    return "block_ptr must run from 0 to the values' count";
  for (int64_t k = 0; k < ns; ++k) {
    const int64_t s = int64_t{f.first[k + 1]} - f.first[k];
    const int64_t r = int64_t{f.row_ptr[k + 1]} - f.row_ptr[k];
    if (s < 1) return "every supernode must have at least one column";
    if (r < 0) return "row_ptr must not decrease";
    if (f.block_ptr[k + 1] - f.block_ptr[k] != (s + r) * s)
      return "each block must hold (columns + rows below) x columns values";
    int64_t last = int64_t{f.first[k + 1]} - 1;
    for (int64_t i = f.row_ptr[k]; i < f.row_ptr[k + 1]; ++i) {
      if (f.rows[i] <= last || f.rows[i] >= n)
        return "the rows below a supernode must increase, past its columns, within n";
      last = f.rows[i];
    }
  }
  if (f.parts < 1) return "there must be at least one part";
  if (f.part_ptr[0] != 0 || f.part_ptr[f.parts] > ns)
    return "part_ptr must run from 0 to at most the supernodes' count";
  for (int64_t p = 0; p < f.parts; ++p)
    if (f.part_ptr[p + 1] < f.part_ptr[p]) return "part_ptr must not decrease";
  // A part's rows below stay within its own columns or fall in the top's: parts swept at once
  // never write the same row.
  const int64_t top = f.top();
  for (int64_t p = 0; p < f.parts; ++p) {
    const int64_t end = f.first[f.part_ptr[p + 1]];
    for (int64_t i = f.row_ptr[f.part_ptr[p]]; i < f.row_ptr[f.part_ptr[p + 1]]; ++i)
      if (f.rows[i] >= end && f.rows[i] < top)
        return "a part's rows below must be its own or the top's";
  }
  std::vector<bool> seen(static_cast<size_t>(n), false);
  for (int64_t i = 0; i < n; ++i) {
    if (f.perm[i] < 0 || f.perm[i] >= n || seen[static_cast<size_t>(f.perm[i])])
      return "perm must be a permutation of 0 .. n-1";
    seen[static_cast<size_t>(f.perm[i])] = true;
  }
  return "";
}

}  // namespace

const char* check_factor(const LdlFactor<float>& f, int64_t num_rows, int64_t num_values) {
  return check(f, num_rows, num_values);
}
const char* check_factor(const LdlFactor<double>& f, int64_t num_rows, int64_t num_values) {
  return check(f, num_rows, num_values);
}

namespace {

template <typename T>
LdlFactor<T> view_of(const StoredFactor& s, const std::vector<T>& values,
                     const std::vector<T>& dinv) {
  LdlFactor<T> f;
  f.n = static_cast<int64_t>(dinv.size());
  f.supernodes = static_cast<int64_t>(s.first.size()) - 1;
  f.first = s.first.data();
  f.row_ptr = s.row_ptr.data();
  f.rows = s.rows.data();
  f.block_ptr = s.block_ptr.data();
  f.values = values.data();
  f.dinv = dinv.data();
  f.perm = s.perm.data();
  f.parts = static_cast<int64_t>(s.part_ptr.size()) - 1;
  f.part_ptr = s.part_ptr.data();
  return f;
}

std::mutex store_mutex;
std::unordered_map<int64_t, std::shared_ptr<const StoredFactor>>& store() {
  static auto* factors = new std::unordered_map<int64_t, std::shared_ptr<const StoredFactor>>();
  return *factors;  // never destroyed: XLA may call after static destructors have run
}

}  // namespace

LdlFactor<float> StoredFactor::view32() const { return view_of(*this, values32, dinv32); }
LdlFactor<double> StoredFactor::view64() const { return view_of(*this, values, dinv); }

int64_t store_factor(std::unique_ptr<StoredFactor> factor) {
  std::lock_guard<std::mutex> lock(store_mutex);
  const int64_t id = static_cast<int64_t>(store().size()) + 1;
  store().emplace(id, std::shared_ptr<const StoredFactor>(std::move(factor)));
  return id;
}

std::shared_ptr<const StoredFactor> stored_factor(int64_t id) {
  std::lock_guard<std::mutex> lock(store_mutex);
  const auto it = store().find(id);
  return it == store().end() ? nullptr : it->second;
}

void ldl_solve(const LdlFactor<float>& f, float* b, int64_t k, int threads,
               const Schedule& schedule, LdlRows rows) {
  solve(f, b, k, threads, schedule, rows);
}
void ldl_solve(const LdlFactor<double>& f, double* b, int64_t k, int threads,
               const Schedule& schedule, LdlRows rows) {
  solve(f, b, k, threads, schedule, rows);
}

}  // namespace optax_bilateral
