#pragma once

#include <cstdio>
#include <deque>
#include <string>

#include "app/options.h"
#include "core/selector.h"

namespace keyframed {

// One row per frame, in frame order, written as soon as it is final. A candidate's
// row (and every row after it) is held back, because a later frame can promote the
// candidate to keyframe (Reason::GapFill) and its row must then say so. A hover can
// hold a candidate for minutes: past kMaxHeldRows rows the held rows are written
// as they stand (bounded memory, little lost to a power cut); a later promotion of
// that candidate is then told only by the promoting row's `promoted` column.
class DecisionLog {
 public:
  DecisionLog() = default;
  DecisionLog(const DecisionLog&) = delete;
  DecisionLog& operator=(const DecisionLog&) = delete;
  ~DecisionLog();

  bool open(const std::string& path, DecisionFormat format, std::string& error);
  // Adds a decision; returns false on a write error. `geotag` says how a keyframe
  // was tagged ("ok", or why position or attitude is missing); empty otherwise.
  bool add(const Decision& d, std::string& error, const std::string& geotag = {});
  // Marks an earlier, still pending row as a keyframe (the selector's finish()).
  void markGapFill(std::int64_t index);
  // Sets the geotag note of a pending row (a candidate promoted to keyframe).
  void setGeotag(std::int64_t index, const std::string& geotag);
  bool close(std::string& error);

  static constexpr std::size_t kMaxHeldRows = 900;  // 30 s at 30 fps

  static std::string header();
  static std::string csvRow(const Decision& d, const std::string& geotag = {});
  static std::string jsonRow(const Decision& d, const std::string& geotag = {});

 private:
  bool flushPending(std::string& error);

  std::FILE* file_ = nullptr;
  DecisionFormat format_ = DecisionFormat::Csv;
  struct Row {
    Decision decision;
    std::string geotag;
  };
  std::deque<Row> pending_;  // empty, or a held candidate's row and those after it
  std::string path_;
};

}  // namespace keyframed
