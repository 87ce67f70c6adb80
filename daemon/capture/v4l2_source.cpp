#include "capture/v4l2_source.h"

#include <dirent.h>
#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <iterator>
#include <numeric>

#include "capture/plane_layout.h"

namespace keyframed {
namespace {

// Formats in order of preference: planar YUV gives the analysis its luma plane
// without a copy; YUYV needs one extraction; MJPEG a full decode.
constexpr std::uint32_t kPreferred[] = {V4L2_PIX_FMT_NV12, V4L2_PIX_FMT_YUV420, V4L2_PIX_FMT_YUYV,
                                        V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_GREY};

int xioctl(int fd, unsigned long request, void* arg) {
  int r = 0;
  do {
    r = ::ioctl(fd, request, arg);
  } while (r < 0 && errno == EINTR);
  return r;
}

std::string errnoText(int err) {
  return std::strerror(err);
}

std::string cString(const std::uint8_t* s, std::size_t n) {
  const auto* c = reinterpret_cast<const char*>(s);
  return std::string(c, strnlen(c, n));
}

std::uint32_t deviceCaps(const v4l2_capability& cap) {
  return (cap.capabilities & V4L2_CAP_DEVICE_CAPS) != 0 ? cap.device_caps : cap.capabilities;
}

std::vector<std::uint32_t> enumFormats(V4l2Io& io, int fd, std::uint32_t type) {
  std::vector<std::uint32_t> out;
  for (std::uint32_t i = 0; i < 64; ++i) {
    v4l2_fmtdesc d{};
    d.index = i;
    d.type = type;
    if (io.ioctl(fd, VIDIOC_ENUM_FMT, &d) < 0) break;
    out.push_back(d.pixelformat);
  }
  return out;
}

// The highest frame rate the driver lists for `fourcc` at the size it would give
// for width x height (0x0: its current size); 0 when it lists none (no
// VIDIOC_ENUM_FRAMEINTERVALS, or no VIDIOC_TRY_FMT to learn the size).
double maxFrameRate(V4l2Io& io, int fd, std::uint32_t fourcc, int width, int height) {
  v4l2_format fmt{};
  fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (io.ioctl(fd, VIDIOC_G_FMT, &fmt) < 0) return 0.0;
  fmt.fmt.pix.pixelformat = fourcc;
  if (width > 0 && height > 0) {
    fmt.fmt.pix.width = static_cast<std::uint32_t>(width);
    fmt.fmt.pix.height = static_cast<std::uint32_t>(height);
  }
  fmt.fmt.pix.field = V4L2_FIELD_NONE;
  fmt.fmt.pix.bytesperline = 0;
  if (io.ioctl(fd, VIDIOC_TRY_FMT, &fmt) < 0 || fmt.fmt.pix.pixelformat != fourcc) return 0.0;
  double best = 0.0;
  for (std::uint32_t i = 0; i < 64; ++i) {
    v4l2_frmivalenum e{};
    e.index = i;
    e.pixel_format = fourcc;
    e.width = fmt.fmt.pix.width;
    e.height = fmt.fmt.pix.height;
    if (io.ioctl(fd, VIDIOC_ENUM_FRAMEINTERVALS, &e) < 0) break;
    // Discrete intervals come one per index; a stepwise or continuous range once,
    // its shortest interval being the fastest rate.
    const v4l2_fract f = e.type == V4L2_FRMIVAL_TYPE_DISCRETE ? e.discrete : e.stepwise.min;
    if (f.numerator > 0) best = std::max(best, static_cast<double>(f.denominator) / f.numerator);
    if (e.type != V4L2_FRMIVAL_TYPE_DISCRETE) break;
  }
  return best;
}

std::string joinFormats(const std::vector<std::uint32_t>& codes) {
  std::string s;
  for (std::uint32_t c : codes) {
    if (!s.empty()) s += ", ";
    s += V4l2Source::fourccString(c);
  }
  return s.empty() ? "none" : s;
}

std::string supportedList() {
  std::string s;
  for (std::uint32_t c : kPreferred) {
    if (!s.empty()) s += ", ";
    s += V4l2Source::fourccString(c);
  }
  return s;
}

std::int64_t monotonicNowNs() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

int videoNumber(const std::string& name) {
  // "video12" -> 12; -1 for anything else (e.g. "video-foo").
  if (name.size() <= 5 || name.compare(0, 5, "video") != 0) return -1;
  int n = 0;
  for (std::size_t i = 5; i < name.size(); ++i) {
    if (name[i] < '0' || name[i] > '9' || n > 100000) return -1;
    n = n * 10 + (name[i] - '0');
  }
  return n;
}

}  // namespace

std::string V4l2Source::fourccString(std::uint32_t fourcc) {
  std::string s;
  for (int i = 0; i < 4; ++i) {
    const char c = static_cast<char>((fourcc >> (8 * i)) & 0xFF);
    s += (c >= 32 && c < 127) ? c : '?';
  }
  while (!s.empty() && s.back() == ' ') s.pop_back();
  return s;
}

std::uint32_t V4l2Source::parseFormat(const std::string& name) {
  std::string n;
  for (char c : name) n += static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  if (n == "NV12") return V4L2_PIX_FMT_NV12;
  if (n == "YUV420" || n == "YU12" || n == "I420") return V4L2_PIX_FMT_YUV420;
  if (n == "YUYV" || n == "YUY2") return V4L2_PIX_FMT_YUYV;
  if (n == "MJPEG" || n == "MJPG") return V4L2_PIX_FMT_MJPEG;
  if (n == "GREY" || n == "GRAY" || n == "GRAY8") return V4L2_PIX_FMT_GREY;
  return 0;
}

std::uint32_t V4l2Source::chooseFormat(const std::vector<std::uint32_t>& offered) {
  for (std::uint32_t want : kPreferred) {
    if (std::find(offered.begin(), offered.end(), want) != offered.end()) return want;
  }
  return 0;
}

std::uint32_t V4l2Source::chooseFormat(const std::vector<FormatRate>& offered, double wantFps) {
  const auto rank = [](std::uint32_t fourcc) {
    const auto* at = std::find(std::begin(kPreferred), std::end(kPreferred), fourcc);
    return static_cast<int>(at - std::begin(kPreferred));  // past the end: not supported
  };
  const int unsupported = static_cast<int>(std::size(kPreferred));
  const FormatRate* best = nullptr;  // preferred among those fast enough
  const FormatRate* fastest = nullptr;
  for (const FormatRate& f : offered) {
    const int r = rank(f.fourcc);
    if (r == unsupported) continue;
    // 1 % slack: 29.97 fps cameras asked for 30.
    const bool enough = wantFps <= 0.0 || f.maxFps <= 0.0 || f.maxFps >= wantFps * 0.99;
    if (enough && (best == nullptr || r < rank(best->fourcc))) best = &f;
    if (fastest == nullptr || f.maxFps > fastest->maxFps ||
        (f.maxFps == fastest->maxFps && r < rank(fastest->fourcc))) {
      fastest = &f;
    }
  }
  if (best != nullptr) return best->fourcc;
  return fastest != nullptr ? fastest->fourcc : 0;
}

std::string V4l2Source::pickDevice(const std::vector<V4l2DeviceInfo>& devices) {
  // A multi-planar node (an ISP's output on a Pi 5, a codec) is passed over while
  // another will do: open() refuses it.
  for (const V4l2DeviceInfo& d : devices) {
    if (!d.capture || !d.streaming || d.multiplanar) continue;
    std::vector<std::uint32_t> offered;
    for (const std::string& f : d.formats) offered.push_back(parseFormat(f));
    if (chooseFormat(offered) != 0) return d.path;
  }
  for (const V4l2DeviceInfo& d : devices) {
    if (d.capture && !d.multiplanar) return d.path;
  }
  for (const V4l2DeviceInfo& d : devices) {
    if (d.capture) return d.path;  // whose open() then says why not
  }
  // A node that could not be opened to look at (no permission, busy): open() then
  // says why, rather than "no camera".
  for (const V4l2DeviceInfo& d : devices) {
    if (d.driver.empty()) return d.path;
  }
  return {};
}

std::int64_t V4l2Source::timevalToNs(long sec, long usec) {
  return static_cast<std::int64_t>(sec) * 1'000'000'000 + static_cast<std::int64_t>(usec) * 1'000;
}

bool V4l2Io::exists(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0;
}

int V4l2Io::open(const std::string& path) {
  return ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
}

int V4l2Io::close(int fd) {
  return ::close(fd);
}

int V4l2Io::ioctl(int fd, unsigned long request, void* arg) {
  return xioctl(fd, request, arg);
}

void* V4l2Io::mmap(std::size_t length, int fd, std::int64_t offset) {
  void* p = ::mmap(nullptr, length, PROT_READ | PROT_WRITE, MAP_SHARED, fd, offset);
  return p == MAP_FAILED ? nullptr : p;
}

int V4l2Io::munmap(void* start, std::size_t length) {
  return ::munmap(start, length);
}

const std::shared_ptr<V4l2Io>& V4l2Io::kernel() {
  static const std::shared_ptr<V4l2Io> io = std::make_shared<V4l2Io>();
  return io;
}

bool V4l2Source::describe(const std::string& path, V4l2DeviceInfo& out, std::string& error) {
  out = V4l2DeviceInfo{};
  out.path = path;
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) {
    error = "no such device: " + path;
    return false;
  }
  if (!S_ISCHR(st.st_mode)) {
    error = "not a device node: " + path;
    return false;
  }
  const int fd = ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    const int err = errno;
    error = "cannot open " + path + ": " + errnoText(err);
    if (err == EACCES) error += " (is the user in group 'video'?)";
    return false;
  }
  v4l2_capability cap{};
  if (xioctl(fd, VIDIOC_QUERYCAP, &cap) < 0) {
    error = path + " is not a V4L2 device (VIDIOC_QUERYCAP: " + errnoText(errno) + ")";
    ::close(fd);
    return false;
  }
  out.driver = cString(cap.driver, sizeof(cap.driver));
  out.card = cString(cap.card, sizeof(cap.card));
  out.busInfo = cString(cap.bus_info, sizeof(cap.bus_info));
  const std::uint32_t caps = deviceCaps(cap);
  out.capture = (caps & (V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_VIDEO_CAPTURE_MPLANE)) != 0;
  out.multiplanar = (caps & V4L2_CAP_VIDEO_CAPTURE) == 0 && out.capture;
  out.streaming = (caps & V4L2_CAP_STREAMING) != 0;
  if (out.capture) {
    const std::uint32_t type = (caps & V4L2_CAP_VIDEO_CAPTURE) != 0
                                   ? V4L2_BUF_TYPE_VIDEO_CAPTURE
                                   : V4L2_BUF_TYPE_VIDEO_CAPTURE_MPLANE;
    for (std::uint32_t c : enumFormats(*V4l2Io::kernel(), fd, type)) {
      out.formats.push_back(fourccString(c));
    }
  }
  ::close(fd);
  return true;
}

std::vector<V4l2DeviceInfo> V4l2Source::listDevices() {
  std::vector<std::pair<int, std::string>> nodes;
  if (DIR* dir = ::opendir("/dev")) {
    while (const dirent* e = ::readdir(dir)) {
      const int n = videoNumber(e->d_name);
      if (n >= 0) nodes.emplace_back(n, std::string("/dev/") + e->d_name);
    }
    ::closedir(dir);
  }
  std::sort(nodes.begin(), nodes.end());
  std::vector<V4l2DeviceInfo> out;
  for (const auto& [n, path] : nodes) {
    V4l2DeviceInfo d;
    std::string ignored;
    describe(path, d, ignored);  // unreadable nodes are listed with an empty driver
    d.path = path;
    out.push_back(std::move(d));
  }
  return out;
}

std::unique_ptr<V4l2Source> V4l2Source::open(const V4l2Options& options, std::string& error) {
  if (options.bufferCount < 2 || options.bufferCount > 32) {
    error = "buffer count must be 2..32, got " + std::to_string(options.bufferCount);
    return nullptr;
  }
  std::unique_ptr<V4l2Source> src(new V4l2Source(options));
  if (!src->start(error)) return nullptr;
  // Pin what was negotiated, so a reopen after the device came back asks for
  // exactly the same stream.
  src->options_.format = src->fourcc_;
  src->options_.width = src->info_.width;
  src->options_.height = src->info_.height;
  return src;
}

V4l2Source::~V4l2Source() {
  shutdown();
}

bool V4l2Source::start(std::string& error) {
  const std::string& path = options_.device;
  if (!io_->exists(path)) {
    error = "no such device: " + path;
    return false;
  }
  fd_ = io_->open(path);
  if (fd_ < 0) {
    const int err = errno;
    error = "cannot open " + path + ": " + errnoText(err);
    if (err == EACCES) error += " (is the user in group 'video'?)";
    return false;
  }
  v4l2_capability cap{};
  if (io_->ioctl(fd_, VIDIOC_QUERYCAP, &cap) < 0) {
    error = path + " is not a V4L2 device (VIDIOC_QUERYCAP: " + errnoText(errno) + ")";
    shutdown();
    return false;
  }
  device_ = V4l2DeviceInfo{};
  device_.path = path;
  device_.driver = cString(cap.driver, sizeof(cap.driver));
  device_.card = cString(cap.card, sizeof(cap.card));
  device_.busInfo = cString(cap.bus_info, sizeof(cap.bus_info));
  const std::uint32_t caps = deviceCaps(cap);
  device_.capture = (caps & (V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_VIDEO_CAPTURE_MPLANE)) != 0;
  device_.streaming = (caps & V4L2_CAP_STREAMING) != 0;
  const std::string who = path + " (" + device_.driver + ": " + device_.card + ")";
  if ((caps & V4L2_CAP_VIDEO_CAPTURE) == 0) {
    error = (caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE) != 0
                ? who + " is a multi-planar capture device, not supported yet"
                : who + " is not a video capture device";
    shutdown();
    return false;
  }
  if (!device_.streaming) {
    error = who + " does not support streaming I/O";
    shutdown();
    return false;
  }

  const std::vector<std::uint32_t> offered = enumFormats(*io_, fd_, V4L2_BUF_TYPE_VIDEO_CAPTURE);
  for (std::uint32_t c : offered) device_.formats.push_back(fourccString(c));
  std::uint32_t want = 0;
  if (!options_.format.empty()) {
    want = parseFormat(options_.format);
    if (want == 0) {
      error = "unknown pixel format '" + options_.format + "' (supported: " + supportedList() + ")";
      shutdown();
      return false;
    }
    if (std::find(offered.begin(), offered.end(), want) == offered.end()) {
      error =
          who + " does not offer " + fourccString(want) + " (offers: " + joinFormats(offered) + ")";
      shutdown();
      return false;
    }
  } else {
    std::vector<FormatRate> rates;
    for (std::uint32_t c : offered) {
      rates.push_back({c, options_.fps > 0.0
                              ? maxFrameRate(*io_, fd_, c, options_.width, options_.height)
                              : 0.0});
    }
    want = chooseFormat(rates, options_.fps);
    if (want == 0) {
      error = who + " offers no supported pixel format (offers: " + joinFormats(offered) +
              "; supported: " + supportedList() + ")";
      shutdown();
      return false;
    }
  }

  v4l2_format fmt{};
  fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (io_->ioctl(fd_, VIDIOC_G_FMT, &fmt) < 0) {
    error = who + ": VIDIOC_G_FMT: " + errnoText(errno);
    shutdown();
    return false;
  }
  fmt.fmt.pix.pixelformat = want;
  if (options_.width > 0 && options_.height > 0) {
    fmt.fmt.pix.width = static_cast<std::uint32_t>(options_.width);
    fmt.fmt.pix.height = static_cast<std::uint32_t>(options_.height);
  }
  fmt.fmt.pix.field = V4L2_FIELD_NONE;
  fmt.fmt.pix.bytesperline = 0;  // let the driver choose its stride
  if (io_->ioctl(fd_, VIDIOC_S_FMT, &fmt) < 0) {
    error = who + ": VIDIOC_S_FMT " + fourccString(want) + ": " + errnoText(errno);
    shutdown();
    return false;
  }
  if (fmt.fmt.pix.pixelformat != want) {
    error = who + " refused " + fourccString(want) + " (gave " +
            fourccString(fmt.fmt.pix.pixelformat) + ")";
    shutdown();
    return false;
  }
  if (fmt.fmt.pix.field != V4L2_FIELD_NONE && fmt.fmt.pix.field != V4L2_FIELD_ANY) {
    // Interlaced frames would still work for sharpness, but warn through the description.
    info_.description = "interlaced ";
  } else {
    info_.description.clear();
  }
  fourccCode_ = want;
  fourcc_ = fourccString(want);
  info_.width = static_cast<int>(fmt.fmt.pix.width);
  info_.height = static_cast<int>(fmt.fmt.pix.height);
  sizeImage_ = fmt.fmt.pix.sizeimage;
  switch (want) {
    case V4L2_PIX_FMT_NV12: pixelFormat_ = PixelFormat::NV12; break;
    case V4L2_PIX_FMT_YUV420: pixelFormat_ = PixelFormat::YUV420; break;
    case V4L2_PIX_FMT_YUYV: pixelFormat_ = PixelFormat::YUYV; break;
    case V4L2_PIX_FMT_GREY: pixelFormat_ = PixelFormat::Gray8; break;
    default: pixelFormat_ = PixelFormat::BGR24; break;  // MJPEG, decoded
  }
  // Sizes from the driver are checked before any arithmetic on them: a frame over
  // 16384 pixels a side, a row over 4 bytes a pixel plus 4 KiB of padding, is not a
  // camera's (and its byte count could overflow a 32-bit size_t).
  const std::uint32_t width = fmt.fmt.pix.width, height = fmt.fmt.pix.height;
  const std::uint32_t bytesPerLine = fmt.fmt.pix.bytesperline;
  if (width == 0 || height == 0 || width > 16384 || height > 16384 ||
      bytesPerLine > 4 * width + 4096) {
    error = who + " reported an unusable frame size: " + std::to_string(width) + "x" +
            std::to_string(height) + ", " + std::to_string(bytesPerLine) + " bytes a row";
    shutdown();
    return false;
  }
  // 4:2:0 chroma covers pixel pairs: an odd size leaves a half pair that the preview
  // and the keyframes' colour conversion cannot take (every frame would fail).
  if ((pixelFormat_ == PixelFormat::NV12 || pixelFormat_ == PixelFormat::YUV420) &&
      (width % 2 != 0 || height % 2 != 0)) {
    error = who + " delivers " + std::to_string(width) + "x" + std::to_string(height) + " " +
            toString(pixelFormat_) +
            ": 4:2:0 needs an even width and height (set camera.width/height, or "
            "camera.pixel_format = \"YUYV\" or \"MJPEG\")";
    shutdown();
    return false;
  }
  const int minStride = pixelFormat_ == PixelFormat::YUYV ? info_.width * 2 : info_.width;
  stride_ = std::max(static_cast<int>(bytesPerLine), minStride);

  // Frame rate: ask, then read back what the driver settled on.
  v4l2_streamparm parm{};
  parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  const bool haveParm = io_->ioctl(fd_, VIDIOC_G_PARM, &parm) == 0;
  if (haveParm && options_.fps > 0.0 &&
      (parm.parm.capture.capability & V4L2_CAP_TIMEPERFRAME) != 0) {
    // timeperframe = 1000 / (fps * 1000), reduced: 30 -> 1/30, 29.97 -> 100/2997.
    auto num = std::uint32_t{1000};
    auto den = static_cast<std::uint32_t>(std::llround(options_.fps * 1000.0));
    const std::uint32_t g = std::gcd(num, den);
    parm.parm.capture.timeperframe.numerator = num / g;
    parm.parm.capture.timeperframe.denominator = den / g;
    // A driver that cannot change its rate still streams at the one it has (read
    // back below, and compared with the wish by the caller).
    (void)io_->ioctl(fd_, VIDIOC_S_PARM, &parm);
  }
  info_.fps = 0.0;
  if (haveParm && io_->ioctl(fd_, VIDIOC_G_PARM, &parm) == 0 &&
      parm.parm.capture.timeperframe.numerator > 0) {
    info_.fps = static_cast<double>(parm.parm.capture.timeperframe.denominator) /
                static_cast<double>(parm.parm.capture.timeperframe.numerator);
  }
  info_.frameCount = -1;

  // The mmap ring.
  v4l2_requestbuffers req{};
  req.count = static_cast<std::uint32_t>(options_.bufferCount);
  req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  req.memory = V4L2_MEMORY_MMAP;
  if (io_->ioctl(fd_, VIDIOC_REQBUFS, &req) < 0) {
    error = who + " does not support mmap streaming (VIDIOC_REQBUFS: " + errnoText(errno) + ")";
    shutdown();
    return false;
  }
  if (req.count < 2) {
    error = who + " granted only " + std::to_string(req.count) + " buffer(s)";
    shutdown();
    return false;
  }
  buffers_.assign(req.count, Buffer{});
  for (std::uint32_t i = 0; i < req.count; ++i) {
    v4l2_buffer buf{};
    buf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = V4L2_MEMORY_MMAP;
    buf.index = i;
    if (io_->ioctl(fd_, VIDIOC_QUERYBUF, &buf) < 0) {
      error = who + ": VIDIOC_QUERYBUF: " + errnoText(errno);
      shutdown();
      return false;
    }
    void* p = io_->mmap(buf.length, fd_, buf.m.offset);
    if (p == nullptr) {
      error = who + ": mmap: " + errnoText(errno);
      shutdown();
      return false;
    }
    buffers_[i] = Buffer{p, buf.length};
    if (io_->ioctl(fd_, VIDIOC_QBUF, &buf) < 0) {
      error = who + ": VIDIOC_QBUF: " + errnoText(errno);
      shutdown();
      return false;
    }
  }
  int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (io_->ioctl(fd_, VIDIOC_STREAMON, &type) < 0) {
    error = who + ": VIDIOC_STREAMON: " + errnoText(errno);
    shutdown();
    return false;
  }
  streaming_ = true;
  held_ = -1;
  haveSequence_ = false;
  driverTimestamps_ = false;  // decided per buffer
  char fps[32];
  std::snprintf(fps, sizeof(fps), "%.6g", info_.fps);
  info_.description += "v4l2:" + path + " (" + device_.driver + ": " + device_.card + ") " +
                       fourcc_ + " " + std::to_string(info_.width) + "x" +
                       std::to_string(info_.height) + "@" + fps;
  return true;
}

void V4l2Source::shutdown() {
  if (fd_ >= 0 && streaming_) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    io_->ioctl(fd_, VIDIOC_STREAMOFF, &type);  // fails harmlessly on a vanished device
  }
  streaming_ = false;
  for (Buffer& b : buffers_) {
    if (b.start != nullptr) io_->munmap(b.start, b.length);
  }
  const bool hadBuffers = !buffers_.empty();
  buffers_.clear();
  if (fd_ >= 0) {
    if (hadBuffers) {
      v4l2_requestbuffers req{};
      req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      req.memory = V4L2_MEMORY_MMAP;
      io_->ioctl(fd_, VIDIOC_REQBUFS, &req);
    }
    io_->close(fd_);
  }
  fd_ = -1;
  held_ = -1;
}

ReadStatus V4l2Source::lose(int err, const char* what, std::string& error) {
  lostReason_ = "device lost: " + options_.device + ": " + errnoText(err) + " (" + what + ")";
  shutdown();
  error = lostReason_;
  return ReadStatus::Error;
}

bool V4l2Source::isCamera(const std::string& path, const std::string& card,
                          const std::string& busInfo) const {
  if (!io_->exists(path)) return false;
  const int fd = io_->open(path);
  if (fd < 0) return false;
  v4l2_capability cap{};
  const bool same = io_->ioctl(fd, VIDIOC_QUERYCAP, &cap) == 0 &&
                    (deviceCaps(cap) & V4L2_CAP_VIDEO_CAPTURE) != 0 &&
                    cString(cap.card, sizeof(cap.card)) == card &&
                    cString(cap.bus_info, sizeof(cap.bus_info)) == busInfo;
  io_->close(fd);
  return same;
}

std::string V4l2Source::findCamera(const std::string& card, const std::string& busInfo) const {
  // Where it was first: a UVC camera's metadata node shares its card and bus.
  if (isCamera(options_.device, card, busInfo)) return options_.device;
  for (int n = 0; n < 256; ++n) {
    const std::string path = "/dev/video" + std::to_string(n);
    if (path != options_.device && isCamera(path, card, busInfo)) return path;
  }
  return {};
}

bool V4l2Source::reopen(std::string& error) {
  // The frames after a reopen must be laid out as before: the pool's buffers and the
  // analysis were sized for them (another camera on the same node, a driver that
  // settles differently, is an error until the right one is back).
  const SourceInfo before = info_;
  const int stride = stride_;
  const std::string fourcc = fourcc_;
  // Which camera it was: another of the same mode on the node (a second UVC camera
  // plugged in meanwhile) would be tagged with this one's calibration and mount.
  const std::string card = device_.card;
  const std::string busInfo = device_.busInfo;
  shutdown();
  if (options_.followCamera) {
    if (std::string at = findCamera(card, busInfo); !at.empty()) options_.device = std::move(at);
  }
  if (!start(error)) {
    // start() may have got as far as a new format before failing: the next attempt
    // compares with the layout from before the loss, not with that one's.
    shutdown();
    info_ = before;
    stride_ = stride;
    fourcc_ = fourcc;
    return false;
  }
  if (device_.card != card || device_.busInfo != busInfo) {
    error = "another camera came back: " + device_.card + " (" + device_.busInfo + "), not " +
            card + " (" + busInfo + ")";
    shutdown();
    info_ = before;
    stride_ = stride;
    fourcc_ = fourcc;
    device_.card = card;
    device_.busInfo = busInfo;
    return false;
  }
  if (info_.width != before.width || info_.height != before.height || stride_ != stride ||
      fourcc_ != fourcc) {
    error = "came back as " + fourcc_ + " " + std::to_string(info_.width) + "x" +
            std::to_string(info_.height) + " (stride " + std::to_string(stride_) + "), not " +
            fourcc + " " + std::to_string(before.width) + "x" + std::to_string(before.height) +
            " (stride " + std::to_string(stride) + ")";
    shutdown();
    info_ = before;
    stride_ = stride;
    fourcc_ = fourcc;
    return false;
  }
  ++reopens_;
  return true;
}

ReadStatus V4l2Source::tryRecover(std::string& error) {
  if (!options_.autoReopen) {
    error = lostReason_.empty() ? "device closed: " + options_.device
                                : lostReason_ + "; call reopen() when it is back";
    return ReadStatus::Error;
  }
  if (options_.maxReopenAttempts > 0 && reopenAttempts_ >= options_.maxReopenAttempts) {
    error = lostReason_ + "; gave up after " + std::to_string(reopenAttempts_) + " reopen attempts";
    return ReadStatus::Error;
  }
  // The first attempt waits too: a device that just vanished is rarely back at once.
  const auto rested =
      interrupter_.wait(-1, 0, std::chrono::milliseconds(std::max(0, options_.reopenIntervalMs)));
  if (rested.wake == Interrupter::Wake::Interrupted) {
    error = "interrupted: " + lostReason_;
    return ReadStatus::Error;
  }
  ++reopenAttempts_;
  const int attempt = reopenAttempts_;
  std::string why;
  if (!reopen(why)) {
    error = lostReason_ + "; reopen attempt " + std::to_string(attempt) + " failed: " + why;
    return ReadStatus::Error;
  }
  return ReadStatus::Frame;  // streaming again; the caller reads the frame
}

bool V4l2Source::requeueHeld(std::string& error) {
  if (held_ < 0) return true;
  v4l2_buffer buf{};
  buf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  buf.memory = V4L2_MEMORY_MMAP;
  buf.index = static_cast<std::uint32_t>(held_);
  held_ = -1;
  if (io_->ioctl(fd_, VIDIOC_QBUF, &buf) < 0) {
    lose(errno, "VIDIOC_QBUF", error);
    return false;
  }
  return true;
}

V4l2Source::BufferUse V4l2Source::readBuffer(const StreamLayout& layout, const std::uint8_t* data,
                                             std::size_t used, std::size_t length,
                                             std::uint32_t flags, MjpegDecoder& mjpeg, Frame& frame,
                                             std::string* why) {
  const auto corrupt = [why](std::string reason) {
    if (why != nullptr) *why = std::move(reason);
    return BufferUse::Corrupt;
  };
  if ((flags & V4L2_BUF_FLAG_ERROR) != 0) return corrupt("the driver flagged the buffer ERROR");
  if (data == nullptr) return corrupt("no buffer memory");
  if (used == 0) return corrupt("empty buffer (bytesused 0)");
  frame = Frame{};
  frame.width = layout.width;
  frame.height = layout.height;
  if (layout.fourcc == V4L2_PIX_FMT_MJPEG) {
    std::string bad;
    if (!mjpeg.decode(data, std::min(used, length), bad, layout.width, layout.height)) {
      return corrupt(bad);
    }
    if (mjpeg.width() != layout.width || mjpeg.height() != layout.height) {
      return corrupt("MJPEG frame of another size");
    }
    frame.format = PixelFormat::BGR24;
    frame.data = mjpeg.bgr();
    frame.stride = mjpeg.stride();
    return BufferUse::Frame;
  }
  const std::size_t need = planeSizes(layout.format, layout.stride, layout.height).total();
  // A short frame is skipped rather than read past the picture.
  if (used < need || length < need) {
    return corrupt("short frame: " + std::to_string(std::min(used, length)) + " of " +
                   std::to_string(need) + " bytes");
  }
  frame.format = layout.format;
  frame.data = data;
  frame.stride = layout.stride;
  return BufferUse::Frame;
}

std::uint64_t V4l2Source::discardQueued() {
  if (fd_ < 0) return 0;
  std::string ignored;
  if (!requeueHeld(ignored)) return 0;
  std::uint64_t n = 0;
  // At most every buffer twice: a driver that fills them as fast as they come back
  // is not waited out. An error here (a lost device) is next()'s to meet.
  for (std::size_t i = 0; i < 2 * buffers_.size(); ++i) {
    v4l2_buffer buf{};
    buf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = V4L2_MEMORY_MMAP;
    if (io_->ioctl(fd_, VIDIOC_DQBUF, &buf) < 0) break;  // EAGAIN: none waits
    if (io_->ioctl(fd_, VIDIOC_QBUF, &buf) < 0) break;
    ++n;
  }
  return n;
}

ReadStatus V4l2Source::next(Frame& frame, std::string& error) {
  if (fd_ < 0) {
    const ReadStatus s = tryRecover(error);
    if (s != ReadStatus::Frame) return s;
  }
  if (!requeueHeld(error)) return ReadStatus::Error;

  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(options_.timeoutMs);
  std::uint64_t skipped = 0;  // frames that arrived unusable in this wait
  std::string skipReason;
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    const Interrupter::Result w =
        interrupter_.wait(fd_, POLLIN, std::max(left, std::chrono::milliseconds(0)));
    if (w.wake == Interrupter::Wake::Interrupted) {
      error = "interrupted: waiting for a frame from " + options_.device;
      return ReadStatus::Error;
    }
    if (w.wake == Interrupter::Wake::Timeout) {
      error = "timeout: no frame from " + options_.device + " within " +
              std::to_string(options_.timeoutMs) + " ms";
      if (skipped > 0) {
        error = "timeout: no usable frame from " + options_.device + " within " +
                std::to_string(options_.timeoutMs) + " ms: " + std::to_string(skipped) +
                " arrived, all unusable (" + skipReason + ")";
      }
      // Open and streaming, but silent or sending only garbage (a UVC camera after a
      // USB glitch): once is a hiccup, twice in a row the stream is started again.
      if (options_.autoReopen && ++stalledWaits_ >= kStalledWaits) {
        stalledWaits_ = 0;
        std::string reason = error;
        lose(ETIMEDOUT, "stalled: restarting the stream", error);
        error = reason + "; " + error;
        return ReadStatus::Error;
      }
      return ReadStatus::Error;
    }
    if (w.wake == Interrupter::Wake::Failed) return lose(w.err, "poll", error);

    v4l2_buffer buf{};
    buf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = V4L2_MEMORY_MMAP;
    if (io_->ioctl(fd_, VIDIOC_DQBUF, &buf) < 0) {
      const int err = errno;
      if (err == EAGAIN) {
        // POLLERR with nothing to dequeue: the queue is dead (vb2 sets it when
        // the driver gives up, the node is unregistered or streaming stopped).
        if ((w.revents & (POLLERR | POLLHUP | POLLNVAL)) != 0) return lose(EIO, "poll", error);
        continue;
      }
      // ENODEV/EIO after an unplug or unbind; anything else also leaves the
      // stream unusable, and a reopen is the way back for both.
      return lose(err, "VIDIOC_DQBUF", error);
    }
    if (buf.index >= buffers_.size()) return lose(EIO, "buffer index out of range", error);
    const int index = static_cast<int>(buf.index);
    held_ = index;

    if (haveSequence_ && buf.sequence > lastSequence_ + 1) {
      sequenceGaps_ += buf.sequence - lastSequence_ - 1;
    }
    lastSequence_ = buf.sequence;
    haveSequence_ = true;

    const bool monotonic =
        (buf.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;
    driverTimestamps_ = monotonic;
    origin_.store(!monotonic ? TimestampOrigin::Arrival
                  : (buf.flags & V4L2_BUF_FLAG_TSTAMP_SRC_MASK) == V4L2_BUF_FLAG_TSTAMP_SRC_SOE
                      ? TimestampOrigin::StartOfExposure
                      : TimestampOrigin::EndOfFrame);
    const std::int64_t ts =
        monotonic ? timevalToNs(buf.timestamp.tv_sec, buf.timestamp.tv_usec) : monotonicNowNs();

    const auto* data = static_cast<const std::uint8_t*>(buffers_[buf.index].start);
    // bytesused 0: the driver put nothing in it (a UVC payload lost on the bus); the
    // buffer still holds an older picture, which must not pass for a new one.
    const std::size_t used = buf.bytesused;
    const StreamLayout layout{fourccCode_, pixelFormat_, info_.width, info_.height, stride_};
    const BufferUse use = readBuffer(layout, data, used, buffers_[buf.index].length, buf.flags,
                                     mjpeg_, frame, &skipReason);
    // A decoded picture lives in the decoder and a corrupt one is skipped: either
    // way the driver can have its buffer back now.
    if (use == BufferUse::Corrupt || fourccCode_ == V4L2_PIX_FMT_MJPEG) {
      if (!requeueHeld(error)) return ReadStatus::Error;
    }
    if (use == BufferUse::Corrupt) {
      ++corruptFrames_;
      ++skipped;
      continue;
    }
    stalledWaits_ = 0;
    // Only a frame ends an outage: a device that opens and then fails at once keeps
    // counting towards maxReopenAttempts.
    reopenAttempts_ = 0;
    frame.timestampNs = ts;
    frame.index = index_++;
    return ReadStatus::Frame;
  }
}

}  // namespace keyframed
