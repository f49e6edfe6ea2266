// kernel.h for x86-64 CPUs with AVX-512 (F, VL, DQ, BW), chosen at run time (atrous.cc).
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>
#if defined(__x86_64__)
#if defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx512f,avx512vl,avx512dq,avx512bw,avx2,fma"))), apply_to = function)
#else
#pragma GCC target("avx512f,avx512vl,avx512dq,avx512bw,avx2,fma,prefer-vector-width=512")
#endif
#define OB_ISA avx512
#define OB_ISA_VECTOR_BYTES 64
#include "kernel_isa.h"
OB_DEFINE_ISA_ENTRIES
#if defined(__clang__)
#pragma clang attribute pop
#endif
#endif
