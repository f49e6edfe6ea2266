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
  void chunk32(const PassArgs<float>&, const SlabLevel<float>&, const SlabPlanes<const float>&, \
               const SlabPlanes<float>&, bool, const Chunk<float>&, Scratch<float>&);        \
  void chunk64(const PassArgs<double>&, const SlabLevel<double>&,                           \
               const SlabPlanes<const double>&, const SlabPlanes<double>&, bool,            \
               const Chunk<double>&, Scratch<double>&);                                     \
  void full32(const PassArgs<float>&, const SlabPass&, const Chunk<float>&, Scratch<float>&); \
  void full64(const PassArgs<double>&, const SlabPass&, const Chunk<double>&,               \
              Scratch<double>&);                                                            \
  void ldl32(const LdlFactor<float>&, const LdlBlock<float>&, LdlStep, int64_t);            \
  void ldl64(const LdlFactor<double>&, const LdlBlock<double>&, LdlStep, int64_t);          \
  void split32(const float*, float* const*, int64_t, int64_t);                              \
  void split64(const double*, double* const*, int64_t, int64_t);                            \
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
  void chunk32(const PassArgs<float>& a, const SlabLevel<float>& l,                         \
               const SlabPlanes<const float>& from, const SlabPlanes<float>& to, bool in_place, \
               const Chunk<float>& ch, Scratch<float>& s) {                                 \
    run_chunk(a, l, from, to, in_place, ch, s);                                             \
  }                                                                                         \
  void chunk64(const PassArgs<double>& a, const SlabLevel<double>& l,                       \
               const SlabPlanes<const double>& from, const SlabPlanes<double>& to,          \
               bool in_place, const Chunk<double>& ch, Scratch<double>& s) {                \
    run_chunk(a, l, from, to, in_place, ch, s);                                             \
  }                                                                                         \
  void full32(const PassArgs<float>& a, const SlabPass& p, const Chunk<float>& ch,          \
              Scratch<float>& s) {                                                          \
    run_slab_chunk(a, p, ch, s);                                                            \
  }                                                                                         \
  void full64(const PassArgs<double>& a, const SlabPass& p, const Chunk<double>& ch,        \
              Scratch<double>& s) {                                                         \
    run_slab_chunk(a, p, ch, s);                                                            \
  }                                                                                         \
  void ldl32(const LdlFactor<float>& f, const LdlBlock<float>& blk, LdlStep step,           \
             int64_t p) {                                                                   \
    ldl_step(f, blk, step, p);                                                              \
  }                                                                                         \
  void ldl64(const LdlFactor<double>& f, const LdlBlock<double>& blk, LdlStep step,         \
             int64_t p) {                                                                   \
    ldl_step(f, blk, step, p);                                                              \
  }                                                                                         \
  void split32(const float* src, float* const* dst, int64_t nc, int64_t n) {                \
    split_planes(src, dst, nc, n);                                                          \
  }                                                                                         \
  void split64(const double* src, double* const* dst, int64_t nc, int64_t n) {              \
    split_planes(src, dst, nc, n);                                                          \
  }                                                                                         \
  }
