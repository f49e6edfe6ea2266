// The LDL^T solve's driver: the factor's checks, blocks of columns on threads, and the
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

// A thread of its own only for at least this many columns: fewer cost more to start than
// they save.
constexpr int64_t kMinColumnsPerThread = 32;
// The widest block one sweep takes: wider blocks read the factor fewer times, and beyond this
// the rows of a block no longer fit the cache (docs/triangle_mesh.md has the measurements).
constexpr int64_t kMaxWidth = 64;

template <typename T>
void sweep(const LdlFactor<T>& f, T* b, int64_t k, int64_t c0, int64_t c1, T* z) {
  constexpr bool f32 = std::is_same_v<T, float>;
  switch (cpu_isa()) {
#if defined(__x86_64__)
    case Isa::kAvx512:
      if constexpr (f32) return avx512::ldl32(f, b, k, c0, c1, z);
      else return avx512::ldl64(f, b, k, c0, c1, z);
    case Isa::kAvx2:
      if constexpr (f32) return avx2::ldl32(f, b, k, c0, c1, z);
      else return avx2::ldl64(f, b, k, c0, c1, z);
#endif
    default:
      if constexpr (f32) return baseline::ldl32(f, b, k, c0, c1, z);
      else return baseline::ldl64(f, b, k, c0, c1, z);
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

// A worker's buffer: taken at its first block, given back when it is done.
template <typename T>
struct Lease {
  typename SolveBuffers<T>::Buffer buffer;

  T* get(size_t size) {
    if (!buffer.data) buffer = buffers<T>().take(size);
    return buffer.data.get();
  }
  ~Lease() {
    if (buffer.data) buffers<T>().give_back(std::move(buffer));
  }
};

template <typename T>
void solve(const LdlFactor<T>& f, T* b, int64_t k, int threads, const Schedule& schedule) {
  if (f.n == 0 || k == 0) return;
  const int64_t workers = std::max<int64_t>(
      1, std::min<int64_t>(threads, k / kMinColumnsPerThread));
  const int64_t blocks = std::max(workers, (k + kMaxWidth - 1) / kMaxWidth);
  const auto size = static_cast<size_t>(f.n * std::max<int64_t>(4, (k + blocks - 1) / blocks));
  run_claimed<Lease<T>>(static_cast<size_t>(blocks), static_cast<int>(workers), schedule,
                        [&](size_t u, Lease<T>& z) {
                          const auto i = static_cast<int64_t>(u);
                          sweep(f, b, k, k * i / blocks, k * (i + 1) / blocks, z.get(size));
                        });
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
               const Schedule& schedule) {
  solve(f, b, k, threads, schedule);
}
void ldl_solve(const LdlFactor<double>& f, double* b, int64_t k, int threads,
               const Schedule& schedule) {
  solve(f, b, k, threads, schedule);
}

}  // namespace optax_bilateral
