#include <filesystem>
#include <fstream>
#include <sstream>

#include <gtest/gtest.h>

#include "app/decision_log.h"
#include "temp_dir.h"

namespace keyframed {
namespace {

std::vector<std::string> lines(const std::string& path) {
  std::ifstream f(path);
  std::vector<std::string> out;
  for (std::string l; std::getline(f, l);) out.push_back(l);
  return out;
}

TEST(DecisionLog, APromotedCandidateIsRewrittenAsKept) {
  const std::string path = (test::processTempDir("keyframed-unit") / "decisions.csv").string();
  DecisionLog log;
  std::string err;
  ASSERT_TRUE(log.open(path, DecisionFormat::Csv, err)) << err;
  Decision d0;
  d0.index = 0;
  d0.kept = true;
  d0.reason = Reason::First;
  Decision d1;
  d1.index = 1;
  d1.candidate = true;
  Decision d2;
  d2.index = 2;
  d2.reason = Reason::Blurry;
  d2.promotedIndex = 1;
  for (const Decision& d : {d0, d1, d2}) ASSERT_TRUE(log.add(d, err)) << err;
  ASSERT_TRUE(log.close(err));
  const auto l = lines(path);
  ASSERT_EQ(l.size(), 4u);
  EXPECT_EQ(l[0], DecisionLog::header());
  EXPECT_EQ(l[2].rfind("1,0,1,gap_fill,", 0), 0u) << l[2];
  EXPECT_EQ(l[3].rfind("2,0,0,blurry,0,1,", 0), 0u) << l[3];
}

TEST(DecisionLog, RowsAreWrittenWhenFinalAndAHeldCandidateIsBounded) {
  const std::string path =
      (test::processTempDir("keyframed-unit") / "decisions-hover.csv").string();
  DecisionLog log;
  std::string err;
  ASSERT_TRUE(log.open(path, DecisionFormat::Csv, err)) << err;
  Decision d;
  d.index = 0;
  d.kept = true;
  d.reason = Reason::First;
  ASSERT_TRUE(log.add(d, err));
  // Blurry frames with no candidate: nothing can change them, so they are on disk
  // at once (a power cut loses none).
  d.kept = false;
  d.reason = Reason::Blurry;
  for (d.index = 1; d.index <= 10; ++d.index) ASSERT_TRUE(log.add(d, err));
  EXPECT_EQ(lines(path).size(), 1u + 11u);
  // A candidate, then a long hover: its rows wait for a promotion, but not forever.
  d.reason = Reason::Redundant;
  d.candidate = true;
  ASSERT_TRUE(log.add(d, err));  // index 11
  d.candidate = false;
  for (d.index = 12; d.index < 12 + 50; ++d.index) ASSERT_TRUE(log.add(d, err));
  EXPECT_EQ(lines(path).size(), 1u + 11u) << "held while the candidate may be promoted";
  const std::int64_t end = 12 + static_cast<std::int64_t>(DecisionLog::kMaxHeldRows) + 10;
  for (; d.index < end; ++d.index) ASSERT_TRUE(log.add(d, err));
  const auto held = lines(path);
  EXPECT_EQ(held.size(), 1u + static_cast<std::size_t>(end)) << "written once held too long";
  EXPECT_EQ(held[12].rfind("11,0,0,redundant,1,", 0), 0u) << held[12];
  // The candidate is promoted after all: the promoting row says which one.
  d.reason = Reason::Blurry;
  d.promotedIndex = 11;
  ASSERT_TRUE(log.add(d, err));
  ASSERT_TRUE(log.close(err));
  const auto all = lines(path);
  ASSERT_EQ(all.size(), 2u + static_cast<std::size_t>(end));
  EXPECT_EQ(all.back().rfind(std::to_string(end) + ",0,0,blurry,0,11,", 0), 0u) << all.back();
}

TEST(DecisionLog, JsonLinesHaveOneObjectPerFrame) {
  const std::string path = (test::processTempDir("keyframed-unit") / "decisions.jsonl").string();
  DecisionLog log;
  std::string err;
  ASSERT_TRUE(log.open(path, DecisionFormat::JsonLines, err));
  Decision d;
  for (int i = 0; i < 3; ++i) {
    d.index = i;
    ASSERT_TRUE(log.add(d, err));
  }
  ASSERT_TRUE(log.close(err));
  const auto l = lines(path);
  ASSERT_EQ(l.size(), 3u);
  EXPECT_EQ(l[1].rfind("{\"index\":1,", 0), 0u);
  EXPECT_NE(l[1].find("\"overlap\":null"), std::string::npos);
}

TEST(DecisionLog, UnwritableDirectoryIsAnError) {
  DecisionLog log;
  std::string err;
  EXPECT_FALSE(log.open("/nonexistent-dir/decisions.csv", DecisionFormat::Csv, err));
  EXPECT_NE(err.find("cannot create"), std::string::npos);
}

TEST(DecisionLog, FullDiskIsReportedNotIgnored) {
  if (!std::filesystem::exists("/dev/full")) GTEST_SKIP() << "no /dev/full on this system";
  DecisionLog log;
  std::string err;
  // The header's write fails at the open already.
  bool ok = log.open("/dev/full", DecisionFormat::Csv, err);
  Decision d;
  d.kept = true;
  for (int i = 0; i < 2000 && ok; ++i) {
    d.index = i;
    ok = log.add(d, err);
  }
  if (ok) ok = log.close(err);
  EXPECT_FALSE(ok);
  EXPECT_NE(err.find("cannot"), std::string::npos);
}

}  // namespace
}  // namespace keyframed
