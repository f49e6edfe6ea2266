// Units of work shared by the calling thread and its helpers, claimed one at a time: the
// à-trous cascade's steps and the LDL solve's parts.
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

namespace optax_bilateral {

// Starts a task on another thread (XLA's intra-op pool under the FFI, whose threads would
// otherwise spin beside threads of our own), now or later; empty: a std::thread per task.
using Schedule = std::function<void(std::function<void()>)>;

// One call's units. Shared, so that a helper that starts after the call ended only reads
// that nothing is left.
struct Claims {
  explicit Claims(size_t n) : total(n) {}
  const size_t total;
  std::atomic<size_t> next{0}, done{0};
  std::mutex mutex;
  std::condition_variable finished;
};

// Runs `units` units, unit k as do_unit(k, state) with a State of the worker's own, on the
// calling thread and up to threads - 1 helpers from `schedule`; returns when all are done.
// The caller works too, so it finishes every unit when a helper starts late, and a busy
// pool never stalls the call.
template <typename State, typename F>
void run_claimed(size_t units, int threads, const Schedule& schedule, const F& do_unit) {
  auto claims = std::make_shared<Claims>(units);
  auto work = [claims, &do_unit, units] {
    State state;
    for (size_t k; (k = claims->next.fetch_add(1)) < units;) {
      do_unit(k, state);
      if (claims->done.fetch_add(1) + 1 == units) {
        std::lock_guard<std::mutex> lock(claims->mutex);
        claims->finished.notify_all();
      }
    }
  };
  const int helpers =
      static_cast<int>(std::min<size_t>(static_cast<size_t>(threads), units)) - 1;
  std::vector<std::thread> own;
  for (int t = 0; t < helpers; ++t) {
    if (schedule) {
      schedule(work);
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

}  // namespace optax_bilateral
