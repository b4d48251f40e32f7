// The driver of a fuzz target where libFuzzer is not linked (every gcc build; CTest runs it): each seed once,
// then --runs inputs made from the seeds by a seeded mutator (byte flips, inserted and erased runs, splices of
// two seeds, random bytes, framing lengths set to extremes). No coverage guidance: the short, fixed smoke run CI
// affords. The long, coverage-guided runs use libFuzzer (test/fuzz/run_fuzz.sh).
//
//   fuzz_<target> [--runs N] [--seed S] [--max-len BYTES] [--write-seeds DIR]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "test/fuzz/fuzz_target.hpp"

namespace {

std::string mutate(const std::vector<std::string>& seeds, std::mt19937_64& rng, std::size_t max_len) {
  std::string input = seeds[rng() % seeds.size()];
  const int rounds = 1 + static_cast<int>(rng() % 6);
  for (int r = 0; r < rounds; ++r) {
    const std::size_t at = input.empty() ? 0 : rng() % input.size();
    switch (rng() % 7) {
      case 0:  // flip bits of a byte
        if (!input.empty()) input[at] = static_cast<char>(input[at] ^ static_cast<char>(1U << (rng() % 8)));
        break;
      case 1:  // set a byte to an interesting value
        if (!input.empty()) {
          static constexpr unsigned char kValues[] = {0x00, 0x01, 0x7f, 0x80, 0xff, 0x08, 0x10, 0x12, 0x1a, 0x22};
          input[at] = static_cast<char>(kValues[rng() % sizeof(kValues)]);
        }
        break;
      case 2: {  // insert random bytes
        std::string bytes(1 + rng() % 16, '\0');
        for (char& c : bytes) c = static_cast<char>(rng());
        input.insert(std::min(at, input.size()), bytes);
        break;
      }
      case 3:  // erase a run
        if (!input.empty()) input.erase(at, 1 + rng() % std::min<std::size_t>(32, input.size() - at));
        break;
      case 4: {  // splice: a piece of another seed
        const std::string& other = seeds[rng() % seeds.size()];
        if (!other.empty()) {
          const std::size_t from = rng() % other.size();
          input.insert(std::min(at, input.size()), other.substr(from, 1 + rng() % (other.size() - from)));
        }
        break;
      }
      case 5:  // a varint or length pushed to an extreme
        if (input.size() >= 2) {
          input[at] = static_cast<char>(0xff);
          if (at + 1 < input.size()) input[at + 1] = static_cast<char>(rng() % 2 == 0 ? 0xff : 0x7f);
        }
        break;
      case 6:  // truncate
        input.resize(at);
        break;
    }
  }
  if (input.size() > max_len) input.resize(max_len);
  return input;
}

int usage() {
  std::fprintf(stderr, "usage: fuzz_<target> [--runs N] [--seed S] [--max-len BYTES] [--write-seeds DIR]\n");
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  unsigned long long runs = 10000;
  unsigned long long seed = 1;
  std::size_t max_len = 65536;
  std::string write_seeds;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (i + 1 >= argc) return usage();
    const char* value = argv[++i];
    if (arg == "--runs") {
      runs = std::strtoull(value, nullptr, 10);
    } else if (arg == "--seed") {
      seed = std::strtoull(value, nullptr, 10);
    } else if (arg == "--max-len") {
      max_len = std::strtoull(value, nullptr, 10);
    } else if (arg == "--write-seeds") {
      write_seeds = value;
    } else {
      return usage();
    }
  }
  const std::vector<std::string> seeds = cvislam::fuzz::seeds();
  if (!write_seeds.empty()) {
    std::filesystem::create_directories(write_seeds);
    for (std::size_t i = 0; i < seeds.size(); ++i) {
      std::ofstream(std::filesystem::path(write_seeds) / ("seed" + std::to_string(i)), std::ios::binary) << seeds[i];
    }
    std::printf("wrote %zu seeds to %s\n", seeds.size(), write_seeds.c_str());
    return 0;
  }
  const auto start = std::chrono::steady_clock::now();
  for (const std::string& s : seeds) {
    LLVMFuzzerTestOneInput(reinterpret_cast<const std::uint8_t*>(s.data()), s.size());
  }
  std::mt19937_64 rng(seed);
  for (unsigned long long i = 0; i < runs; ++i) {
    const std::string input = mutate(seeds, rng, max_len);
    LLVMFuzzerTestOneInput(reinterpret_cast<const std::uint8_t*>(input.data()), input.size());
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("%zu seeds and %llu mutated inputs (seed %llu) run in %.1f s: no crash\n", seeds.size(), runs, seed,
              seconds);
  return 0;
}
