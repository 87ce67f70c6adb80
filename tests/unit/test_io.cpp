// The Rust I/O crate through its C++ wrappers: MCAP writing and Zenoh in-process.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <span>
#include <string>
#include <string_view>
#include <thread>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "output/flight_outputs.h"
#include "output/foxglove_proto.h"
#include "output/h264.h"
#include "output/io.h"
#include "output/io_ffi.h"
#include "output/keyframe_publisher.h"
#include "output/mcap_recorder.h"
#include "output/mcap_repair.h"
#include "output/mcap_replay.h"
#include "temp_dir.h"

namespace keyframed {
namespace {

// In this process's own temp dir, removed at its exit (no stale parts of a run before).
std::string tempPath(const std::string& name) {
  return (test::processTempDir("keyframed-unit") / name).string();
}

std::vector<std::uint8_t> readAll(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

const std::uint8_t kMagic[] = {0x89, 'M', 'C', 'A', 'P', 0x30, '\r', '\n'};

bool hasMagic(const std::vector<std::uint8_t>& b, bool atEnd) {
  if (b.size() < 16) return false;
  const std::size_t off = atEnd ? b.size() - 8 : 0;
  return std::equal(std::begin(kMagic), std::end(kMagic), b.begin() + static_cast<long>(off));
}

TEST(McapWriter, WritesAFileWithHeaderAndFooterMagic) {
  const std::string path = tempPath("basic.mcap");
  std::string error;
  auto w = McapWriter::open({path, "zstd", 4096}, error);
  ASSERT_TRUE(w) << error;
  std::uint16_t schema = 0, channel = 0;
  const std::string js = R"({"type":"object"})";
  ASSERT_TRUE(w->addSchema("test.Msg", "jsonschema",
                           {reinterpret_cast<const std::uint8_t*>(js.data()), js.size()}, schema,
                           error))
      << error;
  EXPECT_GT(schema, 0);
  ASSERT_TRUE(w->addChannel(schema, "/test", "json", {{"k", "v"}}, channel, error)) << error;
  const std::string msg = R"({"a":1})";
  for (std::uint32_t i = 0; i < 100; ++i) {
    ASSERT_TRUE(w->write(channel, i, 1000 + i, 1000 + i,
                         {reinterpret_cast<const std::uint8_t*>(msg.data()), msg.size()}, error))
        << error;
  }
  ASSERT_TRUE(w->flush(true, error)) << error;
  // After a flush the file already starts with the magic and holds the messages.
  EXPECT_TRUE(hasMagic(readAll(path), false));
  ASSERT_TRUE(w->close(error)) << error;
  const auto bytes = readAll(path);
  EXPECT_TRUE(hasMagic(bytes, false));
  EXPECT_TRUE(hasMagic(bytes, true));
  // Closing twice is harmless.
  EXPECT_TRUE(w->close(error));
}

// Reads the messages of `topics` with the streaming reader: (topic index, time, data).
struct ReadBack {
  std::vector<std::tuple<std::uint32_t, std::uint64_t, std::string>> messages;
  bool truncated = false;
  std::string error;
};

ReadBack readMcap(const std::string& path, std::vector<const char*> topics) {
  ReadBack r;
  char err[256] = {};
  kfio_mcap_reader* reader =
      kfio_mcap_reader_open(path.c_str(), topics.data(), topics.size(), err, sizeof err);
  if (reader == nullptr) {
    r.error = err;
    return r;
  }
  std::uint32_t topic = 0;
  std::uint64_t time = 0;
  const std::uint8_t* data = nullptr;
  std::size_t len = 0;
  while (kfio_mcap_reader_next(reader, &topic, &time, &data, &len) == 1)
    r.messages.emplace_back(topic, time, std::string(reinterpret_cast<const char*>(data), len));
  r.truncated = kfio_mcap_reader_truncated(reader) != 0;
  kfio_mcap_reader_close(reader);
  return r;
}

// 1000 JSON messages, a third on /b and the rest on /a (with channel metadata), in
// chunks of 2 KiB compressed as `compression`; a channel /never-written without any,
// with a schema of its own.
void writeSample(const std::string& path, const std::string& compression) {
  std::string error;
  auto w = McapWriter::open({path, compression, 2048}, error);
  ASSERT_TRUE(w) << error;
  std::uint16_t schema = 0, other = 0, a = 0, b = 0, empty = 0;
  ASSERT_TRUE(w->addSchema("s", "jsonschema", {}, schema, error)) << error;
  ASSERT_TRUE(w->addSchema("never.Written", "jsonschema", {}, other, error)) << error;
  ASSERT_TRUE(w->addChannel(schema, "/a", "json", {{"k", "v"}}, a, error)) << error;
  ASSERT_TRUE(w->addChannel(other, "/never-written", "json", {}, empty, error)) << error;
  ASSERT_TRUE(w->addChannel(schema, "/b", "json", {}, b, error)) << error;
  for (std::uint32_t i = 0; i < 1000; ++i) {
    const std::string msg = "message " + std::to_string(i) + std::string(i % 97, 'x');
    ASSERT_TRUE(w->write(i % 3 == 0 ? b : a, i, 5000 + i, 5000 + i,
                         {reinterpret_cast<const std::uint8_t*>(msg.data()), msg.size()}, error))
        << error;
  }
  ASSERT_TRUE(w->close(error)) << error;
}

TEST(McapReader, StreamsTheWantedTopicsAndReportsACut) {
  const std::string path = tempPath("read.mcap");
  ASSERT_NO_FATAL_FAILURE(writeSample(path, "zstd"));

  ReadBack r = readMcap(path, {"/b", "/nothing"});
  ASSERT_EQ(r.error, "");
  ASSERT_EQ(r.messages.size(), 334U);
  EXPECT_FALSE(r.truncated);
  for (std::size_t k = 0; k < r.messages.size(); ++k) {
    const auto i = static_cast<std::uint32_t>(3 * k);
    EXPECT_EQ(std::get<0>(r.messages[k]), 0U);
    EXPECT_EQ(std::get<1>(r.messages[k]), 5000U + i);
    EXPECT_EQ(std::get<2>(r.messages[k]),
              "message " + std::to_string(i) + std::string(i % 97, 'x'));
  }

  // Cut in the middle: what precedes the cut, then "truncated".
  const auto bytes = readAll(path);
  const std::string cut = tempPath("read-cut.mcap");
  std::ofstream(cut, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<long>(bytes.size() / 2));
  r = readMcap(cut, {"/a", "/b"});
  ASSERT_EQ(r.error, "");
  EXPECT_TRUE(r.truncated);
  EXPECT_GT(r.messages.size(), 100U);
  EXPECT_LT(r.messages.size(), 1000U);

  // Garbage after the magic (huge record lengths): an error, not an allocation.
  std::vector<std::uint8_t> garbage(std::begin(kMagic), std::end(kMagic));
  for (int i = 0; i < 4096; ++i) garbage.push_back(static_cast<std::uint8_t>(i * 7 + 0xF3));
  const std::string junk = tempPath("junk.mcap");
  std::ofstream(junk, std::ios::binary)
      .write(reinterpret_cast<const char*>(garbage.data()), static_cast<long>(garbage.size()));
  r = readMcap(junk, {"/a"});
  ASSERT_EQ(r.error, "");
  EXPECT_TRUE(r.messages.empty());
  EXPECT_TRUE(r.truncated);

  // Not an MCAP file at all, or none: an error at open.
  EXPECT_NE(readMcap(tempPath("missing.mcap"), {"/a"}).error.find("cannot read"),
            std::string::npos);
  std::ofstream(junk, std::ios::binary) << "hello";
  EXPECT_NE(readMcap(junk, {"/a"}).error.find("not an MCAP file"), std::string::npos);
}

TEST(McapRepair, AFileCutShortIsRewrittenCompleteWithWhatReadsBack) {
  const std::string path = tempPath("flights/a/flight.mcap");
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  ASSERT_NO_FATAL_FAILURE(writeSample(path, "none"));
  std::string error;
  EXPECT_TRUE(mcapComplete(path));
  const auto whole = readAll(path);
  std::ofstream(path, std::ios::binary | std::ios::trunc)
      .write(reinterpret_cast<const char*>(whole.data()), static_cast<long>(whole.size() / 2));
  EXPECT_FALSE(mcapComplete(path));
  const ReadBack cut = readMcap(path, {"/a", "/b"});
  ASSERT_TRUE(cut.truncated);

  // A stop set before it starts: nothing replaced, an error.
  std::atomic<int> stop{1};
  std::uint64_t n = 0;
  EXPECT_FALSE(recoverMcap(path, path + ".x", n, error, &stop));
  EXPECT_NE(error.find("stopped"), std::string::npos) << error;
  EXPECT_FALSE(std::filesystem::exists(path + ".x"));

  // The running flight (b) is left alone; a half-made .recovering file goes.
  const std::string running = tempPath("flights/b/flight.mcap");
  std::filesystem::create_directories(std::filesystem::path(running).parent_path());
  std::filesystem::copy_file(path, running, std::filesystem::copy_options::overwrite_existing);
  std::ofstream(path + ".recovering") << "half";
  stop = 0;
  // No room for the copy and the reserve: left as it is, and said why.
  const auto noRoom =
      repairFlightRecords(tempPath("flights"), tempPath("flights/b"), stop, std::uint64_t{1} << 62);
  ASSERT_EQ(noRoom.size(), 1U);
  EXPECT_NE(noRoom[0].error.find("not repaired now"), std::string::npos) << noRoom[0].error;
  EXPECT_FALSE(mcapComplete(path));
  const auto repaired = repairFlightRecords(tempPath("flights"), tempPath("flights/b"), stop);
  ASSERT_EQ(repaired.size(), 1U);
  EXPECT_EQ(repaired[0].path, path);
  EXPECT_EQ(repaired[0].error, "");
  EXPECT_EQ(repaired[0].messages, cut.messages.size());
  EXPECT_TRUE(mcapComplete(path));
  EXPECT_FALSE(mcapComplete(running));
  EXPECT_FALSE(std::filesystem::exists(path + ".recovering"));
  const ReadBack again = readMcap(path, {"/a", "/b"});
  EXPECT_FALSE(again.truncated);
  EXPECT_EQ(again.messages, cut.messages);
  // The channel without messages, and its schema, are there too (uncompressed: the
  // sample's chunks are, and the repair keeps the first chunk's compression).
  const auto fixed = readAll(path);
  const std::string_view bytes(reinterpret_cast<const char*>(fixed.data()), fixed.size());
  EXPECT_NE(bytes.find("/never-written"), std::string_view::npos);
  EXPECT_NE(bytes.find("never.Written"), std::string_view::npos);
  // Complete now: a second pass has nothing to do.
  EXPECT_TRUE(repairFlightRecords(tempPath("flights"), tempPath("flights/b"), stop).empty());
  // A part created but never written (a kill or power cut as it began: empty, or a
  // block of zeros) holds nothing: removed, and said so, not refused at every start.
  const std::string empty = tempPath("flights/a/flight-001.mcap");
  const std::string zeros = tempPath("flights/a/flight-002.mcap");
  std::ofstream(empty).close();
  std::ofstream(zeros, std::ios::binary) << std::string(4096, '\0');
  const auto stillborn = repairFlightRecords(tempPath("flights"), tempPath("flights/b"), stop);
  ASSERT_EQ(stillborn.size(), 2U);
  for (const McapRepair& r : stillborn) {
    EXPECT_TRUE(r.removed) << r.path;
    EXPECT_EQ(r.error, "") << r.path;
    EXPECT_FALSE(std::filesystem::exists(r.path)) << r.path;
  }
  EXPECT_TRUE(repairFlightRecords(tempPath("flights"), tempPath("flights/b"), stop).empty());
  // What is not an MCAP file stays as it is.
  const std::string text = tempPath("flights/a/notes.mcap");
  std::ofstream(text) << "not a record";
  const auto refused = repairFlightRecords(tempPath("flights"), tempPath("flights/b"), stop);
  ASSERT_EQ(refused.size(), 1U);
  EXPECT_NE(refused[0].error.find("not an MCAP file"), std::string::npos) << refused[0].error;
  EXPECT_EQ(readAll(text).size(), 12U);
  std::filesystem::remove(text);
}

TEST(McapRepair, CompressedRecordsAreRepairedInTheirOwnCompression) {
  // zstd (select's records) and lz4: the chunks before the cut decompress, and the
  // repaired file is chunked in the same compression, complete and readable.
  for (const std::string codec : {"zstd", "lz4"}) {
    SCOPED_TRACE(codec);
    const std::string path = tempPath("repair-" + codec + ".mcap");
    ASSERT_NO_FATAL_FAILURE(writeSample(path, codec));
    const auto whole = readAll(path);
    std::ofstream(path, std::ios::binary | std::ios::trunc)
        .write(reinterpret_cast<const char*>(whole.data()), static_cast<long>(whole.size() / 2));
    const ReadBack cut = readMcap(path, {"/a", "/b"});
    ASSERT_TRUE(cut.truncated);
    ASSERT_GT(cut.messages.size(), 100U);
    const std::string fixed = path + ".repaired";
    std::uint64_t n = 0;
    std::string error;
    ASSERT_TRUE(recoverMcap(path, fixed, n, error)) << error;
    EXPECT_EQ(n, cut.messages.size());
    EXPECT_TRUE(mcapComplete(fixed));
    const ReadBack again = readMcap(fixed, {"/a", "/b"});
    EXPECT_FALSE(again.truncated);
    EXPECT_EQ(again.messages, cut.messages);
    // Chunk records name their compression; message 10, well before the cut, would be
    // readable in the file if it were stored plain.
    const auto bytes = readAll(fixed);
    const std::string_view text(reinterpret_cast<const char*>(bytes.data()), bytes.size());
    EXPECT_NE(text.find(codec), std::string_view::npos);
    EXPECT_EQ(text.find("message 10xxxxxxxxxx"), std::string_view::npos);
    std::filesystem::remove(path);
    std::filesystem::remove(fixed);
  }
}

TEST(McapRepair, ACorruptChunkEndsTheReadAndIsNotSignedAfresh) {
  // A few bytes flipped inside a chunk (a bad sector, a bit error on the card): the
  // chunk's CRC no longer matches. Reading stops before it, as at a cut, and a
  // repair keeps what precedes it: no damaged message passes for a good one.
  const std::string path = tempPath("flipped.mcap");
  ASSERT_NO_FATAL_FAILURE(writeSample(path, "none"));
  const ReadBack whole = readMcap(path, {"/a", "/b"});
  ASSERT_EQ(whole.messages.size(), 1000U);
  auto bytes = readAll(path);
  const std::string_view text(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  const std::size_t at = text.find("message 500x");  // inside a chunk (uncompressed)
  ASSERT_NE(at, std::string_view::npos);
  bytes[at + 8] = static_cast<std::uint8_t>('9');  // "message 900...": plausible, wrong
  std::ofstream(path, std::ios::binary | std::ios::trunc)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<long>(bytes.size()));
  const ReadBack read = readMcap(path, {"/a", "/b"});
  EXPECT_TRUE(read.truncated);
  EXPECT_GT(read.messages.size(), 100U);
  EXPECT_LT(read.messages.size(), 500U);  // none from the damaged chunk on
  const std::string fixed = path + ".repaired";
  std::uint64_t n = 0;
  std::string error;
  ASSERT_TRUE(recoverMcap(path, fixed, n, error)) << error;
  EXPECT_EQ(n, read.messages.size());
  const ReadBack again = readMcap(fixed, {"/a", "/b"});
  EXPECT_FALSE(again.truncated);
  EXPECT_EQ(again.messages, read.messages);
  std::filesystem::remove(path);
  std::filesystem::remove(fixed);
}

TEST(McapWriter, UnwritablePathIsAnError) {
  std::string error;
  auto w = McapWriter::open({"/nonexistent-dir/x.mcap", "zstd", 0}, error);
  EXPECT_FALSE(w);
  EXPECT_NE(error.find("/nonexistent-dir/x.mcap"), std::string::npos) << error;
}

TEST(McapWriter, BadArgumentsAreErrorsNotCrashes) {
  char err[128] = {};
  EXPECT_EQ(kfio_mcap_open(nullptr, "zstd", 0, err, sizeof err), nullptr);
  EXPECT_NE(std::string(err).find("NULL"), std::string::npos);
  EXPECT_EQ(kfio_mcap_open(tempPath("c.mcap").c_str(), "brotli", 0, err, sizeof err), nullptr);
  EXPECT_NE(std::string(err).find("brotli"), std::string::npos);
  EXPECT_EQ(kfio_mcap_write(nullptr, 1, 0, 0, 0, nullptr, 0, err, sizeof err), -1);
  // A tiny error buffer is truncated, NUL-terminated.
  char small[4] = {1, 1, 1, 1};
  EXPECT_EQ(kfio_mcap_write(nullptr, 1, 0, 0, 0, nullptr, 0, small, sizeof small), -1);
  EXPECT_EQ(small[3], '\0');
  EXPECT_EQ(kfio_mcap_close(nullptr, nullptr, 0), 0);

  std::string error;
  auto w = McapWriter::open({tempPath("d.mcap"), "lz4", 0}, error);
  ASSERT_TRUE(w) << error;
  const std::uint8_t data[] = {1, 2, 3};
  EXPECT_FALSE(w->write(42, 0, 0, 0, data, error));  // unknown channel
  EXPECT_FALSE(error.empty());
  std::uint16_t id = 0;
  EXPECT_FALSE(w->addChannel(7, "/x", "json", {}, id, error));  // unknown schema
  EXPECT_TRUE(w->close(error)) << error;
}

TEST(McapWriter, WriteErrorIsReportedOnce) {
  // /dev/full accepts the open and fails every write with ENOSPC.
  std::string error;
  auto w = McapWriter::open({"/dev/full", "none", 0}, error);
  ASSERT_TRUE(w) << error;
  EXPECT_FALSE(w->flush(false, error));
  EXPECT_NE(error.find("/dev/full"), std::string::npos) << error;
  // The OS's reason, not only the mcap crate's "I/O error from writing, ...".
  EXPECT_NE(error.find("No space left on device"), std::string::npos) << error;
  EXPECT_FALSE(w->close(error));
}

TEST(McapRecorder, RecordsEverythingQueued) {
  const std::string path = tempPath("rec.mcap");
  McapRecorder rec;
  std::string error;
  McapRecorderOptions o;
  o.path = path;
  o.blockWhenFull = true;
  o.maxQueueBytes = 4096;  // producers wait for the writer
  ASSERT_TRUE(rec.open(o, error)) << error;
  std::vector<std::uint8_t> jpeg(3000, 0xAB);
  for (int i = 0; i < 50; ++i) {
    rec.record(McapTopic::Keyframe, i * 1'000'000LL,
               proto::compressedImage(i, "camera", jpeg, "jpeg"),
               static_cast<std::uint32_t>(i + 1));
    rec.recordText(McapTopic::Decision, i * 1'000'000LL, "{\"index\":" + std::to_string(i) + "}");
  }
  ASSERT_TRUE(rec.close(error)) << error;
  const McapRecorderStats s = rec.stats();
  EXPECT_EQ(s.written, 100u);
  EXPECT_EQ(s.dropped, 0u);
  EXPECT_TRUE(hasMagic(readAll(path), true));
}

// Message `i` of a test stream: its number, then padding to `size` bytes.
std::vector<std::uint8_t> numbered(int i, std::size_t size) {
  std::vector<std::uint8_t> m(size, 0x5A);
  std::memcpy(m.data(), &i, sizeof i);
  return m;
}

int numberOf(const std::string& data) {
  int i = -1;
  if (data.size() >= sizeof i) std::memcpy(&i, data.data(), sizeof i);
  return i;
}

TEST(McapRecorder, APartWithVideoEndsBeforeAPictureADecoderCanStartAt) {
  const std::string path = tempPath("rotate-video.mcap");
  McapRecorder rec;
  std::string error;
  McapRecorderOptions o;
  o.path = path;
  o.blockWhenFull = true;
  o.rotateBytes = 4000;  // due after about ten pictures; a group is every 8th
  ASSERT_TRUE(rec.open(o, error)) << error;
  for (int i = 0; i < 60; ++i) {
    rec.record(McapTopic::Video, i * 1'000'000LL, numbered(i, 400), 0, i % 8 == 0);
    rec.recordText(McapTopic::Decision, i * 1'000'000LL, "{\"index\":" + std::to_string(i) + "}");
  }
  ASSERT_TRUE(rec.close(error)) << error;
  const std::vector<std::string> parts = mcapParts(path);
  ASSERT_GE(parts.size(), 3U);
  std::vector<int> seen;
  for (const std::string& part : parts) {
    ReadBack r = readMcap(part, {"/camera/video"});
    ASSERT_EQ(r.error, "") << part;
    ASSERT_FALSE(r.messages.empty()) << part;
    // Each part opens with a group's first picture: it plays on its own.
    EXPECT_EQ(numberOf(std::get<2>(r.messages.front())) % 8, 0) << part;
    for (const auto& m : r.messages) seen.push_back(numberOf(std::get<2>(m)));
  }
  std::vector<int> all(60);
  for (int i = 0; i < 60; ++i) all[static_cast<std::size_t>(i)] = i;
  EXPECT_EQ(seen, all);  // none lost or repeated
  EXPECT_EQ(rec.stats().files, parts.size());
}

TEST(McapRecorder, AVideoThatStopsDoesNotHoldTheRotationBackForLong) {
  const std::string path = tempPath("rotate-stalled.mcap");
  McapRecorder rec;
  std::string error;
  McapRecorderOptions o;
  o.path = path;
  o.rotateBytes = 1000;
  o.videoRotationWaitMs = 50;
  ASSERT_TRUE(rec.open(o, error)) << error;
  rec.record(McapTopic::Video, 0, numbered(0, 1200), 0, true);  // due at once
  // No picture to start at follows: other messages, until a part begins (or 5 s).
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  for (int i = 1; rec.stats().files < 2 && std::chrono::steady_clock::now() < deadline; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    rec.recordText(McapTopic::Decision, i * 1'000'000LL, "{\"index\":" + std::to_string(i) + "}");
  }
  ASSERT_TRUE(rec.close(error)) << error;
  EXPECT_EQ(mcapParts(path).size(), 2U);  // rotated after the wait, not never
}

TEST(McapRecorder, EveryMessageNotRecordedAfterAWriteErrorIsCounted) {
  // Files may grow to 64 kB here (as a disk that fills up): the recorder stops at the
  // first write past it, and what the flight records after that is counted as lost.
  const std::string path = tempPath("efbig.mcap");
  McapRecorder rec;
  std::string error;
  McapRecorderOptions o;
  o.path = path;
  o.compression = "none";
  o.chunkSize = 4096;
  o.flushIntervalMs = 10;
  o.blockWhenFull = true;
  std::mutex m;
  std::condition_variable cv;
  std::string failure;
  o.onFailure = [&](const std::string& line) {
    std::lock_guard lock(m);
    failure = line;
    cv.notify_all();
  };
  ASSERT_TRUE(rec.open(o, error)) << error;
  rlimit old{};
  ASSERT_EQ(getrlimit(RLIMIT_FSIZE, &old), 0);
  rlimit small = old;
  small.rlim_cur = 64 * 1024;
  const auto previous = std::signal(SIGXFSZ, SIG_IGN);  // EFBIG, not a signal
  ASSERT_EQ(setrlimit(RLIMIT_FSIZE, &small), 0);
  const std::vector<std::uint8_t> data(2000, 0x42);
  int sent = 0;
  while (sent < 100) {
    rec.record(McapTopic::Decision, sent * 1'000'000LL, data);
    ++sent;  // counted before the check: the message that saw the failure was sent too
    std::unique_lock lock(m);
    if (!failure.empty()) break;
  }
  {
    std::unique_lock lock(m);
    cv.wait_for(lock, std::chrono::seconds(10), [&] { return !failure.empty(); });
  }
  for (int i = 0; i < 50; ++i, ++sent) rec.record(McapTopic::Decision, sent * 1'000'000LL, data);
  rec.tryRecord(McapTopic::Log, 0, data);
  ++sent;
  EXPECT_FALSE(rec.close(error));
  setrlimit(RLIMIT_FSIZE, &old);
  std::signal(SIGXFSZ, previous);
  ASSERT_NE(failure, "");
  EXPECT_NE(failure.find("File too large"), std::string::npos) << failure;
  const McapRecorderStats st = rec.stats();
  EXPECT_LT(st.written, 40U);
  EXPECT_EQ(st.written + st.dropped, static_cast<std::uint64_t>(sent))
      << st.written << " written, " << st.dropped << " dropped";
  std::filesystem::remove(path);
}

TEST(McapRecorder, OpenFailsOnUnwritablePath) {
  McapRecorder rec;
  std::string error;
  McapRecorderOptions o;
  o.path = "/proc/keyframed-cannot-write.mcap";
  EXPECT_FALSE(rec.open(o, error));
  EXPECT_FALSE(error.empty());
  EXPECT_FALSE(rec.isOpen());
}

TEST(FoxgloveProto, EveryRecordedSchemaHasADescriptorSet) {
  for (const char* name :
       {"foxglove.CompressedImage", "foxglove.CompressedVideo", "foxglove.LocationFix",
        "foxglove.PoseInFrame", "foxglove.CameraCalibration", "foxglove.Log",
        "keyframed.MavlinkPacket"}) {
    EXPECT_GT(proto::descriptorSet(name).size(), 100u) << name;
  }
  EXPECT_TRUE(proto::descriptorSet("foxglove.Nope").empty());
}

TEST(FoxgloveProto, CompressedImageWireFormat) {
  const std::uint8_t jpeg[] = {0xFF, 0xD8, 0xFF, 0xD9};
  const auto m = proto::compressedImage(1'500'000'000LL, "cam", jpeg, "jpeg");
  // timestamp {seconds: 1, nanos: 500000000}, frame_id = 4, data = 2, format = 3.
  const std::vector<std::uint8_t> expected = {0x0A, 0x08, 0x08, 0x01, 0x10, 0x80,
                                              0xCA, 0xB5, 0xEE, 0x01,              // field 1
                                              0x22, 0x03, 'c',  'a',  'm',         // field 4
                                              0x12, 0x04, 0xFF, 0xD8, 0xFF, 0xD9,  // field 2
                                              0x1A, 0x04, 'j',  'p',  'e',  'g'};  // field 3
  EXPECT_EQ(m, expected);
}

TEST(KeyframeIndex, ReadsKeyframesCsvAsJson) {
  const std::string dir = tempPath("kf");
  std::filesystem::create_directories(dir);
  {
    std::ofstream f(dir + "/keyframes.csv");
    f << "sequence,index,file,time_ns,utc_us,lat,lon,alt_amsl,alt_rel,cam_qw,cam_qx,cam_qy,"
         "cam_qz,yaw,pitch,roll,hdop,fix_type,geotag\n"
         "0,5,000005.jpg,166666666,,,,,,,,,,,,,,,\"\"\n"
         "1,42,000042.jpg,1400000000,1700000000000000,47.1,8.5,500.0,50.0,1,0,0,0,0,-90,0,0.8,"
         "3,\"ok, fresh\"\n";
  }
  std::vector<StoredKeyframe> rows;
  std::string error;
  ASSERT_TRUE(readKeyframeIndex(dir, "uav1", "20261202T101500Z", rows, error)) << error;
  ASSERT_EQ(rows.size(), 2u);
  EXPECT_NE(rows[0].metadataJson.find("\"flight\":\"20261202T101500Z\""), std::string::npos);
  EXPECT_EQ(rows[1].sequence, 1);
  EXPECT_EQ(rows[1].file, "000042.jpg");
  EXPECT_NE(rows[0].metadataJson.find("\"lat\":null"), std::string::npos) << rows[0].metadataJson;
  EXPECT_NE(rows[1].metadataJson.find("\"frame_index\":42"), std::string::npos);
  EXPECT_NE(rows[1].metadataJson.find("\"cam_q\":[1,0,0,0]"), std::string::npos);
  EXPECT_NE(rows[1].metadataJson.find("\"geotag\":\"ok, fresh\""), std::string::npos);
  // keyframes.csv has no decision time: an earlier run's keyframe says so.
  EXPECT_NE(rows[1].metadataJson.find("\"decided_ns\":null"), std::string::npos);
  EXPECT_FALSE(readKeyframeIndex(dir + "/missing", "uav1", "", rows, error));
  // An offline run's keyframes have no flight.
  ASSERT_TRUE(readKeyframeIndex(dir, "uav1", "", rows, error)) << error;
  EXPECT_NE(rows[0].metadataJson.find("\"flight\":null"), std::string::npos);
}

TEST(KeyframeIndex, FlightCatalogueListsTheFlightsOnDiskByName) {
  namespace fs = std::filesystem;
  const std::string root = tempPath("flights");
  const auto flight = [&](const std::string& name, int keyframes) {
    fs::create_directories(root + "/" + name + "/keyframes");
    std::ofstream f(root + "/" + name + "/keyframes/keyframes.csv");
    f << "sequence,index,file,time_ns\n";
    for (int i = 0; i < keyframes; ++i) f << i << "," << i * 10 << "," << i << ".jpg,0\n";
  };
  flight("20261202T102000Z", 3);
  flight("20261202T101500Z", 2);
  flight("20261202T101500Z-1", 0);                 // started, no keyframe yet
  fs::create_directories(root + "/not-a-flight");  // no keyframe index: left out
  std::ofstream(root + "/stray.txt") << "x";
  fs::last_write_time(root + "/20261202T101500Z/keyframes/keyframes.csv",
                      fs::file_time_type::clock::now() - std::chrono::minutes(5));
  const std::string json = flightCatalogue(root, "20261202T102000Z");
  const auto a = json.find("{\"flight\":\"20261202T101500Z\",\"keyframes\":2,\"age_s\":");
  ASSERT_NE(a, std::string::npos) << json;
  // Five minutes old (and the second or so this test took).
  const double age = std::strtod(json.c_str() + json.find("\"age_s\":", a) + 8, nullptr);
  EXPECT_GE(age, 300.0) << json;
  EXPECT_LT(age, 301.0) << json;
  const auto b = json.find("{\"flight\":\"20261202T101500Z-1\",\"keyframes\":0,");
  const auto c = json.find("{\"flight\":\"20261202T102000Z\",\"keyframes\":3,");
  ASSERT_NE(a, std::string::npos) << json;
  ASSERT_NE(b, std::string::npos) << json;
  ASSERT_NE(c, std::string::npos) << json;
  EXPECT_TRUE(a < b && b < c) << json;
  EXPECT_EQ(json.find("not-a-flight"), std::string::npos);
  EXPECT_EQ(json.rfind("\"current\":true"), json.find("\"current\":true"));
  EXPECT_NE(json.find("\"current\":true", c), std::string::npos);
  EXPECT_EQ(json.substr(0, 12), "{\"flights\":[");
  EXPECT_EQ(flightCatalogue(root + "/missing", ""), "{\"flights\":[]}");

  // A keyframe a full disk kept out of the index (sequence 1 here) still took its
  // number: the count is the last row's number + 1, not the rows (and a row cut
  // short at the end does not count).
  {
    std::ofstream f(root + "/20261202T102000Z/keyframes/keyframes.csv");
    f << "sequence,index,file,time_ns\n0,0,0.jpg,0\n2,20,2.jpg,0\n3,30,3.jpg,0\n4,4";
  }
  const std::string gap = flightCatalogue(root, "");
  EXPECT_NE(gap.find("{\"flight\":\"20261202T102000Z\",\"keyframes\":4,"), std::string::npos)
      << gap;
  // The running flight's keyframes still queued for the link are not announced (a
  // ground station would fetch them by query while they are on their way); the
  // earlier flights' are all out.
  const auto out = [](std::int64_t n) { return std::min<std::int64_t>(n, 2); };
  const std::string running = flightCatalogue(root, "20261202T102000Z", out);
  EXPECT_NE(running.find("{\"flight\":\"20261202T102000Z\",\"keyframes\":2,"), std::string::npos)
      << running;
  EXPECT_NE(running.find("{\"flight\":\"20261202T101500Z\",\"keyframes\":2,"), std::string::npos)
      << running;
  const std::string none = flightCatalogue(root, "20261202T102000Z", [](std::int64_t) {
    return std::int64_t{-1};  // nothing out yet
  });
  EXPECT_NE(none.find("{\"flight\":\"20261202T102000Z\",\"keyframes\":0,"), std::string::npos)
      << none;
}

TEST(KeyframeIndex, QueryParameters) {
  EXPECT_EQ(keyframeQueryFlight(""), "");
  EXPECT_EQ(keyframeQueryFlight("range=3..5"), "");
  EXPECT_EQ(keyframeQueryFlight("range=3..5;flight=20261202T101500Z"), "20261202T101500Z");
  EXPECT_EQ(keyframeQueryFlight("flight=A-1&range=0.."), "A-1");
  std::int64_t first = 0, last = 0;
  std::string error;
  ASSERT_TRUE(parseKeyframeRange("flight=A;range=3..5", first, last, error)) << error;
  EXPECT_EQ(first, 3);
  EXPECT_EQ(last, 5);
}

TEST(Zenoh, BadConfigIsAClearError) {
  std::string error;
  ZenohSession::Options o;
  o.configJson5 = "{ this is not json5";
  EXPECT_FALSE(ZenohSession::open(o, error));
  EXPECT_NE(error.find("zenoh config"), std::string::npos) << error;
  o.configJson5.clear();
  o.configFile = "/nonexistent/zenoh.json5";
  EXPECT_FALSE(ZenohSession::open(o, error));
  EXPECT_NE(error.find("/nonexistent/zenoh.json5"), std::string::npos) << error;
  EXPECT_FALSE(KeyframePublisher::checkVehicleName("a/b").empty());
  EXPECT_FALSE(KeyframePublisher::checkVehicleName("..").empty());
  EXPECT_FALSE(KeyframePublisher::checkVehicleName(".").empty());
  EXPECT_TRUE(KeyframePublisher::checkVehicleName("..uav").empty());
  EXPECT_TRUE(KeyframePublisher::checkVehicleName("uav-1").empty());
}

TEST(Zenoh, ABlockedKeyframeWaitsAMinuteBeforeTheSessionCloses) {
  // Zenoh closes a session whose blocking put finds no free batch for 5 s: on a slow
  // radio link every keyframe would. Ours waits 60 s, unless the file says otherwise.
  const std::string key = "transport/link/tx/queue/congestion_control/block/wait_before_close";
  std::string value, error;
  ASSERT_TRUE(ZenohSession::configValue("", key, value, error)) << error;
  EXPECT_EQ(value, "60000000");
  const std::string dir = testing::TempDir() + "/kf-zenoh-" + std::to_string(getpid());
  std::filesystem::create_directories(dir);
  std::ofstream(dir + "/plain.json5") << "{ mode: \"peer\" }\n";
  ASSERT_TRUE(ZenohSession::configValue(dir + "/plain.json5", key, value, error)) << error;
  EXPECT_EQ(value, "60000000");
  std::ofstream(dir + "/own.json5")
      << "{ transport: { link: { tx: { queue: { congestion_control: { block: "
         "{ wait_before_close: 2000000 } } } } } } }\n";
  ASSERT_TRUE(ZenohSession::configValue(dir + "/own.json5", key, value, error)) << error;
  EXPECT_EQ(value, "2000000");
  EXPECT_FALSE(ZenohSession::configValue("", "no/such/key", value, error));
  EXPECT_FALSE(error.empty());
  std::filesystem::remove_all(dir);
}

TEST(Zenoh, PublisherAndQueryableDeclareAndUndeclare) {
  // One isolated session (no scouting, no listeners); queries are tested end to end
  // in tests/harness/test_mcap_zenoh.py.
  std::string error;
  ZenohSession::Options o;
  o.configJson5 = R"({mode: "peer", scouting: {multicast: {enabled: false}},
                      listen: {endpoints: []}, connect: {endpoints: []}})";
  auto session = ZenohSession::open(o, error);
  ASSERT_TRUE(session) << error;
  EXPECT_FALSE(session->zid().empty());
  std::atomic<int> calls{0};
  auto q = ZenohQueryable::declare(
      *session, "test/kf/*",
      [&calls](const std::string& key, const std::string&, ZenohReply& reply) {
        ++calls;
        std::string e;
        const std::string body = "payload for " + key;
        reply.ok({}, {reinterpret_cast<const std::uint8_t*>(body.data()), body.size()}, {}, e);
      },
      error);
  ASSERT_TRUE(q) << error;
  auto pub =
      ZenohPublisher::declare(*session, "test/kf/frames", ZenohPublisher::Kind::Reliable, error);
  ASSERT_TRUE(pub) << error;
  const std::uint8_t data[] = {1, 2, 3};
  EXPECT_TRUE(pub->put(data, data, error)) << error;
  q.reset();  // undeclare joins the queryable thread (a hang here fails by timeout)
  pub.reset();
  session.reset();
  EXPECT_EQ(calls.load(), 0);  // an isolated session: nobody asked
}

// A TCP port nothing listens on (yet).
int freeTcpPort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof a;
  int port = 0;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0 &&
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) == 0)
    port = ntohs(a.sin_port);
  ::close(fd);
  return port;
}

TEST(KeyframePublisher, AClientWithoutItsRouterGoesOnAndPublishesOnceItIsUp) {
  const int port = freeTcpPort();
  ASSERT_GT(port, 0);
  const std::string endpoint = "tcp/127.0.0.1:" + std::to_string(port);
  const std::string client = tempPath("client.json5");
  std::ofstream(client) << R"({mode: "client", scouting: {multicast: {enabled: false}},
                              connect: {endpoints: [")" +
                               endpoint + R"("]}})";
  KeyframePublisherOptions o;
  o.configFile = client;
  o.vehicle = "late";
  std::string error;
  // Told not to retry: no router, no publisher.
  EXPECT_FALSE(KeyframePublisher::open(o, error));
  EXPECT_EQ(error.rfind("cannot open zenoh session", 0), 0U) << error;

  std::mutex m;
  std::condition_variable cv;
  std::vector<std::string> late;
  o.retryMs = 200;
  o.onLate = [&](const std::string& message) {
    std::lock_guard lock(m);
    late.push_back(message);
    cv.notify_all();
  };
  error.clear();
  auto publisher = KeyframePublisher::open(o, error);
  ASSERT_TRUE(publisher) << error;
  EXPECT_FALSE(publisher->live());
  EXPECT_EQ(error.rfind("cannot open zenoh session", 0), 0U) << error;  // why, for a warning
  const std::uint8_t jpeg[] = {0xFF, 0xD8, 0xFF, 0xD9};
  EXPECT_FALSE(publisher->publishKeyframe(0, jpeg, "{}", error));
  EXPECT_NE(error.find("no zenoh session yet"), std::string::npos) << error;
  EXPECT_FALSE(publisher->publishStatus("{}", error));
  std::this_thread::sleep_for(std::chrono::milliseconds(700));  // a few tries in vain
  EXPECT_FALSE(publisher->live());

  ZenohSession::Options r;
  r.configJson5 = R"({mode: "router", scouting: {multicast: {enabled: false}},
                      listen: {endpoints: [")" +
                  endpoint + R"("]}})";
  auto router = ZenohSession::open(r, error);
  ASSERT_TRUE(router) << error;
  {
    std::unique_lock lock(m);
    ASSERT_TRUE(cv.wait_for(lock, std::chrono::seconds(10), [&] { return !late.empty(); }));
    EXPECT_NE(late.front().find("zenoh session open at attempt"), std::string::npos)
        << late.front();
  }
  EXPECT_TRUE(publisher->live());
  EXPECT_FALSE(publisher->zid().empty());
  EXPECT_TRUE(publisher->publishKeyframe(1, jpeg, "{}", error)) << error;
  EXPECT_TRUE(publisher->publishStatus("{}", error)) << error;
  publisher.reset();
  router.reset();
}

TEST(KeyframePublisher, StopsRetryingWhenClosed) {
  const int port = freeTcpPort();
  const std::string client = tempPath("client-closed.json5");
  std::ofstream(client) << R"({mode: "client", scouting: {multicast: {enabled: false}},
                              connect: {endpoints: ["tcp/127.0.0.1:)" +
                               std::to_string(port) + R"("]}})";
  KeyframePublisherOptions o;
  o.configFile = client;
  o.retryMs = 60'000;  // the first retry is a minute away: closing must not wait for it
  std::string error;
  const auto start = std::chrono::steady_clock::now();
  auto publisher = KeyframePublisher::open(o, error);
  ASSERT_TRUE(publisher) << error;
  publisher.reset();
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(5));
}

TEST(KeyframePublisher, ASilentRouterHoldsUpOpenOnlyBriefly) {
  // A router that takes the connection and never answers (a hung zenohd): the kernel
  // completes the TCP handshake into the backlog, nothing accepts or replies, and each
  // attempt waits for Zenoh's open_timeout (10 s). With retries on, open() waits
  // kFirstAttemptWaitMs at most and goes on without a session.
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof a;
  ASSERT_EQ(::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
  ASSERT_EQ(::listen(fd, 8), 0);
  ASSERT_EQ(::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len), 0);
  const std::string client = tempPath("client-silent.json5");
  std::ofstream(client) << R"({mode: "client", scouting: {multicast: {enabled: false}},
                              connect: {endpoints: ["tcp/127.0.0.1:)" +
                               std::to_string(ntohs(a.sin_port)) + R"("]}})";
  KeyframePublisherOptions o;
  o.configFile = client;
  o.retryMs = 1000;
  std::string error;
  const auto start = std::chrono::steady_clock::now();
  auto publisher = KeyframePublisher::open(o, error);
  const auto took = std::chrono::steady_clock::now() - start;
  ASSERT_TRUE(publisher) << error;
  EXPECT_FALSE(publisher->live());
  EXPECT_NE(error.find("no answer within 3 s"), std::string::npos) << error;
  EXPECT_GE(took, std::chrono::milliseconds(KeyframePublisher::kFirstAttemptWaitMs - 100));
  EXPECT_LT(took, std::chrono::milliseconds(KeyframePublisher::kFirstAttemptWaitMs + 3000));
  // Closing leaves the attempt inside Zenoh's open to end on its own.
  const auto closing = std::chrono::steady_clock::now();
  publisher.reset();
  EXPECT_LT(std::chrono::steady_clock::now() - closing, std::chrono::seconds(2));
  ::close(fd);
}

TEST(KeyframePublisher, ConfigErrorFailsOpenEvenWithRetries) {
  const std::string bad = tempPath("bad-retry.json5");
  std::ofstream(bad) << R"({mode: "spaceship"})";
  KeyframePublisherOptions o;
  o.configFile = bad;
  o.retryMs = 1000;  // retries are for links, not for a configuration that cannot work
  std::string error;
  EXPECT_FALSE(KeyframePublisher::open(o, error));
  EXPECT_NE(error.find("zenoh config"), std::string::npos) << error;
  EXPECT_NE(error.find("bad-retry.json5"), std::string::npos) << error;
}

TEST(KeyframeRange, QueryParameterForms) {
  std::int64_t a = -1, b = -1;
  std::string error;
  ASSERT_TRUE(parseKeyframeRange("", a, b, error));
  EXPECT_EQ(a, 0);
  EXPECT_EQ(b, INT64_MAX);
  ASSERT_TRUE(parseKeyframeRange("range=3..7", a, b, error)) << error;
  EXPECT_EQ(a, 3);
  EXPECT_EQ(b, 7);
  ASSERT_TRUE(parseKeyframeRange("x=1;range=5..", a, b, error)) << error;
  EXPECT_EQ(a, 5);
  EXPECT_EQ(b, INT64_MAX);
  ASSERT_TRUE(parseKeyframeRange("range=4", a, b, error)) << error;
  EXPECT_EQ(a, 4);
  EXPECT_EQ(b, 4);
  for (const char* bad : {"range=7..3", "range=..3", "range=a..b", "range=-1..2", "range="}) {
    EXPECT_FALSE(parseKeyframeRange(bad, a, b, error)) << bad;
    EXPECT_NE(error.find("bad range"), std::string::npos) << error;
  }
}

// An isolated Zenoh peer (no scouting, no listeners) for FlightOutputs.
std::string isolatedZenohConfig() {
  const std::string path = tempPath("isolated.json5");
  std::ofstream(path) << R"({mode: "peer", scouting: {multicast: {enabled: false}},
                            listen: {endpoints: []}, connect: {endpoints: []}})";
  return path;
}

TEST(KeyframePublisher, CopiesOfUnsavedKeyframesGoOnceTheyAreOnDisk) {
  KeyframePublisherOptions o;
  o.configFile = isolatedZenohConfig();
  o.vehicle = "fulldisk";
  std::string error;
  auto publisher = KeyframePublisher::open(o, error);
  ASSERT_TRUE(publisher) << error;
  const std::vector<std::uint8_t> a(1000, 1);
  const std::vector<std::uint8_t> b(300, 2);
  publisher->keepUnsaved(4, a, "{}");
  publisher->keepUnsaved(5, b, "{}");
  EXPECT_EQ(publisher->unsavedBytes(), 1300U);
  const std::int64_t saved[] = {4, 9};  // 9: never kept, nothing to forget
  publisher->forgetUnsaved(saved);
  EXPECT_EQ(publisher->unsavedBytes(), 300U);
  publisher->forgetUnsaved(saved);  // twice: no change
  EXPECT_EQ(publisher->unsavedBytes(), 300U);
  EXPECT_EQ(publisher->unsavedLetGo(), 0);
}

TEST(FlightOutputs, AFailedKeyframePublishDoesNotStopTheNextOnes) {
  std::vector<std::string> warnings;
  FlightOutputOptions o;
  o.zenohConfig = isolatedZenohConfig();
  o.vehicle = "unit";
  o.warn = [&warnings](const std::string& m) { warnings.push_back(m); };
  FlightOutputs outputs;
  std::string error;
  ASSERT_TRUE(outputs.open(o, 64, 48, nullptr, error)) << error;
  std::vector<std::int64_t> tried;
  outputs.setKeyframePutForTesting(
      [&tried](std::span<const std::uint8_t>, const std::string& meta, std::string& e) {
        const auto at = meta.find("\"sequence\":");
        tried.push_back(std::stoll(meta.substr(at + 11)));
        if (tried.back() >= 1 && tried.back() <= 3) {
          e = "link down";
          return false;
        }
        return true;
      });
  const std::uint8_t jpeg[] = {0xFF, 0xD8, 0xFF, 0xD9};
  for (std::int64_t i = 0; i < 6; ++i) {
    KeyframeRecord r;
    r.sequence = i;
    r.frameIndex = 10 * i;
    r.timeNs = i * 1'000'000;
    outputs.keyframe(r, jpeg);
  }
  EXPECT_EQ(tried, (std::vector<std::int64_t>{0, 1, 2, 3, 4, 5}));
  // Three failures in a burst: one line, not three.
  ASSERT_EQ(warnings.size(), 1U);
  EXPECT_NE(warnings[0].find("keyframe 1 not published: link down"), std::string::npos)
      << warnings[0];
  ASSERT_TRUE(outputs.close("done", error)) << error;
  ASSERT_EQ(warnings.size(), 2U);  // at close: how many failed in all
  EXPECT_NE(warnings[1].find("3 keyframe puts failed"), std::string::npos) << warnings[1];
}

// A congested link for FlightOutputs' keyframe puts: each put notes its sequence
// number, and the first hangs (as a Block put waits for room) until release().
class CongestedLink {
 public:
  explicit CongestedLink(FlightOutputs& outputs) {
    outputs.setKeyframePutForTesting(
        [this](std::span<const std::uint8_t>, const std::string& meta, std::string&) {
          std::unique_lock lock(m_);
          const auto at = meta.find("\"sequence\":");
          tried_.push_back(std::stoll(meta.substr(at + 11)));
          cv_.notify_all();
          cv_.wait(lock, [this] { return released_; });
          return true;
        });
  }
  [[nodiscard]] bool waitForFirstPut() {
    std::unique_lock lock(m_);
    return cv_.wait_for(lock, std::chrono::seconds(10), [this] { return !tried_.empty(); });
  }
  void release() {
    {
      std::lock_guard lock(m_);
      released_ = true;
    }
    cv_.notify_all();
  }
  [[nodiscard]] std::vector<std::int64_t> tried() {
    std::lock_guard lock(m_);
    return tried_;
  }

 private:
  std::mutex m_;
  std::condition_variable cv_;
  bool released_ = false;
  std::vector<std::int64_t> tried_;
};

TEST(FlightOutputs, ALiveRunNeverWaitsForASlowLink) {
  // The first put hangs (a congested link: a Block put waits for room) until released.
  std::vector<std::string> warnings;
  FlightOutputOptions o;
  o.zenohConfig = isolatedZenohConfig();
  o.vehicle = "unit";
  o.offline = false;
  o.warn = [&warnings](const std::string& m) { warnings.push_back(m); };
  FlightOutputs outputs;
  std::string error;
  ASSERT_TRUE(outputs.open(o, 64, 48, nullptr, error)) << error;
  CongestedLink link(outputs);
  const std::uint8_t jpeg[] = {0xFF, 0xD8, 0xFF, 0xD9};
  const auto keyframe = [&](std::int64_t i, bool saved = true, bool indexed = true) {
    KeyframeRecord r;
    r.sequence = i;
    r.frameIndex = 10 * i;
    if (saved) r.file = "/state/keyframes/" + std::to_string(10 * i) + ".jpg";
    r.indexed = saved && indexed;
    outputs.keyframe(r, jpeg);
  };
  keyframe(0);
  ASSERT_TRUE(link.waitForFirstPut());
  // Keyframe 0's put hangs; the output thread goes on: 8 wait, the rest are left to
  // the queryable, and none of these calls waits.
  const auto start = std::chrono::steady_clock::now();
  for (std::int64_t i = 1; i <= 11; ++i) keyframe(i);
  // One the disk could not take is on no disk for the queryable: it waits for the link.
  keyframe(12, /*saved=*/false);
  // Nor one whose JPEG was saved but whose index row the disk did not take: the
  // queryable reads the index.
  keyframe(13, /*saved=*/true, /*indexed=*/false);
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(2));
  ASSERT_EQ(warnings.size(), 1U);
  EXPECT_NE(warnings[0].find("keyframe 9 left to the queryable"), std::string::npos) << warnings[0];
  // The status tells a ground station of none of them yet: keyframe 0 is still on its
  // way (9 to 11, left to the queryable, are told of once 0 to 8 are out).
  EXPECT_EQ(outputs.keyframesOut(14), 0);
  link.release();
  // close() puts what is queued first.
  ASSERT_TRUE(outputs.close("done", error)) << error;
  EXPECT_EQ(link.tried(), (std::vector<std::int64_t>{0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 13}));
  EXPECT_EQ(outputs.keyframesOut(14), 14);
  ASSERT_EQ(warnings.size(), 2U);
  EXPECT_NE(warnings[1].find("3 keyframes left to the queryable"), std::string::npos)
      << warnings[1];
}

TEST(FlightOutputs, AStopOnASlowLinkLeavesWhatIsOnDiskToTheQueryable) {
  // Each put takes 300 ms (a congested radio); at the stop six wait. close() puts
  // them for stopDrainMs at most, then leaves those on disk to the queryable, so that
  // it ends inside systemd's stop timeout; one the disk did not take is still put.
  std::vector<std::string> warnings;
  FlightOutputOptions o;
  o.zenohConfig = isolatedZenohConfig();
  o.vehicle = "unit";
  o.offline = false;
  o.stopDrainMs = 200;
  o.warn = [&warnings](const std::string& m) { warnings.push_back(m); };
  FlightOutputs outputs;
  std::string error;
  ASSERT_TRUE(outputs.open(o, 64, 48, nullptr, error)) << error;
  std::mutex m;
  std::condition_variable started;
  std::vector<std::int64_t> tried;
  outputs.setKeyframePutForTesting(
      [&](std::span<const std::uint8_t>, const std::string& meta, std::string&) {
        {
          std::lock_guard lock(m);
          tried.push_back(std::stoll(meta.substr(meta.find("\"sequence\":") + 11)));
          started.notify_all();
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(300));
        return true;
      });
  const std::uint8_t jpeg[] = {0xFF, 0xD8, 0xFF, 0xD9};
  for (std::int64_t i = 0; i < 7; ++i) {
    KeyframeRecord r;
    r.sequence = i;
    r.frameIndex = 10 * i;
    r.file = "/state/keyframes/" + std::to_string(10 * i) + ".jpg";
    r.indexed = i != 5;  // 5: its index row did not fit on the disk
    outputs.keyframe(r, jpeg);
    if (i == 0) {  // the first is on the link before the stop, however busy the machine
      std::unique_lock lock(m);
      ASSERT_TRUE(started.wait_for(lock, std::chrono::seconds(10), [&] { return !tried.empty(); }));
    }
  }
  ASSERT_TRUE(outputs.close("stopped", error)) << error;
  std::lock_guard lock(m);
  ASSERT_GE(tried.size(), 2U);
  EXPECT_EQ(tried.front(), 0);
  EXPECT_EQ(tried.back(), 5);  // the one not on disk, put whatever the time
  EXPECT_LT(tried.size(), 7U);
  const std::size_t left = 7 - tried.size();
  bool said = false;
  for (const std::string& w : warnings)
    said |= w.find(std::to_string(left) +
                   " keyframes still queued for the link at the stop "
                   "left to the queryable") != std::string::npos;
  EXPECT_TRUE(said) << ::testing::PrintToString(warnings);
}

// A full disk over a slow link: keyframes the disk did not take wait for the link
// past the usual 8, but only up to 32 MB of them; the rest are left to the queryable,
// which serves them from memory, so the queue does not grow for as long as it lasts.
TEST(FlightOutputs, UnsavedKeyframesWaitingForASlowLinkAreBoundedInBytes) {
  FlightOutputOptions o;
  o.zenohConfig = isolatedZenohConfig();
  o.vehicle = "unit";
  o.offline = false;
  std::vector<std::string> warnings;
  o.warn = [&warnings](const std::string& m) { warnings.push_back(m); };
  FlightOutputs outputs;
  std::string error;
  ASSERT_TRUE(outputs.open(o, 64, 48, nullptr, error)) << error;
  CongestedLink link(outputs);
  std::vector<std::uint8_t> jpeg(1u << 20, 0x55);  // 1 MB keyframes
  jpeg[0] = 0xFF;
  jpeg[1] = 0xD8;
  const auto keyframe = [&](std::int64_t i) {
    KeyframeRecord r;
    r.sequence = i;
    r.frameIndex = i;
    r.indexed = false;  // the disk is full
    outputs.keyframe(r, jpeg);
  };
  keyframe(0);
  ASSERT_TRUE(link.waitForFirstPut());
  for (std::int64_t i = 1; i <= 40; ++i) keyframe(i);
  ASSERT_EQ(warnings.size(), 1U);
  EXPECT_NE(warnings[0].find("keyframe 33 left to the queryable"), std::string::npos)
      << warnings[0];
  link.release();
  ASSERT_TRUE(outputs.close("done", error)) << error;
  std::vector<std::int64_t> expected;
  for (std::int64_t i = 0; i <= 32; ++i) expected.push_back(i);
  EXPECT_EQ(link.tried(), expected);
}

// The picture of a 32x24 record's preview frames.
std::vector<std::uint8_t> previewJpeg() {
  std::vector<std::uint8_t> jpeg;
  EXPECT_TRUE(cv::imencode(".jpg", cv::Mat(24, 32, CV_8UC3, cv::Scalar(40, 80, 120)), jpeg));
  return jpeg;
}

// A live run's frame in its record: its decision (index and time) and its picture.
void recordFrame(FlightOutputs& outputs, std::int64_t index, std::int64_t t,
                 std::span<const std::uint8_t> picture, const char* format) {
  Decision d;
  d.index = index;
  d.timestampNs = t;
  outputs.decision(d);
  outputs.recordDecision(d, "{\"index\":" + std::to_string(index) +
                                ",\"timestamp_ns\":" + std::to_string(t) + ",\"kept\":false}");
  outputs.preview(t, picture, format);
}

TEST(McapReplay, FramesKeepTheLiveIndicesAndTheRecordItsSettings) {
  const std::string path = tempPath("replay-index.mcap");
  const std::int64_t start = 1'000'000'000;
  {
    FlightOutputOptions o;
    o.mcapPath = path;
    o.startNs = start;
    FlightOutputs outputs;
    std::string error;
    ASSERT_TRUE(outputs.open(o, 32, 24, nullptr, error)) << error;
    outputs.settings(start, "selection.target=0.75\nselection.mode=\"paper\"\n");
    const std::vector<std::uint8_t> jpeg = previewJpeg();
    for (const std::int64_t index : {0, 5, 9}) {  // the live run dropped 1-4 and 6-8
      recordFrame(outputs, index, start + index * 33'333'333, jpeg, "jpeg");
      // ... and recorded a preview without its decision (its queue full): frame 12
      if (index == 9) outputs.preview(start + 12 * 33'333'333, jpeg, "jpeg");
    }
    outputs.settings(start + 400'000'000, "selection.target=0.8\n");  // a SIGHUP reload
    ASSERT_TRUE(outputs.close("done", error)) << error;
  }
  std::string error;
  const auto replay = McapReplaySource::open(path, error);
  ASSERT_TRUE(replay) << error;
  EXPECT_EQ(replay->selectionSettings(), "selection.target=0.75\nselection.mode=\"paper\"\n");
  EXPECT_EQ(replay->settingsChanges(), 1);
  std::vector<std::int64_t> indices;
  Frame f;
  while (replay->next(f, error) == ReadStatus::Frame) {
    indices.push_back(f.index);
    EXPECT_EQ(replay->format(), "jpeg");  // the image's format, not its frame_id
  }
  // The one without a decision follows the frame before it, never goes back to its
  // position in the stream (3, before 5 and 9).
  EXPECT_EQ(indices, (std::vector<std::int64_t>{0, 5, 9, 10})) << error;
}

TEST(McapReplay, FramesThatShareATimeStillGetIndicesOfTheirOwn) {
  // Pairs of frames stamped alike (an edited record, a camera that stamps badly): the
  // decisions map both to the first one's index; each replayed frame gets its own,
  // or two keyframes would share a file name.
  const std::string path = tempPath("replay-sametime.mcap");
  const std::int64_t start = 1'000'000'000;
  {
    FlightOutputOptions o;
    o.mcapPath = path;
    o.startNs = start;
    FlightOutputs outputs;
    std::string error;
    ASSERT_TRUE(outputs.open(o, 32, 24, nullptr, error)) << error;
    const std::vector<std::uint8_t> jpeg = previewJpeg();
    for (const std::int64_t index : {0, 1, 2, 3})
      recordFrame(outputs, index, start + (index / 2) * 33'333'333, jpeg, "jpeg");
    ASSERT_TRUE(outputs.close("done", error)) << error;
  }
  std::string error;
  const auto replay = McapReplaySource::open(path, error);
  ASSERT_TRUE(replay) << error;
  std::vector<std::int64_t> indices;
  Frame f;
  while (replay->next(f, error) == ReadStatus::Frame) indices.push_back(f.index);
  ASSERT_EQ(indices.size(), 4U) << error;
  for (std::size_t i = 1; i < indices.size(); ++i) EXPECT_GT(indices[i], indices[i - 1]);
  std::filesystem::remove(path);
}

TEST(McapRecorder, EveryPartCarriesTheCalibrationAndTheSettingsInForce) {
  // A part replays on its own as the flight selected at its start; a whole rotated
  // record still says the settings changed once, not once a part.
  const std::string path = tempPath("rotate-settings.mcap");
  for (const std::string& p : mcapParts(path)) std::filesystem::remove(p);
  const std::int64_t start = 1'000'000'000;
  {
    FlightOutputOptions o;
    o.mcapPath = path;
    o.startNs = start;
    o.mcapRotateBytes = 3000;
    FlightOutputs outputs;
    std::string error;
    ASSERT_TRUE(outputs.open(o, 32, 24, nullptr, error)) << error;
    outputs.settings(start, "selection.target=0.75\n");
    const std::vector<std::uint8_t> jpeg = previewJpeg();
    for (std::int64_t i = 0; i < 60; ++i) {
      if (i == 30) outputs.settings(start + i * 33'333'333, "selection.target=0.8\n");
      recordFrame(outputs, i, start + i * 33'333'333, jpeg, "jpeg");
    }
    ASSERT_TRUE(outputs.close("done", error)) << error;
  }
  const std::vector<std::string> parts = mcapParts(path);
  ASSERT_GE(parts.size(), 4U);
  std::string error;
  const auto whole = McapReplaySource::open(path, error);
  ASSERT_TRUE(whole) << error;
  EXPECT_EQ(whole->selectionSettings(), "selection.target=0.75\n");
  EXPECT_EQ(whole->settingsChanges(), 1);
  for (const std::string& part : parts) {
    const ReadBack r = readMcap(part, {"/keyframed/settings"});
    ASSERT_EQ(r.error, "") << part;
    EXPECT_FALSE(r.messages.empty()) << part;
  }
  const auto last = McapReplaySource::open(parts.back(), error);
  ASSERT_TRUE(last) << error;
  EXPECT_EQ(last->selectionSettings(), "selection.target=0.8\n");
  EXPECT_EQ(last->settingsChanges(), 0);
  for (const std::string& p : parts) std::filesystem::remove(p);
}

TEST(McapReplay, AnEmptyLastPartEndsTheRecordInsteadOfFailingIt) {
  // A rotation onto a full disk, or a power cut just after one, leaves the new part
  // empty: the parts before it are the flight, and replay.
  const std::string path = tempPath("replay-emptypart.mcap");
  const std::string next = tempPath("replay-emptypart-001.mcap");
  const std::int64_t start = 1'000'000'000;
  {
    FlightOutputOptions o;
    o.mcapPath = path;
    o.startNs = start;
    FlightOutputs outputs;
    std::string error;
    ASSERT_TRUE(outputs.open(o, 32, 24, nullptr, error)) << error;
    const std::vector<std::uint8_t> jpeg = previewJpeg();
    for (const std::int64_t index : {0, 1, 2})
      recordFrame(outputs, index, start + index * 33'333'333, jpeg, "jpeg");
    ASSERT_TRUE(outputs.close("done", error)) << error;
  }
  std::ofstream(next).close();  // 0 bytes
  std::string error;
  const auto replay = McapReplaySource::open(path, error);
  ASSERT_TRUE(replay) << error;
  EXPECT_TRUE(replay->truncated());
  EXPECT_EQ(replay->parts(), (std::vector<std::string>{path}));
  int frames = 0;
  Frame f;
  while (replay->next(f, error) == ReadStatus::Frame) ++frames;
  EXPECT_EQ(frames, 3) << error;
  std::filesystem::remove(next);
}

TEST(McapReplay, AnH264RecordReplaysFromItsFirstIdrPicture) {
  const std::string path = tempPath("replay-h264.mcap");
  const std::int64_t start = 2'000'000'000;
  constexpr int w = 64, h = 48;
  // Pictures 0-24 of a moving gradient, an IDR every 10; the record holds 3-24, as a
  // part that opened between two IDR pictures does.
  std::vector<std::vector<std::uint8_t>> pictures;
  {
    H264Encoder encoder({.keyframeIntervalNs = 333'333'333, .crf = 18, .fps = 30});
    FlightOutputOptions o;
    o.mcapPath = path;
    o.startNs = start;
    FlightOutputs outputs;
    std::string error;
    ASSERT_TRUE(outputs.open(o, w, h, nullptr, error)) << error;
    std::vector<std::uint8_t> packet;
    for (int i = 0; i < 25; ++i) {
      std::vector<std::uint8_t> picture(w * h * 3 / 2, 128);
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) picture[y * w + x] = static_cast<std::uint8_t>(x + y + 2 * i);
      ASSERT_TRUE(encoder.encode({picture.data(), w, h}, start + i * 33'333'333, packet, error))
          << error;
      pictures.push_back(std::move(picture));
      if (i >= 3) recordFrame(outputs, i, start + i * 33'333'333, packet, "h264");
    }
    ASSERT_TRUE(outputs.close("done", error)) << error;
  }
  ReadBack r = readMcap(path, {"/camera/video", "/camera/preview"});
  ASSERT_EQ(r.error, "");
  ASSERT_EQ(r.messages.size(), 22U);
  for (const auto& m : r.messages) EXPECT_EQ(std::get<0>(m), 0U);  // /camera/video

  std::string error;
  const auto replay = McapReplaySource::open(path, error);
  ASSERT_TRUE(replay) << error;
  EXPECT_EQ(replay->info().frameCount, 15);  // 10-24
  EXPECT_EQ(replay->info().width, w);
  EXPECT_EQ(replay->info().height, h);
  std::vector<std::int64_t> indices;
  Frame f;
  while (replay->next(f, error) == ReadStatus::Frame) {
    indices.push_back(f.index);
    EXPECT_EQ(replay->format(), "h264");
    EXPECT_TRUE(replay->encoded().size() > 0);
    ASSERT_EQ(f.format, PixelFormat::YUV420);
    const auto& truth = pictures[static_cast<std::size_t>(f.index)];
    double err = 0;
    for (int i = 0; i < w * h; ++i)
      err += std::abs(int(f.data[i]) - int(truth[static_cast<std::size_t>(i)]));
    EXPECT_LT(err / (w * h), 2.0) << "picture " << f.index;  // the right picture, decoded
  }
  EXPECT_EQ(error, "");
  std::vector<std::int64_t> expected;
  for (std::int64_t i = 10; i < 25; ++i) expected.push_back(i);
  EXPECT_EQ(indices, expected);
}

std::int64_t unixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

TEST(FlightOutputs, LiveRecordIsInUnixTimeWithTheLogInIt) {
  const std::string path = tempPath("live-times.mcap");
  FlightOutputOptions o;
  o.mcapPath = path;
  o.liveClock = true;
  FlightOutputs outputs;
  std::string error;
  const std::int64_t before = unixNowNs();
  ASSERT_TRUE(outputs.open(o, 64, 48, nullptr, error)) << error;
  // A frame stamped on CLOCK_MONOTONIC, as a camera does.
  const std::int64_t mono = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                std::chrono::steady_clock::now().time_since_epoch())
                                .count();
  Decision d;
  d.index = 0;
  d.timestampNs = mono;
  outputs.decision(d);
  outputs.recordDecision(d, "{}");
  outputs.log(4, "test", "something to warn about");
  ASSERT_TRUE(outputs.close("done", error)) << error;
  const std::int64_t after = unixNowNs();

  ReadBack r = readMcap(path, {"/keyframed/decision", "/keyframed/log"});
  ASSERT_EQ(r.error, "");
  ASSERT_EQ(r.messages.size(), 3U);  // the decision, "recording started", the warning
  bool warned = false;
  for (const auto& [topic, time, data] : r.messages) {
    EXPECT_GE(static_cast<std::int64_t>(time), before) << topic;
    EXPECT_LE(static_cast<std::int64_t>(time), after) << topic;
    if (data.find("something to warn about") != std::string::npos) warned = true;
  }
  EXPECT_TRUE(warned);
}

}  // namespace
}  // namespace keyframed
