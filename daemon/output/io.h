#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "output/io_ffi.h"

// RAII wrappers over the Rust I/O crate's C ABI (io_ffi.h). Every fallible call
// returns false with a one-line message in `error`; nothing throws.
namespace keyframed {

struct McapWriterOptions {
  std::string path;
  std::string compression = "zstd";      // zstd | lz4 | none
  std::uint64_t chunkSize = 256 * 1024;  // target uncompressed chunk size, bytes
};

// One MCAP file being written. Not thread-safe: one thread owns it.
class McapWriter {
 public:
  static std::unique_ptr<McapWriter> open(const McapWriterOptions& options, std::string& error);
  ~McapWriter();
  McapWriter(const McapWriter&) = delete;
  McapWriter& operator=(const McapWriter&) = delete;

  bool addSchema(const std::string& name, const std::string& encoding,
                 std::span<const std::uint8_t> data, std::uint16_t& id, std::string& error);
  bool addChannel(std::uint16_t schemaId, const std::string& topic, const std::string& encoding,
                  const std::vector<std::pair<std::string, std::string>>& metadata,
                  std::uint16_t& id, std::string& error);
  bool write(std::uint16_t channelId, std::uint32_t sequence, std::uint64_t logTimeNs,
             std::uint64_t publishTimeNs, std::span<const std::uint8_t> data, std::string& error);
  // Ends the current chunk so everything so far survives a crash; sync: fsync too.
  bool flush(bool sync, std::string& error);
  // Writes the summary and footer. The writer is unusable afterwards.
  bool close(std::string& error);

  [[nodiscard]] const std::string& path() const { return path_; }

 private:
  McapWriter(kfio_mcap* handle, std::string path) : handle_(handle), path_(std::move(path)) {}
  kfio_mcap* handle_;
  std::string path_;
};

// One MCAP file read in order, only the wanted topics, one chunk in memory at a time.
class McapReader {
 public:
  struct Message {
    std::uint32_t topic = 0;  // index into the topics open() was given
    std::uint64_t logTimeNs = 0;
    std::span<const std::uint8_t> data;  // valid until the next call
  };
  static std::unique_ptr<McapReader> open(const std::string& path,
                                          const std::vector<std::string>& topics,
                                          std::string& error);
  ~McapReader();
  McapReader(const McapReader&) = delete;
  McapReader& operator=(const McapReader&) = delete;

  // The next message; false at the end (of the file, or where it was cut short).
  bool next(Message& message);
  // Once next() has returned false: the file was cut short or is corrupt there.
  [[nodiscard]] bool truncated() const;

 private:
  explicit McapReader(kfio_mcap_reader* handle) : handle_(handle) {}
  kfio_mcap_reader* handle_;
};

// A Zenoh session. Publishers and queryables must not outlive it.
class ZenohSession {
 public:
  struct Options {
    std::string configFile;   // JSON5 file; empty: zenoh's defaults
    std::string configJson5;  // used when configFile is empty
    std::vector<std::pair<std::string, std::string>> overrides;  // key -> JSON5 value
  };
  static std::unique_ptr<ZenohSession> open(const Options& options, std::string& error);
  // Reads a JSON5 configuration file as open() does, without opening a session.
  static bool checkConfigFile(const std::string& path, std::string& error);
  // One setting ("transport/link/tx/...") of what open() would open with from `path`
  // (empty: the defaults), keyframed's defaults applied, as JSON; false with an error.
  // (Keyframes block while the link is congested: zenoh's 5 s before it closes a
  // session so blocked becomes 60 s unless the file sets it.)
  static bool configValue(const std::string& path, const std::string& key, std::string& value,
                          std::string& error);
  ~ZenohSession();
  ZenohSession(const ZenohSession&) = delete;
  ZenohSession& operator=(const ZenohSession&) = delete;

  [[nodiscard]] std::string zid() const;
  [[nodiscard]] kfio_session* handle() const { return handle_; }

 private:
  explicit ZenohSession(kfio_session* handle) : handle_(handle) {}
  kfio_session* handle_;
};

class ZenohPublisher {
 public:
  enum class Kind { Reliable, BestEffort };
  static std::unique_ptr<ZenohPublisher> declare(ZenohSession& session, const std::string& key,
                                                 Kind kind, std::string& error);
  ~ZenohPublisher();
  ZenohPublisher(const ZenohPublisher&) = delete;
  ZenohPublisher& operator=(const ZenohPublisher&) = delete;

  bool put(std::span<const std::uint8_t> payload, std::span<const std::uint8_t> attachment,
           std::string& error);
  [[nodiscard]] const std::string& key() const { return key_; }

 private:
  ZenohPublisher(kfio_publisher* handle, std::string key) : handle_(handle), key_(std::move(key)) {}
  kfio_publisher* handle_;
  std::string key_;
};

// The answer to one query: reply with data (any number of times) or an error.
class ZenohReply {
 public:
  explicit ZenohReply(kfio_reply* reply) : reply_(reply) {}
  // key empty: the query's own key expression.
  bool ok(const std::string& key, std::span<const std::uint8_t> payload,
          std::span<const std::uint8_t> attachment, std::string& error);
  bool fail(const std::string& message, std::string& error);

 private:
  kfio_reply* reply_;
};

// A queryable; the handler runs on the queryable's own thread, one query at a time.
class ZenohQueryable {
 public:
  using Handler =
      std::function<void(const std::string& key, const std::string& parameters, ZenohReply&)>;
  static std::unique_ptr<ZenohQueryable> declare(ZenohSession& session, const std::string& key,
                                                 Handler handler, std::string& error);
  // Waits for a handler in progress; the handler is not called afterwards.
  ~ZenohQueryable();
  ZenohQueryable(const ZenohQueryable&) = delete;
  ZenohQueryable& operator=(const ZenohQueryable&) = delete;

 private:
  ZenohQueryable() = default;
  static void trampoline(void* user, const char* key, const char* parameters,
                         kfio_reply* reply) noexcept;
  kfio_queryable* handle_ = nullptr;
  Handler handler_;
};

}  // namespace keyframed
