#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <span>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "output/io.h"

namespace keyframed {

struct KeyframePublisherOptions {
  std::string configFile;  // zenoh JSON5 config; empty: zenoh's defaults (peer, scouting)
  std::vector<std::pair<std::string, std::string>> overrides;  // key -> JSON5 value
  std::string vehicle = "uav";  // one key chunk: keyframed/<vehicle>/...
  std::string keyframeDir;      // served by the queryable (keyframes.csv + JPEGs)
  // The run's flight (`run`: its directory's name under flightsDir; `select`: its
  // start), in every keyframe's metadata: sequence numbers start again at 0 in each
  // run. Earlier flights' keyframes are served too when a query names them
  // (flight=ID), from flightsDir/ID/keyframes. Empty: no flight id, only this run's.
  std::string flight;
  std::string flightsDir;
  // A session that cannot open (a client whose router is not up yet, a refused
  // password): 0 fails open(); > 0 opens the publisher without a session (after
  // waiting kFirstAttemptWaitMs at most) and tries again every retryMs on a thread of
  // its own, so that the flight is recorded whatever the link does. Until the session
  // opens nothing is put; keyframes are remembered for the queryable, which serves
  // them once it is declared.
  int retryMs = 0;
  // Told when a session opens on a retry, or turns out unusable (any thread).
  std::function<void(const std::string&)> onLate;
  // Of the running flight's N keyframes on disk, how many are out on the link (the
  // rest wait in the put queue): the flights catalogue says no more, as the status
  // does, so that a ground station does not fetch what is on its way. None: all.
  std::function<std::int64_t(std::int64_t)> keyframesOut;
};

// Publishes keyframes and status under keyframed/<vehicle>/ and answers queries for
// any keyframe already on disk (keyframed/<vehicle>/keyframes/<seq>, or a range:
// keyframes/*?range=A..B; an earlier flight's with flight=ID), so a ground station
// that missed some fetches them again, across restarts of the daemon; and, with a
// flight id, for the flights on disk (keyframed/<vehicle>/flights: flightCatalogue),
// so that one that was down for a whole flight learns of it.
class KeyframePublisher {
 public:
  static std::unique_ptr<KeyframePublisher> open(const KeyframePublisherOptions& options,
                                                 std::string& error);
  // How long open() waits for the first attempt when retryMs > 0 (the attempt goes on
  // on the retry thread): a router that accepts and never answers holds it for Zenoh's
  // open_timeout (10 s); peer mode's scouting takes 0.5 s.
  static constexpr int kFirstAttemptWaitMs = 3000;
  // A query is answered with at most this many keyframes (30 MB of 1080p JPEGs), then
  // an error reply that says from which sequence number to ask again.
  static constexpr int kMaxRepliesPerQuery = 64;
  ~KeyframePublisher();
  KeyframePublisher(const KeyframePublisher&) = delete;
  KeyframePublisher& operator=(const KeyframePublisher&) = delete;

  // Reliable, blocking congestion control: waits rather than drops. The metadata is
  // kept (by sequence) for the queryable, so a keyframe fetched later carries the
  // same attachment, scores included, as the one published.
  bool publishKeyframe(std::int64_t sequence, std::span<const std::uint8_t> jpeg,
                       const std::string& metadataJson, std::string& error);
  // The metadata of a keyframe left to the queryable (never put), for its replies.
  void remember(std::int64_t sequence, const std::string& metadataJson);
  // A keyframe that could not be saved (a full disk): the queryable serves it from
  // memory, so one put while no subscriber listened is not lost. Up to
  // kUnsavedBytes are kept; past that the oldest are let go (and counted).
  void keepUnsaved(std::int64_t sequence, std::span<const std::uint8_t> jpeg,
                   const std::string& metadataJson);
  static constexpr std::size_t kUnsavedBytes = 64u << 20;
  // Those of them now saved and indexed: served from disk from now on.
  void forgetUnsaved(std::span<const std::int64_t> sequences);
  // The bytes of JPEG kept by keepUnsaved() now.
  [[nodiscard]] std::size_t unsavedBytes() const;
  [[nodiscard]] std::int64_t unsavedLetGo() const;
  // Best effort; `last` (the flight's final state, done or stopped): reliable and
  // waiting rather than dropped, so that a receiver learns the flight's keyframe
  // count and asks for what it missed.
  bool publishStatus(const std::string& json, std::string& error, bool last = false);
  // Best effort, dropped under congestion: a low-rate JPEG of the live view.
  bool publishPreview(std::span<const std::uint8_t> jpeg, std::string& error);
  // Best effort: the vehicle's pose now (JSON).
  bool publishTelemetry(const std::string& json, std::string& error);

  [[nodiscard]] const std::string& prefix() const { return prefix_; }
  // Whether the session is open (always, unless options.retryMs let open() go on
  // without one).
  [[nodiscard]] bool live() const { return live_.load(std::memory_order_acquire); }
  [[nodiscard]] std::string zid() const { return live() ? session_->zid() : std::string(); }

  // "" when `name` can be a vehicle name (one key chunk), else why not.
  static std::string checkVehicleName(const std::string& name);

 private:
  KeyframePublisher() = default;
  // Declares the publishers and queryables on `session` and goes live.
  bool attach(std::unique_ptr<ZenohSession> session, std::string& error);
  // Shared by the publisher and its retry thread, which may outlive it: a stop while
  // an attempt is inside ZenohSession::open (a router that accepts and never answers
  // holds it for Zenoh's open_timeout, 10 s) leaves that attempt to end on its own.
  struct Retry {
    std::mutex m;
    std::condition_variable cv;
    bool stopping = false;  // the publisher is going: touch it no more
    bool opening = false;   // an attempt is inside ZenohSession::open
    // The first attempt's outcome, for open(), which waits kFirstAttemptWaitMs for it
    // (answered is set by open() too when it waits no longer).
    bool answered = false;
    bool fatal = false;  // a configuration error, or a session that cannot declare
    std::string error;
  };
  // The retry thread: every `retryMs`, a session; `onLate` says how it went. `self` is
  // touched only under retry->m while !retry->stopping.
  static void retryLoop(const std::shared_ptr<Retry>& retry, ZenohSession::Options options,
                        int retryMs, const std::function<void(const std::string&)>& onLate,
                        KeyframePublisher* self);
  // to->put() once the session is open; false with an error before.
  bool put(const std::unique_ptr<ZenohPublisher>& to, std::span<const std::uint8_t> payload,
           std::span<const std::uint8_t> attachment, std::string& error);
  void answer(const std::string& key, const std::string& parameters, ZenohReply& reply);

  std::string prefix_;  // keyframed/<vehicle>
  std::string dir_;
  std::string flight_;
  std::string flightsDir_;
  std::function<std::int64_t(std::int64_t)> keyframesOut_;
  std::unique_ptr<ZenohSession> session_;
  std::unique_ptr<ZenohPublisher> keyframes_;
  std::unique_ptr<ZenohPublisher> status_;
  std::unique_ptr<ZenohPublisher> finalStatus_;  // the same key, reliable
  std::unique_ptr<ZenohPublisher> preview_;
  std::unique_ptr<ZenohPublisher> telemetry_;
  std::unique_ptr<ZenohQueryable> queryable_;
  std::unique_ptr<ZenohQueryable> flightsQueryable_;
  // Set once everything above is declared; none of it changes after.
  std::atomic<bool> live_{false};
  // Set first by the destructor: an answer under way stops between two keyframes
  // rather than sending up to kMaxRepliesPerQuery of them while the daemon stops.
  std::atomic<bool> closing_{false};
  std::shared_ptr<Retry> retry_ = std::make_shared<Retry>();
  std::thread retryThread_;
  mutable std::mutex publishedMutex_;  // publishKeyframe() against answer() (a Zenoh thread)
  std::map<std::int64_t, std::string> published_;  // sequence -> metadata JSON
  struct Unsaved {
    std::vector<std::uint8_t> jpeg;
    std::string metadataJson;
  };
  std::map<std::int64_t, Unsaved> unsaved_;  // under publishedMutex_
  std::size_t unsavedBytes_ = 0;
  std::int64_t unsavedLetGo_ = 0;
};

// The metadata of one keyframe; numbers as text, empty = unknown (JSON null).
struct KeyframeMeta {
  std::string vehicle;
  std::string flight;  // empty: null
  std::int64_t sequence = 0;
  std::int64_t frameIndex = 0;
  std::string file;  // name inside the keyframe directory
  std::int64_t timeNs = 0;
  std::int64_t decidedNs = 0;  // 0: null
  std::string utcUs, lat, lon, altAmsl, altRel;
  std::string camQw, camQx, camQy, camQz;  // camera -> NED
  std::string yaw, pitch, roll, hdop, fixType;
  std::string geotag;      // empty: null
  std::string scoresJson;  // a JSON object, or empty: null
};
std::string toJson(const KeyframeMeta& m);

// One row of <dir>/keyframes.csv (written by KeyframeWriter), as JSON: the same
// field names as the live attachment.
struct StoredKeyframe {
  std::int64_t sequence = -1;
  std::string file;
  std::string metadataJson;
};
// Reads <dir>/keyframes.csv; false with an error when it cannot be read.
// The query parameter range=A..B (both included; A.. to the end; N alone), as the
// queryable takes it. No range parameter: every keyframe (0..INT64_MAX).
bool parseKeyframeRange(const std::string& parameters, std::int64_t& first, std::int64_t& last,
                        std::string& error);

bool readKeyframeIndex(const std::string& dir, const std::string& vehicle,
                       const std::string& flight, std::vector<StoredKeyframe>& out,
                       std::string& error);
// The flight=ID query parameter ("" when absent).
std::string keyframeQueryFlight(const std::string& parameters);

// The answer to keyframed/<vehicle>/flights: every flight directory under flightsDir
// with a keyframe index, by name (the UTC time it started), as JSON:
// {"flights":[{"flight":ID,"keyframes":N,"age_s":S,"current":B},...]}: N keyframes
// in its keyframes.csv, S seconds since that file last changed (its last keyframe),
// current for the running flight (counted as `keyframesOut` says, when given).
std::string flightCatalogue(const std::string& flightsDir, const std::string& current,
                            const std::function<std::int64_t(std::int64_t)>& keyframesOut = {});

}  // namespace keyframed
