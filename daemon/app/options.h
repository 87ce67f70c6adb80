#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/selector.h"

namespace keyframed {

enum class DecisionFormat { Csv, JsonLines };

// Everything `keyframed select` can be told. Each field names its flag.
struct SelectOptions {
  std::string video;                               // positional VIDEO
  std::string outDir;                              // --out DIR (required)
  SelectorConfig selector;                         // --mode, --target, --band, --blur-*, ...
  DecisionFormat decisions = DecisionFormat::Csv;  // --decisions csv|jsonl
  int jpegQuality = 92;                            // --jpeg-quality 1..100
  std::int64_t maxFrames = -1;                     // --max-frames N (stop after N frames)
  std::optional<bool> progress;  // --progress / --no-progress (default: when stderr is a TTY)
  bool quiet = false;            // --quiet: no summary on stdout
};

struct ParseResult {
  bool ok = false;
  bool help = false;
  std::string error;  // one line
};

// Parses the arguments after `select`.
ParseResult parseSelectOptions(const std::vector<std::string>& args, SelectOptions& out);

std::string selectUsage();

}  // namespace keyframed
