#include "capture/libcamera_source.h"

#include <sys/mman.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <map>
#include <mutex>
#include <utility>

#include <libcamera/camera.h>
#include <libcamera/camera_manager.h>
#include <libcamera/control_ids.h>
#include <libcamera/controls.h>
#include <libcamera/framebuffer.h>
#include <libcamera/framebuffer_allocator.h>
#include <libcamera/request.h>
#include <libcamera/stream.h>

#include "capture/libcamera_compat.h"
#include "capture/libcamera_select.h"
#include "capture/plane_layout.h"

namespace keyframed {

struct LibcameraSource::Impl {
  struct Mapping {
    void* base = nullptr;
    std::size_t length = 0;
  };

  std::unique_ptr<libcamera::CameraManager> manager;
  std::shared_ptr<libcamera::Camera> camera;
  bool acquired = false;
  bool started = false;
  std::unique_ptr<libcamera::CameraConfiguration> config;
  libcamera::Stream* stream = nullptr;
  std::unique_ptr<libcamera::FrameBufferAllocator> allocator;
  std::vector<std::unique_ptr<libcamera::Request>> requests;
  std::vector<Mapping> mappings;
  // Each buffer's planes as mapped; contiguousFrame() lays them out as a Frame.
  std::map<const libcamera::FrameBuffer*, std::vector<PlaneSpan>> planes;
  std::vector<std::uint8_t> packed;  // the frame, when its planes are not back to back
  PixelFormat format = PixelFormat::NV12;
  int stride = 0;
  libcamera::Request* held = nullptr;  // lent to the caller until the next call

  // Filled by libcamera's thread, drained by next(). Reserved to the number of
  // requests: pushing never allocates.
  std::mutex mutex;
  std::condition_variable ready;
  std::vector<libcamera::Request*> completed;
  bool disconnected = false;
  bool interrupted = false;  // the owner stops: no more waiting

  // Runs on libcamera's internal thread: hand over and return, no work here.
  void onRequestCompleted(libcamera::Request* request) {
    {
      std::lock_guard lock(mutex);
      completed.push_back(request);
    }
    ready.notify_one();
  }
  void onDisconnected() {
    {
      std::lock_guard lock(mutex);
      disconnected = true;
    }
    ready.notify_one();
  }

  ~Impl() {
    if (camera) {
      if (started) camera->stop();  // completes or cancels every queued request
      camera->requestCompleted.disconnect(this);
      camera->disconnected.disconnect(this);
    }
    requests.clear();
    for (const Mapping& m : mappings) ::munmap(m.base, m.length);
    mappings.clear();
    if (allocator && stream != nullptr) allocator->free(stream);
    allocator.reset();
    if (camera && acquired) camera->release();
    camera.reset();
    if (manager) manager->stop();
  }
};

LibcameraSource::LibcameraSource() : impl_(std::make_unique<Impl>()) {}
LibcameraSource::~LibcameraSource() = default;

std::vector<std::string> LibcameraSource::listCameras(std::string& error) {
  auto manager = std::make_unique<libcamera::CameraManager>();
  std::vector<std::string> ids;
  if (const int r = manager->start(); r < 0) {
    error = "libcamera camera manager failed to start: " + std::string(std::strerror(-r));
    return ids;
  }
  for (const auto& c : manager->cameras()) ids.push_back(c->id());
  manager->stop();
  return ids;
}

std::unique_ptr<LibcameraSource> LibcameraSource::open(const LibcameraOptions& options,
                                                       std::string& error) {
  // One buffer is lent to the caller between calls: with fewer than two, the camera
  // would have no request queued while the analysis holds a frame.
  if (options.bufferCount < 2 || options.bufferCount > 32) {
    error = "buffer count must be 2..32, got " + std::to_string(options.bufferCount);
    return nullptr;
  }
  std::unique_ptr<LibcameraSource> src(new LibcameraSource());
  Impl& d = *src->impl_;
  d.manager = std::make_unique<libcamera::CameraManager>();
  if (const int r = d.manager->start(); r < 0) {
    error = "libcamera camera manager failed to start: " + std::string(std::strerror(-r));
    d.manager.reset();
    return nullptr;
  }
  d.camera = selectCamera(d.manager->cameras(), options.cameraId, error);
  if (!d.camera) return nullptr;
  src->cameraId_ = d.camera->id();
  const std::string who = "camera " + src->cameraId_;
  if (d.camera->acquire() < 0) {
    error = who + " is in use by another process";
    return nullptr;
  }
  d.acquired = true;

  const auto role =
      options.videoRole ? libcamera::StreamRole::VideoRecording : libcamera::StreamRole::Viewfinder;
  d.config = libcamera_compat::generateConfiguration(*d.camera, role);
  if (!d.config || d.config->empty()) {
    error = who + " cannot produce a " + (options.videoRole ? "video" : "viewfinder") + " stream";
    return nullptr;
  }
  libcamera::StreamConfiguration& sc = d.config->at(0);
  const libcamera::PixelFormat pf =
      chooseLibcameraFormat(sc.formats().pixelformats(), options.format, error);
  if (!pf.isValid()) {
    error = who + ": " + error;
    return nullptr;
  }
  sc.pixelFormat = pf;
  sc.size = chooseLibcameraSize(sc.formats(), pf,
                                libcamera::Size(static_cast<unsigned>(std::max(0, options.width)),
                                                static_cast<unsigned>(std::max(0, options.height))),
                                sc.size);
  sc.bufferCount = static_cast<unsigned>(options.bufferCount);
  libcamera_compat::setUprightOrientation(*d.config);
  if (d.config->validate() == libcamera::CameraConfiguration::Invalid) {
    error = who + " rejected " + sc.toString();
    return nullptr;
  }
  if (!toFrameFormat(sc.pixelFormat, d.format)) {
    error = who + " adjusted the format to unsupported " + sc.pixelFormat.toString();
    return nullptr;
  }
  if (d.camera->configure(d.config.get()) < 0) {
    error = who + ": configure " + sc.toString() + " failed";
    return nullptr;
  }
  d.stream = sc.stream();
  d.stride = static_cast<int>(sc.stride);

  d.allocator = std::make_unique<libcamera::FrameBufferAllocator>(d.camera);
  if (d.allocator->allocate(d.stream) < 0) {
    error = who + ": buffer allocation failed";
    return nullptr;
  }
  for (const auto& buffer : d.allocator->buffers(d.stream)) {
    // Map each dmabuf once; planes of one buffer often share it.
    std::map<int, std::size_t> extent;
    for (const auto& p : buffer->planes()) {
      auto& e = extent[p.fd.get()];
      e = std::max<std::size_t>(e, std::size_t{p.offset} + p.length);
    }
    std::map<int, const std::uint8_t*> base;
    for (const auto& [fd, length] : extent) {
      void* m = ::mmap(nullptr, length, PROT_READ, MAP_SHARED, fd, 0);
      if (m == MAP_FAILED) {
        error = who + ": mmap of a frame buffer failed: " + std::strerror(errno);
        return nullptr;
      }
      d.mappings.push_back({m, length});
      base[fd] = static_cast<const std::uint8_t*>(m);
    }
    std::vector<PlaneSpan>& spans = d.planes[buffer.get()];
    for (const auto& p : buffer->planes()) spans.push_back({base[p.fd.get()] + p.offset, p.length});

    std::unique_ptr<libcamera::Request> request = d.camera->createRequest();
    if (!request || request->addBuffer(d.stream, buffer.get()) < 0) {
      error = who + ": cannot create a capture request";
      return nullptr;
    }
    d.requests.push_back(std::move(request));
  }
  // Every buffer's planes must hold the configured picture: said now, not per frame.
  for (const auto& [buffer, spans] : d.planes) {
    if (contiguousFrame(d.format, d.stride, static_cast<int>(sc.size.height), spans, d.packed,
                        error) == nullptr) {
      error = who + ": " + sc.toString() + ": " + error;
      return nullptr;
    }
  }
  d.completed.reserve(d.requests.size());
  d.camera->requestCompleted.connect(&d, &Impl::onRequestCompleted);
  d.camera->disconnected.connect(&d, &Impl::onDisconnected);

  libcamera::ControlList controls;
  if (options.fps > 0.0) {
    const auto us = static_cast<std::int64_t>(std::llround(1e6 / options.fps));
    const std::array<std::int64_t, 2> limits{us, us};
    controls.set(libcamera::controls::FrameDurationLimits,
                 libcamera::Span<const std::int64_t, 2>(limits));
  }
  if (d.camera->start(options.fps > 0.0 ? &controls : nullptr) < 0) {
    error = who + ": start failed";
    return nullptr;
  }
  d.started = true;
  for (auto& r : d.requests) {
    if (d.camera->queueRequest(r.get()) < 0) {
      error = who + ": queueing a request failed";
      return nullptr;
    }
  }

  SourceInfo& info = src->info_;
  info.width = static_cast<int>(sc.size.width);
  info.height = static_cast<int>(sc.size.height);
  info.fps = options.fps;
  info.frameCount = -1;
  src->timeoutMs_ = std::max(1, options.timeoutMs);
  info.description = "libcamera:" + src->cameraId_ + " " + sc.toString();
  return src;
}

void LibcameraSource::interrupt() {
  {
    std::lock_guard lock(impl_->mutex);
    impl_->interrupted = true;
  }
  impl_->ready.notify_all();
}

bool LibcameraSource::failed() const {
  std::lock_guard lock(impl_->mutex);
  return impl_->disconnected;
}

ReadStatus LibcameraSource::next(Frame& frame, std::string& error) {
  Impl& d = *impl_;
  const auto requeue = [&](libcamera::Request* r) {
    r->reuse(libcamera::Request::ReuseBuffers);
    return d.camera->queueRequest(r) == 0;
  };
  if (d.held != nullptr) {
    libcamera::Request* r = std::exchange(d.held, nullptr);
    if (!requeue(r)) {
      error = "camera " + cameraId_ + ": queueing a request failed";
      return ReadStatus::Error;
    }
  }
  // One deadline for the call: cancelled and failed requests do not restart it, so a
  // camera that completes every request as failed is reported, not waited on forever.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeoutMs_);
  std::uint64_t failedInWait = 0;
  for (;;) {
    libcamera::Request* request = nullptr;
    {
      std::unique_lock lock(d.mutex);
      const bool got = d.ready.wait_until(
          lock, deadline, [&] { return !d.completed.empty() || d.disconnected || d.interrupted; });
      if (d.interrupted) {
        error = "interrupted: waiting for a frame from camera " + cameraId_;
        return ReadStatus::Error;
      }
      if (d.disconnected) {
        error = "camera " + cameraId_ + " disconnected";
        return ReadStatus::Error;
      }
      if (!got) {
        error = "timeout: no frame from camera " + cameraId_ + " within " +
                std::to_string(timeoutMs_) + " ms" +
                (failedInWait > 0 ? " (" + std::to_string(failedInWait) + " came back failed)"
                                  : std::string());
        return ReadStatus::Error;
      }
      request = d.completed.front();
      d.completed.erase(d.completed.begin());
    }
    if (request->status() == libcamera::Request::RequestCancelled) {
      if (!requeue(request)) {
        error = "camera " + cameraId_ + ": queueing a request failed";
        return ReadStatus::Error;
      }
      continue;
    }
    libcamera::FrameBuffer* buffer = request->findBuffer(d.stream);
    if (buffer != nullptr) {
      // A failed frame has its number too: counted once, as failed, not as a gap.
      const std::uint32_t sequence = buffer->metadata().sequence;
      if (haveSequence_ && sequence > lastSequence_ + 1)
        sequenceGaps_ += sequence - lastSequence_ - 1;
      lastSequence_ = sequence;
      haveSequence_ = true;
    }
    if (buffer == nullptr || buffer->metadata().status != libcamera::FrameMetadata::FrameSuccess) {
      ++failedFrames_;
      ++failedInWait;
      if (!requeue(request)) {
        error = "camera " + cameraId_ + ": queueing a request failed";
        return ReadStatus::Error;
      }
      continue;
    }
    const auto sensorTs =
        libcamera_compat::metadata(*request).get(libcamera::controls::SensorTimestamp);
    sensorTimestamps_ = sensorTs.has_value();
    origin_.store(sensorTimestamps_ ? TimestampOrigin::StartOfExposure : TimestampOrigin::Unknown);
    std::string why;
    const std::uint8_t* data =
        contiguousFrame(d.format, d.stride, info_.height, d.planes.at(buffer), d.packed, why);
    if (data == nullptr) {  // checked at open: a buffer the camera changed under us
      requeue(request);
      error = "camera " + cameraId_ + ": " + why;
      return ReadStatus::Error;
    }
    frame = Frame{};
    frame.format = d.format;
    frame.data = data;
    frame.width = info_.width;
    frame.height = info_.height;
    frame.stride = d.stride;
    frame.timestampNs =
        sensorTs ? *sensorTs : static_cast<std::int64_t>(buffer->metadata().timestamp);
    frame.index = index_++;
    d.held = request;
    return ReadStatus::Frame;
  }
}

}  // namespace keyframed
