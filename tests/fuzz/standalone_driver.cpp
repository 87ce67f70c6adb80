// Runs LLVMFuzzerTestOneInput without libFuzzer (for GCC builds and the
// sanitizer build of the unit tests): the seed corpus, files given on the command
// line, then deterministic random mutations of the seeds. It finds less than
// coverage-guided fuzzing (tools/fuzz.sh) but runs everywhere, in every CI run.
//
//   fuzz_mavlink_standalone [--iterations N] [--seed S] [--write-seeds DIR] [FILE...]
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>
#include <string>
#include <vector>

#include "seeds.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

namespace {

using Bytes = std::vector<std::uint8_t>;

void run(const Bytes& b) {
  LLVMFuzzerTestOneInput(b.data(), b.size());
}

Bytes mutate(const std::vector<Bytes>& seeds, std::mt19937_64& rng) {
  Bytes out = seeds[rng() % seeds.size()];
  const int edits = 1 + static_cast<int>(rng() % 8);
  for (int e = 0; e < edits; ++e) {
    switch (rng() % 6) {
      case 0:  // flip a bit
        if (!out.empty()) out[rng() % out.size()] ^= static_cast<std::uint8_t>(1U << (rng() % 8));
        break;
      case 1:  // random byte
        if (!out.empty()) out[rng() % out.size()] = static_cast<std::uint8_t>(rng());
        break;
      case 2:  // truncate
        if (!out.empty()) out.resize(rng() % out.size());
        break;
      case 3: {  // splice in another seed
        const Bytes& other = seeds[rng() % seeds.size()];
        out.insert(out.begin() + static_cast<std::ptrdiff_t>(out.empty() ? 0 : rng() % out.size()),
                   other.begin(), other.end());
        break;
      }
      case 4:  // start bytes, which resynchronise the parser mid-frame
        out.insert(out.begin() + static_cast<std::ptrdiff_t>(out.empty() ? 0 : rng() % out.size()),
                   (rng() & 1U) != 0 ? 0xFD : 0xFE);
        break;
      default:  // random garbage run
        for (int i = static_cast<int>(rng() % 32); i > 0; --i) {
          out.push_back(static_cast<std::uint8_t>(rng()));
        }
    }
  }
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  long iterations = 20000;
  std::uint64_t seed = 1;
  std::vector<std::string> files;
  std::string seedDir;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--iterations" && i + 1 < argc) {
      iterations = std::strtol(argv[++i], nullptr, 10);
    } else if (a == "--seed" && i + 1 < argc) {
      seed = std::strtoull(argv[++i], nullptr, 10);
    } else if (a == "--write-seeds" && i + 1 < argc) {
      seedDir = argv[++i];
    } else if (!a.empty() && a[0] == '-') {
      std::fprintf(stderr, "fuzz_mavlink_standalone: unknown option %s\n", a.c_str());
      return 2;
    } else {
      files.push_back(a);
    }
  }
  const std::vector<Bytes> seeds = keyframed::fuzz::mavlinkSeeds();
  if (!seedDir.empty()) {
    std::filesystem::create_directories(seedDir);
    for (std::size_t i = 0; i < seeds.size(); ++i) {
      std::ofstream(seedDir + "/seed-" + std::to_string(i), std::ios::binary)
          .write(reinterpret_cast<const char*>(seeds[i].data()),
                 static_cast<std::streamsize>(seeds[i].size()));
    }
    std::printf("wrote %zu seeds to %s\n", seeds.size(), seedDir.c_str());
    return 0;
  }
  for (const auto& s : seeds) run(s);
  for (const auto& f : files) {
    std::ifstream in(f, std::ios::binary);
    if (!in) {
      std::fprintf(stderr, "fuzz_mavlink_standalone: cannot read %s\n", f.c_str());
      return 1;
    }
    run(Bytes(std::istreambuf_iterator<char>(in), {}));
  }
  std::mt19937_64 rng(seed);
  std::size_t bytes = 0;
  for (long i = 0; i < iterations; ++i) {
    const Bytes b = mutate(seeds, rng);
    bytes += b.size();
    run(b);
  }
  std::printf("fuzz_mavlink_standalone: %zu seeds, %zu files, %ld mutated inputs (%zu bytes): ok\n",
              seeds.size(), files.size(), iterations, bytes);
  return 0;
}
