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

namespace optax_bilateral {

// One cascade's inputs. Pointers are row-major planar arrays of the grid `shape`.
template <typename T>
struct Cascade {
  const T* x = nullptr;      // (channels, *shape) fields, zero where invalid
  const T* guide = nullptr;  // (guide_channels, *shape)
  const T* valid = nullptr;  // (*shape) 0/1, or nullptr: every point valid
  T* out = nullptr;          // (channels, *shape)
  T* work = nullptr;         // (channels, *shape) scratch, needed when the cascade has > 1 step
  // Instead of x and out: fields and outputs of shape (*shape, c_k), their channels
  // interleaved ({pointer, c_k}, the c_k adding up to `channels`). Only for a separable
  // cascade of rank >= 2; `work` is then always needed.
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
  // Starts a task on another thread (XLA's intra-op pool under the FFI), now or later; empty:
  // a std::thread per task. The caller works too, so a task that starts late finds nothing
  // left and a busy pool never stalls the call.
  std::function<void(std::function<void()>)> schedule;
};

// The steps a cascade runs, each one read and one write of the fields: a separable level of a
// grid of rank >= 2 is one step (its passes swept slab by slab), any other pass one step.
int count_steps(const std::vector<int64_t>& shape, int levels, int start, bool separable);

// Runs the cascade; the result is in `out`. `work` may be null when count_steps <= 1.
void run_cascade(const Cascade<float>& c);
void run_cascade(const Cascade<double>& c);

// The instruction set the float kernel was dispatched to ("avx512", "avx2", "baseline").
std::string instruction_set();

}  // namespace optax_bilateral
