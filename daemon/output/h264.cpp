#include "output/h264.h"

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <mutex>
#include <utility>

extern "C" {
#include <libavcodec/avcodec.h>
#include <libavutil/error.h>
#include <libavutil/frame.h>
#include <libavutil/log.h>
#include <libavutil/opt.h>
}

namespace keyframed {

namespace {

std::string avError(int code) {
  char text[AV_ERROR_MAX_STRING_SIZE] = {};
  av_strerror(code, text, sizeof text);
  return text;
}

// libavcodec's informational lines (x264's banner and statistics) would go to stderr;
// its errors still do. Once, and never louder than whoever set it before (OpenCV).
void quietLibav() {
  static std::once_flag once;
  std::call_once(once, [] { av_log_set_level(std::min(av_log_get_level(), AV_LOG_ERROR)); });
}

// `rows` rows of `cols` bytes between a tight plane and one with `stride`.
void copyRows(std::uint8_t* to, int toStride, const std::uint8_t* from, int fromStride, int cols,
              int rows) {
  for (int r = 0; r < rows; ++r) {
    std::memcpy(to + static_cast<std::ptrdiff_t>(r) * toStride,
                from + static_cast<std::ptrdiff_t>(r) * fromStride, static_cast<std::size_t>(cols));
  }
}

}  // namespace

// A libavcodec context with one frame and one packet, freed together. In a named
// namespace: the Impl structs below derive from it (a base from an anonymous namespace
// is refused when a unity build compiles this file inside another).
namespace h264_detail {

struct AvCodec {
  AVCodecContext* ctx = nullptr;
  AVFrame* frame = nullptr;
  AVPacket* packet = nullptr;

  AvCodec() = default;
  AvCodec(const AvCodec&) = delete;
  AvCodec& operator=(const AvCodec&) = delete;
  ~AvCodec() {
    avcodec_free_context(&ctx);
    av_frame_free(&frame);
    av_packet_free(&packet);
  }

  // False with `error` when `codec` is missing (`what` names it) or memory is.
  bool allocate(const AVCodec* codec, const char* what, std::string& error) {
    quietLibav();
    if (codec == nullptr) {
      error = std::string("H.264: this libavcodec has no ") + what;
      return false;
    }
    ctx = avcodec_alloc_context3(codec);
    frame = av_frame_alloc();
    packet = av_packet_alloc();
    if (ctx == nullptr || frame == nullptr || packet == nullptr) {
      error = "H.264: out of memory";
      return false;
    }
    return true;
  }
};

}  // namespace h264_detail

struct H264Encoder::Impl : h264_detail::AvCodec {
  std::int64_t pts = 0;
};

H264Encoder::H264Encoder(Options options) : options_(options) {}
H264Encoder::~H264Encoder() = default;

bool H264Encoder::encode(const I420View& picture, std::int64_t timeNs,
                         std::vector<std::uint8_t>& out, std::string& error) {
  out.clear();
  if (picture.data == nullptr || picture.width < 2 || picture.height < 2 || picture.width % 2 ||
      picture.height % 2) {
    error = "H.264: a picture must have an even size of at least 2x2";
    return false;
  }
  if (!impl_) {
    const AVCodec* codec = avcodec_find_encoder_by_name("libx264");
    auto impl = std::make_unique<Impl>();
    if (!impl->allocate(codec, "libx264 encoder", error)) return false;
    AVCodecContext* ctx = impl->ctx;
    ctx->width = picture.width;
    ctx->height = picture.height;
    ctx->pix_fmt = AV_PIX_FMT_YUV420P;
    const double fps = options_.fps > 0 ? options_.fps : 30.0;
    const AVRational rate = av_d2q(fps, 1001000);
    ctx->framerate = rate;
    ctx->time_base = av_inv_q(rate);
    // IDR pictures are asked for by time (below); x264's own interval, twice that in
    // pictures, only catches timestamps that do not advance.
    ctx->gop_size = std::max(
        2, static_cast<int>(2 * fps * static_cast<double>(options_.keyframeIntervalNs) / 1e9));
    ctx->max_b_frames = 0;
    ctx->thread_count = 1;
    av_opt_set(ctx->priv_data, "preset", "ultrafast", 0);
    av_opt_set(ctx->priv_data, "tune", "zerolatency", 0);
    av_opt_set(ctx->priv_data, "crf", std::to_string(options_.crf).c_str(), 0);
    av_opt_set(ctx->priv_data, "forced-idr", "1", 0);  // a forced key picture is an IDR
    if (const int r = avcodec_open2(ctx, codec, nullptr); r < 0) {
      error = "H.264: cannot open the libx264 encoder: " + avError(r);
      return false;
    }
    impl->frame->format = AV_PIX_FMT_YUV420P;
    impl->frame->width = picture.width;
    impl->frame->height = picture.height;
    if (const int r = av_frame_get_buffer(impl->frame, 0); r < 0) {
      error = "H.264: " + avError(r);
      return false;
    }
    impl_ = std::move(impl);
  }
  Impl& s = *impl_;
  if (picture.width != s.ctx->width || picture.height != s.ctx->height) {
    error = "H.264: the picture size changed from " + std::to_string(s.ctx->width) + "x" +
            std::to_string(s.ctx->height) + " to " + std::to_string(picture.width) + "x" +
            std::to_string(picture.height);
    return false;
  }
  if (const int r = av_frame_make_writable(s.frame); r < 0) {
    error = "H.264: " + avError(r);
    return false;
  }
  const int w = picture.width, h = picture.height;
  const std::uint8_t* u = picture.data + static_cast<std::ptrdiff_t>(w) * h;
  const std::uint8_t* v = u + static_cast<std::ptrdiff_t>(w / 2) * (h / 2);
  copyRows(s.frame->data[0], s.frame->linesize[0], picture.data, w, w, h);
  copyRows(s.frame->data[1], s.frame->linesize[1], u, w / 2, w / 2, h / 2);
  copyRows(s.frame->data[2], s.frame->linesize[2], v, w / 2, w / 2, h / 2);
  s.frame->pts = s.pts++;
  // Half a picture early, so that a stream at its nominal rate keeps its rhythm.
  const auto due = options_.keyframeIntervalNs -
                   static_cast<std::int64_t>(0.5e9 / (options_.fps > 0 ? options_.fps : 30.0));
  const bool idr = lastIdrNs_ && timeNs - *lastIdrNs_ >= due;
  s.frame->pict_type = idr ? AV_PICTURE_TYPE_I : AV_PICTURE_TYPE_NONE;
  if (const int r = avcodec_send_frame(s.ctx, s.frame); r < 0) {
    error = "H.264: encoding failed: " + avError(r);
    return false;
  }
  lastKey_ = false;
  while (true) {
    const int r = avcodec_receive_packet(s.ctx, s.packet);
    if (r == AVERROR(EAGAIN)) break;
    if (r < 0) {
      error = "H.264: encoding failed: " + avError(r);
      return false;
    }
    out.insert(out.end(), s.packet->data, s.packet->data + s.packet->size);
    lastKey_ = lastKey_ || (s.packet->flags & AV_PKT_FLAG_KEY) != 0;
    av_packet_unref(s.packet);
  }
  if (out.empty()) {
    error = "H.264: the encoder held a picture back (it must not delay pictures)";
    return false;
  }
  if (lastKey_) lastIdrNs_ = timeNs;
  return true;
}

struct H264Decoder::Impl : h264_detail::AvCodec {
  std::vector<std::uint8_t> padded;  // libavcodec reads past a packet's end
};

H264Decoder::H264Decoder() = default;
H264Decoder::~H264Decoder() = default;

bool H264Decoder::decode(std::span<const std::uint8_t> packet, std::vector<std::uint8_t>& i420,
                         int& width, int& height, std::string& error) {
  if (!impl_) {
    const AVCodec* codec = avcodec_find_decoder(AV_CODEC_ID_H264);
    auto impl = std::make_unique<Impl>();
    if (!impl->allocate(codec, "H.264 decoder", error)) return false;
    impl->ctx->thread_count = 1;
    impl->ctx->flags |= AV_CODEC_FLAG_LOW_DELAY;  // each packet's picture at once
    if (const int r = avcodec_open2(impl->ctx, codec, nullptr); r < 0) {
      error = "H.264: cannot open the decoder: " + avError(r);
      return false;
    }
    impl_ = std::move(impl);
  }
  Impl& s = *impl_;
  if (packet.empty()) {
    error = "H.264: an empty packet";
    return false;
  }
  s.padded.assign(packet.begin(), packet.end());
  s.padded.resize(packet.size() + AV_INPUT_BUFFER_PADDING_SIZE, 0);
  s.packet->data = s.padded.data();
  s.packet->size = static_cast<int>(packet.size());
  const int sent = avcodec_send_packet(s.ctx, s.packet);
  s.packet->data = nullptr;
  s.packet->size = 0;
  if (sent < 0) {
    error = "H.264: the packet does not decode: " + avError(sent);
    return false;
  }
  const int r = avcodec_receive_frame(s.ctx, s.frame);
  if (r == AVERROR(EAGAIN)) {
    error = "H.264: the packet gave no picture (it needs pictures before it)";
    return false;
  }
  if (r < 0) {
    error = "H.264: the packet does not decode: " + avError(r);
    return false;
  }
  const AVFrame& f = *s.frame;
  if ((f.format != AV_PIX_FMT_YUV420P && f.format != AV_PIX_FMT_YUVJ420P) || f.width < 2 ||
      f.height < 2 || f.width % 2 || f.height % 2) {
    error = "H.264: a picture that is not 4:2:0 of an even size";
    av_frame_unref(s.frame);
    return false;
  }
  width = f.width;
  height = f.height;
  const std::size_t luma = static_cast<std::size_t>(width) * static_cast<std::size_t>(height);
  i420.resize(luma * 3 / 2);
  std::uint8_t* u = i420.data() + luma;
  std::uint8_t* v = u + luma / 4;
  copyRows(i420.data(), width, f.data[0], f.linesize[0], width, height);
  copyRows(u, width / 2, f.data[1], f.linesize[1], width / 2, height / 2);
  copyRows(v, width / 2, f.data[2], f.linesize[2], width / 2, height / 2);
  av_frame_unref(s.frame);
  return true;
}

bool h264EncoderAvailable() {
  return avcodec_find_encoder_by_name("libx264") != nullptr;
}

bool h264HasIdr(std::span<const std::uint8_t> s) {
  // NAL units follow 00 00 01 (a 4-byte start code ends in the same three bytes).
  for (std::size_t i = 0; i + 3 < s.size(); ++i) {
    if (s[i] == 0 && s[i + 1] == 0 && s[i + 2] == 1) {
      if ((s[i + 3] & 0x1F) == 5) return true;
      i += 2;
    }
  }
  return false;
}

}  // namespace keyframed
