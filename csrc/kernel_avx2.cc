// kernel.h for x86-64 CPUs with AVX2 and FMA, chosen at run time (atrous.cc).
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>
#if defined(__x86_64__)
#if defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx2,fma"))), apply_to = function)
#else
#pragma GCC target("avx2,fma")
#endif
#define OB_ISA avx2
#define OB_ISA_VECTOR_BYTES 32
#include "kernel_isa.h"
OB_DEFINE_ISA_ENTRIES
#if defined(__clang__)
#pragma clang attribute pop
#endif
#endif
