#include "output/foxglove_proto.h"

#include <cmath>
#include <cstring>

namespace keyframed::proto {
namespace {
constexpr std::uint32_t kVarint = 0, kFixed64 = 1, kLen = 2, kFixed32 = 5;

std::size_t varintSize(std::uint64_t v) {
  std::size_t n = 1;
  while (v >= 0x80) {
    v >>= 7;
    ++n;
  }
  return n;
}

// The bytes Writer::varint() and doubleField() write for a field below 16 (a one-byte
// tag); zero for a value they leave out.
std::size_t varintFieldSize(std::uint64_t v) {
  return v == 0 ? 0 : 1 + varintSize(v);
}
std::size_t doubleFieldSize(double v) {
  return v == 0.0 && !std::signbit(v) ? 0 : 9;
}
}  // namespace

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

void Writer::rawDouble(double v) {
  std::uint64_t bits = 0;
  std::memcpy(&bits, &v, sizeof bits);
  for (int i = 0; i < 8; ++i) buf_.push_back(static_cast<std::uint8_t>(bits >> (8 * i)));
}

void Writer::doubleField(std::uint32_t field, double v) {
  if (v == 0.0 && !std::signbit(v)) return;
  tag(field, kFixed64);
  rawDouble(v);
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

void Writer::nestedHeader(std::uint32_t field, std::size_t length) {
  tag(field, kLen);
  rawVarint(length);
}

void Writer::message(std::uint32_t field, const Writer& nested) {
  bytes(field, nested.data());
}

void Writer::packedDoubles(std::uint32_t field, std::span<const double> v) {
  if (v.empty()) return;
  tag(field, kLen);
  rawVarint(v.size() * 8);
  for (double d : v) rawDouble(d);
}

void Writer::timestamp(std::uint32_t field, std::int64_t ns) {
  if (ns < 0) ns = 0;
  const auto seconds = static_cast<std::uint64_t>(ns / 1'000'000'000);
  const auto nanos = static_cast<std::uint64_t>(ns % 1'000'000'000);
  // Always present (an empty Timestamp is the epoch), written in place.
  tag(field, kLen);
  rawVarint(varintFieldSize(seconds) + varintFieldSize(nanos));
  varint(1, seconds);
  varint(2, nanos);
}

std::vector<std::uint8_t> compressedImage(std::int64_t timeNs, const std::string& frameId,
                                          std::span<const std::uint8_t> data,
                                          const std::string& format,
                                          std::vector<std::uint8_t> into) {
  Writer w(std::move(into));
  w.reserve(data.size() + 64 + frameId.size());
  w.timestamp(1, timeNs);
  w.string(4, frameId);
  w.bytes(2, data);
  w.string(3, format);
  return w.take();
}

std::vector<std::uint8_t> compressedVideo(std::int64_t timeNs, const std::string& frameId,
                                          std::span<const std::uint8_t> data,
                                          const std::string& format,
                                          std::vector<std::uint8_t> into) {
  Writer w(std::move(into));
  w.reserve(data.size() + 64 + frameId.size());
  w.timestamp(1, timeNs);
  w.string(2, frameId);
  w.bytes(3, data);
  w.string(4, format);
  return w.take();
}

std::vector<std::uint8_t> locationFix(const LocationFixMsg& m, std::vector<std::uint8_t> into) {
  Writer w(std::move(into));
  w.reserve(160 + m.frameId.size());
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
                                      const std::array<double, 4>& q,
                                      std::vector<std::uint8_t> into) {
  // The nested Pose (Vector3 position, Quaternion orientation) written in place, its
  // lengths counted first.
  std::size_t posSize = 0, rotSize = 0;
  for (const double v : position) posSize += doubleFieldSize(v);
  for (const double v : q) rotSize += doubleFieldSize(v);
  const std::size_t poseSize =
      1 + varintSize(posSize) + posSize + 1 + varintSize(rotSize) + rotSize;
  Writer w(std::move(into));
  w.reserve(96 + frameId.size());
  w.timestamp(1, timeNs);
  w.string(2, frameId);
  w.nestedHeader(3, poseSize);
  w.nestedHeader(1, posSize);
  for (std::uint32_t i = 0; i < 3; ++i) w.doubleField(i + 1, position[i]);
  w.nestedHeader(2, rotSize);
  for (std::uint32_t i = 0; i < 4; ++i) w.doubleField(i + 1, q[i]);
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
                                        std::span<const std::uint8_t> packet,
                                        std::vector<std::uint8_t> into) {
  Writer w(std::move(into));
  w.reserve(packet.size() + 32);
  w.timestamp(1, timeNs);
  w.varint(2, systemId);
  w.varint(3, componentId);
  w.varint(4, messageId);
  w.bytes(5, packet);
  return w.take();
}

}  // namespace keyframed::proto
