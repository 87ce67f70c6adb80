#pragma once

// Pure choices behind LibcameraSource: which camera, pixel format and size.
// No camera needed, so they are unit-tested.

#include <memory>
#include <string>
#include <vector>

#include <libcamera/camera.h>
#include <libcamera/geometry.h>
#include <libcamera/pixel_format.h>
#include <libcamera/stream.h>

#include "core/frame.h"

namespace keyframed {

// The camera with `id`, or the first one when `id` is empty. nullptr and a
// one-line error ("no camera found", or the ids that exist) otherwise.
std::shared_ptr<libcamera::Camera> selectCamera(
    const std::vector<std::shared_ptr<libcamera::Camera>>& cameras, const std::string& id,
    std::string& error);

// `wanted` ("NV12", "YUV420", "YUYV"; empty: the first offered of those, in
// that order) among the formats the stream offers. An invalid PixelFormat and
// a one-line error when none fits.
libcamera::PixelFormat chooseLibcameraFormat(const std::vector<libcamera::PixelFormat>& offered,
                                             const std::string& wanted, std::string& error);

// The size to ask for `format`. A stream that offers a range (a scaler: the Pi's
// ISP) is asked for `wanted` itself when it lies within the range (validate() then
// aligns it to the steps): StreamFormats::sizes() of a range is only libcamera's
// list of common sizes, which would turn a 2028x1520 request into 2048x1536.
// Among discrete sizes: the one equal to `wanted`; else the smallest that covers
// it; else the largest. `wanted` of 0x0 keeps `current`.
libcamera::Size chooseLibcameraSize(const libcamera::StreamFormats& formats,
                                    const libcamera::PixelFormat& format,
                                    const libcamera::Size& wanted, const libcamera::Size& current);

// The frame layout a libcamera format maps to; false for formats keyframed
// does not read.
bool toFrameFormat(const libcamera::PixelFormat& format, PixelFormat& out);

}  // namespace keyframed
