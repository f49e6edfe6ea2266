// The non-finite counts (count.h) against std::isfinite: every float16 and bfloat16 bit
// pattern (decoded here from their fields), float32 and float64 specials and random bits,
// complex entries with either part non-finite, and blocks of every size up to 40 (the
// vectorised loops' tails). Built and run by `make sanitize` under AddressSanitizer and
// UndefinedBehaviorSanitizer; exits non-zero on a mismatch.
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "count.h"

namespace ob = optax_bilateral;

namespace {

int failures = 0;

void expect(bool ok, const char* what, int64_t at) {
  if (!ok && failures++ < 20) std::printf("FAIL %s at %lld\n", what, static_cast<long long>(at));
}

// A float16 value from its fields (1 sign, 5 exponent, 10 mantissa bits), written out.
double half_value(uint16_t h) {
  const int exponent = (h >> 10) & 0x1F, mantissa = h & 0x3FF;
  const double sign = (h & 0x8000) ? -1.0 : 1.0;
  if (exponent == 0x1F)
    return mantissa ? std::numeric_limits<double>::quiet_NaN()
                    : sign * std::numeric_limits<double>::infinity();
  if (exponent == 0) return sign * std::ldexp(mantissa, -24);
  return sign * std::ldexp(1024 + mantissa, exponent - 25);
}

// A bfloat16 value: the upper half of a float32.
float bfloat_value(uint16_t b) {
  const uint32_t bits = static_cast<uint32_t>(b) << 16;
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
}

int32_t count_of(ob::Format format, const void* data, int64_t n) {
  int32_t out = -1;
  ob::count_nonfinite(format, data, 1, n, &out);
  return out;
}

void every_16_bit_pattern() {
  std::vector<uint16_t> all(1 << 16);
  int32_t half_bad = 0, bfloat_bad = 0;
  for (int i = 0; i < (1 << 16); ++i) {
    all[i] = static_cast<uint16_t>(i);
    half_bad += !std::isfinite(half_value(all[i]));
    bfloat_bad += !std::isfinite(bfloat_value(all[i]));
    // One entry at a time: each pattern decided alone.
    expect(count_of(ob::Format::kF16, &all[i], 1) == !std::isfinite(half_value(all[i])),
           "float16 pattern", i);
    expect(count_of(ob::Format::kBF16, &all[i], 1) == !std::isfinite(bfloat_value(all[i])),
           "bfloat16 pattern", i);
  }
  expect(count_of(ob::Format::kF16, all.data(), 1 << 16) == half_bad, "float16 total", 0);
  expect(count_of(ob::Format::kBF16, all.data(), 1 << 16) == bfloat_bad, "bfloat16 total", 0);
}

template <typename T>
std::vector<T> drawn(std::mt19937_64& rng, int64_t n) {
  const T specials[] = {std::numeric_limits<T>::quiet_NaN(), -std::numeric_limits<T>::quiet_NaN(),
                        std::numeric_limits<T>::infinity(), -std::numeric_limits<T>::infinity(),
                        std::numeric_limits<T>::max(), std::numeric_limits<T>::lowest(),
                        std::numeric_limits<T>::denorm_min(), T(0), -T(0)};
  std::vector<T> x(static_cast<size_t>(n));
  for (auto& v : x) {
    if (rng() % 3 == 0) {
      v = specials[rng() % (sizeof specials / sizeof specials[0])];
    } else {  // any bit pattern: NaNs with every payload among them
      uint64_t bits = rng();
      std::memcpy(&v, &bits, sizeof v);
    }
  }
  return x;
}

template <typename T>
void real_and_complex(ob::Format real, ob::Format complex, std::mt19937_64& rng) {
  for (int64_t n = 0; n <= 40; ++n) {
    for (int64_t blocks : {1, 2, 3}) {
      const auto x = drawn<T>(rng, 2 * n * blocks);  // also read as n * blocks complex pairs
      std::vector<int32_t> got(static_cast<size_t>(blocks), -1), pairs = got;
      ob::count_nonfinite(real, x.data(), blocks, 2 * n, got.data());
      ob::count_nonfinite(complex, x.data(), blocks, n, pairs.data());
      for (int64_t b = 0; b < blocks; ++b) {
        int32_t want = 0, want_pairs = 0;
        for (int64_t i = 0; i < n; ++i) {
          const T re = x[2 * (b * n + i)], im = x[2 * (b * n + i) + 1];
          want += !std::isfinite(re) + !std::isfinite(im);
          want_pairs += !(std::isfinite(re) && std::isfinite(im));
        }
        expect(got[b] == want, "real block", n * 10 + b);
        expect(pairs[b] == want_pairs, "complex block", n * 10 + b);
      }
    }
  }
}

}  // namespace

int main() {
  every_16_bit_pattern();
  std::mt19937_64 rng(7);
  real_and_complex<float>(ob::Format::kF32, ob::Format::kC64, rng);
  real_and_complex<double>(ob::Format::kF64, ob::Format::kC128, rng);
  if (failures) {
    std::printf("%d count checks failed\n", failures);
    return 1;
  }
  std::printf("count: every check passed\n");
  return 0;
}
