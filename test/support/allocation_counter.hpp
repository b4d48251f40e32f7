// Heap allocations counted by a replaced global operator new. Only binaries that compile
// test/support/allocation_counter.cpp (cvislam_add_test(... COUNT_ALLOCATIONS) or the benchmarks that list it)
// count; the replacement covers plain and aligned new. Memory obtained with malloc directly (Eigen's dynamic
// matrices, C libraries) is not seen.
#pragma once

namespace cvislam::test {

// Allocations through operator new since the program started.
long allocationCount();

}  // namespace cvislam::test
