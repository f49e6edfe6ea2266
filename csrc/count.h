// Counts of non-finite entries (NaN, +-inf) of floating-point buffers, read from their bits: an
// IEEE value is non-finite exactly when its exponent field is all ones. The optimizers' per-leaf
// `nonfinite_count` (one FFI call for every leaf, not one XLA reduction each).
#pragma once

#include <cstdint>

namespace optax_bilateral {

// The storage formats a count reads; a complex entry is two parts of its real format, and
// counts once when either part is non-finite.
enum class Format { kF16, kBF16, kF32, kF64, kC64, kC128 };

// out[b] <- the non-finite entries among `per_block` entries starting at entry b * per_block of
// `data` (b < blocks), saturating at INT32_MAX. `data` holds blocks * per_block entries.
void count_nonfinite(Format format, const void* data, int64_t blocks, int64_t per_block,
                     int32_t* out);

}  // namespace optax_bilateral
