// The a-trous cross-bilateral cascade on planar grids: the native kernel's C++ interface.
//
// One call runs levels start .. levels-1 of docs/method.md's filter on C fields that share
// one guide. Every pass reads the fields planar, (C, n0, ..., n_{d-1}) in row-major order,
// and computes, for each grid point p,
//
//   out[p] = (h0 x[p] + sum_o tap_o (w(p, p+o) x[p+o] + w(p, p-o) x[p-o]))
//            / (h0 + sum_o tap_o (w(p, p+o) + w(p, p-o)))
//
// over one offset o of each pair +o / -o; each w is computed once and used by both points.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "claims.h"

namespace optax_bilateral {

// One cascade's inputs. Pointers are row-major planar arrays of the grid `shape`.
template <typename T>
struct Cascade {
  const T* x = nullptr;      // (channels, *shape) fields, zero where invalid
  const T* guide = nullptr;  // (guide_channels, *shape)
  const T* valid = nullptr;  // (*shape) 0/1, or nullptr: every point valid
  T* out = nullptr;          // (channels, *shape)
  T* work = nullptr;         // (channels, *shape) scratch, where needs_working_copy says so
  // Instead of x and out: fields and outputs of shape (*shape, c_k), their channels
  // interleaved ({pointer, c_k}, the c_k adding up to `channels`). Only for a separable
  // cascade of rank >= 2.
  std::vector<std::pair<const T*, int64_t>> x_fields;
  std::vector<std::pair<T*, int64_t>> out_fields;
  int64_t channels = 1;
  int64_t guide_channels = 1;
  std::vector<int64_t> shape;
  T sigma_d = 0;
  int levels = 0;
  int start = 0;
  bool separable = true;
  int threads = 1;  // the most threads that work on one step, the caller's included
  // Below this many point-channels the call runs on the calling thread alone: starting
  // threads costs more than they save.
  int64_t min_parallel_work = int64_t{1} << 15;
  // Helpers' threads (claims.h): XLA's intra-op pool under the FFI; empty, threads of its own.
  Schedule schedule;
};

// Whether a cascade needs `work`: a separable cascade on a grid of rank >= 2 runs every level
// in place in the output's memory; any other runs one step per pass, alternating between the
// output and the working copy, and needs it from two passes on.
bool needs_working_copy(const std::vector<int64_t>& shape, int levels, int start, bool separable);

// Runs the cascade; the result is in `out` (or `out_fields`).
void run_cascade(const Cascade<float>& c);
void run_cascade(const Cascade<double>& c);

// The instruction set the float kernel was dispatched to ("avx512", "avx2", "baseline").
std::string instruction_set();

}  // namespace optax_bilateral
