#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

// Protobuf wire encoding of the few Foxglove schemas keyframed records (see
// daemon/output/proto/). Hand-written: a dozen fields do not need libprotobuf.
namespace keyframed::proto {

// Appends protobuf fields to a byte buffer.
class Writer {
 public:
  Writer() = default;
  // Writes into `into`, emptied first: a buffer whose room is reused (no allocation
  // when it has enough).
  explicit Writer(std::vector<std::uint8_t> into) : buf_(std::move(into)) { buf_.clear(); }
  void varint(std::uint32_t field, std::uint64_t v);
  void fixed32(std::uint32_t field, std::uint32_t v);
  void doubleField(std::uint32_t field, double v);  // omitted when 0 (proto3 default)
  void bytes(std::uint32_t field, std::span<const std::uint8_t> v);
  void string(std::uint32_t field, const std::string& v);
  void message(std::uint32_t field, const Writer& nested);
  // A nested message's tag and length, for one written in place: exactly `length`
  // bytes of its fields must follow.
  void nestedHeader(std::uint32_t field, std::size_t length);
  void packedDoubles(std::uint32_t field, std::span<const double> v);
  // google.protobuf.Timestamp from nanoseconds since the epoch (negative clamps to 0).
  void timestamp(std::uint32_t field, std::int64_t ns);

  [[nodiscard]] const std::vector<std::uint8_t>& data() const { return buf_; }
  std::vector<std::uint8_t> take() { return std::move(buf_); }
  void reserve(std::size_t n) { buf_.reserve(n); }

 private:
  void rawVarint(std::uint64_t v);
  void tag(std::uint32_t field, std::uint32_t wireType);
  void rawDouble(double v);
  std::vector<std::uint8_t> buf_;
};

// Each message below is written into `into` (emptied first) and returned: pass a
// buffer with room (McapRecorder::buffer()) and nothing is allocated.
std::vector<std::uint8_t> compressedImage(std::int64_t timeNs, const std::string& frameId,
                                          std::span<const std::uint8_t> data,
                                          const std::string& format,
                                          std::vector<std::uint8_t> into = {});

// foxglove.CompressedVideo: one picture of a video stream (h264: Annex B).
std::vector<std::uint8_t> compressedVideo(std::int64_t timeNs, const std::string& frameId,
                                          std::span<const std::uint8_t> data,
                                          const std::string& format,
                                          std::vector<std::uint8_t> into = {});

struct LocationFixMsg {
  std::int64_t timeNs = 0;
  std::string frameId;
  double latitude = 0, longitude = 0, altitude = 0;
  // ENU position covariance (m^2), diagonal only here; unknown when empty.
  std::optional<std::array<double, 3>> varianceEnu;
};
std::vector<std::uint8_t> locationFix(const LocationFixMsg& m, std::vector<std::uint8_t> into = {});

std::vector<std::uint8_t> poseInFrame(std::int64_t timeNs, const std::string& frameId,
                                      const std::array<double, 3>& position,
                                      const std::array<double, 4>& quaternionXyzw,
                                      std::vector<std::uint8_t> into = {});

struct CameraCalibrationMsg {
  std::int64_t timeNs = 0;
  std::string frameId;
  std::uint32_t width = 0, height = 0;
  std::string distortionModel = "plumb_bob";
  std::vector<double> d;
  std::array<double, 9> k{};
  std::array<double, 9> r{1, 0, 0, 0, 1, 0, 0, 0, 1};
  std::array<double, 12> p{};
};
std::vector<std::uint8_t> cameraCalibration(const CameraCalibrationMsg& m);

enum class LogLevel : std::uint8_t {
  Unknown = 0,
  Debug = 1,
  Info = 2,
  Warning = 3,
  Error = 4,
  Fatal = 5
};
std::vector<std::uint8_t> log(std::int64_t timeNs, LogLevel level, const std::string& message,
                              const std::string& name);

std::vector<std::uint8_t> mavlinkPacket(std::int64_t timeNs, std::uint32_t systemId,
                                        std::uint32_t componentId, std::uint32_t messageId,
                                        std::span<const std::uint8_t> packet,
                                        std::vector<std::uint8_t> into = {});

// The FileDescriptorSet (protoc --include_imports) of a schema, e.g.
// "foxglove.CompressedImage"; empty for an unknown name. Generated at build time.
std::span<const std::uint8_t> descriptorSet(const std::string& schemaName);

}  // namespace keyframed::proto
