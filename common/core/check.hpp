// CVISLAM_CHECK(condition, message): a guard against bugs that stays on in every build, NDEBUG included, so the
// builds CI and users run stop at the broken invariant (file, line, condition, message on stderr, then abort)
// instead of going on with a wrong value. Expected failures (bad input, a lost connection) are Result/Status values,
// never checks. The check costs one predictable branch; the failure path allocates nothing.
#pragma once

#include <cstdio>
#include <cstdlib>

namespace cvislam::detail {

[[noreturn]] inline void checkFailed(const char* file, int line, const char* condition, const char* message) noexcept {
  std::fprintf(stderr, "%s:%d: check failed: %s (%s)\n", file, line, condition, message);
  std::fflush(stderr);
  std::abort();
}

}  // namespace cvislam::detail

#define CVISLAM_CHECK(condition, message)                                        \
  do {                                                                           \
    if (!(condition)) [[unlikely]] {                                             \
      ::cvislam::detail::checkFailed(__FILE__, __LINE__, #condition, (message)); \
    }                                                                            \
  } while (false)
