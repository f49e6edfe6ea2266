// kernel.h for any CPU the compiler targets by default (x86-64: SSE2).
#define OB_ISA baseline
#define OB_ISA_VECTOR_BYTES 16
#include "kernel_isa.h"
OB_DEFINE_ISA_ENTRIES
