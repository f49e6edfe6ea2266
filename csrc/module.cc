// The Python extension optax_bilateral._native: the XLA FFI handlers (the a-trous cascade, the
// rules' sub-grid averages and statistics, the mesh solves, the non-finite counts, the step's
// order) and the capsules that register them (jax.ffi.register_ffi_target).
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <initializer_list>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "atrous.h"
#include "count.h"
#include "ldl.h"
#include "local.h"
#include "stats.h"

// The FFI headers' own warnings are not this project's (they are checked with -Wall -Wextra).
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-parameter"
#pragma GCC diagnostic ignored "-Wsign-compare"
#pragma GCC diagnostic ignored "-Wreturn-type"
#pragma GCC diagnostic ignored "-Wshadow"
#pragma GCC diagnostic ignored "-Wconversion"
#include "xla/ffi/api/ffi.h"
#pragma GCC diagnostic pop

namespace ffi = xla::ffi;
namespace ob = optax_bilateral;

namespace {

ffi::Error invalid(const std::string& message) {
  return ffi::Error(ffi::ErrorCode::kInvalidArgument, "optax_bilateral native kernel: " + message);
}

// Entry `at` of a bool or float vector operand (a scalar is a vector of one), or nothing where
// there is none. The step's scalars come as one vector, which XLA computes in one kernel where
// it would compute each scalar operand in a kernel of its own (numerics.one_kernel).
std::optional<double> entry(const ffi::AnyBuffer& v, int64_t at) {
  if (at < 0 || at >= static_cast<int64_t>(v.element_count())) return std::nullopt;
  switch (v.element_type()) {
    case ffi::DataType::PRED: return static_cast<const bool*>(v.untyped_data())[at] ? 1.0 : 0.0;
    case ffi::DataType::F32: return static_cast<const float*>(v.untyped_data())[at];
    case ffi::DataType::F64: return static_cast<const double*>(v.untyped_data())[at];
    default: return std::nullopt;
  }
}

// A cascade's `deeper` operand: where its entry `deeper_at` is > 0, `more` levels after the
// call's own, all at sigma_d times `factor` (sigma_d="auto"'s heavier filter, decided by its
// state: one call, no conditional around two). An empty operand (0,) never deepens.
struct Deeper {
  int64_t more = 0;
  double factor = 1.0;
};

// The levels and sigma_d this call runs: the attributes', or deeper's where its flag says so.
template <typename T>
std::optional<ffi::Error> resolve_deeper(const ffi::AnyBuffer& flag, int64_t at, Deeper deeper,
                                         int64_t& levels, T& sigma) {
  if (deeper.more < 0 || levels + deeper.more > 62)
    return invalid("need deeper_levels >= 0 and levels + deeper_levels <= 62");
  if (flag.element_count() == 0) return std::nullopt;
  const std::optional<double> on = entry(flag, at);
  if (!on) return invalid("deeper must be a bool or float vector with an entry at deeper_at");
  if (*on > 0) {
    levels += deeper.more;
    sigma = sigma * static_cast<T>(deeper.factor);  // as XLA's product of the two
  }
  return std::nullopt;
}

// The cascade's settings from the call's attributes, then the cascade on XLA's threads.
template <typename T>
ffi::Error run_on(ob::Cascade<T>& c, ffi::ThreadPool& pool, int64_t levels, int64_t start,
                  bool separable, int64_t threads) {
  c.levels = static_cast<int>(levels);
  c.start = static_cast<int>(start);
  c.separable = separable;
  c.threads = static_cast<int>(threads);
  // XLA's intra-op threads, which would otherwise spin beside threads of our own.
  c.schedule = [&pool](std::function<void()> task) { pool.Schedule(std::move(task)); };
  ob::run_cascade(c);
  return ffi::Error::Success();
}

template <typename T>
ffi::Error run_typed(ffi::AnyBuffer x, ffi::AnyBuffer guide, ffi::AnyBuffer valid,
                     ffi::AnyBuffer sigma, const ffi::AnyBuffer& flag, int64_t flag_at,
                     Deeper deeper, ffi::AnyBuffer* out, ffi::AnyBuffer* work, int64_t levels,
                     int64_t start, bool separable, bool has_valid, int64_t threads,
                     ffi::ThreadPool& pool) {
  const auto xd = x.dimensions(), gd = guide.dimensions();
  if (xd.size() < 2 || gd.size() != xd.size())
    return invalid("fields (C, *S) and guide (G, *S) must have the same rank >= 2");
  ob::Cascade<T> c;
  c.channels = xd[0];
  c.guide_channels = gd[0];
  for (size_t k = 1; k < xd.size(); ++k) {
    if (xd[k] != gd[k]) return invalid("fields and guide must share their spatial shape");
    c.shape.push_back(xd[k]);
  }
  if (c.guide_channels < 1) return invalid("the guide needs at least one channel");
  if (has_valid && static_cast<int64_t>(valid.element_count()) * c.channels !=
                       static_cast<int64_t>(x.element_count()))
    return invalid("valid must have the spatial shape");
  if (sigma.element_count() != 1) return invalid("sigma_d must be a scalar");
  c.sigma_d = *static_cast<const T*>(sigma.untyped_data());
  if (auto error = resolve_deeper(flag, flag_at, deeper, levels, c.sigma_d)) return *error;
  c.x = static_cast<const T*>(x.untyped_data());
  c.guide = static_cast<const T*>(guide.untyped_data());
  c.valid = has_valid ? static_cast<const T*>(valid.untyped_data()) : nullptr;
  c.out = static_cast<T*>(out->untyped_data());
  c.work = static_cast<T*>(work->untyped_data());
  if (work->element_count() != x.element_count() &&
      ob::needs_working_copy(c.shape, static_cast<int>(levels), static_cast<int>(start), separable))
    return invalid("this cascade needs a working copy of the fields' size");
  return run_on(c, pool, levels, start, separable, threads);
}

ffi::Error atrous(ffi::ThreadPool pool, ffi::AnyBuffer x, ffi::AnyBuffer guide,
                  ffi::AnyBuffer valid, ffi::AnyBuffer sigma, ffi::AnyBuffer flag,
                  ffi::Result<ffi::AnyBuffer> out, ffi::Result<ffi::AnyBuffer> work,
                  int64_t levels, int64_t start, bool separable, bool has_valid, int64_t threads,
                  int64_t deeper_at, int64_t deeper_levels, double deeper_factor) {
  const Deeper deeper{deeper_levels, deeper_factor};
  const auto type = x.element_type();
  if (guide.element_type() != type || out->element_type() != type ||
      sigma.element_type() != type || (has_valid && valid.element_type() != type))
    return invalid("fields, guide, valid, sigma_d and output must share one dtype");
  if (levels < 0 || start < 0 || start > levels || levels > 62)
    return invalid("need 0 <= start <= levels <= 62");
  switch (type) {
    case ffi::DataType::F32:
      return run_typed<float>(x, guide, valid, sigma, flag, deeper_at, deeper, &*out, &*work,
                              levels, start, separable, has_valid, threads, pool);
    case ffi::DataType::F64:
      return run_typed<double>(x, guide, valid, sigma, flag, deeper_at, deeper, &*out, &*work,
                               levels, start, separable, has_valid, threads, pool);
    default:
      return invalid("fields must be float32 or float64");
  }
}

template <typename T>
ffi::Error run_fields_typed(ffi::ThreadPool& pool, ffi::AnyBuffer guide, ffi::AnyBuffer valid,
                            ffi::AnyBuffer sigma, const ffi::AnyBuffer& flag,
                            int64_t flag_at, Deeper deeper, ffi::RemainingArgs fields,
                            ffi::RemainingRets outs, int64_t levels, int64_t start,
                            bool has_valid, int64_t threads) {
  const auto gd = guide.dimensions();
  ob::Cascade<T> c;
  c.guide_channels = gd[0];
  c.shape.assign(gd.begin() + 1, gd.end());
  int64_t points = 1;
  for (int64_t n : c.shape) points *= n;
  if (c.shape.size() < 2) return invalid("interleaved fields need a grid of rank >= 2");
  if (outs.size() != fields.size()) return invalid("one output per field");
  c.channels = 0;
  for (size_t k = 0; k < fields.size(); ++k) {
    auto in = fields.get<ffi::AnyBuffer>(k);
    auto out = outs.get<ffi::AnyBuffer>(k);
    if (!in.has_value() || !out.has_value()) return invalid("fields and outputs are buffers");
    if (in->element_type() != guide.element_type() || (*out)->element_type() != guide.element_type())
      return invalid("fields, outputs and guide must share one dtype");
    const int64_t n = static_cast<int64_t>(in->element_count());
    if (n % points != 0 || static_cast<int64_t>((*out)->element_count()) != n)
      return invalid("each field and its output must be (points, channels)");
    c.x_fields.push_back({static_cast<const T*>(in->untyped_data()), n / points});
    c.out_fields.push_back({static_cast<T*>((*out)->untyped_data()), n / points});
    c.channels += n / points;
  }
  if (has_valid && static_cast<int64_t>(valid.element_count()) != points)
    return invalid("valid must have the spatial shape");
  if (sigma.element_count() != 1) return invalid("sigma_d must be a scalar");
  c.sigma_d = *static_cast<const T*>(sigma.untyped_data());
  if (auto error = resolve_deeper(flag, flag_at, deeper, levels, c.sigma_d)) return *error;
  c.guide = static_cast<const T*>(guide.untyped_data());
  c.valid = has_valid ? static_cast<const T*>(valid.untyped_data()) : nullptr;
  return run_on(c, pool, levels, start, true, threads);
}

// The separable cascade on fields whose channels are interleaved, (points, c_k) each:
// their planes are taken apart inside the call, and the outputs written interleaved.
ffi::Error atrous_fields(ffi::ThreadPool pool, ffi::AnyBuffer guide, ffi::AnyBuffer valid,
                         ffi::AnyBuffer sigma, ffi::AnyBuffer flag, ffi::RemainingArgs fields,
                         ffi::RemainingRets outs, int64_t levels, int64_t start,
                         bool has_valid, int64_t threads, int64_t deeper_at,
                         int64_t deeper_levels, double deeper_factor) {
  const Deeper deeper{deeper_levels, deeper_factor};
  if (levels < 0 || start < 0 || start > levels || levels > 62)
    return invalid("need 0 <= start <= levels <= 62");
  if (guide.dimensions().size() < 2) return invalid("guide must be (G, *S)");
  if (sigma.element_type() != guide.element_type() ||
      (has_valid && valid.element_type() != guide.element_type()))
    return invalid("guide, valid and sigma_d must share one dtype");
  switch (guide.element_type()) {
    case ffi::DataType::F32:
      return run_fields_typed<float>(pool, guide, valid, sigma, flag, deeper_at, deeper, fields,
                                     outs, levels, start, has_valid, threads);
    case ffi::DataType::F64:
      return run_fields_typed<double>(pool, guide, valid, sigma, flag, deeper_at, deeper,
                                      fields, outs, levels, start, has_valid, threads);
    default:
      return invalid("fields must be float32 or float64");
  }
}

// b (n, k) -> A^-1 b with the stored factor `factor` (register_factor); `ordered`: b's rows
// are already in the factor's order (LdlRows::kFactor).
ffi::Error ldl(ffi::ThreadPool pool, ffi::AnyBuffer b, ffi::Result<ffi::AnyBuffer> out,
               int64_t factor, int64_t threads, bool ordered) {
  const auto stored = ob::stored_factor(factor);
  if (!stored) return invalid("no factor is stored under id " + std::to_string(factor));
  const auto dims = b.dimensions();
  const int64_t n = static_cast<int64_t>(stored->perm.size());
  if (dims.size() != 2 || dims[0] != n)
    return invalid("the right-hand side must be (n, k) with n the factor's size");
  if (out->element_type() != b.element_type() || out->element_count() != b.element_count())
    return invalid("the output must match the right-hand side");
  if (threads < 1) return invalid("threads must be >= 1");
  const int64_t k = dims[1];
  const auto bytes = b.size_bytes();
  const ob::Schedule schedule = [&pool](std::function<void()> task) {
    pool.Schedule(std::move(task));
  };
  const auto rows = ordered ? ob::LdlRows::kFactor : ob::LdlRows::kCaller;
  switch (b.element_type()) {
    case ffi::DataType::F32: {
      auto* x = static_cast<float*>(out->untyped_data());
      if (x != b.untyped_data()) std::memcpy(x, b.untyped_data(), bytes);
      ob::ldl_solve(stored->view32(), x, k, static_cast<int>(threads), schedule, rows);
      return ffi::Error::Success();
    }
    case ffi::DataType::F64: {
      auto* x = static_cast<double*>(out->untyped_data());
      if (x != b.untyped_data()) std::memcpy(x, b.untyped_data(), bytes);
      ob::ldl_solve(stored->view64(), x, k, static_cast<int>(threads), schedule, rows);
      return ffi::Error::Success();
    }
    default:
      return invalid("the right-hand side must be float32 or float64");
  }
}

// The sub-grid a call's attributes describe over the array x.
ob::Subgrid subgrid_of(const ffi::AnyBuffer& x, ffi::Span<const int64_t> axes, int64_t stride) {
  ob::Subgrid g;
  const auto dims = x.dimensions();
  g.shape.assign(dims.begin(), dims.end());
  g.axes.assign(axes.begin(), axes.end());
  g.stride = stride;
  return g;
}

// A float32 or float64 scalar output set to `value` (a statistic's answer where it did not run).
void set_scalar(ffi::AnyBuffer& out, double value) {
  if (out.element_type() == ffi::DataType::F32)
    *static_cast<float*>(out.untyped_data()) = static_cast<float>(value);
  if (out.element_type() == ffi::DataType::F64) *static_cast<double*>(out.untyped_data()) = value;
}

// A statistic's `run` flag, entry `run_at` of its operand (nonzero: true): false where the
// caller discards the outputs (the rule's selects). Then the call is done: zeros in `outs`, no
// work. An invalid `run` is an error; otherwise nothing (the call goes on).
std::optional<ffi::Error> unless_run(const ffi::AnyBuffer& run, int64_t run_at,
                                     std::initializer_list<ffi::AnyBuffer*> outs) {
  const std::optional<double> flag = entry(run, run_at);
  if (!flag) return invalid("run must be a bool or float vector with an entry at run_at");
  if (*flag != 0) return std::nullopt;
  for (ffi::AnyBuffer* out : outs) std::memset(out->untyped_data(), 0, out->size_bytes());
  return ffi::Error::Success();
}

// x (*shape) -> its local averages at every `stride`-th entry along `axes` (local.h); `finite`:
// x read as numpy.nan_to_num makes it.
ffi::Error local_average(ffi::AnyBuffer x, ffi::AnyBuffer run, ffi::Result<ffi::AnyBuffer> out,
                         ffi::Result<ffi::AnyBuffer> work, ffi::Span<const int64_t> axes,
                         int64_t stride, bool finite, int64_t run_at) {
  const ob::Read read = finite ? ob::Read::kFinite : ob::Read::kAsIs;
  const ob::Subgrid s = subgrid_of(x, axes, stride);
  const std::string problem = ob::check_subgrid(s);
  if (!problem.empty()) return invalid(problem);
  const auto type = x.element_type();
  if (out->element_type() != type || work->element_type() != type)
    return invalid("the local average's output and scratch must have the input's dtype");
  if (static_cast<int64_t>(out->element_count()) != ob::subgrid_size(s))
    return invalid("the local average's output must have the sub-grid's shape");
  if (static_cast<int64_t>(work->element_count()) < ob::subgrid_work_size(s))
    return invalid("the local average's scratch is too small");
  if (auto done = unless_run(run, run_at, {&*out})) return *done;
  switch (type) {
    case ffi::DataType::F32:
      ob::subgrid_average(s, static_cast<const float*>(x.untyped_data()),
                          static_cast<float*>(out->untyped_data()),
                          static_cast<float*>(work->untyped_data()), read);
      return ffi::Error::Success();
    case ffi::DataType::F64:
      ob::subgrid_average(s, static_cast<const double*>(x.untyped_data()),
                          static_cast<double*>(out->untyped_data()),
                          static_cast<double*>(work->untyped_data()), read);
      return ffi::Error::Success();
    default:
      return invalid("the local average takes float32 or float64");
  }
}

// The mean distance of a's texels at the sub-grid from b's (stats.h), or their mean norm, times
// `scale`; where `run` is false, entry `otherwise_at` of `otherwise` ((0,): 0) and no work (the
// rule's choice between the two, made here rather than in a select kernel of XLA's); with
// `keep`, also a's sub-grid (what the rule keeps as the next b; zeros where not run).
ffi::Error texel_distance_mean(ffi::AnyBuffer a, ffi::AnyBuffer b, ffi::AnyBuffer run,
                               ffi::AnyBuffer otherwise, ffi::Result<ffi::AnyBuffer> out,
                               ffi::Result<ffi::AnyBuffer> kept, ffi::Span<const int64_t> axes,
                               int64_t stride, bool has_b, int64_t run_at, bool keep,
                               int64_t otherwise_at, double scale) {
  const ob::Subgrid g = subgrid_of(a, axes, stride);
  const std::string problem = ob::check_texel_grid(g);
  if (!problem.empty()) return invalid(problem);
  const auto type = a.element_type();
  if (out->element_type() != type || out->element_count() != 1 ||
      (has_b && b.element_type() != type))
    return invalid("the mean is a scalar of a's dtype, and b has a's dtype");
  if (has_b && static_cast<int64_t>(b.element_count()) != ob::texel_subgrid_size(g))
    return invalid("b must have the sub-grid's shape");
  if (kept->element_type() != type ||
      static_cast<int64_t>(kept->element_count()) != (keep ? ob::texel_subgrid_size(g) : 0))
    return invalid("kept must be a's sub-grid with keep, else empty, of a's dtype");
  std::optional<double> fallback = 0.0;
  if (otherwise.element_count() != 0) fallback = entry(otherwise, otherwise_at);
  if (!fallback) return invalid("otherwise must be a float vector with an entry at otherwise_at");
  if (auto done = unless_run(run, run_at, {&*out, &*kept})) {
    set_scalar(*out, *fallback);
    return *done;
  }
  switch (type) {
    case ffi::DataType::F32:  // the mean as float, then the product in float, as XLA's
      *static_cast<float*>(out->untyped_data()) =
          static_cast<float>(ob::texel_distance_mean(
              g, static_cast<const float*>(a.untyped_data()),
              has_b ? static_cast<const float*>(b.untyped_data()) : nullptr,
              keep ? static_cast<float*>(kept->untyped_data()) : nullptr)) *
          static_cast<float>(scale);
      return ffi::Error::Success();
    case ffi::DataType::F64:
      *static_cast<double*>(out->untyped_data()) =
          ob::texel_distance_mean(g, static_cast<const double*>(a.untyped_data()),
                                  has_b ? static_cast<const double*>(b.untyped_data()) : nullptr,
                                  keep ? static_cast<double*>(kept->untyped_data()) : nullptr) *
          scale;
      return ffi::Error::Success();
    default:
      return invalid("the texel distance takes float32 or float64");
  }
}

// A double limit as T: past T's largest value (no T lies beyond it) infinity, not a cast
// out of T's range.
template <typename T>
T in_range(double limit) {
  const double top = static_cast<double>(std::numeric_limits<T>::max());
  return limit > top ? std::numeric_limits<T>::infinity() : static_cast<T>(limit);
}

template <typename T>
void correlation_typed(const ob::Subgrid& g, const std::vector<int64_t>& pairs,
                       ffi::AnyBuffer grad, ffi::AnyBuffer m, ffi::AnyBuffer observed,
                       T c1, double limit, bool drop_zero, double* sums) {
  const auto od = observed.dimensions();
  const bool given = observed.element_count() > 0;  // else the texels' mask from grad
  const ob::Noise<T> noise{static_cast<const T*>(grad.untyped_data()),
                           static_cast<const T*>(m.untyped_data()),
                           given ? static_cast<const bool*>(observed.untyped_data()) : nullptr,
                           std::vector<int64_t>(od.begin(), od.end()),
                           c1,
                           in_range<T>(limit),
                           drop_zero};
  ob::correlation_sums(g, pairs, noise, sums);
}

// An observed mask for the grid g: bool, of g's rank, each dimension g's or 1 (broadcast).
std::optional<ffi::Error> check_mask(const ob::Subgrid& g, const ffi::AnyBuffer& observed) {
  if (observed.element_type() != ffi::DataType::PRED) return invalid("observed must be a bool mask");
  const auto od = observed.dimensions();
  const std::string problem = ob::check_noise_mask(g, std::vector<int64_t>(od.begin(), od.end()));
  if (!problem.empty()) return invalid(problem);
  return std::nullopt;
}

// The correlated-noise check's operands, checked: the sub-grid, the pair axes and c1.
struct NoiseCall {
  ob::Subgrid grid;
  std::vector<int64_t> pairs;
  double c1 = 1;
};

std::optional<ffi::Error> check_noise_call(const ffi::AnyBuffer& grad, const ffi::AnyBuffer& m,
                                           const ffi::AnyBuffer& observed,
                                           const ffi::AnyBuffer& c1, ffi::Span<const int64_t> axes,
                                           ffi::Span<const int64_t> pair_axes, int64_t stride,
                                           double limit, int64_t c1_at, NoiseCall& call) {
  if (!(limit > 0)) return invalid("limit must be > 0 (inf: no clip)");
  call.grid = subgrid_of(grad, axes, stride);
  const ob::Subgrid& g = call.grid;
  const std::string problem = ob::check_texel_grid(g);
  if (!problem.empty()) return invalid(problem);
  std::vector<int64_t>& pairs = call.pairs;
  pairs.assign(pair_axes.begin(), pair_axes.end());
  for (size_t k = 0; k < pairs.size(); ++k) {
    if (std::find(g.axes.begin(), g.axes.end(), pairs[k]) == g.axes.end() ||
        std::find(pairs.begin(), pairs.begin() + static_cast<std::ptrdiff_t>(k), pairs[k]) !=
            pairs.begin() + static_cast<std::ptrdiff_t>(k))
      return invalid("each pair axis must be a spatial axis, named once");
  }
  const auto dims = grad.dimensions(), md = m.dimensions();
  if (m.element_type() != grad.element_type() ||
      !std::equal(dims.begin(), dims.end(), md.begin(), md.end()))
    return invalid("grad and m must share their shape and dtype");
  if (grad.element_type() != ffi::DataType::F32 && grad.element_type() != ffi::DataType::F64)
    return invalid("the correlation sums take float32 or float64");
  // An empty bool mask: the texels' mask is read from grad (stats.h's Noise).
  const bool from_grad =
      observed.element_count() == 0 && observed.element_type() == ffi::DataType::PRED;
  if (!from_grad) {
    if (auto error = check_mask(g, observed)) return *error;
  }
  const std::optional<double> c = entry(c1, c1_at);
  if (!c || c1.element_type() == ffi::DataType::PRED)
    return invalid("c1 must be a float vector with an entry at c1_at");
  call.c1 = *c;
  return std::nullopt;
}

// The sums (stats.h) in double, (3 pairs + 2), each rounded to grad's dtype T as the sums'
// output holds it.
template <typename T>
std::vector<double> noise_sums(const NoiseCall& call, const ffi::AnyBuffer& grad,
                               const ffi::AnyBuffer& m, const ffi::AnyBuffer& observed,
                               double limit, bool drop_zero) {
  std::vector<double> sums(3 * call.pairs.size() + 2);
  correlation_typed<T>(call.grid, call.pairs, grad, m, observed, static_cast<T>(call.c1), limit,
                       drop_zero, sums.data());
  for (double& x : sums) x = static_cast<T>(x);
  return sums;
}

// The correlated-noise check's sums (stats.h), (3 pairs + 2) of grad's dtype, of
// z = clip(grad, -limit, limit) - m / c1 and y = m / c1 where observed (a bool mask,
// broadcast; empty: each texel's from grad, the gradient as given, with drop_zero), else 0.
ffi::Error correlation_sums(ffi::AnyBuffer grad, ffi::AnyBuffer m, ffi::AnyBuffer observed,
                            ffi::AnyBuffer c1, ffi::AnyBuffer run, ffi::Result<ffi::AnyBuffer> out,
                            ffi::Span<const int64_t> axes, ffi::Span<const int64_t> pair_axes,
                            int64_t stride, double limit, bool drop_zero, int64_t c1_at,
                            int64_t run_at) {
  NoiseCall call;
  if (auto error = check_noise_call(grad, m, observed, c1, axes, pair_axes, stride, limit, c1_at,
                                    call))
    return *error;
  const auto type = grad.element_type();
  if (out->element_type() != type || out->element_count() != 3 * call.pairs.size() + 2)
    return invalid("the sums are (3 pair axes + 2) of grad's dtype");
  if (auto done = unless_run(run, run_at, {&*out})) return *done;
  if (type == ffi::DataType::F32) {
    const std::vector<double> sums = noise_sums<float>(call, grad, m, observed, limit, drop_zero);
    std::copy(sums.begin(), sums.end(), static_cast<float*>(out->untyped_data()));
  } else {
    const std::vector<double> sums = noise_sums<double>(call, grad, m, observed, limit, drop_zero);
    std::copy(sums.begin(), sums.end(), static_cast<double*>(out->untyped_data()));
  }
  return ffi::Error::Success();
}

// The test's answer (noise_test) where `run` says it is due, else entry `stored_at` of
// `stored` (the answer kept from the last check): one call where XLA would compute the answer
// and the choice in a kernel of their own. `lag` is entry lag_at of c1's vector.
ffi::Error correlated_noise(ffi::AnyBuffer grad, ffi::AnyBuffer m, ffi::AnyBuffer observed,
                            ffi::AnyBuffer c1, ffi::AnyBuffer run, ffi::AnyBuffer stored,
                            ffi::Result<ffi::AnyBuffer> out, ffi::Span<const int64_t> axes,
                            ffi::Span<const int64_t> pair_axes, int64_t stride, double limit,
                            bool drop_zero, int64_t c1_at, int64_t run_at, int64_t lag_at,
                            int64_t stored_at, double correlated, double noisy) {
  NoiseCall call;
  if (auto error = check_noise_call(grad, m, observed, c1, axes, pair_axes, stride, limit, c1_at,
                                    call))
    return *error;
  const auto type = grad.element_type();
  if (out->element_type() != type || out->element_count() != 1)
    return invalid("the answer is a scalar of grad's dtype");
  if (call.pairs.empty()) return invalid("the test needs at least one pair axis");
  const std::optional<double> lag = entry(c1, lag_at);
  const std::optional<double> kept = entry(stored, stored_at);
  if (!lag || !kept) return invalid("lag and stored must be float vectors with their entries");
  if (auto done = unless_run(run, run_at, {&*out})) {
    set_scalar(*out, *kept);
    return *done;
  }
  if (type == ffi::DataType::F32) {
    const std::vector<double> sums = noise_sums<float>(call, grad, m, observed, limit, drop_zero);
    *static_cast<float*>(out->untyped_data()) =
        ob::noise_test<float>(sums.data(), call.pairs.size(), static_cast<float>(*lag),
                              correlated, noisy);
  } else {
    const std::vector<double> sums = noise_sums<double>(call, grad, m, observed, limit, drop_zero);
    *static_cast<double*>(out->untyped_data()) =
        ob::noise_test<double>(sums.data(), call.pairs.size(), *lag, correlated, noisy);
  }
  return ffi::Error::Success();
}

// sigma_d="auto"'s blend at the sub-grid (stats.h): lam gate (the sub-grid's shape) and gate.
template <typename T>
ffi::Error blend_typed(const ob::Subgrid& g, ffi::AnyBuffer m, ffi::AnyBuffer v, ffi::AnyBuffer r,
                       ffi::AnyBuffer scalars, ffi::AnyBuffer* out, ffi::AnyBuffer* gate,
                       double gain, double power, double low, double span) {
  const T* k = static_cast<const T*>(scalars.untyped_data());
  const ob::Blend<T> b{k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7],
                       static_cast<T>(gain), static_cast<T>(power), static_cast<T>(low),
                       static_cast<T>(span)};
  *static_cast<T*>(gate->untyped_data()) = ob::blend_weights(
      g, static_cast<const T*>(m.untyped_data()), static_cast<const T*>(v.untyped_data()),
      static_cast<const T*>(r.untyped_data()), b, static_cast<T*>(out->untyped_data()));
  return ffi::Error::Success();
}

ffi::Error blend_weights(ffi::AnyBuffer m, ffi::AnyBuffer v, ffi::AnyBuffer r,
                         ffi::AnyBuffer scalars, ffi::AnyBuffer run, ffi::Result<ffi::AnyBuffer> out,
                         ffi::Result<ffi::AnyBuffer> gate, ffi::Span<const int64_t> axes,
                         int64_t stride, double gain, double power, double low, double span,
                         int64_t run_at) {
  const ob::Subgrid g = subgrid_of(m, axes, stride);
  const std::string problem = ob::check_texel_grid(g);
  const auto dims = m.dimensions();
  if (!problem.empty()) return invalid(problem);
  const auto type = m.element_type();
  const auto vd = v.dimensions();
  for (ffi::AnyBuffer* b : {&v, &r, &scalars, &*out, &*gate})
    if (b->element_type() != type) return invalid("the blend's operands must share one dtype");
  if (!std::equal(dims.begin(), dims.end(), vd.begin(), vd.end()))
    return invalid("m and v must share their shape");
  const auto sub = static_cast<size_t>(ob::texel_subgrid_size(g));
  if (r.element_count() != sub || out->element_count() != sub)
    return invalid("the residual and the output must have the sub-grid's shape");
  if (scalars.element_count() != 8 || gate->element_count() != 1)
    return invalid("the blend takes 8 scalars and gives one gate");
  if (auto done = unless_run(run, run_at, {&*out, &*gate})) return *done;
  switch (type) {
    case ffi::DataType::F32:
      return blend_typed<float>(g, m, v, r, scalars, &*out, &*gate, gain, power, low, span);
    case ffi::DataType::F64:
      return blend_typed<double>(g, m, v, r, scalars, &*out, &*gate, gain, power, low, span);
    default:
      return invalid("the blend takes float32 or float64");
  }
}

// The step's mean texel norm at the sub-grid (stats.h's step_norm) from its parts: m, v, B m,
// B v and the gradient as given (*shape; a texel observed where its gradient is finite, and
// with drop_zero not all 0), lam (the sub-grid's shape, or (0,) without has_lam); inv_c1 and
// inv_c2 are entries of `scalars`. The blend is taken where has_lam, entry blend_at of
// `scalars` is nonzero and entry gate_at of `gate` is > 0 (sigma_d="auto": its statistics
// computed at this step, its gate open since the last).
template <typename T>
void step_norm_typed(const ob::Subgrid& g, const ffi::AnyBuffer* parts[5], ffi::AnyBuffer lam,
                     bool drop_zero, bool blend, const double k[4], ffi::AnyBuffer& out) {
  const T* arrays[5];
  for (int i = 0; i < 5; ++i) arrays[i] = static_cast<const T*>(parts[i]->untyped_data());
  const ob::Step<T> s = ob::step_of<T>(arrays, static_cast<const T*>(lam.untyped_data()),
                                       drop_zero, blend, k);
  *static_cast<T*>(out.untyped_data()) = static_cast<T>(ob::step_norm(g, s));
}

ffi::Error step_norm(ffi::AnyBuffer m, ffi::AnyBuffer v, ffi::AnyBuffer bm, ffi::AnyBuffer bv,
                     ffi::AnyBuffer grad, ffi::AnyBuffer lam, ffi::AnyBuffer scalars,
                     ffi::AnyBuffer gate, ffi::Result<ffi::AnyBuffer> out,
                     ffi::Span<const int64_t> axes, int64_t stride, bool has_lam, bool drop_zero,
                     int64_t inv_c1_at, int64_t inv_c2_at, int64_t blend_at, int64_t gate_at,
                     double eps, double eps_root) {
  const ob::Subgrid g = subgrid_of(m, axes, stride);
  const std::string problem = ob::check_texel_grid(g);
  if (!problem.empty()) return invalid(problem);
  const auto type = m.element_type();
  if (type != ffi::DataType::F32 && type != ffi::DataType::F64)
    return invalid("the step's norm takes float32 or float64");
  const auto dims = m.dimensions();
  const ffi::AnyBuffer* parts[5] = {&m, &v, &bm, &bv, &grad};
  for (const ffi::AnyBuffer* b : parts) {
    const auto bd = b->dimensions();
    if (b->element_type() != type || !std::equal(dims.begin(), dims.end(), bd.begin(), bd.end()))
      return invalid("m, v, B m, B v and the gradient must share their shape and dtype");
  }
  const int64_t sub = has_lam ? ob::texel_subgrid_size(g) : 0;
  if (static_cast<int64_t>(lam.element_count()) != sub || (has_lam && lam.element_type() != type))
    return invalid("lam must have the sub-grid's shape and m's dtype with has_lam, else be empty");
  if (out->element_type() != type || out->element_count() != 1)
    return invalid("the norm is a scalar of m's dtype");
  const std::optional<double> inv_c1 = entry(scalars, inv_c1_at);
  const std::optional<double> inv_c2 = entry(scalars, inv_c2_at);
  const std::optional<double> computed = entry(scalars, blend_at);
  const std::optional<double> open = entry(gate, gate_at);
  if (!inv_c1 || !inv_c2 || !computed || !open || scalars.element_type() == ffi::DataType::PRED)
    return invalid("scalars must be a float vector with entries at inv_c1_at, inv_c2_at and "
                   "blend_at, and gate a vector with one at gate_at");
  const bool blend = has_lam && *computed != 0 && *open > 0;
  const double k[4] = {*inv_c1, *inv_c2, eps, eps_root};
  if (type == ffi::DataType::F32)
    step_norm_typed<float>(g, parts, lam, drop_zero, blend, k, *out);
  else
    step_norm_typed<double>(g, parts, lam, drop_zero, blend, k, *out);
  return ffi::Error::Success();
}

// Each operand's count of non-finite entries (count.h), one int32 per block: an output of b
// entries splits its operand into b equal blocks (a vmapped call's batch). `totals`: the
// operands are the arrays, then as many int32 totals (one per block), and each count is added
// to its total, saturating at INT32_MAX (the optimizers' running counts, without an XLA
// kernel for each sum).
ffi::Error count_nonfinite(ffi::RemainingArgs xs, ffi::RemainingRets counts, bool totals) {
  const size_t n_arrays = totals ? xs.size() / 2 : xs.size();
  if (counts.size() != n_arrays || (totals && xs.size() % 2 != 0))
    return invalid("one count per operand (and, with totals, one total per operand)");
  for (size_t k = 0; k < n_arrays; ++k) {
    auto x = xs.get<ffi::AnyBuffer>(k);
    auto out = counts.get<ffi::AnyBuffer>(k);
    if (!x.has_value() || !out.has_value()) return invalid("operands and counts are buffers");
    if ((*out)->element_type() != ffi::DataType::S32) return invalid("counts must be int32");
    ob::Format format;
    switch (x->element_type()) {
      case ffi::DataType::F16: format = ob::Format::kF16; break;
      case ffi::DataType::BF16: format = ob::Format::kBF16; break;
      case ffi::DataType::F32: format = ob::Format::kF32; break;
      case ffi::DataType::F64: format = ob::Format::kF64; break;
      case ffi::DataType::C64: format = ob::Format::kC64; break;
      case ffi::DataType::C128: format = ob::Format::kC128; break;
      default: return invalid("the count takes float16, bfloat16, float32, float64 or complex");
    }
    const auto blocks = static_cast<int64_t>((*out)->element_count());
    const auto n = static_cast<int64_t>(x->element_count());
    if (blocks < 1 || n % blocks != 0)
      return invalid("each operand must split into its count's number of blocks");
    auto* c = static_cast<int32_t*>((*out)->untyped_data());
    ob::count_nonfinite(format, x->untyped_data(), blocks, n / blocks, c);
    if (!totals) continue;
    auto total = xs.get<ffi::AnyBuffer>(n_arrays + k);
    if (!total.has_value() || total->element_type() != ffi::DataType::S32 ||
        static_cast<int64_t>(total->element_count()) != blocks)
      return invalid("each total must be int32, one per block of its operand");
    const auto* t = static_cast<const int32_t*>(total->untyped_data());
    const int64_t top = std::numeric_limits<int32_t>::max();
    for (int64_t b = 0; b < blocks; ++b)
      c[b] = static_cast<int32_t>(std::min<int64_t>(int64_t{t[b]} + c[b], top));
  }
  return ffi::Error::Success();
}

// The arrays themselves, once the tokens exist: outputs 0..n-1 are operands 0..n-1, aliased
// (XLA gives each output its operand's buffer), and the operands after them are tokens. What
// reads the outputs is then scheduled after the tokens' producers: an update's last kernel
// runs after the statistic read from its parts, and may write its output over one of them.
// Nothing moves; where XLA gave an output a buffer of its own, its operand is copied there.
ffi::Error after(ffi::RemainingArgs xs, ffi::RemainingRets ys) {
  if (xs.size() < ys.size()) return invalid("one operand per output, then the tokens");
  for (size_t k = 0; k < ys.size(); ++k) {
    auto x = xs.get<ffi::AnyBuffer>(k);
    auto y = ys.get<ffi::AnyBuffer>(k);
    if (!x.has_value() || !y.has_value()) return invalid("operands and outputs are buffers");
    if (x->element_type() != (*y)->element_type() || x->size_bytes() != (*y)->size_bytes())
      return invalid("each output must have its operand's dtype and size");
    if (x->untyped_data() != (*y)->untyped_data() && x->size_bytes() > 0)
      std::memcpy((*y)->untyped_data(), x->untyped_data(), x->size_bytes());
  }
  return ffi::Error::Success();
}

}  // namespace

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wshadow"  // inside the FFI's macro
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralAtrous, atrous,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()  // fields (C, *S)
                                  .Arg<ffi::AnyBuffer>()  // guide (G, *S)
                                  .Arg<ffi::AnyBuffer>()  // valid (*S), or (0,) without a mask
                                  .Arg<ffi::AnyBuffer>()  // sigma_d, a scalar
                                  .Arg<ffi::AnyBuffer>()  // deeper's flag vector, or (0,)
                                  .Ret<ffi::AnyBuffer>()  // the filtered fields
                                  .Ret<ffi::AnyBuffer>()  // the working copy
                                  .Attr<int64_t>("levels")
                                  .Attr<int64_t>("start")
                                  .Attr<bool>("separable")
                                  .Attr<bool>("has_valid")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("deeper_at")
                                  .Attr<int64_t>("deeper_levels")
                                  .Attr<double>("deeper_factor"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralAtrousFields, atrous_fields,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()  // guide (G, *S)
                                  .Arg<ffi::AnyBuffer>()  // valid (*S), or (0,)
                                  .Arg<ffi::AnyBuffer>()  // sigma_d, a scalar
                                  .Arg<ffi::AnyBuffer>()  // deeper's flag vector, or (0,)
                                  .RemainingArgs()        // the fields, (points, c_k)
                                  .RemainingRets()        // their outputs, alike
                                  .Attr<int64_t>("levels")
                                  .Attr<int64_t>("start")
                                  .Attr<bool>("has_valid")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("deeper_at")
                                  .Attr<int64_t>("deeper_levels")
                                  .Attr<double>("deeper_factor"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralLdl, ldl,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()  // b (n, k)
                                  .Ret<ffi::AnyBuffer>()  // A^-1 b
                                  .Attr<int64_t>("factor")
                                  .Attr<int64_t>("threads")
                                  .Attr<bool>("ordered"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralLocalAverage, local_average,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // x (*shape)
                                  .Arg<ffi::AnyBuffer>()  // run: a bool or float vector
                                  .Ret<ffi::AnyBuffer>()  // the averages at the sub-grid
                                  .Ret<ffi::AnyBuffer>()  // the scratch between passes
                                  .Attr<ffi::Span<const int64_t>>("axes")
                                  .Attr<int64_t>("stride")
                                  .Attr<bool>("finite")
                                  .Attr<int64_t>("run_at"));  // run's entry
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralTexelDistanceMean, texel_distance_mean,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // a (*shape)
                                  .Arg<ffi::AnyBuffer>()  // b (the sub-grid's shape), or (0,)
                                  .Arg<ffi::AnyBuffer>()  // run: a bool or float vector
                                  .Arg<ffi::AnyBuffer>()  // otherwise: a float vector, or (0,)
                                  .Ret<ffi::AnyBuffer>()  // the mean, a scalar
                                  .Ret<ffi::AnyBuffer>()  // a's sub-grid (keep), or (0,)
                                  .Attr<ffi::Span<const int64_t>>("axes")
                                  .Attr<int64_t>("stride")
                                  .Attr<bool>("has_b")
                                  .Attr<int64_t>("run_at")  // run's entry
                                  .Attr<bool>("keep")
                                  .Attr<int64_t>("otherwise_at")
                                  .Attr<double>("scale"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralCorrelationSums, correlation_sums,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // grad (*shape)
                                  .Arg<ffi::AnyBuffer>()  // m (*shape)
                                  .Arg<ffi::AnyBuffer>()  // observed, bool (*shape or 1s; (0,):
                                                          // the texels' from grad)
                                  .Arg<ffi::AnyBuffer>()  // c1: a float vector
                                  .Arg<ffi::AnyBuffer>()  // run: a bool or float vector
                                  .Ret<ffi::AnyBuffer>()  // the sums (3 pair axes + 2)
                                  .Attr<ffi::Span<const int64_t>>("axes")
                                  .Attr<ffi::Span<const int64_t>>("pair_axes")
                                  .Attr<int64_t>("stride")
                                  .Attr<double>("limit")  // |grad| clipped to it
                                  .Attr<bool>("drop_zero")  // with no mask: all-0 texels out
                                  .Attr<int64_t>("c1_at")  // c1's entry
                                  .Attr<int64_t>("run_at"));  // run's entry
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralCorrelatedNoise, correlated_noise,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // grad (*shape)
                                  .Arg<ffi::AnyBuffer>()  // m (*shape)
                                  .Arg<ffi::AnyBuffer>()  // observed, bool (*shape or 1s; (0,):
                                                          // the texels' from grad)
                                  .Arg<ffi::AnyBuffer>()  // c1 and lag: a float vector
                                  .Arg<ffi::AnyBuffer>()  // run: a bool or float vector
                                  .Arg<ffi::AnyBuffer>()  // stored: a float vector
                                  .Ret<ffi::AnyBuffer>()  // the answer, a scalar
                                  .Attr<ffi::Span<const int64_t>>("axes")
                                  .Attr<ffi::Span<const int64_t>>("pair_axes")
                                  .Attr<int64_t>("stride")
                                  .Attr<double>("limit")
                                  .Attr<bool>("drop_zero")
                                  .Attr<int64_t>("c1_at")
                                  .Attr<int64_t>("run_at")
                                  .Attr<int64_t>("lag_at")
                                  .Attr<int64_t>("stored_at")
                                  .Attr<double>("correlated")
                                  .Attr<double>("noisy"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralBlendWeights, blend_weights,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // m (*shape)
                                  .Arg<ffi::AnyBuffer>()  // v (*shape)
                                  .Arg<ffi::AnyBuffer>()  // the residual (the sub-grid's shape)
                                  .Arg<ffi::AnyBuffer>()  // the step's 8 scalars (stats.h)
                                  .Arg<ffi::AnyBuffer>()  // run: a bool or float vector
                                  .Ret<ffi::AnyBuffer>()  // lam gate (the sub-grid's shape)
                                  .Ret<ffi::AnyBuffer>()  // gate, a scalar
                                  .Attr<ffi::Span<const int64_t>>("axes")
                                  .Attr<int64_t>("stride")
                                  .Attr<double>("gain")
                                  .Attr<double>("power")
                                  .Attr<double>("low")
                                  .Attr<double>("span")
                                  .Attr<int64_t>("run_at"));  // run's entry
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralStepNorm, step_norm,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // m (*shape)
                                  .Arg<ffi::AnyBuffer>()  // v (*shape)
                                  .Arg<ffi::AnyBuffer>()  // B m (*shape)
                                  .Arg<ffi::AnyBuffer>()  // B v (*shape)
                                  .Arg<ffi::AnyBuffer>()  // the gradient as given (*shape)
                                  .Arg<ffi::AnyBuffer>()  // lam (the sub-grid's shape), or (0,)
                                  .Arg<ffi::AnyBuffer>()  // the step's scalars: a float vector
                                  .Arg<ffi::AnyBuffer>()  // gate: a bool or float vector
                                  .Ret<ffi::AnyBuffer>()  // the mean norm, a scalar
                                  .Attr<ffi::Span<const int64_t>>("axes")
                                  .Attr<int64_t>("stride")
                                  .Attr<bool>("has_lam")
                                  .Attr<bool>("drop_zero")
                                  .Attr<int64_t>("inv_c1_at")
                                  .Attr<int64_t>("inv_c2_at")
                                  .Attr<int64_t>("blend_at")
                                  .Attr<int64_t>("gate_at")
                                  .Attr<double>("eps")
                                  .Attr<double>("eps_root"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralAfter, after,
                              ffi::Ffi::Bind()
                                  .RemainingArgs()   // the arrays, then the tokens
                                  .RemainingRets());  // the arrays, aliased to their operands
XLA_FFI_DEFINE_HANDLER_SYMBOL(OptaxBilateralCountNonfinite, count_nonfinite,
                              ffi::Ffi::Bind()
                                  .RemainingArgs()  // the arrays (then their totals)
                                  .RemainingRets()  // their counts, int32 (batch...)
                                  .Attr<bool>("totals"));
#pragma GCC diagnostic pop

namespace {

PyObject* registrations(PyObject*, PyObject*) {
  const std::pair<const char*, void*> targets[] = {
      {"optax_bilateral_atrous", reinterpret_cast<void*>(&OptaxBilateralAtrous)},
      {"optax_bilateral_atrous_fields", reinterpret_cast<void*>(&OptaxBilateralAtrousFields)},
      {"optax_bilateral_ldl", reinterpret_cast<void*>(&OptaxBilateralLdl)},
      {"optax_bilateral_local_average", reinterpret_cast<void*>(&OptaxBilateralLocalAverage)},
      {"optax_bilateral_texel_distance_mean",
       reinterpret_cast<void*>(&OptaxBilateralTexelDistanceMean)},
      {"optax_bilateral_correlation_sums", reinterpret_cast<void*>(&OptaxBilateralCorrelationSums)},
      {"optax_bilateral_correlated_noise", reinterpret_cast<void*>(&OptaxBilateralCorrelatedNoise)},
      {"optax_bilateral_blend_weights", reinterpret_cast<void*>(&OptaxBilateralBlendWeights)},
      {"optax_bilateral_step_norm", reinterpret_cast<void*>(&OptaxBilateralStepNorm)},
      {"optax_bilateral_count_nonfinite", reinterpret_cast<void*>(&OptaxBilateralCountNonfinite)},
      {"optax_bilateral_after", reinterpret_cast<void*>(&OptaxBilateralAfter)},
  };
  PyObject* dict = PyDict_New();
  if (!dict) return nullptr;
  for (const auto& [name, handler] : targets) {
    PyObject* capsule = PyCapsule_New(handler, nullptr, nullptr);
    if (!capsule || PyDict_SetItemString(dict, name, capsule) < 0) {
      Py_XDECREF(capsule);
      Py_DECREF(dict);
      return nullptr;
    }
    Py_DECREF(capsule);
  }
  return dict;
}

// A buffer of the Python object, C-contiguous, released when this goes out of scope.
class Buffer {
 public:
  // Not acquired where an earlier buffer failed: the C API is not called with an error set.
  Buffer(PyObject* obj, bool writable, const char* name) : name_(name) {
    const int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    ok_ = !PyErr_Occurred() && PyObject_GetBuffer(obj, &view_, flags) == 0;
  }
  ~Buffer() {
    if (ok_) PyBuffer_Release(&view_);
  }
  Buffer(const Buffer&) = delete;
  Buffer& operator=(const Buffer&) = delete;

  bool ok() const { return ok_; }
  // 'i' (int32), 'q' (int64), 'f' (float32) or 'd' (float64) when the buffer holds that
  // type, else 0.
  char kind() const {
    const std::string f = view_.format ? view_.format : "B";
    const std::string code = f.size() == 2 && (f[0] == '=' || f[0] == '<' || f[0] == '@')
                                 ? f.substr(1) : f;
    if ((code == "i" || code == "l") && view_.itemsize == 4) return 'i';
    if ((code == "q" || code == "l") && view_.itemsize == 8) return 'q';
    if (code == "f" && view_.itemsize == 4) return 'f';
    if (code == "d" && view_.itemsize == 8) return 'd';
    return 0;
  }
  int64_t size() const { return static_cast<int64_t>(view_.len / view_.itemsize); }
  void* data() const { return view_.buf; }
  const char* name() const { return name_; }

 private:
  Py_buffer view_{};
  bool ok_ = false;
  const char* name_;
};

PyObject* value_error(const std::string& message) {
  PyErr_SetString(PyExc_ValueError, ("ldl_solve: " + message).c_str());
  return nullptr;
}

struct LdlArgs {
  const Buffer &first, &row_ptr, &rows, &block_ptr, &values, &dinv, &perm, &part_ptr, &b;
};

template <typename T>
PyObject* ldl_typed(const LdlArgs& a, int threads, ob::LdlRows order) {
  ob::LdlFactor<T> f;
  f.n = a.dinv.size();
  f.supernodes = a.first.size() - 1;
  f.first = static_cast<const int32_t*>(a.first.data());
  f.row_ptr = static_cast<const int32_t*>(a.row_ptr.data());
  f.rows = static_cast<const int32_t*>(a.rows.data());
  f.block_ptr = static_cast<const int64_t*>(a.block_ptr.data());
  f.values = static_cast<const T*>(a.values.data());
  f.dinv = static_cast<const T*>(a.dinv.data());
  f.perm = static_cast<const int32_t*>(a.perm.data());
  f.parts = a.part_ptr.size() - 1;
  f.part_ptr = static_cast<const int32_t*>(a.part_ptr.data());
  const std::string problem = ob::check_factor(f, a.rows.size(), a.values.size());
  if (!problem.empty()) return value_error(problem);
  const int64_t k = f.n == 0 ? 0 : a.b.size() / f.n;
  T* x = static_cast<T*>(a.b.data());
  Py_BEGIN_ALLOW_THREADS ob::ldl_solve(f, x, k, threads, {}, order);
  Py_END_ALLOW_THREADS Py_RETURN_NONE;
}

// ldl_solve(first, row_ptr, rows, block_ptr, values, dinv, perm, part_ptr, b, threads,
// ordered=False): b (n, k) <- A^-1 b in place (ldl.h); `ordered`: b's rows in the factor's order.
PyObject* ldl_solve(PyObject*, PyObject* args) {
  PyObject *o_first, *o_row_ptr, *o_rows, *o_block_ptr, *o_values, *o_dinv, *o_perm, *o_parts,
      *o_b;
  int threads = 1, ordered = 0;
  if (!PyArg_ParseTuple(args, "OOOOOOOOOi|p", &o_first, &o_row_ptr, &o_rows, &o_block_ptr,
                        &o_values, &o_dinv, &o_perm, &o_parts, &o_b, &threads, &ordered))
    return nullptr;
  const Buffer first(o_first, false, "first"), row_ptr(o_row_ptr, false, "row_ptr"),
      rows(o_rows, false, "rows"), block_ptr(o_block_ptr, false, "block_ptr"),
      values(o_values, false, "values"), dinv(o_dinv, false, "dinv"), perm(o_perm, false, "perm"),
      part_ptr(o_parts, false, "part_ptr"), b(o_b, true, "b");
  for (const Buffer* buf :
       {&first, &row_ptr, &rows, &block_ptr, &values, &dinv, &perm, &part_ptr, &b})
    if (!buf->ok()) return nullptr;  // the buffer protocol's own error (e.g. b read-only)
  for (const Buffer* buf : {&first, &row_ptr, &rows, &perm, &part_ptr})
    if (buf->kind() != 'i') return value_error(std::string(buf->name()) + " must be int32");
  if (part_ptr.size() < 2) return value_error("part_ptr must have one entry per part, plus one");
  if (block_ptr.kind() != 'q') return value_error("block_ptr must be int64");
  const char t = b.kind();
  if (t != 'f' && t != 'd') return value_error("b must be float32 or float64");
  if (values.kind() != t || dinv.kind() != t)
    return value_error("values and dinv must have b's dtype");
  const int64_t n = dinv.size();
  if (first.size() < 1 || row_ptr.size() != first.size() || block_ptr.size() != first.size())
    return value_error("first, row_ptr and block_ptr must have one entry per supernode, plus one");
  if (perm.size() != n) return value_error("perm must have n entries, n = len(dinv)");
  if (n == 0 ? b.size() != 0 : b.size() % n != 0)
    return value_error("b must be (n, k), n = len(dinv)");
  if (threads < 1) return value_error("threads must be >= 1");
  const LdlArgs a{first, row_ptr, rows, block_ptr, values, dinv, perm, part_ptr, b};
  const auto order = ordered ? ob::LdlRows::kFactor : ob::LdlRows::kCaller;
  return t == 'f' ? ldl_typed<float>(a, threads, order) : ldl_typed<double>(a, threads, order);
}

template <typename T>
std::vector<T> copy_of(const Buffer& b) {
  const T* p = static_cast<const T*>(b.data());
  return std::vector<T>(p, p + b.size());
}

// register_factor(first, row_ptr, rows, block_ptr, values, dinv, perm, part_ptr) -> id: a
// float64 factor (ldl.h) checked and kept for the process's life, in float64 and float32, for
// XLA's calls.
PyObject* register_factor(PyObject*, PyObject* args) {
  PyObject *o_first, *o_row_ptr, *o_rows, *o_block_ptr, *o_values, *o_dinv, *o_perm, *o_parts;
  if (!PyArg_ParseTuple(args, "OOOOOOOO", &o_first, &o_row_ptr, &o_rows, &o_block_ptr,
                        &o_values, &o_dinv, &o_perm, &o_parts))
    return nullptr;
  const Buffer first(o_first, false, "first"), row_ptr(o_row_ptr, false, "row_ptr"),
      rows(o_rows, false, "rows"), block_ptr(o_block_ptr, false, "block_ptr"),
      values(o_values, false, "values"), dinv(o_dinv, false, "dinv"), perm(o_perm, false, "perm"),
      part_ptr(o_parts, false, "part_ptr");
  for (const Buffer* buf : {&first, &row_ptr, &rows, &block_ptr, &values, &dinv, &perm, &part_ptr})
    if (!buf->ok()) return nullptr;
  for (const Buffer* buf : {&first, &row_ptr, &rows, &perm, &part_ptr})
    if (buf->kind() != 'i') return value_error(std::string(buf->name()) + " must be int32");
  if (part_ptr.size() < 2) return value_error("part_ptr must have one entry per part, plus one");
  if (block_ptr.kind() != 'q') return value_error("block_ptr must be int64");
  if (values.kind() != 'd' || dinv.kind() != 'd')
    return value_error("values and dinv must be float64");
  if (first.size() < 1 || row_ptr.size() != first.size() || block_ptr.size() != first.size())
    return value_error("first, row_ptr and block_ptr must have one entry per supernode, plus one");
  if (perm.size() != dinv.size()) return value_error("perm must have n entries, n = len(dinv)");
  auto f = std::make_unique<ob::StoredFactor>();
  f->first = copy_of<int32_t>(first);
  f->row_ptr = copy_of<int32_t>(row_ptr);
  f->rows = copy_of<int32_t>(rows);
  f->block_ptr = copy_of<int64_t>(block_ptr);
  f->values = copy_of<double>(values);
  f->dinv = copy_of<double>(dinv);
  f->perm = copy_of<int32_t>(perm);
  f->part_ptr = copy_of<int32_t>(part_ptr);
  const std::string problem =
      ob::check_factor(f->view64(), static_cast<int64_t>(f->rows.size()),
                       static_cast<int64_t>(f->values.size()));
  if (!problem.empty()) return value_error(problem);
  f->values32.assign(f->values.begin(), f->values.end());
  f->dinv32.assign(f->dinv.begin(), f->dinv.end());
  return PyLong_FromLongLong(ob::store_factor(std::move(f)));
}

PyObject* instruction_set(PyObject*, PyObject*) {
  return PyUnicode_FromString(ob::instruction_set().c_str());
}

PyMethodDef methods[] = {
    {"registrations", registrations, METH_NOARGS,
     "{target name: capsule} of the XLA FFI handlers this extension defines."},
    {"instruction_set", instruction_set, METH_NOARGS,
     "The instruction set the kernel runs with on this CPU."},
    {"register_factor", register_factor, METH_VARARGS,
     "register_factor(first, row_ptr, rows, block_ptr, values, dinv, perm, part_ptr) -> id: a "
     "float64 factor (csrc/ldl.h), checked and kept for the process's life, for the XLA FFI target "
     "optax_bilateral_ldl (attribute factor=id)."},
    {"ldl_solve", ldl_solve, METH_VARARGS,
     "ldl_solve(first, row_ptr, rows, block_ptr, values, dinv, perm, part_ptr, b, threads, "
     "ordered=False): b (n, k) <- A^-1 b in place, A = P (I + L) D (I + L)^T P^T, L by "
     "supernodes (csrc/ldl.h); ordered: b's rows are already in the factor's order."},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native",
                      "The a-trous filter's native CPU kernel (XLA FFI).", -1, methods,
                      nullptr, nullptr, nullptr, nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__native() { return PyModule_Create(&module); }
