#ifndef SYMKF_INTERNAL
#if defined(__GNUC__)
#define SYMKF_INTERNAL __attribute__((visibility("hidden")))
#else
#define SYMKF_INTERNAL
#endif
#endif
