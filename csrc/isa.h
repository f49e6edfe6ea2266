// The instruction set the kernels run with: the CPU's widest, chosen once at run time.
#pragma once

#include <string>

namespace optax_bilateral {

enum class Isa { kBaseline, kAvx2, kAvx512 };

// The widest instruction set the CPU has, or a narrower one that $OPTAX_BILATERAL_ISA names
// ("baseline", "avx2"; for tests and benchmarks). Read once per process.
Isa cpu_isa();

// "avx512", "avx2" or "baseline".
std::string isa_name(Isa isa);

}  // namespace optax_bilateral
