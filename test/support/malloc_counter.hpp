// Heap allocations counted at the C level: this object library replaces malloc, calloc, realloc,
// posix_memalign, aligned_alloc and memalign in the test executable (which shared libraries resolve to
// first), so allocations inside OpenCV, Eigen's dynamic matrices and operator new are all seen. Not for
// sanitizer builds, which replace the same functions.
#pragma once

namespace cvislam::test {

// Calls to the allocation functions since the program started, from any thread.
long mallocCount();
// Calls made by the calling thread only.
long threadMallocCount();

}  // namespace cvislam::test
