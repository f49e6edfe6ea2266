// The LDL^T sweeps (ldl.h) against A x = b computed densely in float64, A = P (I + L) D
// (I + L)^T P^T built from a random factor by supernodes (NaN in every unread slot of a block),
// in one to three parts and a top: sizes from empty to a few hundred rows, block widths around
// the padded and the widest ones, one to three threads, float and double; and check_factor's
// verdict on broken factors. Built and run by `make sanitize` under
// AddressSanitizer and UndefinedBehaviorSanitizer; exits non-zero on a mismatch.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <limits>
#include <numeric>
#include <random>
#include <thread>
#include <vector>

#include "isa.h"
#include "ldl.h"

namespace ob = optax_bilateral;

namespace {

struct Factor {
  int64_t n;
  std::vector<int32_t> first, row_ptr, rows, perm;
  std::vector<int64_t> block_ptr;
  std::vector<int32_t> part_ptr;
  std::vector<double> values, d;
  std::vector<double> dense;  // L (n, n), strictly lower
};

// `parts` parts of random sizes, then a top (possibly empty); supernodes of 1 to 12 columns,
// each with a random set of rows below it (about 16, as sparse as a mesh's factor, so that the
// factor stays well conditioned): a part's within its own columns or the top's.
Factor random_factor(int64_t n, unsigned seed, int64_t parts) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-0.5, 0.5);
  Factor f{n, {0}, {0}, {}, std::vector<int32_t>(static_cast<size_t>(n)), {0}, {0}, {}, {}, {}};
  f.dense.assign(static_cast<size_t>(n * n), 0.0);
  // Column bounds: parts' ends at random cuts, the top from the last.
  std::vector<int64_t> ends;
  for (int64_t p = 0; p < parts; ++p) ends.push_back(n == 0 ? 0 : static_cast<int64_t>(rng() % static_cast<unsigned>(n + 1)));
  std::sort(ends.begin(), ends.end());
  const int64_t top = parts > 0 ? ends.back() : 0;
  ends.push_back(n);
  size_t part = 0;
  while (f.first.back() < n) {
    const int64_t j0 = f.first.back();
    while (part < ends.size() && ends[part] <= j0) {
      if (part < static_cast<size_t>(parts)) f.part_ptr.push_back(static_cast<int32_t>(f.first.size() - 1));
      ++part;
    }
    const int64_t end = ends[part];
    const int64_t s = std::min<int64_t>(end - j0, 1 + static_cast<int64_t>(rng() % 12));
    std::vector<int32_t> below;
    for (int64_t i = j0 + s; i < n; ++i)
      if ((i < end || i >= top) &&
          rng() % static_cast<unsigned>(std::max<int64_t>(4, n / 16)) == 0)
        below.push_back(static_cast<int32_t>(i));
    for (int64_t r = 0; r < s + static_cast<int64_t>(below.size()); ++r)
      for (int64_t t = 0; t < s; ++t) {
        const int64_t row = r < s ? j0 + r : below[static_cast<size_t>(r - s)];
        // The diagonal and above are stored but never read: make them loud.
        const double v = row > j0 + t ? u(rng) : 1e30;
        f.values.push_back(v);
        if (row > j0 + t) f.dense[static_cast<size_t>(row * n + j0 + t)] = v;
      }
    f.rows.insert(f.rows.end(), below.begin(), below.end());
    f.first.push_back(static_cast<int32_t>(j0 + s));
    f.row_ptr.push_back(static_cast<int32_t>(f.rows.size()));
    f.block_ptr.push_back(static_cast<int64_t>(f.values.size()));
  }
  while (f.part_ptr.size() < static_cast<size_t>(parts) + 1)
    f.part_ptr.push_back(static_cast<int32_t>(f.first.size() - 1));
  for (int64_t j = 0; j < n; ++j) f.d.push_back(1.0 + u(rng));
  std::iota(f.perm.begin(), f.perm.end(), 0);
  std::shuffle(f.perm.begin(), f.perm.end(), rng);
  return f;
}

// A x for the factor's A, x (n, k) row-major: P (I + L) D (I + L)^T P^T x, densely.
std::vector<double> apply(const Factor& f, const std::vector<double>& x, int64_t k) {
  const auto n = static_cast<size_t>(f.n);
  const auto K = static_cast<size_t>(k);
  std::vector<double> y(n * K), z(n * K);
  for (size_t i = 0; i < n; ++i)  // y = P^T x
    for (size_t c = 0; c < K; ++c) y[i * K + c] = x[static_cast<size_t>(f.perm[i]) * K + c];
  z = y;  // z = D (I + L)^T y
  for (size_t j = 0; j < n; ++j) {
    for (size_t i = j + 1; i < n; ++i)
      for (size_t c = 0; c < K; ++c) z[j * K + c] += f.dense[i * n + j] * y[i * K + c];
    for (size_t c = 0; c < K; ++c) z[j * K + c] *= f.d[j];
  }
  y = z;  // y = (I + L) z
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < i; ++j)
      for (size_t c = 0; c < K; ++c) y[i * K + c] += f.dense[i * n + j] * z[j * K + c];
  std::vector<double> out(n * K);  // out = P y
  for (size_t i = 0; i < n; ++i)
    for (size_t c = 0; c < K; ++c) out[static_cast<size_t>(f.perm[i]) * K + c] = y[i * K + c];
  return out;
}

template <typename T>
ob::LdlFactor<T> view(const Factor& f, const std::vector<T>& values, const std::vector<T>& dinv) {
  ob::LdlFactor<T> lf;
  lf.n = f.n;
  lf.supernodes = static_cast<int64_t>(f.first.size()) - 1;
  lf.first = f.first.data();
  lf.row_ptr = f.row_ptr.data();
  lf.rows = f.rows.data();
  lf.block_ptr = f.block_ptr.data();
  lf.values = values.data();
  lf.dinv = dinv.data();
  lf.perm = f.perm.data();
  lf.parts = static_cast<int64_t>(f.part_ptr.size()) - 1;
  lf.part_ptr = f.part_ptr.data();
  return lf;
}

template <typename T>
int check(const Factor& f, int64_t k, int threads, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<double> x(static_cast<size_t>(f.n * k));
  for (double& v : x) v = u(rng);
  const std::vector<double> b = apply(f, x, k);
  std::vector<T> values(f.values.size()), dinv(f.d.size());
  for (size_t i = 0; i < f.values.size(); ++i)
    values[i] = f.values[i] > 1e29 ? std::numeric_limits<T>::quiet_NaN() : static_cast<T>(f.values[i]);
  for (size_t i = 0; i < f.d.size(); ++i) dinv[i] = static_cast<T>(1.0 / f.d[i]);
  std::vector<T> got(b.begin(), b.end());
  const ob::LdlFactor<T> lf = view(f, values, dinv);
  // The same solve of NaN first: the buffers it gives back, which this solve takes, hold NaN
  // wherever they were written, so a read of a value this solve did not write shows.
  std::vector<T> poison(got.size(), std::numeric_limits<T>::quiet_NaN());
  ob::ldl_solve(lf, poison.data(), k, threads);
  if (*ob::check_factor(lf, static_cast<int64_t>(f.rows.size()),
                        static_cast<int64_t>(f.values.size())) != '\0') {
    std::printf("FAIL: a sound factor was refused (n %lld)\n", static_cast<long long>(f.n));
    return 1;
  }
  const std::vector<T> given = got;
  ob::ldl_solve(lf, got.data(), k, threads);
  // Helpers from a schedule (as XLA's pool gives them): started at once on threads of the
  // test's, or only after the solve returned (the caller then sweeps every block, and the late
  // helpers must find none left); the same values either way.
  std::vector<std::thread> started;
  std::vector<std::function<void()>> late;
  const ob::Schedule now = [&](std::function<void()> task) { started.emplace_back(std::move(task)); };
  const ob::Schedule after = [&](std::function<void()> task) { late.push_back(std::move(task)); };
  for (const ob::Schedule* schedule : {&now, &after}) {
    std::vector<T> again = given;
    ob::ldl_solve(lf, again.data(), k, threads, *schedule);
    for (auto& t : started) t.join();
    for (auto& task : late) task();
    started.clear();
    late.clear();
    if (!got.empty() && std::memcmp(again.data(), got.data(), got.size() * sizeof(T)) != 0) {
      std::printf("FAIL: n %lld k %lld threads %d: scheduled helpers changed the result\n",
                  static_cast<long long>(f.n), static_cast<long long>(k), threads);
      return 1;
    }
  }
  // b already in the factor's order (swept in b itself where the columns are one block of 4 to
  // 64): the same sums, so the same bits, row for row.
  const size_t K = static_cast<size_t>(k);
  std::vector<T> ordered(got.size());
  for (size_t i = 0; i < static_cast<size_t>(f.n); ++i)
    for (size_t c = 0; c < K; ++c) ordered[i * K + c] = given[static_cast<size_t>(f.perm[i]) * K + c];
  ob::ldl_solve(lf, ordered.data(), k, threads, {}, ob::LdlRows::kFactor);
  for (size_t i = 0; i < static_cast<size_t>(f.n); ++i)
    if (K != 0 && std::memcmp(&ordered[i * K], &got[static_cast<size_t>(f.perm[i]) * K],
                              K * sizeof(T)) != 0) {
      std::printf("FAIL: n %lld k %lld threads %d: b in the factor's order changed row %zu\n",
                  static_cast<long long>(f.n), static_cast<long long>(k), threads, i);
      return 1;
    }
  // The random factors are mildly conditioned: float32 keeps about 4 digits through the sweeps.
  const double tol = sizeof(T) == 4 ? 2e-3 : 1e-9;
  double worst = 0;
  for (size_t i = 0; i < x.size(); ++i) worst = std::max(worst, std::abs(got[i] - x[i]));
  if (!(worst <= tol)) {
    std::printf("FAIL: n %lld k %lld threads %d %s: max error %g\n", static_cast<long long>(f.n),
                static_cast<long long>(k), threads, sizeof(T) == 4 ? "float" : "double", worst);
    return 1;
  }
  return 0;
}

int check_refusals() {
  int failures = 0;
  // A sound 4-point factor: supernodes {0, 1} with row 3 below, and {2, 3}.
  const Factor good{4, {0, 2, 4}, {0, 1, 1}, {3}, {3, 1, 0, 2}, {0, 6, 10}, {0, 2},
                    std::vector<double>(10, 0.1), {1, 1, 1, 1}, {}};
  const std::vector<double> dinv(4, 1.0);
  auto expect = [&](const char* what, Factor f) {
    const char* problem = ob::check_factor(view(f, f.values, dinv),
                                           static_cast<int64_t>(f.rows.size()),
                                           static_cast<int64_t>(f.values.size()));
    if (*problem == '\0') {
      std::printf("FAIL: %s was accepted\n", what);
      ++failures;
    }
  };
  if (*ob::check_factor(view(good, good.values, dinv), 1, 10) != '\0') {
    std::printf("FAIL: the sound factor was refused\n");
    ++failures;
  }
  Factor f = good;
  f.rows = {1};
  expect("a row within its supernode", f);
  f.rows = {4};
  expect("a row past n", f);
  f.rows = {-1};
  expect("a negative row", f);
  f = good;
  f.first = {0, 2, 3};
  expect("first not reaching n", f);
  f.first = {1, 2, 4};
  expect("first not from 0", f);
  f.first = {0, 0, 4};
  expect("an empty supernode", f);
  f = good;
  f.row_ptr = {0, 1, 2};
  expect("row_ptr past the rows", f);
  f.row_ptr = {0, 2, 1};
  f.rows = {3, 3};
  expect("repeated rows and a decreasing row_ptr", f);
  f = good;
  f.block_ptr = {0, 5, 10};
  expect("a block of the wrong size", f);
  f.block_ptr = {0, 6, 11};
  expect("block_ptr past the values", f);
  f = good;
  f.part_ptr = {0, 1};  // the first supernode a part, the second the top: sound
  if (*ob::check_factor(view(f, f.values, dinv), 1, 10) != '\0') {
    std::printf("FAIL: a sound part and top were refused\n");
    ++failures;
  }
  f.part_ptr = {0, 1, 2};
  expect("a part's row below in another part", f);
  f.part_ptr = {0, 3};
  expect("part_ptr past the supernodes", f);
  f.part_ptr = {0, 2, 1};
  expect("a decreasing part_ptr", f);
  f.part_ptr = {1, 2};
  expect("part_ptr not from 0", f);
  f.part_ptr = {0};
  expect("no part", f);
  f = good;
  f.perm = {0, 1, 1, 2};
  expect("a repeated index in perm", f);
  f.perm = {0, 1, 2, 4};
  expect("an index past n in perm", f);
  f.perm = {0, -1, 2, 3};
  expect("a negative index in perm", f);
  return failures;
}

// SolveBuffers: the smallest kept buffer that fits, the kept bytes within the limit.
int check_buffers() {
  int failures = 0;
  auto expect = [&](bool ok, const char* what) {
    if (!ok) {
      std::printf("FAIL: SolveBuffers: %s\n", what);
      ++failures;
    }
  };
  ob::SolveBuffers<float> pool(1000);  // bytes: two buffers of 100 floats, not three
  auto a = pool.take(100), b = pool.take(100), c = pool.take(60);
  const float* c_data = c.data.get();
  expect(a.size == 100 && c.size == 60 && pool.kept_bytes() == 0, "new buffers of the size asked");
  pool.give_back(std::move(a));
  pool.give_back(std::move(c));
  expect(pool.kept_bytes() == 640, "two buffers kept");
  auto d = pool.take(50);
  expect(d.data.get() == c_data && pool.kept_bytes() == 400, "the smallest that fits is taken");
  auto e = pool.take(101);
  expect(e.size == 101 && pool.kept_bytes() == 400, "none fits: a new one, the kept one stays");
  pool.give_back(std::move(b));
  expect(pool.kept_bytes() == 800, "two of 100 kept");
  pool.give_back(std::move(e));  // 404 more: the smallest kept (400) goes
  expect(pool.kept_bytes() == 804, "the smallest kept buffer freed to stay within the limit");
  pool.give_back(std::move(d));  // 240 more: 804 + 240 > 1000, so the 400 goes
  expect(pool.kept_bytes() == 644, "within the limit");
  pool.give_back(ob::SolveBuffers<float>::Buffer{std::unique_ptr<float[]>(new float[300]), 300});
  expect(pool.kept_bytes() == 644, "a buffer over the limit alone is not kept");
  auto f = pool.take(100);
  expect(f.size == 101 && pool.kept_bytes() == 240, "the 101 taken, the 60 kept");
  return failures;
}

}  // namespace

int main() {
  int failures = check_refusals() + check_buffers(), cases = 21;
  unsigned seed = 0;
  for (int64_t n : {0, 1, 2, 7, 50, 300})
    for (int64_t k : {0, 1, 3, 4, 5, 16, 33, 64, 70, 130})
      for (int threads : {1, 2, 3}) {
        const Factor f = random_factor(n, seed, 1 + (seed / 3) % 3);
        failures += check<float>(f, k, threads, seed) + check<double>(f, k, threads, seed);
        cases += 2;
        ++seed;
      }
  std::printf("%d passed, %d failed (instruction set %s)\n", cases - failures, failures,
              ob::isa_name(ob::cpu_isa()).c_str());
  return failures != 0;
}
