// Solves with a sparse LDL^T factor for many right-hand sides at once: the mesh smoothing's
// M^-1 = (I + lambda L)^-1, factorised once per (mesh, lambda) by SciPy's SuperLU in METIS' order
// on the Python side.
//
//   A = P (I + L) D (I + L)^T P^T,   P[perm[i], i] = 1,
//
// L strictly lower triangular, stored by supernodes: runs of consecutive columns that share
// their rows below the run, each a dense block. Every right-hand side of b (n, k), row-major,
// goes through the same forward and backward sweeps; a row below a supernode is read once per
// supernode and block of columns, not once per entry of L.
//
// The supernodes come in parts, then a top: the parts are disjoint subtrees of the elimination
// tree (their rows below stay within their own columns or fall in the top's), so threads sweep
// them at once, each part's updates to the top's rows summed in rows of its own; the top, the
// tree's upper levels, is swept after them (forward) and before them (backward).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>

#include "claims.h"

namespace optax_bilateral {

template <typename T>
struct LdlFactor {
  int64_t n = 0;
  int64_t supernodes = 0;
  const int32_t* first = nullptr;      // (supernodes + 1) first column of each; the last is n
  const int32_t* row_ptr = nullptr;    // (supernodes + 1) where each one's rows start in `rows`
  const int32_t* rows = nullptr;       // the rows below each supernode, each past its columns
  const int64_t* block_ptr = nullptr;  // (supernodes + 1) where each one's block starts
  // Supernode k of s columns and r rows below: an (s + r, s) row-major block, its first s rows
  // L[j0 + u, j0 + t] for t < u (the diagonal and above unread), then L[rows[i], j0 + t].
  const T* values = nullptr;
  const T* dinv = nullptr;        // (n) 1 / D
  const int32_t* perm = nullptr;  // (n) a permutation of 0 .. n-1; in a sweep, null: b's rows
                                  // are in the factor's order
  // (parts + 1) part p is supernodes part_ptr[p] .. part_ptr[p+1]-1; the top is from
  // part_ptr[parts] to the last.
  int64_t parts = 0;
  const int32_t* part_ptr = nullptr;

  // The top's first column (n where the top is empty).
  int64_t top() const { return supernodes == 0 ? n : first[part_ptr[parts]]; }
};

// Where b's rows are: row i of b is row perm[i] of the caller's order (kCaller: the factor's
// perm reads them), or b is already in the factor's order (kFactor: a block that is all of b's
// columns is swept in b itself, with no working copy of its rows).
enum class LdlRows { kCaller, kFactor };

// The working rows of one block of columns c0 .. c1 of b (n, k): z holds the n rows in the
// factor's order (b itself where the block is swept in place), `stride` values a row (the
// block's width, narrow ones padded to 4); `own` holds `parts` copies of the top's rows.
template <typename T>
struct LdlBlock {
  T* b;
  int64_t k, c0, c1, stride;
  T* z;
  T* own;

  bool in_place() const { return z == b; }
  T* part_rows(const LdlFactor<T>& f, int64_t p) const {
    return own + p * (f.n - f.top()) * stride;
  }
};

// A block's steps, in this order: every part's forward step (at once), the top's steps, every
// part's backward step (at once).
enum class LdlStep { kPartForward, kTop, kPartBackward };

// The first problem found in a factor's index arrays (`rows` of `num_rows` entries, blocks
// adding up to `num_values`), or "" when it is sound: every later read stays in bounds and no
// two parts write the same row.
const char* check_factor(const LdlFactor<float>& f, int64_t num_rows, int64_t num_values);
const char* check_factor(const LdlFactor<double>& f, int64_t num_rows, int64_t num_values);

// Buffers handed out to the solves of any thread and taken back, kept for later solves while
// they add up to at most `kept_bytes`.
template <typename T>
class SolveBuffers {
 public:
  struct Buffer {
    std::unique_ptr<T[]> data;  // uninitialised: a block's gather writes every value it reads
    size_t size = 0;
  };

  explicit SolveBuffers(size_t kept_bytes) : limit_(kept_bytes) {}

  // A buffer of at least `size` values: the smallest kept one that holds it, or a new one.
  Buffer take(size_t size) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      auto best = kept_.end();
      for (auto it = kept_.begin(); it != kept_.end(); ++it)
        if (it->size >= size && (best == kept_.end() || it->size < best->size)) best = it;
      if (best != kept_.end()) {
        Buffer out = std::move(*best);
        kept_.erase(best);
        bytes_ -= out.size * sizeof(T);
        return out;
      }
    }
    return Buffer{std::unique_ptr<T[]>(new T[size]), size};
  }

  // Keeps `b`, freeing the smallest kept buffers as needed to stay within the limit; frees
  // `b` itself if it alone is over it.
  void give_back(Buffer b) {
    const size_t bytes = b.size * sizeof(T);
    if (bytes > limit_) return;
    std::lock_guard<std::mutex> lock(mutex_);
    std::sort(kept_.begin(), kept_.end(),
              [](const Buffer& x, const Buffer& y) { return x.size < y.size; });
    while (bytes_ + bytes > limit_) {
      bytes_ -= kept_.front().size * sizeof(T);
      kept_.erase(kept_.begin());
    }
    bytes_ += bytes;
    kept_.push_back(std::move(b));
  }

  size_t kept_bytes() {
    std::lock_guard<std::mutex> lock(mutex_);
    return bytes_;
  }

 private:
  const size_t limit_;
  std::mutex mutex_;
  std::vector<Buffer> kept_;
  size_t bytes_ = 0;
};

// b <- A^-1 b for b (n, k) row-major, on up to `threads` threads (helpers from `schedule`, or
// threads of its own where it is empty): blocks of columns, each swept part by part, then its
// top, then part by part again, in a working copy of its rows (or in b: LdlRows::kFactor with
// 4 to 64 columns) and of the top's rows once per part (SolveBuffers, kept between calls). The
// sums' order depends neither on the threads nor on `rows`. The factor must have passed
// check_factor.
void ldl_solve(const LdlFactor<float>& f, float* b, int64_t k, int threads,
               const Schedule& schedule = {}, LdlRows rows = LdlRows::kCaller);
void ldl_solve(const LdlFactor<double>& f, double* b, int64_t k, int threads,
               const Schedule& schedule = {}, LdlRows rows = LdlRows::kCaller);

// A factor held by the extension, in both precisions, for XLA's calls to find by its id.
struct StoredFactor {
  std::vector<int32_t> first, row_ptr, rows, perm, part_ptr;
  std::vector<int64_t> block_ptr;
  std::vector<double> values, dinv;
  std::vector<float> values32, dinv32;

  LdlFactor<float> view32() const;
  LdlFactor<double> view64() const;
};

// Keeps a factor (which must have passed check_factor) for the life of the process and
// returns its id (ids count from 1).
int64_t store_factor(std::unique_ptr<StoredFactor> factor);
// The factor stored under `id`, or null.
std::shared_ptr<const StoredFactor> stored_factor(int64_t id);

}  // namespace optax_bilateral
