#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace keyframed {

// A tight I420 picture: Y (width x height), then U and V (width/2 x height/2 each);
// width and height even.
struct I420View {
  const std::uint8_t* data = nullptr;
  int width = 0;
  int height = 0;
};

// H.264 through libavcodec (its libx264 encoder), in the form Foxglove's
// CompressedVideo asks for: Annex B, one packet per picture and none held back (no
// B-frames, no lookahead: x264's zerolatency tuning), the SPS and PPS repeated in
// front of every IDR picture. An IDR picture opens once `keyframeIntervalNs` of the
// pictures' own time has passed since the last (also when the caller skips pictures),
// so that a reader (or a record cut by a power loss) can start decoding there. One
// thread: it runs on the caller's.
class H264Encoder {
 public:
  struct Options {
    std::int64_t keyframeIntervalNs = 1'000'000'000;  // picture time between IDRs
    int crf = 23;     // x264's constant rate factor (0 lossless .. 51)
    double fps = 30;  // the stream's nominal rate (rate control, half-a-picture slack)
  };

  explicit H264Encoder(Options options);
  ~H264Encoder();
  H264Encoder(const H264Encoder&) = delete;
  H264Encoder& operator=(const H264Encoder&) = delete;

  // Encodes one picture taken at `timeNs` into `out` (replaced). The encoder opens at
  // the first picture's size; another size later is an error. False with `error` when
  // libavcodec has no H.264 encoder or fails.
  bool encode(const I420View& picture, std::int64_t timeNs, std::vector<std::uint8_t>& out,
              std::string& error);
  // Whether the last packet encode() gave was an IDR picture.
  [[nodiscard]] bool lastWasKeyframe() const { return lastKey_; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  Options options_;
  bool lastKey_ = false;
  std::optional<std::int64_t> lastIdrNs_;
};

// Decodes the packets H264Encoder wrote (any Annex B H.264 without B-frames, one
// picture per packet) into tight I420 pictures.
class H264Decoder {
 public:
  H264Decoder();
  ~H264Decoder();
  H264Decoder(const H264Decoder&) = delete;
  H264Decoder& operator=(const H264Decoder&) = delete;

  // One packet in, its picture out (`i420` resized to width * height * 3 / 2). False
  // with `error` when the packet does not decode, including a packet that needs
  // pictures before it (a P picture ahead of the first IDR).
  bool decode(std::span<const std::uint8_t> packet, std::vector<std::uint8_t>& i420, int& width,
              int& height, std::string& error);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Whether this libavcodec has the H.264 encoder H264Encoder uses (libx264).
bool h264EncoderAvailable();

// True when an Annex B byte stream holds an IDR slice (NAL unit type 5): a decoder can
// start at this packet.
bool h264HasIdr(std::span<const std::uint8_t> annexB);

}  // namespace keyframed
