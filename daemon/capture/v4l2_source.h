#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "capture/frame_source.h"
#include "capture/interrupter.h"
#include "capture/mjpeg_decoder.h"

namespace keyframed {

// One /dev/video* node as VIDIOC_QUERYCAP describes it.
struct V4l2DeviceInfo {
  std::string path;
  std::string driver;
  std::string card;
  std::string busInfo;
  bool capture = false;              // single- or multi-planar video capture
  bool streaming = false;            // supports mmap streaming I/O
  std::vector<std::string> formats;  // fourccs the capture queue offers ("YUYV", "NV12", ...)
  bool multiplanar = false;  // capture through the multi-planar API only (not supported yet)
};

// The system calls V4l2Source makes on its device node, behind one interface so
// that tests can stand in for a driver. The default implementation is the kernel's.
// `open` returns a descriptor poll() can watch (a fake driver hands out an eventfd
// it makes readable when a buffer is done).
class V4l2Io {
 public:
  virtual ~V4l2Io() = default;
  [[nodiscard]] virtual bool exists(const std::string& path);
  virtual int open(const std::string& path);  // read-write, non-blocking; -1 and errno
  virtual int close(int fd);
  virtual int ioctl(int fd, unsigned long request, void* arg);          // EINTR retried
  virtual void* mmap(std::size_t length, int fd, std::int64_t offset);  // nullptr on failure
  virtual int munmap(void* start, std::size_t length);
  static const std::shared_ptr<V4l2Io>& kernel();
};

// What to ask the driver for. Zero/empty fields keep the driver's current setting.
struct V4l2Options {
  std::string device = "/dev/video0";
  // "" picks the first offered of NV12, YUV420 (YU12), YUYV, MJPEG, GREY.
  // Otherwise one of those names (or a fourcc such as "YU12", "MJPG").
  std::string format;
  int width = 0;
  int height = 0;
  double fps = 0.0;      // VIDIOC_S_PARM when > 0 and the driver supports it
  int bufferCount = 4;   // mmap ring size
  int timeoutMs = 2000;  // longest wait for one frame (interrupt() ends it sooner)
  // Recovery when the device disappears (unplugged, driver unbound): when on,
  // next() keeps trying to reopen the same path every `reopenIntervalMs` (each
  // failed attempt returns Error), up to `maxReopenAttempts` (0: no limit).
  bool autoReopen = false;
  int reopenIntervalMs = 500;
  int maxReopenAttempts = 0;
  // The node was picked, not named (camera.device ""): a camera that comes back on
  // another node (a USB camera re-enumerated while its old node was still held) is
  // found there by its card and bus (VIDIOC_QUERYCAP), /dev/video0-255.
  bool followCamera = false;
  std::shared_ptr<V4l2Io> io;  // null: the kernel (tests pass a fake driver)
};

// V4L2 capture (single-planar, mmap streaming) behind FrameSource. Frames are
// borrowed from the driver's buffer ring: the buffer goes back to the driver
// on the following next() call. Timestamps are the driver's, on
// CLOCK_MONOTONIC, when it says so (V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC);
// otherwise the dequeue time on CLOCK_MONOTONIC. MJPEG is decoded to BGR24.
class V4l2Source final : public FrameSource {
 public:
  ~V4l2Source() override;
  V4l2Source(const V4l2Source&) = delete;
  V4l2Source& operator=(const V4l2Source&) = delete;

  // Every /dev/video* node in numeric order, capture-capable or not. Nodes that
  // cannot be opened are listed with an empty driver.
  static std::vector<V4l2DeviceInfo> listDevices();
  // QUERYCAP + ENUM_FMT of one node; false and a one-line error when missing.
  static bool describe(const std::string& path, V4l2DeviceInfo& out, std::string& error);
  // The camera to use when none is named: the first node that streams a format this
  // source reads (a Pi's unicam node offers only Bayer, a codec's only its output),
  // else the first capture node (its open() then says what is wrong); "" for none.
  static std::string pickDevice(const std::vector<V4l2DeviceInfo>& devices);

  // Opens, negotiates and starts streaming. nullptr and a one-line error when
  // the device is missing, not a capture device, or offers no supported format.
  static std::unique_ptr<V4l2Source> open(const V4l2Options& options, std::string& error);

  [[nodiscard]] const SourceInfo& info() const override { return info_; }
  ReadStatus next(Frame& frame, std::string& error) override;
  // Wakes a next() that waits for a frame or for the device to come back.
  void interrupt() override { interrupter_.raise(); }
  // Lost, and next() will not try to reopen it (no autoReopen, or out of attempts).
  [[nodiscard]] bool failed() const override {
    return lost() && (!options_.autoReopen || (options_.maxReopenAttempts > 0 &&
                                               reopenAttempts_ >= options_.maxReopenAttempts));
  }

  std::uint64_t discardQueued() override;
  // Closes and reopens the device with the same options (after it came back).
  // Frame indices continue. False and a one-line error while it is still gone.
  [[nodiscard]] bool reopen(std::string& error);
  // With followCamera: the node the camera of this card and bus is on now, its old
  // one first; "" when it is on none.
  [[nodiscard]] std::string findCamera(const std::string& card, const std::string& busInfo) const;

  // True after the device went away (ENODEV/EIO/...) until a reopen succeeds.
  [[nodiscard]] bool lost() const { return fd_ < 0; }
  // The negotiated V4L2 fourcc ("YUYV", "NV12", "YU12", "MJPG", "GREY").
  [[nodiscard]] const std::string& fourcc() const { return fourcc_; }
  // The format the frames are delivered in (BGR24 for MJPEG).
  [[nodiscard]] PixelFormat pixelFormat() const { return pixelFormat_; }
  // True when the driver stamps buffers on CLOCK_MONOTONIC.
  [[nodiscard]] bool driverTimestamps() const { return driverTimestamps_; }
  [[nodiscard]] const V4l2DeviceInfo& device() const { return device_; }
  // Frames the driver skipped (gaps in v4l2_buffer.sequence).
  [[nodiscard]] std::uint64_t sequenceGaps() const { return sequenceGaps_.load(); }
  // Buffers flagged V4L2_BUF_FLAG_ERROR or MJPEG frames that failed to decode, skipped.
  [[nodiscard]] std::uint64_t corruptFrames() const { return corruptFrames_.load(); }
  [[nodiscard]] std::uint64_t lostFrames() const override {
    return sequenceGaps_.load() + corruptFrames_.load();
  }
  // From the buffer flags: V4L2_BUF_FLAG_TSTAMP_SRC_SOE or _EOF on a monotonic
  // timestamp (most drivers: EOF, which is also what a driver that says nothing
  // means; uvcvideo and CSI-2 receivers: SOE), Arrival without one.
  [[nodiscard]] TimestampOrigin timestampOrigin() const override { return origin_.load(); }
  [[nodiscard]] std::uint64_t reopenCount() const { return reopens_; }

  // Parses a format name ("NV12", "yuv420", "YU12", "MJPEG", ...) to a V4L2
  // fourcc; 0 when unknown.
  static std::uint32_t parseFormat(const std::string& name);
  static std::string fourccString(std::uint32_t fourcc);
  // Picks the preferred fourcc among those offered; 0 when none is supported.
  static std::uint32_t chooseFormat(const std::vector<std::uint32_t>& offered);
  // A format offered and the highest frame rate the driver lists for it at the size
  // it would deliver (VIDIOC_TRY_FMT, VIDIOC_ENUM_FRAMEINTERVALS); 0 when it lists none.
  struct FormatRate {
    std::uint32_t fourcc = 0;
    double maxFps = 0.0;
  };
  // The preferred format that reaches `wantFps` (or whose rate is unknown); when none
  // does, the fastest (a USB 2 webcam gives 1080p YUYV at 5 fps, MJPEG at 30): a
  // luma plane without a copy is worth less than the frames themselves. 0 when none
  // is supported.
  static std::uint32_t chooseFormat(const std::vector<FormatRate>& offered, double wantFps);
  // Driver timeval on CLOCK_MONOTONIC to nanoseconds.
  static std::int64_t timevalToNs(long sec, long usec);

  // The negotiated stream, as readBuffer() needs it.
  struct StreamLayout {
    std::uint32_t fourcc = 0;                // V4L2 fourcc
    PixelFormat format = PixelFormat::YUYV;  // of the buffer (MJPEG: ignored)
    int width = 0;
    int height = 0;
    int stride = 0;  // bytes per row of the first plane
  };
  enum class BufferUse { Frame, Corrupt };
  // What one filled buffer (`used` of `length` bytes, v4l2_buffer `flags`) gives:
  // `frame`'s format, data, size and stride (not its time or index). Raw formats
  // point into the buffer; MJPEG is decoded into `mjpeg` (BGR24, which then holds
  // the picture). Corrupt: flagged V4L2_BUF_FLAG_ERROR, shorter than the picture,
  // or a JPEG that fails to decode or has another size than negotiated. Pure but
  // for the decoder: the seam that tests drive with buffers made up in memory.
  // `why`, when given, says what was wrong with a corrupt one.
  static BufferUse readBuffer(const StreamLayout& layout, const std::uint8_t* data,
                              std::size_t used, std::size_t length, std::uint32_t flags,
                              MjpegDecoder& mjpeg, Frame& frame, std::string* why = nullptr);

 private:
  [[nodiscard]] bool isCamera(const std::string& path, const std::string& card,
                              const std::string& busInfo) const;
  struct Buffer {
    void* start = nullptr;
    std::size_t length = 0;
  };

  explicit V4l2Source(V4l2Options options)
      : options_(std::move(options)), io_(options_.io ? options_.io : V4l2Io::kernel()) {}
  bool start(std::string& error);
  void shutdown();
  bool requeueHeld(std::string& error);
  ReadStatus lose(int err, const char* what, std::string& error);
  ReadStatus tryRecover(std::string& error);

  V4l2Options options_;
  std::shared_ptr<V4l2Io> io_;
  V4l2DeviceInfo device_;
  SourceInfo info_;
  int fd_ = -1;
  std::vector<Buffer> buffers_;
  int held_ = -1;  // buffer index lent to the caller, requeued on the next call
  bool streaming_ = false;
  std::string fourcc_;
  std::uint32_t fourccCode_ = 0;
  PixelFormat pixelFormat_ = PixelFormat::YUYV;
  int stride_ = 0;
  std::size_t sizeImage_ = 0;
  bool driverTimestamps_ = false;
  std::atomic<TimestampOrigin> origin_{TimestampOrigin::Unknown};
  MjpegDecoder mjpeg_;
  Interrupter interrupter_;
  std::int64_t index_ = 0;
  std::uint32_t lastSequence_ = 0;
  bool haveSequence_ = false;
  std::atomic<std::uint64_t> sequenceGaps_{0};
  std::atomic<std::uint64_t> corruptFrames_{0};
  // Frame waits in a row that timed out: at kStalledWaits (autoReopen) the stream is
  // restarted as if the device had been lost.
  int stalledWaits_ = 0;
  static constexpr int kStalledWaits = 2;
  std::uint64_t reopens_ = 0;
  int reopenAttempts_ = 0;
  std::string lostReason_;
};

}  // namespace keyframed
