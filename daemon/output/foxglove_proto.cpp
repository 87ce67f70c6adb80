#include "output/foxglove_proto.h"

#include <cmath>
#include <cstring>

namespace keyframed::proto {
namespace {
constexpr std::uint32_t kVarint = 0, kFixed64 = 1, kLen = 2, kFixed32 = 5;
}

void Writer::rawVarint(std::uint64_t v) {
  while (v >= 0x80) {
    buf_.push_back(static_cast<std::uint8_t>(v | 0x80));
    v >>= 7;
  }
  buf_.push_back(static_cast<std::uint8_t>(v));
}

void Writer::tag(std::uint32_t field, std::uint32_t wireType) {
  rawVarint((static_cast<std::uint64_t>(field) << 3) | wireType);
}

void Writer::varint(std::uint32_t field, std::uint64_t v) {
  if (v == 0) return;
  tag(field, kVarint);
  rawVarint(v);
}

void Writer::fixed32(std::uint32_t field, std::uint32_t v) {
  if (v == 0) return;
  tag(field, kFixed32);
  for (int i = 0; i < 4; ++i) buf_.push_back(static_cast<std::uint8_t>(v >> (8 * i)));
}

void Writer::doubleField(std::uint32_t field, double v) {
  if (v == 0.0 && !std::signbit(v)) return;
  tag(field, kFixed64);
  std::uint64_t bits = 0;
  std::memcpy(&bits, &v, sizeof bits);
  for (int i = 0; i < 8; ++i) buf_.push_back(static_cast<std::uint8_t>(bits >> (8 * i)));
}

void Writer::bytes(std::uint32_t field, std::span<const std::uint8_t> v) {
  tag(field, kLen);
  rawVarint(v.size());
  buf_.insert(buf_.end(), v.begin(), v.end());
}

void Writer::string(std::uint32_t field, const std::string& v) {
  if (v.empty()) return;
  bytes(field, {reinterpret_cast<const std::uint8_t*>(v.data()), v.size()});
}

void Writer::message(std::uint32_t field, const Writer& nested) {
  bytes(field, nested.data());
}

void Writer::packedDoubles(std::uint32_t field, std::span<const double> v) {
  if (v.empty()) return;
  tag(field, kLen);
  rawVarint(v.size() * 8);
  for (double d : v) {
    std::uint64_t bits = 0;
    std::memcpy(&bits, &d, sizeof bits);
    for (int i = 0; i < 8; ++i) buf_.push_back(static_cast<std::uint8_t>(bits >> (8 * i)));
  }
}

void Writer::timestamp(std::uint32_t field, std::int64_t ns) {
  if (ns < 0) ns = 0;
  Writer t;
  t.varint(1, static_cast<std::uint64_t>(ns / 1'000'000'000));  // seconds
  t.varint(2, static_cast<std::uint64_t>(ns % 1'000'000'000));  // nanos
  message(field, t);  // always present: an empty Timestamp is the epoch
}

std::vector<std::uint8_t> compressedImage(std::int64_t timeNs, const std::string& frameId,
                                          std::span<const std::uint8_t> data,
                                          const std::string& format) {
  Writer w;
  w.reserve(data.size() + 64 + frameId.size());
  w.timestamp(1, timeNs);
  w.string(4, frameId);
  w.bytes(2, data);
  w.string(3, format);
  return w.take();
}

std::vector<std::uint8_t> compressedVideo(std::int64_t timeNs, const std::string& frameId,
                                          std::span<const std::uint8_t> data,
                                          const std::string& format) {
  Writer w;
  w.reserve(data.size() + 64 + frameId.size());
  w.timestamp(1, timeNs);
  w.string(2, frameId);
  w.bytes(3, data);
  w.string(4, format);
  return w.take();
}

std::vector<std::uint8_t> locationFix(const LocationFixMsg& m) {
  Writer w;
  w.timestamp(6, m.timeNs);
  w.string(7, m.frameId);
  w.doubleField(1, m.latitude);
  w.doubleField(2, m.longitude);
  w.doubleField(3, m.altitude);
  if (m.varianceEnu) {
    const auto& v = *m.varianceEnu;
    const std::array<double, 9> cov{v[0], 0, 0, 0, v[1], 0, 0, 0, v[2]};
    w.packedDoubles(4, cov);
    w.varint(5, 2);  // DIAGONAL_KNOWN
  }
  return w.take();
}

std::vector<std::uint8_t> poseInFrame(std::int64_t timeNs, const std::string& frameId,
                                      const std::array<double, 3>& position,
                                      const std::array<double, 4>& q) {
  Writer pos, rot, pose, w;
  pos.doubleField(1, position[0]);
  pos.doubleField(2, position[1]);
  pos.doubleField(3, position[2]);
  rot.doubleField(1, q[0]);
  rot.doubleField(2, q[1]);
  rot.doubleField(3, q[2]);
  rot.doubleField(4, q[3]);
  pose.message(1, pos);
  pose.message(2, rot);
  w.timestamp(1, timeNs);
  w.string(2, frameId);
  w.message(3, pose);
  return w.take();
}

std::vector<std::uint8_t> cameraCalibration(const CameraCalibrationMsg& m) {
  Writer w;
  w.timestamp(1, m.timeNs);
  w.string(9, m.frameId);
  w.fixed32(2, m.width);
  w.fixed32(3, m.height);
  w.string(4, m.distortionModel);
  w.packedDoubles(5, m.d);
  w.packedDoubles(6, m.k);
  w.packedDoubles(7, m.r);
  w.packedDoubles(8, m.p);
  return w.take();
}

std::vector<std::uint8_t> log(std::int64_t timeNs, LogLevel level, const std::string& message,
                              const std::string& name) {
  Writer w;
  w.timestamp(1, timeNs);
  w.varint(2, static_cast<std::uint64_t>(level));
  w.string(3, message);
  w.string(4, name);
  return w.take();
}

std::vector<std::uint8_t> mavlinkPacket(std::int64_t timeNs, std::uint32_t systemId,
                                        std::uint32_t componentId, std::uint32_t messageId,
                                        std::span<const std::uint8_t> packet) {
  Writer w;
  w.reserve(packet.size() + 32);
  w.timestamp(1, timeNs);
  w.varint(2, systemId);
  w.varint(3, componentId);
  w.varint(4, messageId);
  w.bytes(5, packet);
  return w.take();
}

}  // namespace keyframed::proto
