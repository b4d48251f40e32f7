#include "test/support/malloc_counter.hpp"

#include <atomic>
#include <cerrno>
#include <cstddef>

extern "C" {
void* __libc_malloc(std::size_t size);                           // NOLINT(bugprone-reserved-identifier)
void* __libc_calloc(std::size_t count, std::size_t size);        // NOLINT(bugprone-reserved-identifier)
void* __libc_realloc(void* pointer, std::size_t size);           // NOLINT(bugprone-reserved-identifier)
void* __libc_memalign(std::size_t alignment, std::size_t size);  // NOLINT(bugprone-reserved-identifier)
}

namespace {
std::atomic<long> g_calls{0};
// Initial-exec TLS: reading it never allocates (a dynamic TLS access could call malloc inside malloc).
__attribute__((tls_model("initial-exec"))) thread_local long t_calls = 0;

void countCall() {
  g_calls.fetch_add(1, std::memory_order_relaxed);
  ++t_calls;
}
}  // namespace

namespace cvislam::test {
long mallocCount() {
  return g_calls.load(std::memory_order_relaxed);
}
long threadMallocCount() {
  return t_calls;
}
}  // namespace cvislam::test

// NOLINTBEGIN(cppcoreguidelines-no-malloc, readability-inconsistent-declaration-parameter-name)
extern "C" {
void* malloc(std::size_t size) {
  countCall();
  return __libc_malloc(size);
}
void* calloc(std::size_t count, std::size_t size) {
  countCall();
  return __libc_calloc(count, size);
}
void* realloc(void* pointer, std::size_t size) {
  countCall();
  return __libc_realloc(pointer, size);
}
int posix_memalign(void** out, std::size_t alignment, std::size_t size) {
  countCall();
  *out = __libc_memalign(alignment, size);
  return *out != nullptr ? 0 : ENOMEM;
}
void* aligned_alloc(std::size_t alignment, std::size_t size) {
  countCall();
  return __libc_memalign(alignment, size);
}
void* memalign(std::size_t alignment, std::size_t size) {
  countCall();
  return __libc_memalign(alignment, size);
}
}
// NOLINTEND(cppcoreguidelines-no-malloc, readability-inconsistent-declaration-parameter-name)
