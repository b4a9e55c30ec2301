/* The exported API (everything else is static, or hidden under -fvisibility=hidden). */
#ifndef SYMKF_API
#if defined(__GNUC__)
#define SYMKF_API __attribute__((visibility("default")))
#else
#define SYMKF_API
#endif
#endif
