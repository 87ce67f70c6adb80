#include "tagging/exif_writer.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <mutex>
#include <vector>

// exiv2 0.27 hands images out as std::auto_ptr, deprecated in C++11 and still provided
// by libstdc++; the warning is about exiv2's API, not this file.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wdeprecated-declarations"
#include <exiv2/exiv2.hpp>

#include "tagging/camera_mount.h"
#include "tagging/pix4d_fisheye.h"

namespace keyframed {
namespace {

// Pix4D's XMP namespace (https://support.pix4d.com/hc/en-us/articles/360016450032); the
// trailing slash is how Pix4D-aware cameras (Parrot Sequoia, DJI) write it.
constexpr const char* kPix4dNs = "http://pix4d.com/camera/1.0/";
// keyframed's own XMP namespace, for what Pix4D's cannot say exactly: an OpenCV fisheye
// calibration (Pix4D's fisheye model is another polynomial). docs/formats.md.
constexpr const char* kKeyframedNs = "https://github.com/keyframed/keyframed/xmp/1.0/";

// Typical 1-sigma user range error of a standalone single-frequency GPS receiver;
// accuracy ~ DOP x UERE when the receiver does not report h_acc/v_acc.
constexpr double kUereM = 5.0;

void xmpLock(void* data, bool lock) {
  auto* m = static_cast<std::mutex*>(data);
  if (lock) {
    m->lock();
  } else {
    m->unlock();
  }
}

// XmpParser::initialize is not thread-safe itself: run it (and the namespace
// registration) exactly once, with a lock the XMP toolkit uses afterwards.
void initExiv2Once() {
  static std::once_flag once;
  std::call_once(once, [] {
    static std::mutex toolkitMutex;
    Exiv2::XmpParser::initialize(xmpLock, &toolkitMutex);
    Exiv2::XmpProperties::registerNs(kPix4dNs, "Camera");
    Exiv2::XmpProperties::registerNs(kKeyframedNs, "Keyframed");
    // Warnings (e.g. about odd input files) would go to stderr; errors come back to us
    // as exceptions anyway.
    Exiv2::LogMsg::setLevel(Exiv2::LogMsg::error);
  });
}

Exiv2::URational rational(double v, std::uint32_t den) {
  // Clamped: a nonsense value must not wrap round into a plausible one.
  const long long n = std::min(std::llround(std::abs(v) * den), 0xFFFFFFFFLL);
  return {static_cast<std::uint32_t>(n), den};
}

std::string format(const char* fmt, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, fmt, v);
  return buf;
}

// Degrees as EXIF deg/min/sec rationals; seconds in micro-arcseconds (3e-8 m).
void setDms(Exiv2::ExifData& exif, const char* key, double deg) {
  const std::int64_t totalUas = std::llround(std::abs(deg) * 3600.0 * 1e6);
  const std::int64_t d = totalUas / (3600LL * 1000000);
  const std::int64_t m = (totalUas / (60LL * 1000000)) % 60;
  const std::int64_t s = totalUas % (60LL * 1000000);
  Exiv2::URationalValue v;
  v.value_.push_back({static_cast<std::uint32_t>(d), 1});
  v.value_.push_back({static_cast<std::uint32_t>(m), 1});
  v.value_.push_back({static_cast<std::uint32_t>(s), 1000000});
  exif[key].setValue(&v);
}

void setByte(Exiv2::ExifData& exif, const char* key, const char* values) {
  Exiv2::Value::AutoPtr v = Exiv2::Value::create(Exiv2::unsignedByte);
  v->read(values);
  exif[key].setValue(v.get());
}

// EXIF's "undefined" bytes, given as decimal numbers ("48 50 51 50" is "0232").
void setUndefined(Exiv2::ExifData& exif, const char* key, const char* values) {
  Exiv2::Value::AutoPtr v = Exiv2::Value::create(Exiv2::undefined);
  v->read(values);
  exif[key].setValue(v.get());
}

// The tags EXIF 2.32 requires of every compressed (JPEG) image, whatever else is known.
void writeRequired(Exiv2::ExifData& exif) {
  setUndefined(exif, "Exif.Photo.ExifVersion", "48 50 51 50");      // "0232": OffsetTime is 2.31
  setUndefined(exif, "Exif.Photo.FlashpixVersion", "48 49 48 48");  // "0100"
  setUndefined(exif, "Exif.Photo.ComponentsConfiguration", "1 2 3 0");  // Y Cb Cr
  exif["Exif.Photo.ColorSpace"] = static_cast<std::uint16_t>(1);        // sRGB
  exif["Exif.Image.XResolution"] = Exiv2::URational(72, 1);
  exif["Exif.Image.YResolution"] = Exiv2::URational(72, 1);
  exif["Exif.Image.ResolutionUnit"] = static_cast<std::uint16_t>(2);    // inches
  exif["Exif.Image.YCbCrPositioning"] = static_cast<std::uint16_t>(1);  // centred (JFIF)
}

void writeCamera(Exiv2::ExifData& exif, Exiv2::XmpData& xmp, const CameraModel& cam) {
  if (!cam.make.empty()) exif["Exif.Image.Make"] = cam.make;
  if (!cam.model.empty()) exif["Exif.Image.Model"] = cam.model;
  if (cam.width > 0 && cam.height > 0) {
    exif["Exif.Photo.PixelXDimension"] = static_cast<std::uint32_t>(cam.width);
    exif["Exif.Photo.PixelYDimension"] = static_cast<std::uint32_t>(cam.height);
  }
  if (std::isfinite(cam.focalLengthMm)) {
    exif["Exif.Photo.FocalLength"] = rational(cam.focalLengthMm, 1000);
  }
  const double f35 = cam.focalLength35mm();
  if (std::isfinite(f35) && f35 >= 1.0 && f35 < 65535.0) {
    exif["Exif.Photo.FocalLengthIn35mmFilm"] = static_cast<std::uint16_t>(std::lround(f35));
  }
  // The tags carry one focal length in mm: each axis's focal length in pixels comes
  // back through its own pixel pitch. A calibration's fx and fy then set the pitches'
  // ratio (pixels fx / fy times as tall as wide), whatever height a datasheet gives the
  // sensor; without one, square pixels: a video mode crops the sensor's height (16:9
  // of a 4:3 sensor), so the datasheet's height would make them a third too tall.
  const bool sensorKnown = std::isfinite(cam.sensorWidthMm) && cam.width > 0 && cam.height > 0;
  const double squareH = cam.sensorWidthMm * cam.height / std::max(cam.width, 1);
  double sensorH = squareH;
  if (cam.calibrated() && std::isfinite(cam.fx) && std::isfinite(cam.fy) && cam.fy > 0.0)
    sensorH = squareH * cam.fx / cam.fy;
  if (sensorKnown) {
    // Pixels per millimetre (FocalPlaneResolutionUnit 4): COLMAP, OpenSfM/ODM and
    // exiftool convert any unit, but the readers of Pix4D's PrincipalPoint (mm) that
    // multispectral cameras ship take this value as pixels per mm whatever the unit.
    // To 1e-6 px/mm (1 um pixels: 1000 px/mm, 1e9 of the 4.3e9 a rational holds), so
    // that the principal point and focal length in pixels come back to 1e-8.
    exif["Exif.Photo.FocalPlaneXResolution"] = rational(cam.width / cam.sensorWidthMm, 1000000);
    exif["Exif.Photo.FocalPlaneYResolution"] = rational(cam.height / sensorH, 1000000);
    exif["Exif.Photo.FocalPlaneResolutionUnit"] = std::uint16_t{4};
  }
  if (!cam.calibrated()) return;  // no fabricated intrinsics
  const bool fisheye = cam.lens == CameraModel::Lens::Fisheye;
  xmp["Xmp.Camera.ModelType"] = fisheye ? "fisheye" : "perspective";
  if (sensorKnown) {
    const double pitchX = cam.sensorWidthMm / cam.width;
    const double pitchY = sensorH / cam.height;
    // Millimetres from the image's top-left corner; OpenCV puts that corner at
    // (-0.5, -0.5) pixels.
    xmp["Xmp.Camera.PrincipalPoint"] =
        format("%.6f", (cam.cx + 0.5) * pitchX) + "," + format("%.6f", (cam.cy + 0.5) * pitchY);
    xmp[fisheye ? "Xmp.Keyframed.FisheyeFocalLength" : "Xmp.Camera.PerspectiveFocalLength"] =
        format("%.6f", cam.fx * pitchX);
    // Readers that also accept pixels look for the unit (MicaSense's writes it too).
    if (!fisheye) xmp["Xmp.Camera.PerspectiveFocalLengthUnits"] = "mm";
  }
  const auto d = [&](std::size_t i) { return i < cam.distortion.size() ? cam.distortion[i] : 0.0; };
  std::string dist;
  // Pix4D R1,R2,R3,T1,T2 <- OpenCV k1,k2,k3,p1,p2 (same polynomial; docs/formats.md);
  // a fisheye's k1..k4 as OpenCV has them.
  const std::vector<double> terms = fisheye ? std::vector<double>{d(0), d(1), d(2), d(3)}
                                            : std::vector<double>{d(0), d(1), d(4), d(2), d(3)};
  for (double v : terms) {
    if (!dist.empty()) {
      dist += ',';
    }
    dist += format("%.9g", v);
  }
  xmp[fisheye ? "Xmp.Keyframed.FisheyeDistortion" : "Xmp.Camera.PerspectiveDistortion"] = dist;
  // Pix4D's own fisheye model, fitted to the lens (pix4d_fisheye.h): what Pix4D reads.
  if (const auto p = fisheye ? pix4dFisheye(cam) : std::nullopt) {
    std::string affine, poly;
    for (std::size_t i = 0; i < 4; ++i) {
      if (i > 0) {
        affine += ',';
        poly += ',';
      }
      affine += format("%.6f", p->affine[i] + 0.0);
      poly += format("%.9g", p->polynomial[i] + 0.0);
    }
    xmp["Xmp.Camera.FisheyeAffineMatrix"] = affine;
    xmp["Xmp.Camera.FisheyePolynomial"] = poly;
  }
}

void writeTime(Exiv2::ExifData& exif, std::int64_t utcUs, bool gps) {
  const std::int64_t secs = utcUs >= 0 ? utcUs / 1000000 : (utcUs - 999999) / 1000000;
  const std::int64_t micros = utcUs - secs * 1000000;
  const std::time_t t = static_cast<std::time_t>(secs);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y:%m:%d %H:%M:%S", &tm);
  // The JPEG is made on board at the capture: its DateTime is the same instant. No
  // SubSecTime beside it: OpenDroneMap reads that one's "066" as 0.66 s (the digits
  // without their leading zeros), which puts keyframes out of order; without it ODM
  // takes whole seconds, and the rest read SubSecTimeOriginal or the GPS time.
  exif["Exif.Photo.DateTimeOriginal"] = std::string(buf);
  exif["Exif.Image.DateTime"] = std::string(buf);
  std::snprintf(buf, sizeof buf, "%03d", static_cast<int>(micros / 1000));
  exif["Exif.Photo.SubSecTimeOriginal"] = std::string(buf);
  exif["Exif.Photo.OffsetTimeOriginal"] = std::string("+00:00");
  exif["Exif.Photo.OffsetTime"] = std::string("+00:00");
  if (!gps) return;
  Exiv2::URationalValue v;
  v.value_.push_back({static_cast<std::uint32_t>(tm.tm_hour), 1});
  v.value_.push_back({static_cast<std::uint32_t>(tm.tm_min), 1});
  v.value_.push_back({static_cast<std::uint32_t>(tm.tm_sec * 1000000 + micros), 1000000});
  exif["Exif.GPSInfo.GPSTimeStamp"].setValue(&v);
  std::strftime(buf, sizeof buf, "%Y:%m:%d", &tm);
  exif["Exif.GPSInfo.GPSDateStamp"] = std::string(buf);
}

void writeGps(Exiv2::ExifData& exif, Exiv2::XmpData& xmp, const GeoPosition& p,
              const GpsQuality& q) {
  setByte(exif, "Exif.GPSInfo.GPSVersionID", "2 3 0 0");
  exif["Exif.GPSInfo.GPSLatitudeRef"] = std::string(p.latDeg < 0 ? "S" : "N");
  setDms(exif, "Exif.GPSInfo.GPSLatitude", p.latDeg);
  exif["Exif.GPSInfo.GPSLongitudeRef"] = std::string(p.lonDeg < 0 ? "W" : "E");
  setDms(exif, "Exif.GPSInfo.GPSLongitude", p.lonDeg);
  setByte(exif, "Exif.GPSInfo.GPSAltitudeRef", p.altAmslM < 0 ? "1" : "0");
  exif["Exif.GPSInfo.GPSAltitude"] = rational(p.altAmslM, 1000);
  exif["Exif.GPSInfo.GPSMapDatum"] = std::string("WGS-84");
  if (q.fixType >= 3) {
    exif["Exif.GPSInfo.GPSMeasureMode"] = std::string("3");
  } else if (q.fixType == 2) {
    exif["Exif.GPSInfo.GPSMeasureMode"] = std::string("2");
  }
  if (q.satellites >= 0) exif["Exif.GPSInfo.GPSSatellites"] = std::to_string(q.satellites);
  // GPSDOP: PDOP for a 3D fix, HDOP for a 2D one, as EXIF defines it. PDOP from HDOP
  // and VDOP; HDOP alone where VDOP is unknown.
  double dop = q.hdop;
  if (q.fixType >= 3 && std::isfinite(q.hdop) && std::isfinite(q.vdop))
    dop = std::hypot(q.hdop, q.vdop);
  if (std::isfinite(dop)) exif["Exif.GPSInfo.GPSDOP"] = rational(dop, 1000);
  // Receiver-reported accuracy first; DOP x UERE only for standalone fixes (an RTK
  // fix's DOP says nothing about its centimetre accuracy).
  const bool standalone = q.fixType >= 2 && q.fixType <= 4;
  double xy = q.hAccuracyM;
  if (!std::isfinite(xy) && standalone) xy = q.hdop * kUereM;
  double z = q.vAccuracyM;
  if (!std::isfinite(z) && standalone) z = q.vdop * kUereM;
  if (std::isfinite(xy)) xmp["Xmp.Camera.GPSXYAccuracy"] = format("%.3f", xy);
  if (std::isfinite(z)) xmp["Xmp.Camera.GPSZAccuracy"] = format("%.3f", z);
}

void buildTags(Exiv2::Image& image, const TagSet& tags) {
  Exiv2::ExifData& exif = image.exifData();
  Exiv2::XmpData& xmp = image.xmpData();
  exif["Exif.Image.Software"] = tags.software;
  writeRequired(exif);
  if (tags.camera != nullptr) {
    // Intrinsics refer to the camera's resolution; the JPEG may be a scaled copy.
    const int w = image.pixelWidth();
    const int h = image.pixelHeight();
    const CameraModel& c = *tags.camera;
    if (c.width > 0 && w > 0 && h > 0 && (c.width != w || c.height != h)) {
      writeCamera(exif, xmp, c.scaledTo(w, h));
    } else {
      writeCamera(exif, xmp, c);
    }
  }
  // The picture's size, which EXIF requires, also without a camera model.
  if (exif.findKey(Exiv2::ExifKey("Exif.Photo.PixelXDimension")) == exif.end() &&
      image.pixelWidth() > 0 && image.pixelHeight() > 0) {
    exif["Exif.Photo.PixelXDimension"] = static_cast<std::uint32_t>(image.pixelWidth());
    exif["Exif.Photo.PixelYDimension"] = static_cast<std::uint32_t>(image.pixelHeight());
  }
  if (tags.utcUs) writeTime(exif, *tags.utcUs, tags.position.has_value());
  if (tags.position) writeGps(exif, xmp, *tags.position, tags.gps);
  if (tags.cameraToNed) {
    const Pix4dAngles a = pix4dAngles(*tags.cameraToNed);
    // Rounded to the micro-degree written, then into range: a yaw of 359.99999995
    // is "0.000000", not "360.000000", and a roll of -179.9999996 is "180.000000".
    const auto micro = [](double deg) { return std::round(deg * 1e6) / 1e6; };
    double yaw = std::fmod(micro(a.yawDeg), 360.0);
    if (yaw < 0.0) yaw += 360.0;
    double roll = micro(a.rollDeg);
    if (roll <= -180.0) roll += 360.0;
    xmp["Xmp.Camera.Yaw"] = format("%.6f", yaw + 0.0);  // + 0.0: never "-0.000000"
    xmp["Xmp.Camera.Pitch"] = format("%.6f", micro(a.pitchDeg) + 0.0);
    xmp["Xmp.Camera.Roll"] = format("%.6f", roll + 0.0);
  }
}

}  // namespace

bool writeTags(std::vector<std::uint8_t>& jpeg, const TagSet& tags, std::string& error) {
  if (jpeg.empty()) {
    error = "cannot tag an empty JPEG buffer";
    return false;
  }
  try {
    initExiv2Once();
    Exiv2::Image::AutoPtr image =
        Exiv2::ImageFactory::open(jpeg.data(), static_cast<long>(jpeg.size()));
    if (image.get() == nullptr || image->imageType() != Exiv2::ImageType::jpeg) {
      error = "not a JPEG image";
      return false;
    }
    image->readMetadata();
    buildTags(*image, tags);
    image->writeMetadata();
    Exiv2::BasicIo& io = image->io();
    io.seek(0, Exiv2::BasicIo::beg);
    const long size = static_cast<long>(io.size());
    std::vector<std::uint8_t> out(static_cast<std::size_t>(size));
    if (io.read(out.data(), size) != size) {
      error = "exiv2: short read of the tagged JPEG";
      return false;
    }
    jpeg.swap(out);
    return true;
  } catch (const Exiv2::AnyError& e) {
    error = std::string("exiv2: ") + e.what();
  } catch (const std::exception& e) {
    error = std::string("tagging failed: ") + e.what();
  }
  return false;
}

}  // namespace keyframed

#pragma GCC diagnostic pop
