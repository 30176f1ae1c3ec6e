// The CPU's x86 features as the compiler's run-time check sees them (for systems without /proc/cpuinfo).
// Built at the portable level by dynbtf/decoder/native/__init__.py; Python: probe_cpu_features().
#include <cstring>

extern "C" int dynbtf_cpu_supports(const char* name) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    // __builtin_cpu_supports takes string literals only
    if (!std::strcmp(name, "avx2")) return __builtin_cpu_supports("avx2") != 0;
    if (!std::strcmp(name, "fma")) return __builtin_cpu_supports("fma") != 0;
    if (!std::strcmp(name, "f16c")) return __builtin_cpu_supports("f16c") != 0;
    if (!std::strcmp(name, "bmi2")) return __builtin_cpu_supports("bmi2") != 0;
    if (!std::strcmp(name, "avx512f")) return __builtin_cpu_supports("avx512f") != 0;
    if (!std::strcmp(name, "avx512bw")) return __builtin_cpu_supports("avx512bw") != 0;
    if (!std::strcmp(name, "avx512dq")) return __builtin_cpu_supports("avx512dq") != 0;
    if (!std::strcmp(name, "avx512vl")) return __builtin_cpu_supports("avx512vl") != 0;
    if (!std::strcmp(name, "avx512cd")) return __builtin_cpu_supports("avx512cd") != 0;
    if (!std::strcmp(name, "avx512bf16")) return __builtin_cpu_supports("avx512bf16") != 0;
#endif
    (void)name;
    return 0;
}
