#include "output/keyframe_publisher.h"
#include "core/thread_name.h"

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <thread>

namespace keyframed {
namespace {

std::string jsonString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    if (static_cast<unsigned char>(c) >= 0x20) out += c;
  }
  return out + "\"";
}

std::string orNull(const std::string& number) {
  return number.empty() ? "null" : number;
}

// Splits one CSV line; fields may be "quoted" (no embedded quotes are written).
std::vector<std::string> splitCsv(const std::string& line) {
  std::vector<std::string> out(1);
  bool quoted = false;
  for (char c : line) {
    if (c == '"') {
      quoted = !quoted;
    } else if (c == ',' && !quoted) {
      out.emplace_back();
    } else if (c != '\r') {
      out.back() += c;
    }
  }
  return out;
}

bool readFile(const std::string& path, std::vector<std::uint8_t>& out, std::string& error) {
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) {
    error = "cannot open " + path + ": " + std::strerror(errno);
    return false;
  }
  out.clear();
  std::uint8_t buf[65536];
  std::size_t n = 0;
  while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) out.insert(out.end(), buf, buf + n);
  const bool ok = std::ferror(f) == 0;
  std::fclose(f);
  if (!ok) error = "cannot read " + path;
  return ok;
}

std::span<const std::uint8_t> asBytes(const std::string& s) {
  return {reinterpret_cast<const std::uint8_t*>(s.data()), s.size()};
}

}  // namespace

std::string toJson(const KeyframeMeta& m) {
  std::string s =
      "{\"vehicle\":" + jsonString(m.vehicle) +
      ",\"flight\":" + (m.flight.empty() ? std::string("null") : jsonString(m.flight)) +
      ",\"sequence\":" + std::to_string(m.sequence) +
      ",\"frame_index\":" + std::to_string(m.frameIndex) + ",\"file\":" + jsonString(m.file) +
      ",\"time_ns\":" + std::to_string(m.timeNs) +
      ",\"decided_ns\":" + (m.decidedNs > 0 ? std::to_string(m.decidedNs) : std::string("null")) +
      ",\"utc_us\":" + orNull(m.utcUs) + ",\"lat\":" + orNull(m.lat) + ",\"lon\":" + orNull(m.lon) +
      ",\"alt_amsl\":" + orNull(m.altAmsl) + ",\"alt_rel\":" + orNull(m.altRel) + ",\"cam_q\":";
  if (m.camQw.empty()) {
    s += "null";
  } else {
    s += "[" + m.camQw + "," + m.camQx + "," + m.camQy + "," + m.camQz + "]";
  }
  s += ",\"yaw\":" + orNull(m.yaw) + ",\"pitch\":" + orNull(m.pitch) +
       ",\"roll\":" + orNull(m.roll) + ",\"hdop\":" + orNull(m.hdop) +
       ",\"fix_type\":" + orNull(m.fixType) +
       ",\"geotag\":" + (m.geotag.empty() ? std::string("null") : jsonString(m.geotag)) +
       ",\"scores\":" + (m.scoresJson.empty() ? std::string("null") : m.scoresJson) + "}";
  return s;
}

bool readKeyframeIndex(const std::string& dir, const std::string& vehicle,
                       const std::string& flight, std::vector<StoredKeyframe>& out,
                       std::string& error) {
  const std::string path = dir + "/keyframes.csv";
  std::ifstream f(path);
  if (!f) {
    error = "cannot open " + path + ": " + std::strerror(errno);
    return false;
  }
  std::string line;
  if (!std::getline(f, line)) return true;  // empty: no keyframes yet
  const std::vector<std::string> header = splitCsv(line);
  auto col = [&header](const char* name) -> int {
    for (std::size_t i = 0; i < header.size(); ++i)
      if (header[i] == name) return static_cast<int>(i);
    return -1;
  };
  const int cSeq = col("sequence"), cIndex = col("index"), cFile = col("file");
  if (cSeq < 0 || cIndex < 0 || cFile < 0) {
    error = path + ": unexpected header";
    return false;
  }
  out.clear();
  while (std::getline(f, line)) {
    const std::vector<std::string> v = splitCsv(line);
    if (v.size() != header.size()) continue;  // a row being written
    auto get = [&](const char* name) -> std::string {
      const int c = col(name);
      return c < 0 ? std::string() : v[static_cast<std::size_t>(c)];
    };
    KeyframeMeta m;
    m.vehicle = vehicle;
    m.flight = flight;
    try {
      m.sequence = std::stoll(v[static_cast<std::size_t>(cSeq)]);
      m.frameIndex = std::stoll(v[static_cast<std::size_t>(cIndex)]);
      m.timeNs = std::stoll(get("time_ns"));
    } catch (const std::exception&) {
      continue;
    }
    m.file = v[static_cast<std::size_t>(cFile)];
    m.utcUs = get("utc_us");
    m.lat = get("lat");
    m.lon = get("lon");
    m.altAmsl = get("alt_amsl");
    m.altRel = get("alt_rel");
    m.camQw = get("cam_qw");
    m.camQx = get("cam_qx");
    m.camQy = get("cam_qy");
    m.camQz = get("cam_qz");
    if (m.camQx.empty() || m.camQy.empty() || m.camQz.empty()) m.camQw.clear();
    m.yaw = get("yaw");
    m.pitch = get("pitch");
    m.roll = get("roll");
    m.hdop = get("hdop");
    m.fixType = get("fix_type");
    m.geotag = get("geotag");
    out.push_back(StoredKeyframe{m.sequence, m.file, toJson(m)});
  }
  return true;
}

std::string KeyframePublisher::checkVehicleName(const std::string& name) {
  if (name.empty()) return "vehicle name is empty";
  if (name == "." || name == "..")
    return "vehicle name '" + name + "' is no name (a ground station's folder for it)";
  for (char c : name) {
    if (c == '/' || c == '*' || c == '$' || c == '?' || c == '#' ||
        static_cast<unsigned char>(c) <= 0x20)
      return "vehicle name '" + name + "' must be one key chunk (no / * $ ? # or spaces)";
  }
  return {};
}

std::unique_ptr<KeyframePublisher> KeyframePublisher::open(const KeyframePublisherOptions& o,
                                                           std::string& error) {
  if (std::string e = checkVehicleName(o.vehicle); !e.empty()) {
    error = e;
    return nullptr;
  }
  std::unique_ptr<KeyframePublisher> p(new KeyframePublisher());
  p->prefix_ = "keyframed/" + o.vehicle;
  p->dir_ = o.keyframeDir;
  p->flight_ = o.flight;
  p->flightsDir_ = o.flightsDir;
  p->keyframesOut_ = o.keyframesOut;
  ZenohSession::Options so;
  so.configFile = o.configFile;
  so.overrides = o.overrides;
  if (o.retryMs <= 0) {
    std::unique_ptr<ZenohSession> session = ZenohSession::open(so, error);
    if (!session || !p->attach(std::move(session), error)) return nullptr;
    return p;
  }
  // The first attempt runs on the retry thread, and open() waits for it only so long:
  // a router that accepts and never answers holds an attempt for Zenoh's open_timeout
  // (10 s), which must not hold up the camera. A configuration error stays an error;
  // a link that is not there (yet) is tried again.
  Retry& r = *p->retry_;
  p->retryThread_ = std::thread(retryLoop, p->retry_, so, o.retryMs, o.onLate, p.get());
  std::unique_lock lock(r.m);
  if (!r.cv.wait_for(lock, std::chrono::milliseconds(kFirstAttemptWaitMs),
                     [&] { return r.answered; })) {
    r.answered = true;  // the attempt's outcome goes to onLate now
    error = "cannot open zenoh session: no answer within " +
            std::to_string(kFirstAttemptWaitMs / 1000) + " s (going on without it)";
    return p;
  }
  error = r.error;
  if (r.fatal) {
    lock.unlock();
    return nullptr;  // the thread has ended; the destructor joins it
  }
  return p;
}

bool KeyframePublisher::attach(std::unique_ptr<ZenohSession> session, std::string& error) {
  session_ = std::move(session);
  using Kind = ZenohPublisher::Kind;
  const auto declare = [&](std::unique_ptr<ZenohPublisher>& to, const char* key, Kind kind) {
    to = ZenohPublisher::declare(*session_, prefix_ + key, kind, error);
    return to != nullptr;
  };
  bool ok = declare(keyframes_, "/keyframe", Kind::Reliable) &&
            declare(status_, "/status", Kind::BestEffort) &&
            declare(finalStatus_, "/status", Kind::Reliable) &&
            declare(preview_, "/preview", Kind::BestEffort) &&
            declare(telemetry_, "/telemetry", Kind::BestEffort);
  if (ok && !dir_.empty()) {
    queryable_ = ZenohQueryable::declare(
        *session_, prefix_ + "/keyframes/*",
        [this](const std::string& key, const std::string& parameters, ZenohReply& reply) {
          answer(key, parameters, reply);
        },
        error);
    ok = queryable_ != nullptr;
  }
  if (ok && !flight_.empty() && !flightsDir_.empty()) {
    const std::string dir = flightsDir_, current = flight_, key = prefix_ + "/flights";
    flightsQueryable_ = ZenohQueryable::declare(
        *session_, key,
        [dir, current, key, out = keyframesOut_](const std::string&, const std::string&,
                                                 ZenohReply& reply) {
          const std::string json = flightCatalogue(dir, current, out);
          std::string ignored;
          // On its own key, not the query's: a fleet's answers to keyframed/*/flights
          // say which vehicle each is from.
          reply.ok(key, asBytes(json), {}, ignored);
        },
        error);
    ok = flightsQueryable_ != nullptr;
  }
  if (ok) live_.store(true, std::memory_order_release);
  return ok;
}

void KeyframePublisher::retryLoop(const std::shared_ptr<Retry>& retry,
                                  ZenohSession::Options options, int retryMs,
                                  const std::function<void(const std::string&)>& onLate,
                                  KeyframePublisher* self) {
  nameThisThread("kf-zenoh-open");
  std::unique_lock lock(retry->m);
  for (int attempt = 1;; ++attempt) {
    if (attempt > 1 && retry->cv.wait_for(lock, std::chrono::milliseconds(retryMs),
                                          [&] { return retry->stopping; }))
      return;
    if (retry->stopping) return;
    retry->opening = true;
    lock.unlock();
    std::string error;
    std::unique_ptr<ZenohSession> session = ZenohSession::open(options, error);
    lock.lock();
    retry->opening = false;
    if (retry->stopping) return;  // the publisher went meanwhile: the session closes here
    // A configuration error (or a session that cannot declare) is no link problem:
    // trying again would not help.
    bool fatal = false;
    const bool opened = session != nullptr;
    if (opened) {
      fatal = !self->attach(std::move(session), error);
      if (fatal) error = "zenoh session open but not usable: " + error;
    } else {
      fatal = error.rfind("cannot open zenoh session", 0) != 0;
      if (!fatal && attempt > 1) continue;
    }
    if (!retry->answered) {  // open() is waiting for this first attempt
      retry->answered = true;
      retry->fatal = fatal;
      retry->error = error;
      lock.unlock();
      retry->cv.notify_all();
      if (fatal || self->live()) return;
      lock.lock();
      continue;
    }
    if (!fatal && !opened) continue;
    lock.unlock();
    if (onLate) {
      onLate(fatal ? error
                   : "zenoh session open at attempt " + std::to_string(attempt) +
                         ": publishing; the ground station fetches the keyframes before");
    }
    return;
  }
}

std::string flightCatalogue(const std::string& flightsDir, const std::string& current,
                            const std::function<std::int64_t(std::int64_t)>& keyframesOut) {
  namespace fs = std::filesystem;
  std::vector<std::string> names;
  std::error_code ec;
  for (fs::directory_iterator it(flightsDir, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code e2;
    if (it->is_directory(e2) && fs::is_regular_file(it->path() / "keyframes" / "keyframes.csv", e2))
      names.push_back(it->path().filename().string());
  }
  std::sort(names.begin(), names.end());
  const auto now = fs::file_time_type::clock::now();
  std::string json = "{\"flights\":[";
  bool firstItem = true;
  for (const std::string& name : names) {
    const std::string index = flightsDir + "/" + name + "/keyframes/keyframes.csv";
    // Rows counted, not parsed (a state directory may hold many long flights): the
    // complete lines after the header, one per keyframe, sequence numbers from 0.
    std::ifstream f(index, std::ios::binary);
    if (!f) continue;
    std::size_t lines = 0;
    char buf[16384];
    // The last complete row's sequence number, from the last bytes read: a keyframe a
    // full disk kept out of the index still took its number, so the count is the
    // last number + 1 where that is more than the rows.
    std::string tail;
    while (f.read(buf, sizeof buf) || f.gcount() > 0) {
      const auto got = static_cast<std::size_t>(f.gcount());
      lines += static_cast<std::size_t>(std::count(buf, buf + got, '\n'));
      tail = (tail + std::string(buf, got))
                 .substr(std::max<std::size_t>(tail.size() + got, sizeof buf) - sizeof buf);
      if (!f) break;
    }
    std::size_t count = lines > 0 ? lines - 1 : 0;
    if (const auto end = tail.rfind('\n'); lines > 1 && end != std::string::npos && end > 0) {
      const auto start = tail.rfind('\n', end - 1);
      if (start != std::string::npos) {
        std::size_t seq = 0;
        const char* first = tail.data() + start + 1;
        const auto parsed = std::from_chars(first, tail.data() + end, seq);
        if (parsed.ec == std::errc() && parsed.ptr != first && *parsed.ptr == ',' &&
            seq + 1 > count)
          count = seq + 1;
      }
    }
    if (name == current && keyframesOut) {
      count = static_cast<std::size_t>(std::clamp<std::int64_t>(
          keyframesOut(static_cast<std::int64_t>(count)), 0, static_cast<std::int64_t>(count)));
    }
    std::error_code e2;
    const auto changed = fs::last_write_time(index, e2);
    char age[32] = "null";  // unknown: never taken for a recent flight
    if (!e2) {
      std::snprintf(age, sizeof age, "%.1f",
                    std::max(0.0, std::chrono::duration<double>(now - changed).count()));
    }
    char item[112];
    std::snprintf(item, sizeof item, ",\"keyframes\":%zu,\"age_s\":%s,\"current\":%s}", count, age,
                  name == current ? "true" : "false");
    json += (firstItem ? "{\"flight\":" : ",{\"flight\":") + jsonString(name) + item;
    firstItem = false;
  }
  return json + "]}";
}

KeyframePublisher::~KeyframePublisher() {
  closing_.store(true, std::memory_order_release);
  bool opening = false;
  {
    std::lock_guard lock(retry_->m);
    retry_->stopping = true;
    opening = retry_->opening;
  }
  retry_->cv.notify_all();
  if (retryThread_.joinable()) {
    // An attempt inside Zenoh's open may take its open_timeout: it ends on its own and
    // touches nothing of this publisher's (the process may exit before it does).
    if (opening)
      retryThread_.detach();
    else
      retryThread_.join();
  }
  // The queryable's thread may be inside answer(): stop it before the rest goes.
  queryable_.reset();
  flightsQueryable_.reset();
  // Every publisher is undeclared before the session closes: one left for after
  // keeps the session's runtime alive (LeakSanitizer reports it).
  keyframes_.reset();
  status_.reset();
  finalStatus_.reset();
  preview_.reset();
  telemetry_.reset();
  session_.reset();
}

std::string keyframeQueryFlight(const std::string& parameters) {
  std::size_t start = 0;
  while (start <= parameters.size()) {
    std::size_t end = parameters.find_first_of(";&", start);
    if (end == std::string::npos) end = parameters.size();
    if (parameters.compare(start, 7, "flight=") == 0 && end - start >= 7)
      return parameters.substr(start + 7, end - start - 7);
    start = end + 1;
  }
  return {};
}

bool parseKeyframeRange(const std::string& parameters, std::int64_t& first, std::int64_t& last,
                        std::string& error) {
  first = 0;
  last = INT64_MAX;
  std::string value;
  bool found = false;
  std::size_t start = 0;
  while (start <= parameters.size()) {
    std::size_t end = parameters.find_first_of(";&", start);
    if (end == std::string::npos) end = parameters.size();
    const std::string item = parameters.substr(start, end - start);
    if (item.rfind("range=", 0) == 0) {
      value = item.substr(6);
      found = true;
    }
    start = end + 1;
  }
  if (!found) return true;
  const std::size_t dots = value.find("..");
  const auto number = [](const std::string& text, std::int64_t& out) {
    if (text.empty() || text.find_first_not_of("0123456789") != std::string::npos) return false;
    errno = 0;
    out = std::strtoll(text.c_str(), nullptr, 10);
    return errno == 0;
  };
  const std::string a = dots == std::string::npos ? value : value.substr(0, dots);
  const std::string b = dots == std::string::npos ? value : value.substr(dots + 2);
  if (!number(a, first) || (!b.empty() && !number(b, last)) || last < first) {
    error =
        "bad range '" + value + "': FIRST..LAST, FIRST.. or N (sequence numbers, LAST >= FIRST)";
    return false;
  }
  return true;
}

void KeyframePublisher::answer(const std::string& key, const std::string& parameters,
                               ZenohReply& reply) {
  std::string error;
  const std::string last = key.substr(key.rfind('/') + 1);
  const bool all = last == "*" || last == "**";
  std::int64_t wanted = -1;
  if (!all) {
    char* end = nullptr;
    errno = 0;
    wanted = std::strtoll(last.c_str(), &end, 10);
    // Canonical digits only: "05", "+5" or "-0" parse, but a reply on keyframes/5
    // would not match the query's key, and it would get no answer at all.
    if (last.empty() || errno != 0 || *end != '\0' || wanted < 0 ||
        std::to_string(wanted) != last) {
      reply.fail("not a keyframe sequence number: '" + last + "'", error);
      return;
    }
  }
  // keyframes/*?range=A..B: the keyframes A to B (both included) in one query.
  std::int64_t first = 0, final = INT64_MAX;
  if (!parseKeyframeRange(parameters, first, final, error)) {
    std::string ignored;
    reply.fail(error, ignored);
    return;
  }
  if (!all && (wanted < first || wanted > final)) {
    // keyframes/5?range=0..3 asks for nothing: said so, not "no keyframe 5 (yet)".
    std::string ignored;
    reply.fail("keyframe " + last + " is outside the range asked for", ignored);
    return;
  }
  // flight=ID: an earlier run's keyframes (its own sequence numbers), from its directory.
  const std::string flight = keyframeQueryFlight(parameters);
  const bool own = flight.empty() || flight == flight_;
  std::string dir = dir_;
  if (!own) {
    const bool name =
        flight.find_first_of("/\\") == std::string::npos && flight != "." && flight != "..";
    std::error_code ec;
    if (flightsDir_.empty() || !name ||
        !std::filesystem::is_directory(flightsDir_ + "/" + flight + "/keyframes", ec)) {
      std::string ignored;
      reply.fail("no flight '" + flight + "' here", ignored);
      return;
    }
    dir = flightsDir_ + "/" + flight + "/keyframes";
  }
  std::vector<StoredKeyframe> rows;
  // The ones a full disk kept in memory (this flight's only), by sequence. Copied
  // before the index is read: one saved in between (its copy forgotten) is then in the
  // index, not missing from both.
  std::map<std::int64_t, Unsaved> inMemory;
  if (own) {
    std::lock_guard lock(publishedMutex_);
    for (const auto& [seq, u] : unsaved_) {
      if (seq >= first && seq <= final && (all || seq == wanted)) inMemory[seq] = u;
    }
  }
  const bool indexRead = readKeyframeIndex(dir, prefix_.substr(prefix_.find('/') + 1),
                                           own ? flight_ : flight, rows, error);
  if (own) {
    std::lock_guard lock(publishedMutex_);
    // What was published live, where known (the CSV has no scores).
    for (StoredKeyframe& r : rows) {
      if (const auto it = published_.find(r.sequence); it != published_.end()) {
        r.metadataJson = it->second;
      }
    }
    std::set<std::int64_t> onDisk;
    for (const StoredKeyframe& r : rows) onDisk.insert(r.sequence);
    std::erase_if(inMemory, [&](const auto& kv) { return onDisk.contains(kv.first); });
    for (const auto& [seq, u] : inMemory) rows.push_back(StoredKeyframe{seq, {}, u.metadataJson});
    std::sort(rows.begin(), rows.end(), [](const StoredKeyframe& a, const StoredKeyframe& b) {
      return a.sequence < b.sequence;
    });
  }
  if (!indexRead && inMemory.empty()) {
    std::string ignored;
    reply.fail(error, ignored);
    return;
  }
  bool found = false;
  int sent = 0;
  std::vector<std::uint8_t> jpeg;
  for (const StoredKeyframe& r : rows) {
    if (!all && r.sequence != wanted) continue;
    if (r.sequence < first || r.sequence > final) continue;
    // The parameters to ask with for the rest, as they stand: the range's end and the
    // flight kept, so that a querier that follows them gets the rest of what it asked for.
    const auto askAgain = [&](const std::string& why) {
      std::string ignored;
      reply.fail(why + ": ask again with range=" + std::to_string(r.sequence) + ".." +
                     (final == INT64_MAX ? std::string() : std::to_string(final)) +
                     (flight.empty() ? std::string() : ";flight=" + flight),
                 ignored);
    };
    if (closing_.load(std::memory_order_acquire)) {
      askAgain("the daemon is stopping");
      return;
    }
    if (sent == kMaxRepliesPerQuery) {
      // A whole flight in one answer would hold a radio link for minutes, past any
      // querier's timeout, while it asked again: the rest is asked for by range.
      askAgain("at most " + std::to_string(kMaxRepliesPerQuery) + " keyframes a query");
      return;
    }
    found = true;
    if (const auto m = inMemory.find(r.sequence); m != inMemory.end()) {
      jpeg = m->second.jpeg;
    } else if (!readFile(dir + "/" + r.file, jpeg, error)) {
      std::string ignored;
      reply.fail(error, ignored);
      ++sent;  // an error reply counts towards the cap too
      continue;
    }
    const std::string replyKey = prefix_ + "/keyframes/" + std::to_string(r.sequence);
    if (!reply.ok(replyKey, jpeg, asBytes(r.metadataJson), error)) return;
    ++sent;
  }
  if (!found && !all) {
    std::string ignored;
    reply.fail("no keyframe " + std::to_string(wanted) + " (yet)", ignored);
  }
}

void KeyframePublisher::remember(std::int64_t sequence, const std::string& metadataJson) {
  std::lock_guard lock(publishedMutex_);
  published_[sequence] = metadataJson;
}

void KeyframePublisher::keepUnsaved(std::int64_t sequence, std::span<const std::uint8_t> jpeg,
                                    const std::string& metadataJson) {
  std::lock_guard lock(publishedMutex_);
  Unsaved& u = unsaved_[sequence];
  unsavedBytes_ -= u.jpeg.size();
  u.jpeg.assign(jpeg.begin(), jpeg.end());
  u.metadataJson = metadataJson;
  unsavedBytes_ += u.jpeg.size();
  while (unsavedBytes_ > kUnsavedBytes && unsaved_.size() > 1) {
    unsavedBytes_ -= unsaved_.begin()->second.jpeg.size();
    unsaved_.erase(unsaved_.begin());
    ++unsavedLetGo_;
  }
}

void KeyframePublisher::forgetUnsaved(std::span<const std::int64_t> sequences) {
  std::lock_guard lock(publishedMutex_);
  for (const std::int64_t seq : sequences) {
    if (const auto it = unsaved_.find(seq); it != unsaved_.end()) {
      unsavedBytes_ -= it->second.jpeg.size();
      unsaved_.erase(it);
    }
  }
}

std::size_t KeyframePublisher::unsavedBytes() const {
  std::lock_guard lock(publishedMutex_);
  return unsavedBytes_;
}

std::int64_t KeyframePublisher::unsavedLetGo() const {
  std::lock_guard lock(publishedMutex_);
  return unsavedLetGo_;
}

bool KeyframePublisher::put(const std::unique_ptr<ZenohPublisher>& to,
                            std::span<const std::uint8_t> payload,
                            std::span<const std::uint8_t> attachment, std::string& error) {
  if (!live()) {
    error = "no zenoh session yet (the queryable serves keyframes later)";
    return false;
  }
  return to->put(payload, attachment, error);
}

bool KeyframePublisher::publishKeyframe(std::int64_t sequence, std::span<const std::uint8_t> jpeg,
                                        const std::string& metadataJson, std::string& error) {
  remember(sequence, metadataJson);
  return put(keyframes_, jpeg, asBytes(metadataJson), error);
}

bool KeyframePublisher::publishPreview(std::span<const std::uint8_t> jpeg, std::string& error) {
  return put(preview_, jpeg, {}, error);
}

bool KeyframePublisher::publishTelemetry(const std::string& json, std::string& error) {
  return put(telemetry_, asBytes(json), {}, error);
}

bool KeyframePublisher::publishStatus(const std::string& json, std::string& error, bool last) {
  return put(last ? finalStatus_ : status_, asBytes(json), {}, error);
}

}  // namespace keyframed
