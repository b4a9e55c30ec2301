#ifdef SYMKF_FLOAT
typedef uint32_t symkf_bits;
#define SYMKF_EXP_BITS ((symkf_bits) 0x7F800000u)
#define SYMKF_EXP_ONE ((symkf_bits) 0x00800000u)
#else
typedef uint64_t symkf_bits;
#define SYMKF_EXP_BITS ((symkf_bits) 0x7FF0000000000000u)
#define SYMKF_EXP_ONE ((symkf_bits) 0x0010000000000000u)
#endif
/* 1 if all n entries are finite: NaN/Inf have all exponent bits set, and only they carry
   (bits & EXP) + ONE into the top bit (integer operations only: no floating-point exception). */
static inline int symkf_finite(const casadi_real *v, int n) {
  symkf_bits any = 0, bits;
  int i;
  for (i = 0; i < n; ++i) {
    memcpy(&bits, v + i, sizeof bits);
    any |= (bits & SYMKF_EXP_BITS) + SYMKF_EXP_ONE;
  }
  return (any >> (sizeof(symkf_bits) * 8u - 1u)) == 0u;
}
