// The entry points one instruction-set build of kernel.h exports.
#pragma once

#include <cstdint>

#include "kernel.h"
#include "ldl_kernel.h"

namespace optax_bilateral {


#define OB_DECLARE_ISA(isa)                                                                 \
  namespace isa {                                                                           \
  void block32(const PassArgs<float>&, int64_t, int64_t, int64_t, int64_t, Scratch<float>&); \
  void block64(const PassArgs<double>&, int64_t, int64_t, int64_t, int64_t,                 \
               Scratch<double>&);                                                           \
  void slabs32(const PassArgs<float>&, const SlabLevel<float>&, int64_t, int64_t,            \
               Scratch<float>&);                                                            \
  void slabs64(const PassArgs<double>&, const SlabLevel<double>&, int64_t, int64_t,          \
               Scratch<double>&);                                                           \
  void ldl32(const LdlFactor<float>&, float*, int64_t, int64_t, int64_t, float*);           \
  void ldl64(const LdlFactor<double>&, double*, int64_t, int64_t, int64_t, double*);        \
  }

OB_DECLARE_ISA(baseline)
#if defined(__x86_64__)
OB_DECLARE_ISA(avx2)
OB_DECLARE_ISA(avx512)
#endif

}  // namespace optax_bilateral

// In a kernel_*.cc, after OB_ISA is defined and kernel.h included: the two entry points.
#define OB_DEFINE_ISA_ENTRIES                                                               \
  namespace optax_bilateral::OB_ISA {                                                        \
  void block32(const PassArgs<float>& a, int64_t r0, int64_t r1, int64_t c0, int64_t c1,    \
               Scratch<float>& s) {                                                         \
    run_block(a, r0, r1, c0, c1, s);                                                        \
  }                                                                                         \
  void block64(const PassArgs<double>& a, int64_t r0, int64_t r1, int64_t c0, int64_t c1,   \
               Scratch<double>& s) {                                                        \
    run_block(a, r0, r1, c0, c1, s);                                                        \
  }                                                                                         \
  void slabs32(const PassArgs<float>& a, const SlabLevel<float>& l, int64_t i0, int64_t i1,  \
               Scratch<float>& s) {                                                         \
    run_slabs(a, l, i0, i1, s);                                                             \
  }                                                                                         \
  void slabs64(const PassArgs<double>& a, const SlabLevel<double>& l, int64_t i0,           \
               int64_t i1, Scratch<double>& s) {                                            \
    run_slabs(a, l, i0, i1, s);                                                             \
  }                                                                                         \
  void ldl32(const LdlFactor<float>& f, float* b, int64_t k, int64_t c0, int64_t c1,         \
             float* z) {                                                                    \
    ldl_block(f, b, k, c0, c1, z);                                                          \
  }                                                                                         \
  void ldl64(const LdlFactor<double>& f, double* b, int64_t k, int64_t c0, int64_t c1,       \
             double* z) {                                                                   \
    ldl_block(f, b, k, c0, c1, z);                                                          \
  }                                                                                         \
  }
