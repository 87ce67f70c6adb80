#include "output/io.h"

#include <array>
#include <cstdio>

namespace keyframed {
namespace {

// Error buffer for one C call.
struct Err {
  std::array<char, 512> buf{};
  char* data() { return buf.data(); }
  [[nodiscard]] std::size_t size() const { return buf.size(); }
  [[nodiscard]] std::string str() const { return buf[0] != 0 ? buf.data() : "unknown error"; }
};

}  // namespace

// ---- McapWriter ----

std::unique_ptr<McapWriter> McapWriter::open(const McapWriterOptions& o, std::string& error) {
  Err e;
  kfio_mcap* h =
      kfio_mcap_open(o.path.c_str(), o.compression.c_str(), o.chunkSize, e.data(), e.size());
  if (h == nullptr) {
    error = e.str();
    return nullptr;
  }
  return std::unique_ptr<McapWriter>(new McapWriter(h, o.path));
}

std::unique_ptr<McapReader> McapReader::open(const std::string& path,
                                             const std::vector<std::string>& topics,
                                             std::string& error) {
  std::vector<const char*> names;
  names.reserve(topics.size());
  for (const std::string& t : topics) names.push_back(t.c_str());
  Err e;
  kfio_mcap_reader* h =
      kfio_mcap_reader_open(path.c_str(), names.data(), names.size(), e.data(), e.size());
  if (h == nullptr) {
    error = e.str();
    return nullptr;
  }
  return std::unique_ptr<McapReader>(new McapReader(h));
}

McapReader::~McapReader() {
  kfio_mcap_reader_close(handle_);
}

bool McapReader::next(Message& m) {
  const std::uint8_t* data = nullptr;
  std::size_t len = 0;
  if (kfio_mcap_reader_next(handle_, &m.topic, &m.logTimeNs, &data, &len) != 1) return false;
  m.data = {data, len};
  return true;
}

bool McapReader::truncated() const {
  return kfio_mcap_reader_truncated(handle_) != 0;
}

McapWriter::~McapWriter() {
  if (handle_ != nullptr) kfio_mcap_close(handle_, nullptr, 0);
}

bool McapWriter::addSchema(const std::string& name, const std::string& encoding,
                           std::span<const std::uint8_t> data, std::uint16_t& id,
                           std::string& error) {
  Err e;
  if (handle_ == nullptr) {
    error = path_ + ": closed";
    return false;
  }
  if (kfio_mcap_add_schema(handle_, name.c_str(), encoding.c_str(), data.data(), data.size(), &id,
                           e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

bool McapWriter::addChannel(std::uint16_t schemaId, const std::string& topic,
                            const std::string& encoding,
                            const std::vector<std::pair<std::string, std::string>>& metadata,
                            std::uint16_t& id, std::string& error) {
  Err e;
  if (handle_ == nullptr) {
    error = path_ + ": closed";
    return false;
  }
  std::vector<const char*> keys, values;
  for (const auto& [k, v] : metadata) {
    keys.push_back(k.c_str());
    values.push_back(v.c_str());
  }
  if (kfio_mcap_add_channel(handle_, schemaId, topic.c_str(), encoding.c_str(), keys.data(),
                            values.data(), keys.size(), &id, e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

bool McapWriter::write(std::uint16_t channelId, std::uint32_t sequence, std::uint64_t logTimeNs,
                       std::uint64_t publishTimeNs, std::span<const std::uint8_t> data,
                       std::string& error) {
  Err e;
  if (handle_ == nullptr) {
    error = path_ + ": closed";
    return false;
  }
  if (kfio_mcap_write(handle_, channelId, sequence, logTimeNs, publishTimeNs, data.data(),
                      data.size(), e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

bool McapWriter::flush(bool sync, std::string& error) {
  Err e;
  if (handle_ == nullptr) {
    error = path_ + ": closed";
    return false;
  }
  if (kfio_mcap_flush(handle_, sync ? 1 : 0, e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

bool McapWriter::close(std::string& error) {
  if (handle_ == nullptr) return true;
  Err e;
  const int rc = kfio_mcap_close(handle_, e.data(), e.size());
  handle_ = nullptr;
  if (rc != 0) {
    error = e.str();
    return false;
  }
  return true;
}

// ---- ZenohSession ----

std::unique_ptr<ZenohSession> ZenohSession::open(const Options& o, std::string& error) {
  std::vector<const char*> keys, values;
  for (const auto& [k, v] : o.overrides) {
    keys.push_back(k.c_str());
    values.push_back(v.c_str());
  }
  Err e;
  kfio_session* h = kfio_session_open(
      o.configFile.empty() ? nullptr : o.configFile.c_str(),
      o.configFile.empty() && !o.configJson5.empty() ? o.configJson5.c_str() : nullptr, keys.data(),
      values.data(), keys.size(), e.data(), e.size());
  if (h == nullptr) {
    error = e.str();
    return nullptr;
  }
  return std::unique_ptr<ZenohSession>(new ZenohSession(h));
}

bool ZenohSession::checkConfigFile(const std::string& path, std::string& error) {
  Err e;
  if (kfio_zenoh_config_check(path.c_str(), e.data(), e.size()) == 0) return true;
  error = e.str();
  return false;
}

bool ZenohSession::configValue(const std::string& path, const std::string& key, std::string& value,
                               std::string& error) {
  Err e;
  std::array<char, 4096> out{};
  if (kfio_zenoh_config_get(path.empty() ? nullptr : path.c_str(), key.c_str(), out.data(),
                            out.size(), e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  value = out.data();
  return true;
}

ZenohSession::~ZenohSession() {
  kfio_session_close(handle_);
}

std::string ZenohSession::zid() const {
  std::array<char, 64> buf{};
  if (kfio_session_zid(handle_, buf.data(), buf.size()) != 0) return {};
  return buf.data();
}

// ---- ZenohPublisher ----

std::unique_ptr<ZenohPublisher> ZenohPublisher::declare(ZenohSession& session,
                                                        const std::string& key, Kind kind,
                                                        std::string& error) {
  Err e;
  kfio_publisher* h = kfio_publisher_declare(
      session.handle(), key.c_str(),
      kind == Kind::Reliable ? KFIO_PUB_RELIABLE : KFIO_PUB_BEST_EFFORT, e.data(), e.size());
  if (h == nullptr) {
    error = e.str();
    return nullptr;
  }
  return std::unique_ptr<ZenohPublisher>(new ZenohPublisher(h, key));
}

ZenohPublisher::~ZenohPublisher() {
  kfio_publisher_undeclare(handle_);
}

bool ZenohPublisher::put(std::span<const std::uint8_t> payload,
                         std::span<const std::uint8_t> attachment, std::string& error) {
  Err e;
  if (kfio_publisher_put(handle_, payload.data(), payload.size(), attachment.data(),
                         attachment.size(), e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

// ---- ZenohQueryable ----

bool ZenohReply::ok(const std::string& key, std::span<const std::uint8_t> payload,
                    std::span<const std::uint8_t> attachment, std::string& error) {
  Err e;
  if (kfio_reply_ok(reply_, key.empty() ? nullptr : key.c_str(), payload.data(), payload.size(),
                    attachment.data(), attachment.size(), e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

bool ZenohReply::fail(const std::string& message, std::string& error) {
  Err e;
  if (kfio_reply_err(reply_, message.c_str(), e.data(), e.size()) != 0) {
    error = e.str();
    return false;
  }
  return true;
}

std::unique_ptr<ZenohQueryable> ZenohQueryable::declare(ZenohSession& session,
                                                        const std::string& key, Handler handler,
                                                        std::string& error) {
  std::unique_ptr<ZenohQueryable> q(new ZenohQueryable());
  q->handler_ = std::move(handler);
  Err e;
  // The object's address is stable (heap) and outlives the queryable (destructor).
  q->handle_ = kfio_queryable_declare(session.handle(), key.c_str(), &ZenohQueryable::trampoline,
                                      q.get(), e.data(), e.size());
  if (q->handle_ == nullptr) {
    error = e.str();
    return nullptr;
  }
  return q;
}

ZenohQueryable::~ZenohQueryable() {
  kfio_queryable_undeclare(handle_);
}

void ZenohQueryable::trampoline(void* user, const char* key, const char* parameters,
                                kfio_reply* reply) noexcept {
  auto* self = static_cast<ZenohQueryable*>(user);
  ZenohReply r(reply);
  // No exception may unwind into Rust, not even one from saying what went wrong (out
  // of memory): that one is swallowed, and the querier gets no reply.
  try {
    self->handler_(key, parameters, r);
  } catch (const std::exception& ex) {
    try {
      std::string ignored;
      r.fail(std::string("internal error: ") + ex.what(), ignored);
    } catch (...) {
    }
  } catch (...) {
    try {
      std::string ignored;
      r.fail("internal error", ignored);
    } catch (...) {
    }
  }
}

}  // namespace keyframed
