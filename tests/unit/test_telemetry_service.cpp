// The telemetry thread as a MAVLink camera component: TIMESYNC, the camera protocol
// (CAMERA_IMAGE_CAPTURED, re-requests), MAVLink 1 framing, its log, and where udpin
// replies go. Driven through an in-memory link (or real UDP sockets for udpin).
#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <climits>
#include <cmath>
#include <condition_variable>
#include <cstdlib>
#include <deque>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "mavlink_messages.h"
#include "tagging/camera_mount.h"
#include "telemetry/link.h"
#include "telemetry/mavlink_codec.h"
#include "telemetry/pose_store.h"
#include "telemetry/telemetry_service.h"

namespace keyframed {
namespace {

using test::heartbeat;
using test::kDeg;
using test::kMs;

// Both ends of an in-memory link: what the "autopilot" pushes in, what the service
// wrote, whether writes succeed, and a one-shot read error.
struct LinkState {
  std::mutex m;
  std::condition_variable cv;
  std::deque<std::vector<std::uint8_t>> in;
  std::vector<std::vector<std::uint8_t>> out;
  bool writable = true;
  bool failNextRead = false;
  int pins = 0;
};

class MemoryLink final : public MavlinkLink {
 public:
  explicit MemoryLink(std::shared_ptr<LinkState> s) : s_(std::move(s)) {}
  Status read(std::uint8_t* buffer, std::size_t capacity, std::size_t& size, std::int64_t& timeNs,
              int timeoutMs, std::string& error) override {
    std::unique_lock lock(s_->m);
    if (s_->failNextRead) {
      s_->failNextRead = false;
      error = "unplugged";
      return Status::Error;
    }
    if (!s_->cv.wait_for(lock, std::chrono::milliseconds(timeoutMs),
                         [&] { return !s_->in.empty(); })) {
      return Status::Timeout;
    }
    const auto pkt = std::move(s_->in.front());
    s_->in.pop_front();
    size = std::min(capacity, pkt.size());
    std::copy(pkt.begin(), pkt.begin() + static_cast<std::ptrdiff_t>(size), buffer);
    timeNs = monotonicNowNs();
    return Status::Data;
  }
  bool write(const std::uint8_t* data, std::size_t size, std::string&) override {
    std::lock_guard lock(s_->m);
    if (!s_->writable) return false;
    s_->out.emplace_back(data, data + size);
    s_->cv.notify_all();
    return true;
  }
  bool reopen(std::string&) override { return true; }
  void pinPeerToLastSender() override {
    std::lock_guard lock(s_->m);
    ++s_->pins;
  }
  [[nodiscard]] std::string describe() const override { return "memory"; }

 private:
  std::shared_ptr<LinkState> s_;
};

// Waits until pred() holds (polling), up to timeoutMs.
bool eventually(const std::function<bool()>& pred, int timeoutMs = 3000) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeoutMs);
  while (std::chrono::steady_clock::now() < deadline) {
    if (pred()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return pred();
}

// What a service logged, collected from its thread.
class LogCollector {
 public:
  void attach(TelemetryService& svc) {
    svc.setLogSink([this](TelemetryLogLevel, const std::string& m) {
      std::lock_guard lock(m_);
      lines_.push_back(m);
    });
  }
  // Lines that contain `text`.
  int count(const std::string& text) const {
    std::lock_guard lock(m_);
    int n = 0;
    for (const auto& l : lines_) n += l.find(text) != std::string::npos ? 1 : 0;
    return n;
  }
  // The number right after `text`, in each line that has it.
  std::vector<double> numbersAfter(const std::string& text) const {
    std::lock_guard lock(m_);
    std::vector<double> out;
    for (const auto& l : lines_) {
      if (const auto at = l.find(text); at != std::string::npos)
        out.push_back(std::strtod(l.c_str() + at + text.size(), nullptr));
    }
    return out;
  }
  std::string all() const {
    std::lock_guard lock(m_);
    std::string out;
    for (const auto& l : lines_) out += l + "\n";
    return out;
  }

 private:
  mutable std::mutex m_;
  std::vector<std::string> lines_;
};

// The autopilot (and others) on the far side of a MemoryLink.
class Peer {
 public:
  Peer() : state(std::make_shared<LinkState>()) {}

  std::unique_ptr<MavlinkLink> link() { return std::make_unique<MemoryLink>(state); }

  void push(const std::vector<std::uint8_t>& bytes) {
    std::lock_guard lock(state->m);
    state->in.push_back(bytes);
    state->cv.notify_all();
  }

  // Everything the service wrote so far, parsed (frames are kept for their magic).
  std::vector<mavlink_message_t> written() {
    std::vector<std::vector<std::uint8_t>> out;
    {
      std::lock_guard lock(state->m);
      out = state->out;
    }
    std::vector<mavlink_message_t> msgs;
    MavlinkParser parser;
    for (const auto& pkt : out) {
      parser.feed(pkt.data(), pkt.size(), [&](const mavlink_message_t& m) { msgs.push_back(m); });
    }
    return msgs;
  }

  std::vector<mavlink_message_t> written(std::uint32_t msgid) {
    std::vector<mavlink_message_t> r;
    for (const auto& m : written()) {
      if (m.msgid == msgid) r.push_back(m);
    }
    return r;
  }

  // Waits for `count` messages of msgid from the service.
  std::vector<mavlink_message_t> waitFor(std::uint32_t msgid, std::size_t count = 1,
                                         int timeoutMs = 3000) {
    std::vector<mavlink_message_t> r;
    eventually(
        [&] {
          r = written(msgid);
          return r.size() >= count;
        },
        timeoutMs);
    return r;
  }

  // The service's `n`-th TIMESYNC request (from 1), once it has sent that many.
  std::optional<mavlink_timesync_t> timesyncRequest(std::size_t n, int timeoutMs = 3000) {
    const auto requests = waitFor(MAVLINK_MSG_ID_TIMESYNC, n, timeoutMs);
    if (requests.size() < n) return std::nullopt;
    mavlink_timesync_t req;
    mavlink_msg_timesync_decode(&requests[n - 1], &req);
    return req;
  }

  void setWritable(bool w) {
    std::lock_guard lock(state->m);
    state->writable = w;
  }

  std::shared_ptr<LinkState> state;
};

std::vector<std::uint8_t> timesync(MavlinkEncoder& enc, std::int64_t tc1, std::int64_t ts1) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_timesync_pack_status(s, c, st, m, tc1, ts1);
      });
}

std::vector<std::uint8_t> requestMessage(MavlinkEncoder& enc, std::uint8_t targetSys,
                                         std::uint8_t targetComp, float msgId, float p2,
                                         float p3 = 0) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_command_long_pack_status(s, c, st, m, targetSys, targetComp,
                                             MAV_CMD_REQUEST_MESSAGE, 0, msgId, p2, p3, 0, 0, 0, 0);
      });
}

std::vector<std::uint8_t> quadHeartbeat(MavlinkEncoder& enc) {
  return heartbeat(enc, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4);
}

mavlink_camera_image_captured_t decodeCapture(const mavlink_message_t& m) {
  mavlink_camera_image_captured_t c;
  mavlink_msg_camera_image_captured_decode(&m, &c);
  return c;
}

std::vector<std::int32_t> indices(const std::vector<mavlink_message_t>& msgs) {
  std::vector<std::int32_t> r;
  for (const auto& m : msgs) r.push_back(decodeCapture(m).image_index);
  return r;
}

CaptureReport capture(std::int32_t index) {
  CaptureReport r;
  r.timeNs = monotonicNowNs();
  r.imageIndex = index;
  r.fileUrl = "file:///k/" + std::to_string(index) + ".jpg";
  return r;
}

TelemetryServiceConfig serviceConfig() {
  TelemetryServiceConfig c;
  c.url = "memory";
  return c;
}

// A tlog recorded by a station whose clock ran 200 s behind GPS time (no RTC, no
// NTP): the frames follow GPS time, and each is fed the records up to its own time
// and a little after, not 200 s of them more, which would push the history (two
// minutes) past its own samples and leave the survey's first minutes untagged.
TEST(TelemetryService, ATlogFarBehindGpsTimeIsFedOnlyAsFarAsEachFrame) {
  MavlinkEncoder ap(1, 1);
  const std::int64_t utc0 = 1'790'000'000'000'000'000;  // UTC at the autopilot's boot
  const std::int64_t behind = 200'000 * kMs;
  std::vector<TimedPacket> packets;
  const auto add = [&](std::int64_t bootMs, std::vector<std::uint8_t> bytes) {
    packets.push_back({utc0 - behind + bootMs * kMs, std::move(bytes)});
  };
  add(900, quadHeartbeat(ap));
  for (std::int64_t ms = 1000; ms <= 300'000; ms += 200) {
    const auto boot = static_cast<std::uint32_t>(ms);
    add(ms,
        ap.encode([&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
          const float q[4] = {1, 0, 0, 0};
          mavlink_msg_attitude_quaternion_pack_status(s, c, st, m, boot, q[0], q[1], q[2], q[3], 0,
                                                      0, 0, nullptr);
        }));
    if (ms % 1000 == 0) {
      add(ms, ap.encode(
                  [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
                    mavlink_msg_system_time_pack_status(
                        s, c, st, m, static_cast<std::uint64_t>((utc0 + ms * kMs) / 1000), boot);
                  }));
    }
  }
  TelemetryService svc(serviceConfig(), CameraDescription{});
  svc.startFromPackets(std::move(packets), /*utc=*/true);
  for (const std::int64_t s : {5, 60, 150, 290}) {
    const std::int64_t frame = utc0 + s * 1000 * kMs;  // the frame's GPS time
    svc.advanceReplay(frame);
    const Pose p = svc.decoder().poseAt(frame);
    EXPECT_TRUE(p.attitude.has_value()) << "frame at boot time " << s << " s: " << p.staleReason;
  }
  ASSERT_TRUE(svc.decoder().recordClockAheadNs().has_value());
  EXPECT_NEAR(static_cast<double>(*svc.decoder().recordClockAheadNs()),
              static_cast<double>(-behind), 1e6);
  svc.stop();
}

TEST(TelemetryService, TimesyncOnlyFromTheAutopilotAndOnlyForOurOwnRequests) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1), gcs(255, 190), apGimbal(1, 154);
  peer.push(quadHeartbeat(ap));
  const auto first = peer.timesyncRequest(1);
  ASSERT_TRUE(first.has_value());
  const mavlink_timesync_t req = *first;
  ASSERT_EQ(req.tc1, 0);

  // The autopilot's clock is 777 s ahead of ours (ahead: ours, the monotonic clock,
  // may have run for less than that on a machine just booted).
  const std::int64_t ahead = 777'000 * kMs;
  // A ground station answering (with its own clock), another component of the
  // vehicle, and the autopilot answering a request we never sent: all ignored.
  peer.push(timesync(gcs, req.ts1 + 3'600'000 * kMs, req.ts1));
  peer.push(timesync(apGimbal, req.ts1 + 5 * ahead, req.ts1));
  peer.push(timesync(ap, req.ts1 + 12'345 + ahead, req.ts1 + 12'345));
  ASSERT_TRUE(eventually([&] { return svc.stats().timesyncRejected == 3; }));
  EXPECT_EQ(svc.decoder().clockSource(), ClockMapper::Source::None);
  EXPECT_FALSE(svc.decoder().clockOffsetNs().has_value());

  // The autopilot's answer to our request sets the clock.
  const std::int64_t pushedAt = monotonicNowNs();
  peer.push(timesync(ap, req.ts1 + ahead, req.ts1));
  ASSERT_TRUE(
      eventually([&] { return svc.decoder().clockSource() == ClockMapper::Source::Timesync; }));
  const std::int64_t seenBy = monotonicNowNs();
  const auto offset = svc.decoder().clockOffsetNs();
  ASSERT_TRUE(offset.has_value());
  // offset = ts1 + rtt/2 - tc1 = rtt/2 - ahead (the answer was pushed at once), the
  // answer read between pushedAt and seenBy.
  EXPECT_NEAR(static_cast<double>(*offset + ahead) / kMs, 0.0, 50.0);
  EXPECT_GE(*offset + ahead, (pushedAt - req.ts1) / 2 - 1);
  EXPECT_LE(*offset + ahead, (seenBy - req.ts1) / 2 + 1);
  // The same answer again (a duplicate datagram) is not a second sample.
  peer.push(timesync(ap, req.ts1 + ahead + 100 * kMs, req.ts1));
  ASSERT_TRUE(eventually([&] { return svc.stats().timesyncRejected == 4; }));
  EXPECT_EQ(*svc.decoder().clockOffsetNs(), *offset);

  // The autopilot's own request is not answered (PX4 would take our clock for its
  // onboard computer's): every TIMESYNC we send is a request of ours.
  const std::size_t before = peer.written(MAVLINK_MSG_ID_TIMESYNC).size();
  const auto parsed = svc.stats().parser.messages;
  peer.push(timesync(ap, 0, 123'456'789));
  ASSERT_TRUE(eventually([&] { return svc.stats().parser.messages > parsed; }));  // read
  ASSERT_GT(peer.waitFor(MAVLINK_MSG_ID_TIMESYNC, before + 1).size(), before);
  for (const mavlink_message_t& m : peer.written(MAVLINK_MSG_ID_TIMESYNC)) {
    mavlink_timesync_t t;
    mavlink_msg_timesync_decode(&m, &t);
    EXPECT_EQ(t.tc1, 0);
    EXPECT_NE(t.ts1, 123'456'789);
  }
  svc.stop();
}

TEST(TelemetryService, AnAnswerToARequestASecondOldSetsTheClock) {
  // A slow radio link: the answer to the first request comes after some 20 further
  // requests (40 Hz until the clock has settled), half a second or more later.
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  peer.push(quadHeartbeat(ap));
  const auto req = peer.timesyncRequest(1);
  ASSERT_TRUE(req.has_value());
  // Half a second of them at least (16 kept were once all there was).
  ASSERT_TRUE(peer.timesyncRequest(20, 5000).has_value());
  const std::int64_t ahead = 60'000 * kMs;
  peer.push(timesync(ap, req->ts1 + ahead, req->ts1));
  ASSERT_TRUE(
      eventually([&] { return svc.decoder().clockSource() == ClockMapper::Source::Timesync; }));
  EXPECT_EQ(svc.stats().timesyncRejected, 0U);
  // The bounds of a one-second round trip: the offset lies within it.
  const std::int64_t offset = *svc.decoder().clockOffsetNs();
  EXPECT_GE(offset, -ahead);
  EXPECT_LE(offset, -ahead + 2'000 * kMs);
  // The camera's messages are on the autopilot's clock from now on, as its capture
  // reports are: CAMERA_INFORMATION's time_boot_ms too.
  const std::int64_t asked = monotonicNowNs();
  peer.push(requestMessage(ap, 0, 0, MAVLINK_MSG_ID_CAMERA_INFORMATION, 0));
  const auto infos = peer.waitFor(MAVLINK_MSG_ID_CAMERA_INFORMATION);
  ASSERT_FALSE(infos.empty());
  const auto expectedMs = static_cast<double>((asked - offset) / kMs);
  EXPECT_NEAR(mavlink_msg_camera_information_get_time_boot_ms(&infos.back()), expectedMs, 1000.0);
  svc.stop();
}

TEST(TelemetryService, CameraInformationSaysNaNForWhatItDoesNotKnow) {
  Peer peer;
  CameraDescription cam;  // no calibration: focal length and sensor size unknown
  cam.width = 1920;
  cam.height = 1080;
  TelemetryService svc(serviceConfig(), cam);
  svc.setCaptureRequestSink([](bool) { return CaptureAnswer::Taken; });
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  peer.push(quadHeartbeat(ap));
  peer.push(requestMessage(ap, 0, 0, MAVLINK_MSG_ID_CAMERA_INFORMATION, 0));
  const auto infos = peer.waitFor(MAVLINK_MSG_ID_CAMERA_INFORMATION);
  svc.stop();
  ASSERT_EQ(infos.size(), 1U);
  mavlink_camera_information_t info;
  mavlink_msg_camera_information_decode(&infos[0], &info);
  EXPECT_TRUE(std::isnan(info.focal_length));
  EXPECT_TRUE(std::isnan(info.sensor_size_h));
  EXPECT_TRUE(std::isnan(info.sensor_size_v));
  EXPECT_EQ(info.resolution_h, 1920);
  EXPECT_EQ(info.resolution_v, 1080);
  EXPECT_EQ(info.flags & CAMERA_CAP_FLAGS_CAPTURE_IMAGE, CAMERA_CAP_FLAGS_CAPTURE_IMAGE);
  EXPECT_EQ(svc.stats().infoSent, 1U);
}

TEST(TelemetryService, ACommandIntIsAnsweredAsACommandLong) {
  // MAVLink's command protocol lets a ground station send any command as COMMAND_INT:
  // the camera answers it, rather than leave it to time out.
  Peer peer;
  CameraDescription cam;
  cam.width = 1920;
  cam.height = 1080;
  TelemetryService svc(serviceConfig(), cam);
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder gcs(255, 190);
  peer.push(
      gcs.encode([&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_command_int_pack_status(s, c, st, m, 0, MAV_COMP_ID_CAMERA, MAV_FRAME_GLOBAL,
                                            MAV_CMD_REQUEST_MESSAGE, 0, 0,
                                            MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0);
      }));
  const auto infos = peer.waitFor(MAVLINK_MSG_ID_CAMERA_INFORMATION);
  const auto acks = peer.waitFor(MAVLINK_MSG_ID_COMMAND_ACK);
  svc.stop();
  EXPECT_EQ(infos.size(), 1U);
  ASSERT_EQ(acks.size(), 1U);
  mavlink_command_ack_t a;
  mavlink_msg_command_ack_decode(&acks[0], &a);
  EXPECT_EQ(a.command, MAV_CMD_REQUEST_MESSAGE);
  EXPECT_EQ(a.result, MAV_RESULT_ACCEPTED);
  EXPECT_EQ(a.target_system, 255);
}

TEST(MavlinkEncoder, IdsAbove255GoAsMavlink2InMavlink1Mode) {
  MavlinkEncoder enc(1, 100, /*mavlink1=*/true);
  const auto hb = heartbeat(enc, MAV_TYPE_CAMERA, MAV_AUTOPILOT_INVALID);
  ASSERT_FALSE(hb.empty());
  EXPECT_EQ(hb[0], MAVLINK_STX_MAVLINK1);
  const float q[4] = {1, 0, 0, 0};
  const char url[205] = "file:///x.jpg";  // the pack copies all 205 bytes
  const auto cap = enc.encode([&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st,
                                  mavlink_message_t* m) {
    mavlink_msg_camera_image_captured_pack_status(s, c, st, m, 1, 2, 0, 3, 4, 5, 6, q, 7, 1, url);
  });
  ASSERT_FALSE(cap.empty());
  EXPECT_EQ(cap[0], MAVLINK_STX);  // MAVLink 2: the 24-bit id survives
  const auto hb2 = heartbeat(enc, MAV_TYPE_CAMERA, MAV_AUTOPILOT_INVALID);
  EXPECT_EQ(hb2[0], MAVLINK_STX_MAVLINK1);  // and the mode is kept

  MavlinkParser parser;
  std::vector<mavlink_message_t> got;
  for (const auto* pkt : {&hb, &cap, &hb2}) {
    parser.feed(pkt->data(), pkt->size(), [&](const mavlink_message_t& m) { got.push_back(m); });
  }
  ASSERT_EQ(got.size(), 3U);
  EXPECT_EQ(got[1].msgid, MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED);
  EXPECT_EQ(decodeCapture(got[1]).image_index, 7);
  // One sequence: 0, 1, 2.
  EXPECT_EQ(got[0].seq, 0);
  EXPECT_EQ(got[1].seq, 1);
  EXPECT_EQ(got[2].seq, 2);
}

TEST(TelemetryService, Mavlink1ModeSendsTheCameraProtocolAsMavlink2) {
  Peer peer;
  auto cfg = serviceConfig();
  cfg.mavlink1 = true;
  TelemetryService svc(cfg, CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1, true);
  peer.push(quadHeartbeat(ap));
  peer.push(requestMessage(ap, 1, 100, MAVLINK_MSG_ID_CAMERA_INFORMATION, 0));
  svc.reportCapture(capture(0));
  ASSERT_EQ(peer.waitFor(MAVLINK_MSG_ID_CAMERA_INFORMATION).size(), 1U);
  ASSERT_EQ(peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED).size(), 1U);
  svc.stop();
  for (const auto& m : peer.written()) {
    EXPECT_EQ(m.magic, m.msgid > 255 ? MAVLINK_STX : MAVLINK_STX_MAVLINK1) << m.msgid;
  }
}

TEST(TelemetryService, AnAutopilotSpeakingMavlink1OnlyIsSaidOnce) {
  // Two links side by side: an autopilot on MAVLink 1, and one on MAVLink 2.
  struct Side {
    Peer peer;
    std::unique_ptr<TelemetryService> svc;
    LogCollector logged;
    MavlinkEncoder ap;
    explicit Side(bool v1) : ap(1, 1, v1) {}
  };
  Side v1(true), v2(false);
  for (Side* side : {&v1, &v2}) {
    side->svc = std::make_unique<TelemetryService>(serviceConfig(), CameraDescription{});
    side->logged.attach(*side->svc);
    std::string error;
    ASSERT_TRUE(side->svc->start(side->peer.link(), error)) << error;
  }
  // Heartbeats 200 ms apart until the MAVLink 1 side is said (after 3 s of them; 8 s
  // at the most on a busy machine), then a second more of them: said once, not again.
  const auto pushFor = [&](std::chrono::milliseconds d, const std::function<bool()>& done) {
    const auto end = std::chrono::steady_clock::now() + d;
    while (std::chrono::steady_clock::now() < end && !done()) {
      for (Side* side : {&v1, &v2}) side->peer.push(quadHeartbeat(side->ap));
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
  };
  pushFor(std::chrono::seconds(8), [&] { return v1.logged.count("speaks MAVLink 1 only") > 0; });
  pushFor(std::chrono::seconds(1), [] { return false; });
  for (Side* side : {&v1, &v2}) {
    side->svc->stop();
    EXPECT_EQ(side->logged.count("speaks MAVLink 1 only"), side == &v1 ? 1 : 0)
        << (side == &v1 ? "MAVLink 1" : "MAVLink 2");
  }
}

TEST(MavlinkCameraAttitude, IsInMavlinksCameraFrame) {
  const Quaternion level{1, 0, 0, 0};
  auto near = [](const Quaternion& a, const Quaternion& b) { return angleBetween(a, b) < 1e-9; };
  // A forward camera on a level vehicle heading north: zero rotation.
  EXPECT_TRUE(near(mavlinkCameraAttitude(cameraToNed(level, CameraMount{0, 0, 0})), level));
  // A nadir camera heading north: pitched down by 90 degrees.
  const Quaternion down = quaternionFromEuler(0, -90 * kDeg, 0);
  EXPECT_TRUE(near(mavlinkCameraAttitude(cameraToNed(level, CameraMount{0, -90, 0})), down));
  // ... heading east.
  const Quaternion east = quaternionFromEuler(0, 0, 90 * kDeg);
  EXPECT_TRUE(near(mavlinkCameraAttitude(cameraToNed(east, CameraMount{0, -90, 0})),
                   quaternionFromEuler(0, -90 * kDeg, 90 * kDeg)));
  // A forward camera rolled with the vehicle.
  const Quaternion rolled = quaternionFromEuler(20 * kDeg, 5 * kDeg, -30 * kDeg);
  EXPECT_TRUE(near(mavlinkCameraAttitude(cameraToNed(rolled, CameraMount{0, 0, 0})), rolled));
}

TEST(TelemetryService, CaptureReportCarriesPoseTimeAndTheMavlinkAttitude) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  peer.push(quadHeartbeat(ap));

  CaptureReport r = capture(4);
  GeoPosition p;
  p.latDeg = 47.3977419;
  p.lonDeg = 8.5455938;
  p.altAmslM = 535.25;
  p.altRelM = 60.5;
  r.pose.position = p;
  r.pose.utcUs = 1'790'000'000'123'456;
  r.cameraAttitude = cameraToNed(Quaternion{}, CameraMount{0, -90, 0});  // nadir, north
  svc.reportCapture(r);
  svc.reportCapture(capture(5));  // no pose at all
  CaptureReport unsaved = capture(6);
  unsaved.saved = false;  // a full disk
  svc.reportCapture(unsaved);
  const auto caps = peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 3);
  svc.stop();
  ASSERT_EQ(caps.size(), 3U);
  const auto c = decodeCapture(caps[0]);
  EXPECT_EQ(c.image_index, 4);
  EXPECT_EQ(c.lat, 473977419);
  EXPECT_EQ(c.lon, 85455938);
  EXPECT_EQ(c.alt, 535250);
  EXPECT_EQ(c.relative_alt, 60500);
  EXPECT_EQ(c.time_utc, 1'790'000'000'123'456ULL);
  EXPECT_EQ(c.capture_result, 1);
  EXPECT_EQ(c.camera_id, 0);
  EXPECT_STREQ(std::string(c.file_url, strnlen(c.file_url, sizeof c.file_url)).c_str(),
               "file:///k/4.jpg");
  const double s = std::sqrt(0.5);
  EXPECT_NEAR(c.q[0], s, 1e-6);  // pitch -90: (cos 45, 0, -sin 45, 0)
  EXPECT_NEAR(c.q[1], 0.0, 1e-6);
  EXPECT_NEAR(c.q[2], -s, 1e-6);
  EXPECT_NEAR(c.q[3], 0.0, 1e-6);

  // No position: "unknown" (INT32_MAX), never 0,0; no attitude: NaN; no UTC: 0.
  const auto u = decodeCapture(caps[1]);
  EXPECT_EQ(u.lat, INT32_MAX);
  EXPECT_EQ(u.lon, INT32_MAX);
  EXPECT_EQ(u.alt, INT32_MAX);
  EXPECT_EQ(u.relative_alt, INT32_MAX);
  EXPECT_TRUE(std::isnan(u.q[0]));
  EXPECT_EQ(u.time_utc, 0U);
  EXPECT_EQ(u.capture_result, 1);  // the image itself was taken
  // Not written to disk: a failed capture, with no file to point at.
  const auto f = decodeCapture(caps[2]);
  EXPECT_EQ(f.image_index, 6);
  EXPECT_EQ(f.capture_result, 0);
  EXPECT_EQ(f.file_url[0], '\0');
}

TEST(TelemetryService, CapturesWaitForTheLinkAndAreCountedWhenReallySent) {
  Peer peer;
  auto cfg = serviceConfig();
  cfg.maxPendingCaptures = 4;
  TelemetryService svc(cfg, CameraDescription{});
  LogCollector logged;
  logged.attach(svc);
  std::string error;
  peer.setWritable(false);  // no peer yet / the radio refuses
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  for (int i = 0; i < 6; ++i) svc.reportCapture(capture(i));
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  auto st = svc.stats();
  EXPECT_EQ(st.capturesSent, 0U);
  EXPECT_EQ(st.capturesPending, 4U);
  EXPECT_EQ(st.capturesDropped, 2U);  // bounded: the oldest two
  EXPECT_TRUE(eventually([&] { return logged.count("capture report") >= 1; }));
  peer.setWritable(true);  // the link is back
  const auto caps = peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 4);
  EXPECT_EQ(indices(caps), (std::vector<std::int32_t>{2, 3, 4, 5}));
  ASSERT_TRUE(eventually([&] { return svc.stats().capturesSent == 4; }));
  EXPECT_EQ(svc.stats().capturesPending, 0U);
  svc.stop();
}

TEST(TelemetryService, RequestMessageResendsCapturesByImageIndex) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1), gcs(255, 190);
  peer.push(quadHeartbeat(ap));
  ASSERT_TRUE(eventually([&] { return svc.decoder().autopilotSystem() == 1; }));
  for (int i = 0; i < 5; ++i) svc.reportCapture(capture(i));
  ASSERT_EQ(peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 5).size(), 5U);

  auto ackResults = [&] {
    std::vector<int> r;
    for (const auto& m : peer.written(MAVLINK_MSG_ID_COMMAND_ACK)) {
      mavlink_command_ack_t a;
      mavlink_msg_command_ack_decode(&m, &a);
      EXPECT_EQ(a.command, MAV_CMD_REQUEST_MESSAGE);
      EXPECT_EQ(a.target_system, 255);
      r.push_back(a.result);
    }
    return r;
  };
  const auto id = static_cast<float>(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED);
  peer.push(requestMessage(gcs, 1, 100, id, 3));  // just image 3
  auto caps = peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 6);
  ASSERT_EQ(caps.size(), 6U);
  EXPECT_EQ(decodeCapture(caps[5]).image_index, 3);
  EXPECT_EQ(ackResults(), (std::vector<int>{MAV_RESULT_ACCEPTED}));

  peer.push(requestMessage(gcs, 1, 100, id, 1, 2));  // images 1..2
  caps = peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 8);
  ASSERT_EQ(caps.size(), 8U);
  EXPECT_EQ(decodeCapture(caps[6]).image_index, 1);
  EXPECT_EQ(decodeCapture(caps[7]).image_index, 2);

  peer.push(requestMessage(gcs, 1, 100, id, 42));  // never taken
  ASSERT_TRUE(eventually([&] { return ackResults().size() == 3; }));
  EXPECT_EQ(ackResults().back(), MAV_RESULT_FAILED);

  peer.push(requestMessage(gcs, 1, 100, id, 3, -1));  // 3 and all after it
  caps = peer.waitFor(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED, 10);
  ASSERT_EQ(caps.size(), 10U);
  EXPECT_EQ(decodeCapture(caps[8]).image_index, 3);
  EXPECT_EQ(decodeCapture(caps[9]).image_index, 4);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  svc.stop();
  EXPECT_EQ(peer.written(MAVLINK_MSG_ID_CAMERA_IMAGE_CAPTURED).size(), 10U);
  EXPECT_EQ(svc.stats().capturesResent, 5U);
  EXPECT_EQ(svc.stats().capturesSent, 5U);
}

std::vector<std::uint8_t> command(MavlinkEncoder& enc, std::uint16_t cmd, float p1, float p2,
                                  float p3, float p4) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_command_long_pack_status(s, c, st, m, 1, 100, cmd, 0, p1, p2, p3, p4, 0, 0, 0);
      });
}

std::vector<std::pair<int, int>> acks(Peer& peer) {
  std::vector<std::pair<int, int>> r;
  for (const auto& m : peer.written(MAVLINK_MSG_ID_COMMAND_ACK)) {
    mavlink_command_ack_t a;
    mavlink_msg_command_ack_decode(&m, &a);
    r.emplace_back(a.command, a.result);
  }
  return r;
}

TEST(TelemetryService, ImageStartCaptureAsksTheSelectorOnceOrAtAnInterval) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::atomic<int> requests{0}, ticks{0};
  std::atomic<bool> full{false};
  svc.setCaptureRequestSink([&](bool intervalTick) {
    if (full) return CaptureAnswer::Busy;
    ++requests;
    ticks += intervalTick ? 1 : 0;
    return CaptureAnswer::Taken;
  });
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder gcs(255, 190);
  constexpr int kStart = MAV_CMD_IMAGE_START_CAPTURE;
  // One image, sequence 1; the same command again (a retransmission) takes none.
  peer.push(command(gcs, kStart, 0, 0, 1, 1));
  peer.push(command(gcs, kStart, 0, 0, 1, 1));
  ASSERT_TRUE(eventually([&] { return acks(peer).size() == 2; }));
  EXPECT_EQ(requests.load(), 1);
  // Sequence 2 is a new one; while the selector is full it is refused, to be retried.
  full = true;
  peer.push(command(gcs, kStart, 0, 0, 1, 2));
  ASSERT_TRUE(eventually([&] { return acks(peer).size() == 3; }));
  EXPECT_EQ(acks(peer)[2].second, MAV_RESULT_TEMPORARILY_REJECTED);
  full = false;
  peer.push(command(gcs, kStart, 0, 0, 1, 2));
  ASSERT_TRUE(eventually([&] { return requests.load() == 2; }));
  // Another ground station's sequence 2 is its own request.
  MavlinkEncoder gcs2(254, 191);
  peer.push(command(gcs2, kStart, 0, 0, 1, 2));
  ASSERT_TRUE(eventually([&] { return requests.load() == 3; }));
  // Nonsense: no interval (or under 0.05 s) for several images, a negative count; and a
  // command for another camera (1: one attached to the autopilot).
  peer.push(command(gcs, kStart, 0, 0, 5, 0));
  peer.push(command(gcs, kStart, 0, 0.01F, 5, 0));
  peer.push(command(gcs, kStart, 0, 1, -1, 0));
  peer.push(command(gcs, kStart, 1, 0, 1, 7));
  ASSERT_TRUE(eventually([&] { return acks(peer).size() == 9; }));
  for (std::size_t i = 5; i < 9; ++i) EXPECT_EQ(acks(peer)[i].second, MAV_RESULT_DENIED) << i;
  EXPECT_EQ(requests.load(), 3);
  EXPECT_EQ(ticks.load(), 0);
  // Three images 0.1 s apart, the first at once.
  const auto t0 = std::chrono::steady_clock::now();
  peer.push(command(gcs, kStart, 0, 0.1F, 3, 0));
  ASSERT_TRUE(eventually([&] { return requests.load() == 6; }));
  EXPECT_GE(std::chrono::steady_clock::now() - t0, std::chrono::milliseconds(180));
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  EXPECT_EQ(requests.load(), 6);  // and no more
  EXPECT_EQ(ticks.load(), 3);     // each said to be an interval's
  // Until stopped; the status says so while it runs.
  peer.push(command(gcs, kStart, 0, 0.05F, 0, 0));
  ASSERT_TRUE(eventually([&] { return requests.load() >= 9; }));
  svc.reportCapture(capture(0));
  svc.reportCapture(capture(1));
  peer.push(requestMessage(gcs, 1, 100, MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS, 0));
  const auto status = peer.waitFor(MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS);
  ASSERT_EQ(status.size(), 1U);
  mavlink_camera_capture_status_t cs;
  mavlink_msg_camera_capture_status_decode(&status[0], &cs);
  EXPECT_EQ(cs.image_status, 3);
  EXPECT_NEAR(cs.image_interval, 0.05, 1e-6);
  EXPECT_EQ(cs.image_count, 2);
  peer.push(command(gcs, MAV_CMD_IMAGE_STOP_CAPTURE, 0, 0, 0, 0));
  ASSERT_TRUE(eventually([&] { return acks(peer).back().first == MAV_CMD_IMAGE_STOP_CAPTURE; }));
  const int stopped = requests.load();
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  svc.stop();
  EXPECT_LE(requests.load(), stopped + 1);  // one may have been due as the stop came
  EXPECT_EQ(acks(peer).back().second, MAV_RESULT_ACCEPTED);
  EXPECT_EQ(svc.stats().captureRequests, static_cast<std::uint64_t>(requests.load()));
  EXPECT_EQ(svc.stats().captureRefused, 1U);
}

TEST(TelemetryService, OnceTheSourceHasEndedCapturesAreDeniedAndAnIntervalStops) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::atomic<int> requests{0};
  std::atomic<bool> ended{false};
  svc.setCaptureRequestSink([&](bool) {
    if (ended) return CaptureAnswer::Ended;
    ++requests;
    return CaptureAnswer::Taken;
  });
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder gcs(255, 190);
  constexpr int kStart = MAV_CMD_IMAGE_START_CAPTURE;
  // An interval capture runs until the source ends, then stops by itself.
  peer.push(command(gcs, kStart, 0, 0.05F, 0, 0));
  ASSERT_TRUE(eventually([&] { return requests.load() >= 3; }));
  ended = true;
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  peer.push(requestMessage(gcs, 1, 100, MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS, 0));
  const auto status = peer.waitFor(MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS);
  ASSERT_EQ(status.size(), 1U);
  mavlink_camera_capture_status_t cs;
  mavlink_msg_camera_capture_status_decode(&status[0], &cs);
  EXPECT_EQ(cs.image_status, 0);  // idle
  // A single image and a new interval capture are denied, not accepted and dropped.
  peer.push(command(gcs, kStart, 0, 0, 1, 5));
  peer.push(command(gcs, kStart, 0, 1, 0, 0));
  ASSERT_TRUE(eventually([&] { return acks(peer).size() == 4; }));
  svc.stop();
  const auto a = acks(peer);
  EXPECT_EQ(a[0].second, MAV_RESULT_ACCEPTED);
  EXPECT_EQ(a[1].first, MAV_CMD_REQUEST_MESSAGE);
  EXPECT_EQ(a[2], std::make_pair(kStart, static_cast<int>(MAV_RESULT_DENIED)));
  EXPECT_EQ(a[3], std::make_pair(kStart, static_cast<int>(MAV_RESULT_DENIED)));
  EXPECT_EQ(svc.stats().captureRequests, static_cast<std::uint64_t>(requests.load()));
  EXPECT_EQ(svc.stats().captureRefused, 3U);  // the interval's last tick and the two commands
}

TEST(TelemetryService, WithoutASelectorTheCameraRefusesToCapture) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder gcs(255, 190);
  peer.push(command(gcs, MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, 1));
  peer.push(requestMessage(gcs, 1, 100, MAVLINK_MSG_ID_CAMERA_INFORMATION, 0));
  const auto infos = peer.waitFor(MAVLINK_MSG_ID_CAMERA_INFORMATION);
  svc.stop();
  ASSERT_EQ(infos.size(), 1U);
  mavlink_camera_information_t info;
  mavlink_msg_camera_information_decode(&infos[0], &info);
  EXPECT_EQ(info.flags & CAMERA_CAP_FLAGS_CAPTURE_IMAGE, 0U);
  ASSERT_FALSE(acks(peer).empty());
  EXPECT_EQ(acks(peer)[0], std::make_pair(static_cast<int>(MAV_CMD_IMAGE_START_CAPTURE),
                                          static_cast<int>(MAV_RESULT_UNSUPPORTED)));
}

TEST(TelemetryService, LogsTheClockOnceAndLinkDropsAndReconnects) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  LogCollector logged;
  logged.attach(svc);
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  peer.push(quadHeartbeat(ap));
  // Answer two requests with the same clock: one record, not one per answer.
  const std::int64_t behind = 5'000 * kMs;
  for (std::size_t n = 1; n <= 2; ++n) {
    const auto req = peer.timesyncRequest(n);
    ASSERT_TRUE(req.has_value());
    peer.push(timesync(ap, req->ts1 - behind, req->ts1));
  }
  ASSERT_TRUE(eventually([&] { return logged.count("autopilot clock: timesync, offset ") == 1; }))
      << logged.all();
  // 5000 ms and half the round trip.
  const auto offsetMs = logged.numbersAfter("autopilot clock: timesync, offset ");
  ASSERT_EQ(offsetMs.size(), 1U);
  EXPECT_GE(offsetMs[0], 5000.0);
  EXPECT_LT(offsetMs[0], 5100.0);
  EXPECT_EQ(logged.count("following the autopilot at system 1 component 1"), 1);
  EXPECT_EQ(logged.count("best round trip"), 1);
  {
    std::lock_guard lock(peer.state->m);
    peer.state->failNextRead = true;
  }
  ASSERT_TRUE(eventually([&] { return logged.count("reopened") == 1; }));
  EXPECT_EQ(logged.count("memory: unplugged; reopening"), 1);
  EXPECT_EQ(svc.stats().reconnects, 1U);
  svc.stop();
  EXPECT_EQ(logged.count("autopilot clock"), 1);
}

TEST(TelemetryService, ASerialDeviceThatAppearsLaterIsOpenedThen) {
  // A USB autopilot powered after the companion: its device is not there at start.
  // The service starts anyway, says so once, and reads it once it appears (a
  // pseudo-terminal, linked to the configured name).
  const std::string dir = ::testing::TempDir() + "kf_serial_later_" + std::to_string(::getpid());
  std::filesystem::create_directories(dir);
  const std::string device = dir + "/ttyACM-autopilot";
  std::filesystem::remove(device);
  TelemetryServiceConfig cfg;
  cfg.url = "serial:" + device + ":115200";
  cfg.waitForSerialDevice = true;
  TelemetryService svc(cfg, CameraDescription{});
  LogCollector logged;
  logged.attach(svc);
  std::string error;
  ASSERT_TRUE(svc.start(error)) << error;
  EXPECT_EQ(logged.count("going on without telemetry"), 1) << logged.all();
  const int master = ::posix_openpt(O_RDWR | O_NOCTTY);
  char name[128] = {};
  if (master < 0 || ::grantpt(master) != 0 || ::unlockpt(master) != 0 ||
      ::ptsname_r(master, name, sizeof name) != 0) {
    svc.stop();
    GTEST_SKIP() << "no pseudo-terminal";
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(1200));  // a reopen or two fail
  std::filesystem::create_symlink(name, device);
  ASSERT_TRUE(eventually([&] { return svc.stats().reconnects == 1; }, 4000)) << logged.all();
  MavlinkEncoder ap(1, 1);
  const auto hb = quadHeartbeat(ap);
  ASSERT_EQ(::write(master, hb.data(), hb.size()), static_cast<ssize_t>(hb.size()));
  EXPECT_TRUE(eventually([&] { return svc.decoder().autopilotSystem() == 1; }, 3000));
  svc.stop();
  ::close(master);
  // The failed attempts before it appeared were not each a warning.
  EXPECT_EQ(logged.count("cannot open serial port"), 1) << logged.all();
  EXPECT_EQ(svc.stats().linkErrors, 0U);
  std::filesystem::remove_all(dir);
}

TEST(TelemetryService, ASerialDeviceMissingAtStartFailsWithoutWaitForSerialDevice) {
  TelemetryServiceConfig cfg;
  cfg.url = "serial:/dev/kf-no-such-autopilot:57600";
  TelemetryService svc(cfg, CameraDescription{});
  std::string error;
  EXPECT_FALSE(svc.start(error));
  EXPECT_NE(error.find("kf-no-such-autopilot"), std::string::npos) << error;
}

TEST(TelemetryService, AFrameCutShortBeforeAReopenDoesNotSwallowTheNext) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  auto cut = quadHeartbeat(ap);
  cut.resize(8);  // the serial adapter was unplugged mid-frame
  peer.push(cut);
  ASSERT_TRUE(eventually([&] {
    std::lock_guard lock(peer.state->m);
    return peer.state->in.empty();
  }));
  {
    std::lock_guard lock(peer.state->m);
    peer.state->failNextRead = true;
  }
  ASSERT_TRUE(eventually([&] { return svc.stats().reconnects == 1; }));
  // Plugged back in: the first frame is read whole, not as the rest of the cut one.
  peer.push(quadHeartbeat(ap));
  EXPECT_TRUE(eventually([&] { return svc.decoder().autopilotSystem() == 1; }, 1500));
  svc.stop();
  EXPECT_EQ(svc.stats().parser.messages, 1U);
}

// To nobody in particular (as MAVLink 1 has it), or to the given system and component.
std::vector<std::uint8_t> commandAck(MavlinkEncoder& enc, std::uint16_t command,
                                     std::uint8_t result, std::uint8_t targetSystem = 0,
                                     std::uint8_t targetComponent = 0) {
  return enc.encode(
      [&](std::uint8_t s, std::uint8_t c, mavlink_status_t* st, mavlink_message_t* m) {
        mavlink_msg_command_ack_pack_status(s, c, st, m, command, result, 0, 0, targetSystem,
                                            targetComponent);
      });
}

TEST(TelemetryService, AsksTheAutopilotForItsMessageRatesUntilItAnswers) {
  Peer peer;
  TelemetryServiceConfig cfg = serviceConfig();
  cfg.messageRateHz = 20.0;
  TelemetryService svc(cfg, CameraDescription{});
  LogCollector logged;
  logged.attach(svc);
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1), gimbal(1, 154);
  peer.push(quadHeartbeat(ap));
  const auto rates = [&] {
    std::vector<mavlink_command_long_t> r;
    for (const auto& m : peer.written(MAVLINK_MSG_ID_COMMAND_LONG)) {
      mavlink_command_long_t c;
      mavlink_msg_command_long_decode(&m, &c);
      if (c.command == MAV_CMD_SET_MESSAGE_INTERVAL) r.push_back(c);
    }
    return r;
  };
  ASSERT_TRUE(eventually([&] { return rates().size() == 4; }));
  // To the autopilot: attitude and position at 20 Hz, GPS at 5 Hz, its UTC at 1 Hz.
  std::vector<std::pair<int, int>> asked;
  for (const auto& c : rates()) {
    EXPECT_EQ(c.target_system, 1);
    EXPECT_EQ(c.target_component, 1);
    EXPECT_EQ(c.confirmation, 0);
    asked.emplace_back(static_cast<int>(c.param1), static_cast<int>(c.param2));
  }
  EXPECT_EQ(asked, (std::vector<std::pair<int, int>>{{MAVLINK_MSG_ID_ATTITUDE, 50'000},
                                                     {MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 50'000},
                                                     {MAVLINK_MSG_ID_GPS_RAW_INT, 200'000},
                                                     {MAVLINK_MSG_ID_SYSTEM_TIME, 1'000'000}}));
  // Unanswered: asked again 2 s later (confirmation 1).
  ASSERT_TRUE(eventually([&] { return rates().size() == 8; }, 3500));
  EXPECT_EQ(rates()[4].confirmation, 1);
  // An acknowledgement from another component, or of another command, is not the answer.
  peer.push(commandAck(gimbal, MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_ACCEPTED));
  peer.push(commandAck(ap, MAV_CMD_REQUEST_MESSAGE, MAV_RESULT_ACCEPTED));
  // Nor the autopilot's answer to a ground station's own request on the same link.
  peer.push(commandAck(ap, MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_ACCEPTED, 255, 190));
  peer.push(commandAck(ap, MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_ACCEPTED, 1,
                       static_cast<std::uint8_t>(cfg.componentId)));
  ASSERT_TRUE(eventually([&] { return svc.stats().rateAccepted == 1; }));
  std::this_thread::sleep_for(std::chrono::milliseconds(2300));
  EXPECT_EQ(svc.stats().rateAccepted, 1U) << "the ground station's answer was taken";
  EXPECT_EQ(rates().size(), 8U) << "answered: not asked again";
  EXPECT_EQ(svc.stats().rateRequests, 8U);
  svc.stop();
  EXPECT_EQ(logged.count("attitude and position at 20 Hz"), 1);
}

TEST(TelemetryService, AsksForTheGimbalsAttitudeWhenTheCameraIsOnAGimbal) {
  // ArduPilot sends GIMBAL_DEVICE_ATTITUDE_STATUS in its EXTRA3 group, often at 1-2 Hz:
  // a camera tagged by the gimbal's attitude asks for it at the attitude's rate.
  Peer peer;
  TelemetryServiceConfig cfg = serviceConfig();
  cfg.messageRateHz = 20.0;
  TelemetryService svc(cfg, CameraDescription{});
  svc.setGimbalMount(true);
  LogCollector logged;
  logged.attach(svc);
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  peer.push(quadHeartbeat(ap));
  const auto rates = [&] {
    std::vector<std::pair<int, int>> r;
    for (const auto& m : peer.written(MAVLINK_MSG_ID_COMMAND_LONG)) {
      mavlink_command_long_t c;
      mavlink_msg_command_long_decode(&m, &c);
      if (c.command == MAV_CMD_SET_MESSAGE_INTERVAL && c.target_system == 1 &&
          c.target_component == 1) {
        r.emplace_back(static_cast<int>(c.param1), static_cast<int>(c.param2));
      }
    }
    return r;
  };
  ASSERT_TRUE(eventually([&] { return rates().size() >= 5; }));
  EXPECT_EQ(rates(), (std::vector<std::pair<int, int>>{
                         {MAVLINK_MSG_ID_ATTITUDE, 50'000},
                         {MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 50'000},
                         {MAVLINK_MSG_ID_GPS_RAW_INT, 200'000},
                         {MAVLINK_MSG_ID_SYSTEM_TIME, 1'000'000},
                         {MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, 50'000}}));
  peer.push(commandAck(ap, MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_ACCEPTED));
  ASSERT_TRUE(eventually([&] { return svc.stats().rateAccepted == 1; }));
  svc.stop();
  EXPECT_EQ(svc.stats().rateRequests, 5U);
  EXPECT_EQ(logged.count("attitude and position and the gimbal's attitude at 20 Hz"), 1)
      << logged.all();
}

TEST(TelemetryService, LeavesTheAutopilotsRatesAloneWhenToldTo) {
  Peer peer;
  TelemetryServiceConfig cfg = serviceConfig();
  cfg.messageRateHz = 0.0;
  TelemetryService svc(cfg, CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  peer.push(quadHeartbeat(ap));
  ASSERT_GE(peer.waitFor(MAVLINK_MSG_ID_TIMESYNC, 3).size(), 3U);  // the loop ran a while
  svc.stop();
  EXPECT_TRUE(peer.written(MAVLINK_MSG_ID_COMMAND_LONG).empty());
  EXPECT_EQ(svc.stats().rateRequests, 0U);
}

TEST(TelemetryService, LinkSilenceIsLoggedOnceAndItsEnd) {
  Peer peer;
  TelemetryService svc(serviceConfig(), CameraDescription{});
  LogCollector logged;
  logged.attach(svc);
  std::string error;
  ASSERT_TRUE(svc.start(peer.link(), error)) << error;
  MavlinkEncoder ap(1, 1);
  ASSERT_TRUE(
      eventually([&] { return logged.count("no MAVLink data on memory for ") == 1; }, 5000));
  // Said once 3 s of silence have passed.
  const auto silentS = logged.numbersAfter("no MAVLink data on memory for ");
  ASSERT_EQ(silentS.size(), 1U);
  EXPECT_EQ(silentS[0], 3.0);
  peer.push(quadHeartbeat(ap));
  ASSERT_TRUE(eventually([&] { return logged.count("MAVLink data on memory again") == 1; }));
  EXPECT_EQ(logged.count("no MAVLink data"), 1);
  svc.stop();
}

// ------------------------------------------------------------------ udpin, two senders

int udpSocket(sockaddr_in& addr) {
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  addr = {};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof addr;
  if (fd < 0 || ::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 ||
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
    return -1;
  }
  return fd;
}

// Message ids heard on fd within timeoutMs.
std::vector<std::uint32_t> hear(int fd, int timeoutMs) {
  std::vector<std::uint32_t> ids;
  MavlinkParser parser;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeoutMs);
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    if (left <= 0) return ids;
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(left)) <= 0) continue;
    std::uint8_t buf[2048];
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) continue;
    parser.feed(buf, static_cast<std::size_t>(n),
                [&](const mavlink_message_t& m) { ids.push_back(m.msgid); });
  }
}

// A loopback UDP address no socket is bound to (port 0 when none could be had): for
// the service to listen on.
sockaddr_in freeLoopbackPort() {
  sockaddr_in a{};
  const int fd = udpSocket(a);
  if (fd < 0) return {};
  ::close(fd);
  return a;
}

TEST(MavlinkLink, AUdpPortAlreadyListenedOnIsRefusedNotShared) {
  const sockaddr_in to = freeLoopbackPort();
  ASSERT_NE(to.sin_port, 0);
  const std::string url = "udpin:127.0.0.1:" + std::to_string(ntohs(to.sin_port));
  std::string error;
  auto first = openMavlinkLink(url, error);
  ASSERT_NE(first, nullptr) << error;
  // A second listener (say `keyframed select --telemetry` beside the service) would
  // take every datagram from the first if the port were shared.
  auto second = openMavlinkLink(url, error);
  EXPECT_EQ(second, nullptr);
  EXPECT_NE(error.find("cannot listen on udp 127.0.0.1:"), std::string::npos) << error;
  EXPECT_NE(error.find("Address already in use"), std::string::npos) << error;
  first.reset();
  // Once the first is closed, the port is free again at once (UDP has no TIME_WAIT).
  error.clear();
  auto third = openMavlinkLink(url, error);
  EXPECT_NE(third, nullptr) << error;
}

TEST(MavlinkLink, UdpinAnswersTheAutopilotNotTheLastSender) {
  sockaddr_in apAddr{}, gcsAddr{};
  const int apFd = udpSocket(apAddr);
  const int gcsFd = udpSocket(gcsAddr);
  ASSERT_GE(apFd, 0);
  ASSERT_GE(gcsFd, 0);
  const sockaddr_in to = freeLoopbackPort();
  ASSERT_NE(to.sin_port, 0);

  auto cfg = serviceConfig();
  cfg.url = "udpin:127.0.0.1:" + std::to_string(ntohs(to.sin_port));
  TelemetryService svc(cfg, CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(error)) << error;
  auto sendFrom = [&](int fd, const std::vector<std::uint8_t>& pkt) {
    ::sendto(fd, pkt.data(), pkt.size(), 0, reinterpret_cast<const sockaddr*>(&to), sizeof to);
  };
  MavlinkEncoder ap(1, 1), gcs(255, 190);
  sendFrom(apFd, quadHeartbeat(ap));
  ASSERT_TRUE(eventually([&] { return svc.decoder().autopilotSystem() == 1; }));
  // A ground station on the same port keeps talking, after the autopilot.
  std::atomic<bool> done{false};
  std::thread chatter([&] {
    while (!done) {
      sendFrom(gcsFd, heartbeat(gcs, MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID));
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  });
  std::thread gcsEar;
  std::vector<std::uint32_t> heardByGcs;
  gcsEar = std::thread([&] { heardByGcs = hear(gcsFd, 3200); });
  const auto heardByAp = hear(apFd, 3200);
  gcsEar.join();
  done = true;
  chatter.join();
  svc.stop();
  ::close(apFd);
  ::close(gcsFd);
  // HEARTBEAT (1 Hz) and TIMESYNC (1 Hz) go to the autopilot, nothing to the GCS.
  int heartbeats = 0, timesyncs = 0;
  for (auto id : heardByAp) {
    heartbeats += id == MAVLINK_MSG_ID_HEARTBEAT ? 1 : 0;
    timesyncs += id == MAVLINK_MSG_ID_TIMESYNC ? 1 : 0;
  }
  EXPECT_GE(heartbeats, 2);
  EXPECT_GE(timesyncs, 2);
  EXPECT_TRUE(heardByGcs.empty()) << heardByGcs.size() << " messages went to the GCS";
}

TEST(MavlinkLink, EachUdpDatagramStartsOnAFrameBoundary) {
  sockaddr_in apAddr{};
  const int apFd = udpSocket(apAddr);
  ASSERT_GE(apFd, 0);
  const sockaddr_in to = freeLoopbackPort();
  ASSERT_NE(to.sin_port, 0);
  auto cfg = serviceConfig();
  cfg.url = "udpin:127.0.0.1:" + std::to_string(ntohs(to.sin_port));
  TelemetryService svc(cfg, CameraDescription{});
  std::string error;
  ASSERT_TRUE(svc.start(error)) << error;
  auto sendFrom = [&](const std::vector<std::uint8_t>& pkt) {
    ::sendto(apFd, pkt.data(), pkt.size(), 0, reinterpret_cast<const sockaddr*>(&to), sizeof to);
  };
  MavlinkEncoder ap(1, 1);
  // A datagram that ends mid-frame (cut short, or another protocol's packet that
  // happens to hold a start byte), then a good one: a frame never spans datagrams.
  auto cut = quadHeartbeat(ap);
  cut.resize(8);
  sendFrom(cut);
  sendFrom(quadHeartbeat(ap));
  EXPECT_TRUE(eventually([&] { return svc.decoder().autopilotSystem() == 1; }, 1500));
  svc.stop();
  ::close(apFd);
  EXPECT_EQ(svc.stats().parser.messages, 1U);
}

}  // namespace
}  // namespace keyframed
