#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "app/options.h"
#include "app/text_io.h"
#include "core/selector.h"

namespace keyframed {

// One row per frame, in frame order, written as soon as it is final. A candidate's
// row (and every row after it) is held back, because a later frame can promote the
// candidate to keyframe (Reason::GapFill) and its row must then say so. A hover can
// hold a candidate for minutes: past kMaxHeldRows rows the held rows are written
// as they stand (bounded memory, little lost to a power cut); a later promotion of
// that candidate is then told only by the promoting row's `promoted` column.
// Rows a write error (a full disk) kept out are kept and written, whole, once the
// disk takes them (up to kMaxUnwrittenRows; past that the oldest are let go).
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

  static constexpr std::size_t kMaxHeldRows = 900;         // 30 s at 30 fps
  static constexpr std::size_t kMaxUnwrittenRows = 18000;  // 10 min at 30 fps, ~3 MB
  // After a write error, rows are tried again every this many frames (about 1 s).
  static constexpr int kRetryEvery = 30;

  // Rows let go unwritten (more than kMaxUnwrittenRows waited for the disk).
  [[nodiscard]] std::int64_t rowsLost() const { return rowsLost_; }

  static std::string header();
  static std::string csvRow(const Decision& d, const std::string& geotag = {});
  static std::string jsonRow(const Decision& d, const std::string& geotag = {});
  // The same rows appended to s (no newline): nothing is allocated once s has room.
  static void appendCsvRow(std::string& s, const Decision& d, std::string_view geotag = {});
  static void appendJsonRow(std::string& s, const Decision& d, std::string_view geotag = {});

 private:
  // Writes the first n pending rows (all by default); on an error they stay pending
  // and the file is cut back to its last whole row. After an error, only every
  // kRetryEvery-th call tries again unless `now`.
  bool flushPending(std::string& error, std::size_t n = SIZE_MAX, bool now = false);

  RowFile file_;
  DecisionFormat format_ = DecisionFormat::Csv;
  struct Row {
    Decision decision;
    std::string geotag;
  };
  // Rows not yet written: a held candidate's and those after it, and any a write
  // error kept out, in frame order. A vector: its room stays once grown, where a
  // deque of rows this size would take and free a block every other row.
  std::vector<Row> pending_;
  std::string text_;            // the rows being written
  bool heldCandidate_ = false;  // a candidate's row is pending: it may be promoted
  std::size_t heldRows_ = 0;    // its row and those after it
  std::int64_t rowsLost_ = 0;
  int retryIn_ = 0;        // calls until the next try after a write error
  std::string lastError_;  // that error
  std::string path_;
};

}  // namespace keyframed
