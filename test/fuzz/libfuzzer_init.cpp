// Linked into the libFuzzer builds of the targets only: with CVISLAM_FUZZ_WRITE_SEEDS=DIR in the environment, the
// target writes its seeds (fuzz_target.hpp) into DIR and exits, so test/fuzz/run_fuzz.sh starts each fuzzer from
// them without a committed corpus.
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "test/fuzz/fuzz_target.hpp"

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  const char* dir = std::getenv("CVISLAM_FUZZ_WRITE_SEEDS");
  if (dir == nullptr) return 0;
  const auto seeds = cvislam::fuzz::seeds();
  std::filesystem::create_directories(dir);
  for (std::size_t i = 0; i < seeds.size(); ++i) {
    std::ofstream(std::filesystem::path(dir) / ("seed" + std::to_string(i)), std::ios::binary) << seeds[i];
  }
  std::printf("wrote %zu seeds to %s\n", seeds.size(), dir);
  std::exit(0);
}
