/* casadi_real must agree with SYMKF_FLOAT (define SYMKF_FLOAT, not casadi_real, for float). */
#ifdef SYMKF_FLOAT
typedef char symkf_real_is_float[(sizeof(casadi_real) == sizeof(float)) ? 1 : -1];
#else
typedef char symkf_real_is_double[(sizeof(casadi_real) == sizeof(double)) ? 1 : -1];
#endif
