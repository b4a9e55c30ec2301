#ifndef casadi_real
#ifdef SYMKF_FLOAT
#define casadi_real float
#else
#define casadi_real double
#endif
#endif
