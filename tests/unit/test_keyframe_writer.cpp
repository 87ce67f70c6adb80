#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <climits>
#include <csignal>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "app/decision_log.h"
#include "app/keyframe_writer.h"
#include "app/text_io.h"

namespace keyframed {
namespace {

namespace fs = std::filesystem;

// A disk that fills up and gets room again, without root: RLIMIT_FSIZE makes a write
// past `bytes` fail (EFBIG; SIGXFSZ ignored meanwhile), a write across it short.
class FullDisk {
 public:
  explicit FullDisk(rlim_t bytes) {
    getrlimit(RLIMIT_FSIZE, &saved_);
    previous_ = std::signal(SIGXFSZ, SIG_IGN);
    rlimit small = saved_;
    small.rlim_cur = bytes;
    setrlimit(RLIMIT_FSIZE, &small);
  }
  ~FullDisk() { roomAgain(); }
  FullDisk(const FullDisk&) = delete;
  FullDisk& operator=(const FullDisk&) = delete;
  void roomAgain() {
    if (done_) return;
    setrlimit(RLIMIT_FSIZE, &saved_);
    std::signal(SIGXFSZ, previous_);
    done_ = true;
  }

 private:
  rlimit saved_{};
  void (*previous_)(int) = SIG_DFL;
  bool done_ = false;
};

std::string read(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  std::string s(fs::exists(p) ? fs::file_size(p) : 0, '\0');
  f.read(s.data(), static_cast<std::streamsize>(s.size()));
  return s;
}

std::vector<std::string> lines(const fs::path& p) {
  std::ifstream f(p);
  std::vector<std::string> out;
  for (std::string l; std::getline(f, l);) out.push_back(l);
  return out;
}

// A disk that reports an I/O error on syncing keyframes.csv: this executable's
// fdatasync (below) comes before the C library's, for the writer's calls too.
std::atomic<bool> g_failIndexSync{false};

bool isIndexFile(int fd) {
  char link[PATH_MAX];
  const std::string proc = "/proc/self/fd/" + std::to_string(fd);
  const ssize_t n = ::readlink(proc.c_str(), link, sizeof link - 1);
  return n > 0 && std::string_view(link, static_cast<std::size_t>(n)).ends_with("/keyframes.csv");
}

class WriterTest : public testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::path(testing::TempDir()) /
           ("keyframed-writer-" + std::to_string(getpid()) + "-" +
            testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  // A 320x240 keyframe of noise (tens of kB of JPEG, far above the small "disk").
  static cv::Mat noise(int seed) {
    cv::Mat m(240, 320, CV_8UC3);
    cv::theRNG().state = static_cast<std::uint64_t>(seed) + 1;
    cv::randu(m, 0, 256);
    return m;
  }

  // Writes keyframe `index`; returns whether it was saved and keeps its bytes.
  bool write(KeyframeWriter& w, std::int64_t index, std::string& error) {
    KeyframeRecord rec;
    const bool saved =
        w.write(noise(static_cast<int>(index)), index, index * 1'000'000, nullptr, rec, error);
    EXPECT_TRUE(rec.encoded) << error;
    EXPECT_EQ(rec.indexed, saved);
    EXPECT_EQ(rec.file.empty(), !saved);
    jpegs_.emplace_back(w.lastJpeg().begin(), w.lastJpeg().end());
    return saved;
  }

  [[nodiscard]] KeyframeWriterConfig configHere() const {
    KeyframeWriterConfig config;
    config.dir = dir_.string();
    return config;
  }

  // Adds rows from d.index on, one a frame, until the log writes again (it tries
  // about once a second of frames after a write error); d.index ends past the last.
  static bool addUntilWritten(DecisionLog& log, Decision& d, std::string& err) {
    for (int i = 0; i <= DecisionLog::kRetryEvery; ++i) {
      const bool written = log.add(d, err);
      ++d.index;
      if (written) return true;
    }
    return false;
  }

  // The index's sequence and file columns, checking every row is whole.
  std::vector<std::pair<int, std::string>> indexRows() const {
    const auto l = lines(dir_ / "keyframes.csv");
    EXPECT_FALSE(l.empty());
    std::vector<std::pair<int, std::string>> rows;
    for (std::size_t i = 1; i < l.size(); ++i) {
      EXPECT_EQ(l[i].back(), '"') << "a row cut short: " << l[i];
      const auto c1 = l[i].find(',');
      const auto c2 = l[i].find(',', c1 + 1);
      const auto c3 = l[i].find(',', c2 + 1);
      rows.emplace_back(std::stoi(l[i].substr(0, c1)), l[i].substr(c2 + 1, c3 - c2 - 1));
    }
    return rows;
  }

  fs::path dir_;
  std::vector<std::vector<std::uint8_t>> jpegs_;  // by sequence
};

TEST_F(WriterTest, ARowFileEndsAtItsLastWholeRowWhenTheDiskTakesPartOfOne) {
  RowFile f;
  std::string error;
  const fs::path path = dir_ / "rows.csv";
  ASSERT_TRUE(f.open(path.string(), "a,b\n", error)) << error;
  const std::string row(100, 'x');
  {
    FullDisk disk(1000);  // room for the header and 9 rows of 101 bytes, and a part
    int written = 0;
    while (f.append(row + "\n", error)) ++written;
    EXPECT_EQ(written, 9);
    EXPECT_NE(error.find("cannot write " + path.string()), std::string::npos) << error;
    EXPECT_EQ(error.find("cannot cut back"), std::string::npos) << error;
    EXPECT_EQ(fs::file_size(path), 4U + 9 * 101);  // not 1000: the part is gone
    disk.roomAgain();
  }
  // The same row, again and whole, then on as before.
  ASSERT_TRUE(f.append(row + "\n", error)) << error;
  ASSERT_TRUE(f.append("last\n", error)) << error;
  ASSERT_TRUE(f.close(error)) << error;
  const auto l = lines(path);
  ASSERT_EQ(l.size(), 12U);
  for (std::size_t i = 1; i < 11; ++i) EXPECT_EQ(l[i], row) << i;
  EXPECT_EQ(l[11], "last");
  EXPECT_FALSE(f.append("after close\n", error));
}

TEST_F(WriterTest, KeyframesAFullDiskDidNotTakeAreSavedInOrderOnceItHasRoom) {
  KeyframeWriter w;
  std::string error;
  KeyframeWriterConfig config = configHere();
  ASSERT_TRUE(w.open(config, error)) << error;
  ASSERT_TRUE(write(w, 0, error)) << error;
  EXPECT_TRUE(w.takeIndexedLate().empty());  // indexed in time
  {
    FullDisk full(8000);  // the index fits, a keyframe does not
    EXPECT_FALSE(write(w, 5, error));
    EXPECT_NE(error.find("000005.jpg"), std::string::npos) << error;
    EXPECT_FALSE(write(w, 9, error));
    EXPECT_EQ(w.count(), 3);
    EXPECT_EQ(w.saved(), 1);
    EXPECT_FALSE(fs::exists(dir_ / "000005.jpg"));
    EXPECT_FALSE(fs::exists(dir_ / "000005.jpg.tmp")) << "a part-written file left behind";
  }
  // Room again: the held ones go first, then the new one.
  ASSERT_TRUE(write(w, 12, error)) << error;
  EXPECT_EQ(w.saved(), 4);
  EXPECT_EQ(w.savedLate(), 2);
  EXPECT_EQ(w.letGo(), 0);
  // Sequences 1 and 2 are on disk now (not 3: its write() said so itself), once.
  EXPECT_EQ(w.takeIndexedLate(), (std::vector<std::int64_t>{1, 2}));
  EXPECT_TRUE(w.takeIndexedLate().empty());
  {
    FullDisk full(8000);
    EXPECT_FALSE(write(w, 20, error));
    full.roomAgain();
    ASSERT_TRUE(w.close(error)) << error;  // saved at the close
  }
  EXPECT_EQ(w.saved(), 5);
  const std::vector<std::pair<int, std::string>> expected = {{0, "000000.jpg"},
                                                             {1, "000005.jpg"},
                                                             {2, "000009.jpg"},
                                                             {3, "000012.jpg"},
                                                             {4, "000020.jpg"}};
  EXPECT_EQ(indexRows(), expected);
  for (const auto& [seq, file] : expected) {
    const std::string bytes = read(dir_ / file);
    const auto& jpeg = jpegs_[static_cast<std::size_t>(seq)];
    EXPECT_EQ(bytes, std::string(jpeg.begin(), jpeg.end())) << file;
  }
}

TEST_F(WriterTest, AKeyframeSavedWhoseRowTheDiskDidNotTakeIsIndexedLate) {
  // Small keyframes (a few hundred bytes of JPEG) and a file size limit just past the
  // index: the picture is saved, its row is not; the next keyframe writes it first.
  KeyframeWriter w;
  std::string error;
  ASSERT_TRUE(w.open(configHere(), error)) << error;
  cv::Mat small(16, 16, CV_8UC3);
  KeyframeRecord rec;
  constexpr int kBefore = 60;  // rows enough to make the index longer than a picture
  for (int i = 0; i < kBefore; ++i) {
    cv::randu(small, 0, 256);
    ASSERT_TRUE(w.write(small, i, i * 1'000'000LL, nullptr, rec, error)) << error;
  }
  EXPECT_TRUE(w.takeIndexedLate().empty());
  const auto indexSize = fs::file_size(dir_ / "keyframes.csv");
  ASSERT_GT(indexSize, fs::file_size(dir_ / "000059.jpg") + 100);
  {
    FullDisk full(indexSize + 20);  // the picture fits, a row more does not
    EXPECT_FALSE(w.write(small, kBefore, kBefore * 1'000'000LL, nullptr, rec, error));
    EXPECT_FALSE(rec.indexed);
    EXPECT_FALSE(rec.file.empty()) << "the picture is saved";
    EXPECT_TRUE(fs::exists(dir_ / "000060.jpg"));
    EXPECT_NE(error.find("keyframes.csv"), std::string::npos) << error;
  }
  ASSERT_TRUE(w.write(small, kBefore + 1, (kBefore + 1) * 1'000'000LL, nullptr, rec, error))
      << error;
  EXPECT_TRUE(rec.indexed);
  EXPECT_EQ(w.takeIndexedLate(), (std::vector<std::int64_t>{kBefore}));  // not the next one
  EXPECT_EQ(w.savedLate(), 0);  // the picture itself was saved in time
  ASSERT_TRUE(w.close(error)) << error;
  const auto rows = indexRows();
  ASSERT_EQ(rows.size(), static_cast<std::size_t>(kBefore + 2));
  for (int i = 0; i < kBefore + 2; ++i) EXPECT_EQ(rows[static_cast<std::size_t>(i)].first, i);
}

TEST_F(WriterTest, AnIndexTheDiskCannotSyncIsAnErrorThoughItsRowsAreWritten) {
  KeyframeWriter w;
  std::string error;
  ASSERT_TRUE(w.open(configHere(), error)) << error;
  cv::Mat small(16, 16, CV_8UC3);
  cv::randu(small, 0, 256);
  KeyframeRecord rec;
  ASSERT_TRUE(w.write(small, 0, 0, nullptr, rec, error)) << error;
  g_failIndexSync = true;
  const bool saved = w.write(small, 1, 1'000'000, nullptr, rec, error);
  g_failIndexSync = false;
  EXPECT_FALSE(saved) << "an error the run must report";
  EXPECT_NE(error.find("cannot sync " + (dir_ / "keyframes.csv").string()), std::string::npos)
      << error;
  EXPECT_NE(error.find(std::strerror(EIO)), std::string::npos) << error;
  EXPECT_EQ(w.syncErrors(), 1);
  // The keyframe is on disk and in the index (it reads back): served, not held.
  EXPECT_TRUE(rec.indexed);
  EXPECT_FALSE(rec.file.empty());
  EXPECT_EQ(w.saved(), 2);
  ASSERT_TRUE(w.write(small, 2, 2'000'000, nullptr, rec, error)) << error;
  EXPECT_TRUE(w.takeIndexedLate().empty()) << "no row was late";
  ASSERT_TRUE(w.close(error)) << error;
  EXPECT_EQ(indexRows(), (std::vector<std::pair<int, std::string>>{
                             {0, "000000.jpg"}, {1, "000001.jpg"}, {2, "000002.jpg"}}));
}

TEST_F(WriterTest, HeldKeyframesAreBoundedTheOldestLetGo) {
  KeyframeWriter w;
  std::string error;
  KeyframeWriterConfig config = configHere();
  config.maxHeldBytes = 1;  // one keyframe held at most
  ASSERT_TRUE(w.open(config, error)) << error;
  {
    FullDisk full(8000);
    for (std::int64_t i = 0; i < 4; ++i) EXPECT_FALSE(write(w, i, error));
  }
  EXPECT_EQ(w.letGo(), 3);
  ASSERT_TRUE(w.close(error)) << error;
  EXPECT_EQ(w.saved(), 1);
  EXPECT_EQ(w.count() - w.saved(), 3);
  const std::vector<std::pair<int, std::string>> expected = {{3, "000003.jpg"}};
  EXPECT_EQ(indexRows(), expected);
  EXPECT_FALSE(fs::exists(dir_ / "000000.jpg"));
}

TEST_F(WriterTest, AKeyframeStillHeldAtTheCloseIsAnError) {
  KeyframeWriter w;
  std::string error;
  KeyframeWriterConfig config = configHere();
  ASSERT_TRUE(w.open(config, error)) << error;
  FullDisk full(8000);
  EXPECT_FALSE(write(w, 0, error));
  error.clear();
  EXPECT_FALSE(w.close(error));
  EXPECT_NE(error.find("000000.jpg"), std::string::npos) << error;
}

TEST_F(WriterTest, DecisionRowsAWriteErrorKeptOutAreWrittenWholeLater) {
  const fs::path path = dir_ / "decisions.csv";
  DecisionLog log;
  std::string err;
  ASSERT_TRUE(log.open(path.string(), DecisionFormat::Csv, err)) << err;
  Decision d;
  d.reason = Reason::Blurry;
  for (d.index = 0; d.index < 5; ++d.index) ASSERT_TRUE(log.add(d, err)) << err;
  const auto before = fs::file_size(path);
  {
    // Room for part of a row: the write is cut short, the file cut back.
    FullDisk full(before + 40);
    for (; d.index < 15; ++d.index) EXPECT_FALSE(log.add(d, err));
    EXPECT_NE(err.find("decisions.csv"), std::string::npos) << err;
    EXPECT_EQ(fs::file_size(path), before) << "a part-written row left in the file";
  }
  // Tried again about a second of frames later: then every held row goes.
  ASSERT_TRUE(addUntilWritten(log, d, err)) << err;
  ASSERT_TRUE(log.close(err)) << err;
  EXPECT_EQ(log.rowsLost(), 0);
  const auto l = lines(path);
  ASSERT_EQ(l.size(), 1u + static_cast<std::size_t>(d.index));
  for (int i = 0; i < d.index; ++i) {
    EXPECT_EQ(l[static_cast<std::size_t>(i) + 1].rfind(std::to_string(i) + ",", 0), 0u)
        << l[static_cast<std::size_t>(i) + 1];
  }
}

TEST_F(WriterTest, ACandidatePromotedWhileItsRowWaitsForTheDiskIsWrittenAsKept) {
  const fs::path path = dir_ / "decisions.csv";
  DecisionLog log;
  std::string err;
  ASSERT_TRUE(log.open(path.string(), DecisionFormat::Csv, err)) << err;
  Decision d;
  d.reason = Reason::Blurry;
  for (d.index = 0; d.index < 3; ++d.index) ASSERT_TRUE(log.add(d, err)) << err;
  {
    FullDisk full(fs::file_size(path));
    for (; d.index < 5; ++d.index) EXPECT_FALSE(log.add(d, err));
    Decision candidate = d;  // index 5
    candidate.reason = Reason::Redundant;
    candidate.candidate = true;
    EXPECT_FALSE(log.add(candidate, err));
    Decision promoting = d;
    promoting.index = 6;
    promoting.promotedIndex = 5;
    EXPECT_FALSE(log.add(promoting, err));
    d.index = 7;
  }
  ASSERT_TRUE(addUntilWritten(log, d, err)) << err;
  ASSERT_TRUE(log.close(err)) << err;
  const auto l = lines(path);
  ASSERT_GE(l.size(), 1u + 8u);
  EXPECT_EQ(l[6].rfind("5,0,1,gap_fill,0,", 0), 0u) << l[6];
  EXPECT_EQ(l[7].rfind("6,0,0,blurry,0,5,", 0), 0u) << l[7];
}

TEST_F(WriterTest, DecisionRowsStillUnwrittenAtTheCloseAreCountedAndAnError) {
  const fs::path path = dir_ / "decisions.jsonl";
  DecisionLog log;
  std::string err;
  ASSERT_TRUE(log.open(path.string(), DecisionFormat::JsonLines, err)) << err;
  Decision d;
  d.kept = true;
  FullDisk full(10);
  for (d.index = 0; d.index < 3; ++d.index) EXPECT_FALSE(log.add(d, err));
  err.clear();
  EXPECT_FALSE(log.close(err));
  EXPECT_EQ(log.rowsLost(), 3);
  EXPECT_NE(err.find("decisions.jsonl"), std::string::npos) << err;
  full.roomAgain();
  EXPECT_EQ(fs::file_size(path), 0u);
}

}  // namespace
}  // namespace keyframed

extern "C" int fdatasync(int fd) {
  if (keyframed::g_failIndexSync.load() && keyframed::isIndexFile(fd)) {
    errno = EIO;
    return -1;
  }
  return static_cast<int>(::syscall(SYS_fdatasync, fd));
}
