#include "count.h"

#include <cstring>
#include <limits>

namespace optax_bilateral {

namespace {

// Non-finite entries among n entries of `parts` unsigned words each (a real value: one word;
// a complex one: two), saturating at INT32_MAX. memcpy keeps the reads free of aliasing rules.
template <typename Word, int parts>
int32_t count_block(const unsigned char* bytes, int64_t n, Word exponent) {
  constexpr int64_t kTop = std::numeric_limits<int32_t>::max();
  int64_t found = 0;
  for (int64_t i = 0; i < n; ++i) {
    Word w[parts];
    std::memcpy(w, bytes + i * static_cast<int64_t>(sizeof w), sizeof w);
    bool bad = false;
    for (int k = 0; k < parts; ++k) bad |= (w[k] & exponent) == exponent;
    found += bad;
  }
  return static_cast<int32_t>(found < kTop ? found : kTop);
}

template <typename Word, int parts>
void count_blocks(const void* data, int64_t blocks, int64_t per_block, Word exponent,
                  int32_t* out) {
  const auto* bytes = static_cast<const unsigned char*>(data);
  const int64_t stride = per_block * static_cast<int64_t>(sizeof(Word)) * parts;
  for (int64_t b = 0; b < blocks; ++b)
    out[b] = count_block<Word, parts>(bytes + b * stride, per_block, exponent);
}

}  // namespace

void count_nonfinite(Format format, const void* data, int64_t blocks, int64_t per_block,
                     int32_t* out) {
  switch (format) {
    case Format::kF16:
      return count_blocks<uint16_t, 1>(data, blocks, per_block, 0x7C00u, out);
    case Format::kBF16:
      return count_blocks<uint16_t, 1>(data, blocks, per_block, 0x7F80u, out);
    case Format::kF32:
      return count_blocks<uint32_t, 1>(data, blocks, per_block, 0x7F800000u, out);
    case Format::kF64:
      return count_blocks<uint64_t, 1>(data, blocks, per_block, 0x7FF0000000000000u, out);
    case Format::kC64:
      return count_blocks<uint32_t, 2>(data, blocks, per_block, 0x7F800000u, out);
    case Format::kC128:
      return count_blocks<uint64_t, 2>(data, blocks, per_block, 0x7FF0000000000000u, out);
  }
}

}  // namespace optax_bilateral
