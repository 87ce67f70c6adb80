#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wdeprecated-declarations"  // exiv2 0.27 uses auto_ptr
#include <exiv2/exiv2.hpp>

#include "tagging/camera_mount.h"
#include "tagging/exif_writer.h"
#include "tagging/jpeg_encoder.h"
#include "tagging/pix4d_fisheye.h"
#include "telemetry/pose_store.h"
#include "temp_dir.h"

namespace keyframed {
namespace {

namespace fs = std::filesystem;

constexpr std::int64_t kUtcUs = 1780308000LL * 1000000 + 123456;  // 2026-06-01T10:00:00.123456Z

std::vector<std::uint8_t> photoJpeg() {
  const cv::Mat img = cv::imread(KEYFRAMED_PHOTO_DIR "/aero1.jpg", cv::IMREAD_COLOR);
  std::vector<std::uint8_t> out;
  if (img.empty()) return out;
  JpegEncoder enc;
  std::string error;
  if (!enc.encode(img(cv::Rect(0, 0, 320, 240)), 90, out, error)) out.clear();
  return out;
}

CameraModel calibratedCamera() {
  CameraModel c;
  c.make = "Acme";
  c.model = "Eye 2";
  c.width = 320;
  c.height = 240;
  c.fx = c.fy = 300.0;
  c.cx = 159.5;
  c.cy = 119.5;
  c.distortion = {-0.11, 0.05, 0.0012, -0.0034, 0.021};
  c.sensorWidthMm = 6.4;
  c.sensorHeightMm = 4.8;
  c.focalLengthMm = 6.0;
  return c;
}

// Runs exiftool on the JPEG; empty when exiftool is not installed.
std::string exiftoolJson(const std::vector<std::uint8_t>& jpeg, const std::string& name) {
  const fs::path p = test::processTempDir("keyframed-tagging") / name;
  std::ofstream(p, std::ios::binary)
      .write(reinterpret_cast<const char*>(jpeg.data()), static_cast<std::streamsize>(jpeg.size()));
  // -validate (beside -all): what exiftool finds wrong or missing in the file, as
  // ExifTool:Validate, "errors warnings minor-warnings" with -n.
  const std::string cmd = "exiftool -n -j -G1 -a -all -validate '" + p.string() + "' 2>&1";
  std::string text;
  if (FILE* f = popen(cmd.c_str(), "r")) {
    char buf[4096];
    std::size_t n;
    while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) text.append(buf, n);
    pclose(f);
  }
  return text;
}

bool haveExiftool() {
  return std::system("exiftool -ver >/dev/null 2>&1") == 0;
}

// The raw value of "key" in exiftool's JSON (quotes removed); "" when absent.
std::string field(const std::string& json, const std::string& key) {
  const std::string k = "\"" + key + "\": ";
  const std::size_t at = json.find(k);
  if (at == std::string::npos) return "";
  std::size_t b = at + k.size();
  if (json[b] == '"') {
    const std::size_t e = json.find('"', b + 1);
    return json.substr(b + 1, e - b - 1);
  }
  const std::size_t e = json.find_first_of(",\n}", b);
  return json.substr(b, e - b);
}

double number(const std::string& json, const std::string& key) {
  const std::string v = field(json, key);
  return v.empty() ? NAN : std::stod(v);
}

class TaggingTest : public testing::Test {
 protected:
  void SetUp() override {
    jpeg_ = photoJpeg();
    if (jpeg_.empty()) GTEST_SKIP() << "aero1.jpg not found in " KEYFRAMED_PHOTO_DIR;
  }

  std::string tagAndRead(const TagSet& tags, const std::string& name) {
    std::string error;
    EXPECT_TRUE(writeTags(jpeg_, tags, error)) << error;
    return exiftoolJson(jpeg_, name);
  }

  std::vector<std::uint8_t> jpeg_;
};

TEST_F(TaggingTest, NorthEastFullSetReadByExiftool) {
  if (!haveExiftool()) GTEST_SKIP() << "exiftool not installed (Debian: libimage-exiftool-perl)";
  const CameraModel cam = calibratedCamera();
  TagSet t;
  t.camera = &cam;
  t.position = GeoPosition{47.3977418, 8.5455938, 123.456, 50.0};
  t.gps.fixType = 3;
  t.gps.hdop = 0.83;
  t.gps.satellites = 17;
  t.gps.hAccuracyM = 1.25;
  t.gps.vAccuracyM = 2.5;
  t.utcUs = kUtcUs;
  t.cameraToNed = fromPix4dAngles({123.4567, 12.3456, -3.2109});
  const std::string j = tagAndRead(t, "ne.jpg");
  // Every tag EXIF requires is there, and none is malformed.
  EXPECT_EQ(field(j, "ExifTool:Validate"), "0 0 0") << j;

  EXPECT_NEAR(number(j, "Composite:GPSLatitude"), 47.3977418, 1e-7) << j;
  EXPECT_NEAR(number(j, "Composite:GPSLongitude"), 8.5455938, 1e-7);
  EXPECT_EQ(field(j, "GPS:GPSLatitudeRef"), "N");
  EXPECT_EQ(field(j, "GPS:GPSLongitudeRef"), "E");
  EXPECT_NEAR(number(j, "GPS:GPSAltitude"), 123.456, 1e-3);
  EXPECT_EQ(field(j, "GPS:GPSAltitudeRef"), "0");
  EXPECT_NEAR(number(j, "GPS:GPSDOP"), 0.83, 1e-9);  // 3D, but VDOP unknown: HDOP
  EXPECT_EQ(field(j, "GPS:GPSVersionID"), "2 3 0 0");
  EXPECT_EQ(field(j, "GPS:GPSMapDatum"), "WGS-84");
  EXPECT_EQ(field(j, "GPS:GPSMeasureMode"), "3");
  EXPECT_EQ(field(j, "GPS:GPSSatellites"), "17");
  EXPECT_EQ(field(j, "GPS:GPSDateStamp"), "2026:06:01");
  EXPECT_EQ(field(j, "GPS:GPSTimeStamp"), "10:00:00.123456");

  EXPECT_EQ(field(j, "IFD0:Make"), "Acme");
  EXPECT_EQ(field(j, "IFD0:Model"), "Eye 2");
  EXPECT_EQ(field(j, "IFD0:Software"), "keyframed");
  EXPECT_EQ(field(j, "ExifIFD:DateTimeOriginal"), "2026:06:01 10:00:00");
  EXPECT_EQ(field(j, "ExifIFD:SubSecTimeOriginal"), "123");
  EXPECT_EQ(field(j, "ExifIFD:OffsetTimeOriginal"), "+00:00");
  EXPECT_EQ(field(j, "IFD0:ModifyDate"), "2026:06:01 10:00:00");
  EXPECT_EQ(field(j, "ExifIFD:SubSecTime"), "");  // which OpenDroneMap misreads
  EXPECT_EQ(field(j, "ExifIFD:OffsetTime"), "+00:00");
  EXPECT_NEAR(number(j, "ExifIFD:FocalLength"), 6.0, 1e-9);
  EXPECT_EQ(field(j, "ExifIFD:FocalLengthIn35mmFormat"), "34");  // 300 * 36 / 320 = 33.75
  // Pixels per mm (unit 4): 320 px over a 6.4 mm wide sensor.
  EXPECT_NEAR(number(j, "ExifIFD:FocalPlaneXResolution"), 320 / 6.4, 1e-3);
  EXPECT_NEAR(number(j, "ExifIFD:FocalPlaneYResolution"), 240 / 4.8, 1e-3);
  EXPECT_EQ(field(j, "ExifIFD:FocalPlaneResolutionUnit"), "4");
  EXPECT_EQ(field(j, "ExifIFD:ExifImageWidth"), "320");

  EXPECT_NEAR(number(j, "XMP-Camera:Yaw"), 123.4567, 1e-3);
  EXPECT_NEAR(number(j, "XMP-Camera:Pitch"), 12.3456, 1e-3);
  EXPECT_NEAR(number(j, "XMP-Camera:Roll"), -3.2109, 1e-3);
  EXPECT_NEAR(number(j, "XMP-Camera:GPSXYAccuracy"), 1.25, 1e-9);
  EXPECT_NEAR(number(j, "XMP-Camera:GPSZAccuracy"), 2.5, 1e-9);
  EXPECT_EQ(field(j, "XMP-Camera:ModelType"), "perspective");
  EXPECT_EQ(field(j, "XMP-Camera:PerspectiveDistortion"), "-0.11,0.05,0.021,0.0012,-0.0034");
  EXPECT_EQ(field(j, "XMP-Camera:PrincipalPoint"), "3.200000,2.400000");
  EXPECT_NEAR(number(j, "XMP-Camera:PerspectiveFocalLength"), 6.0, 1e-6);
  EXPECT_EQ(field(j, "XMP-Camera:PerspectiveFocalLengthUnits"), "mm");
  // The principal point in mm times FocalPlaneXResolution is OpenCV's cx + 0.5, as a
  // reader that takes the resolution as pixels per mm computes it.
  EXPECT_NEAR(3.2 * number(j, "ExifIFD:FocalPlaneXResolution"), 160.0, 1e-3);
  // Pix4D's namespace as Pix4D-aware cameras write it (exiftool names the group from
  // the prefix, so the address itself is checked in the bytes).
  const std::string bytes(jpeg_.begin(), jpeg_.end());
  EXPECT_NE(bytes.find("xmlns:Camera=\"http://pix4d.com/camera/1.0/\""), std::string::npos);
}

TEST_F(TaggingTest, FisheyeLensReadByExiftool) {
  // cv::fisheye's k1..k4 go as they are into keyframed's namespace, ModelType says
  // fisheye, and none of the pinhole's Perspective* tags is written.
  if (!haveExiftool()) GTEST_SKIP() << "exiftool not installed (Debian: libimage-exiftool-perl)";
  CameraModel cam = calibratedCamera();
  cam.lens = CameraModel::Lens::Fisheye;
  cam.fx = cam.fy = 120.0;
  cam.distortion = {0.031, -0.0072, 0.0011, -0.00019};
  cam.focalLengthMm = NAN;
  TagSet t;
  t.camera = &cam;
  const std::string j = tagAndRead(t, "fisheye.jpg");
  EXPECT_EQ(field(j, "XMP-Camera:ModelType"), "fisheye") << j;
  EXPECT_EQ(field(j, "XMP-Keyframed:FisheyeDistortion"), "0.031,-0.0072,0.0011,-0.00019") << j;
  EXPECT_NEAR(number(j, "XMP-Keyframed:FisheyeFocalLength"), 120.0 * 6.4 / 320, 1e-6);
  EXPECT_EQ(field(j, "XMP-Camera:PrincipalPoint"), "3.200000,2.400000");
  EXPECT_EQ(field(j, "XMP-Camera:PerspectiveFocalLength"), "");
  EXPECT_EQ(field(j, "XMP-Camera:PerspectiveFocalLengthUnits"), "");
  EXPECT_EQ(field(j, "XMP-Camera:PerspectiveDistortion"), "");
  // Pix4D's fisheye model, fitted (Pix4dFisheye tests the fit itself).
  const auto p = pix4dFisheye(cam);
  ASSERT_TRUE(p);
  char affine[96];
  std::snprintf(affine, sizeof affine, "%.6f,0.000000,0.000000,%.6f", p->affine[0], p->affine[3]);
  EXPECT_EQ(field(j, "XMP-Camera:FisheyeAffineMatrix"), affine) << j;
  const std::string poly = field(j, "XMP-Camera:FisheyePolynomial");
  ASSERT_EQ(poly.rfind("0,1,", 0), 0U) << poly;
  double p2 = NAN, p3 = NAN;
  ASSERT_EQ(std::sscanf(poly.c_str() + 4, "%lf,%lf", &p2, &p3), 2) << poly;
  EXPECT_NEAR(p2, p->polynomial[2], 1e-8);
  EXPECT_NEAR(p3, p->polynomial[3], 1e-8);
  const std::string bytes(jpeg_.begin(), jpeg_.end());
  EXPECT_NE(bytes.find("xmlns:Keyframed=\"https://github.com/keyframed/keyframed/xmp/1.0/\""),
            std::string::npos);
}

TEST_F(TaggingTest, SouthWestAndBelowSeaLevel) {
  if (!haveExiftool()) GTEST_SKIP() << "exiftool not installed (Debian: libimage-exiftool-perl)";
  TagSet t;
  t.position = GeoPosition{-33.8567844, -70.6482925, -12.345, 0.0};
  t.gps.fixType = 2;
  t.gps.hdop = 1.5;
  const std::string j = tagAndRead(t, "sw.jpg");
  EXPECT_NEAR(number(j, "GPS:GPSDOP"), 1.5, 1e-9);  // a 2D fix: HDOP
  EXPECT_NEAR(number(j, "Composite:GPSLatitude"), -33.8567844, 1e-7) << j;
  EXPECT_NEAR(number(j, "Composite:GPSLongitude"), -70.6482925, 1e-7);
  EXPECT_EQ(field(j, "GPS:GPSLatitudeRef"), "S");
  EXPECT_EQ(field(j, "GPS:GPSLongitudeRef"), "W");
  EXPECT_NEAR(number(j, "GPS:GPSAltitude"), 12.345, 1e-3);
  EXPECT_EQ(field(j, "GPS:GPSAltitudeRef"), "1");
  EXPECT_NEAR(number(j, "Composite:GPSAltitude"), -12.345, 1e-3);
  EXPECT_EQ(field(j, "GPS:GPSMeasureMode"), "2");
  EXPECT_EQ(field(j, "GPS:GPSSatellites"), "");  // not said by the receiver
  // No receiver accuracy: HDOP x 5 m UERE for a standalone fix.
  EXPECT_NEAR(number(j, "XMP-Camera:GPSXYAccuracy"), 7.5, 1e-9);
  EXPECT_EQ(field(j, "XMP-Camera:GPSZAccuracy"), "");  // no VDOP either
  // The tags EXIF requires are there without a camera model too.
  EXPECT_EQ(field(j, "ExifTool:Validate"), "0 0 0") << j;
  // No camera, no time: none of their tags.
  EXPECT_EQ(field(j, "ExifIFD:DateTimeOriginal"), "");
  EXPECT_EQ(field(j, "IFD0:ModifyDate"), "");
  EXPECT_EQ(field(j, "ExifIFD:SubSecTimeOriginal"), "");
  EXPECT_EQ(field(j, "GPS:GPSTimeStamp"), "");
  EXPECT_EQ(field(j, "IFD0:Make"), "");
}

TEST_F(TaggingTest, UncalibratedVideoModeHasSquarePixelsNotTheSensorsAspect) {
  if (!haveExiftool()) GTEST_SKIP() << "exiftool not installed (Debian: libimage-exiftool-perl)";
  // A 16:9 mode of a 4:3 sensor (6.4 x 4.8 mm) crops its height: with the datasheet's
  // height the tags would say pixels a third taller than wide.
  CameraModel cam;
  cam.width = 320;
  cam.height = 180;
  cam.sensorWidthMm = 6.4;
  cam.sensorHeightMm = 4.8;
  cam.focalLengthMm = 4.0;
  TagSet t;
  t.camera = &cam;
  const std::string j = tagAndRead(t, "crop.jpg");
  EXPECT_NEAR(number(j, "ExifIFD:FocalPlaneXResolution"), 50.0, 1e-3) << j;
  EXPECT_NEAR(number(j, "ExifIFD:FocalPlaneYResolution"), 50.0, 1e-3) << j;
}

TEST_F(TaggingTest, NoPositionWritesNoGpsTags) {
  if (!haveExiftool()) GTEST_SKIP() << "exiftool not installed (Debian: libimage-exiftool-perl)";
  CameraModel lens;  // uncalibrated: only what is known
  lens.focalLengthMm = 4.5;
  lens.sensorWidthMm = 6.0;
  TagSet t;
  t.camera = &lens;
  t.utcUs = kUtcUs;
  t.gps.hdop = 0.9;  // quality without a position is not tagged
  const std::string j = tagAndRead(t, "nogps.jpg");
  EXPECT_EQ(j.find("\"GPS:"), std::string::npos) << j;
  EXPECT_EQ(j.find("GPSLatitude"), std::string::npos);
  EXPECT_EQ(j.find("Accuracy"), std::string::npos);
  EXPECT_EQ(field(j, "ExifIFD:DateTimeOriginal"), "2026:06:01 10:00:00");
  EXPECT_EQ(field(j, "ExifIFD:FocalLengthIn35mmFormat"), "27");  // 4.5 * 36 / 6
  EXPECT_NEAR(number(j, "ExifIFD:FocalLength"), 4.5, 1e-9);
  EXPECT_EQ(field(j, "XMP-Camera:ModelType"), "");  // no fabricated intrinsics
  EXPECT_EQ(field(j, "XMP-Camera:PerspectiveDistortion"), "");
  EXPECT_EQ(field(j, "XMP-Camera:Yaw"), "");
}

TEST_F(TaggingTest, Exiv2ReadsTheTagsBack) {
  const CameraModel cam = calibratedCamera();
  TagSet t;
  t.camera = &cam;
  t.position = GeoPosition{-0.000001, 179.9999999, 0.0004, 0.0};
  t.cameraToNed = cameraToNed(Quaternion{}, CameraMount{});
  std::string error;
  ASSERT_TRUE(writeTags(jpeg_, t, error)) << error;
  // Still a decodable picture of the same size.
  EXPECT_EQ(cv::imdecode(jpeg_, cv::IMREAD_COLOR).size(), cv::Size(320, 240));

  auto image = Exiv2::ImageFactory::open(jpeg_.data(), static_cast<long>(jpeg_.size()));
  image->readMetadata();
  const Exiv2::ExifData& exif = image->exifData();
  const auto lat = exif.findKey(Exiv2::ExifKey("Exif.GPSInfo.GPSLatitude"));
  ASSERT_NE(lat, exif.end());
  ASSERT_EQ(lat->count(), 3);
  EXPECT_EQ(lat->toRational(0).first, 0);
  EXPECT_EQ(lat->toRational(2).second, 1000000);
  EXPECT_EQ(lat->toRational(2).first, 3600);  // 1e-6 deg = 0.0036 arcsec
  const auto lon = exif.findKey(Exiv2::ExifKey("Exif.GPSInfo.GPSLongitude"));
  ASSERT_NE(lon, exif.end());
  EXPECT_EQ(lon->toRational(0).first, 179);
  EXPECT_EQ(lon->toRational(1).first, 59);
  EXPECT_EQ(lon->toRational(2).first, 59999640);  // 59.99964 arcsec
  const auto alt = exif.findKey(Exiv2::ExifKey("Exif.GPSInfo.GPSAltitude"));
  ASSERT_NE(alt, exif.end());
  EXPECT_EQ(alt->toRational(0), (Exiv2::Rational{0, 1000}));  // 0.4 mm rounds to 0
  const Exiv2::XmpData& xmp = image->xmpData();
  const auto yaw = xmp.findKey(Exiv2::XmpKey("Xmp.Camera.Yaw"));
  ASSERT_NE(yaw, xmp.end());
  EXPECT_NEAR(std::stod(yaw->toString()), 0.0, 1e-6);
}

// An angle a hair under its wrap point is written in range: a yaw of 359.99999995
// (heading 5e-8 degrees west of north) is "0.000000", never "360.000000".
TEST_F(TaggingTest, AnglesAtTheWrapAreWrittenInRange) {
  const double tiny = 5e-8 * std::numbers::pi / 180.0;
  TagSet t;
  t.cameraToNed = cameraToNed(quaternionFromEuler(0, 0, -tiny), CameraMount{});
  const Pix4dAngles raw = pix4dAngles(*t.cameraToNed);
  ASSERT_GT(raw.yawDeg, 359.9999999);  // the case: 360 once printed with 6 decimals
  std::string error;
  ASSERT_TRUE(writeTags(jpeg_, t, error)) << error;
  auto image = Exiv2::ImageFactory::open(jpeg_.data(), static_cast<long>(jpeg_.size()));
  image->readMetadata();
  const Exiv2::XmpData& xmp = image->xmpData();
  const auto text = [&](const char* key) {
    const auto it = xmp.findKey(Exiv2::XmpKey(key));
    return it == xmp.end() ? std::string("missing") : it->toString();
  };
  EXPECT_EQ(text("Xmp.Camera.Yaw"), "0.000000");
  EXPECT_EQ(text("Xmp.Camera.Pitch"), "0.000000");
  EXPECT_EQ(text("Xmp.Camera.Roll"), "0.000000");
}

TEST_F(TaggingTest, IntrinsicsFollowAScaledJpeg) {
  // The camera was calibrated at 640x480; the keyframe is 320x240.
  CameraModel cam = calibratedCamera().scaledTo(640, 480);
  TagSet t;
  t.camera = &cam;
  std::string error;
  ASSERT_TRUE(writeTags(jpeg_, t, error)) << error;
  auto image = Exiv2::ImageFactory::open(jpeg_.data(), static_cast<long>(jpeg_.size()));
  image->readMetadata();
  const auto w = image->exifData().findKey(Exiv2::ExifKey("Exif.Photo.PixelXDimension"));
  ASSERT_NE(w, image->exifData().end());
  EXPECT_EQ(w->toLong(), 320);
  const auto pp = image->xmpData().findKey(Exiv2::XmpKey("Xmp.Camera.PrincipalPoint"));
  ASSERT_NE(pp, image->xmpData().end());
  EXPECT_EQ(pp->toString(), "3.200000,2.400000");
}

TEST(Tagging, CorruptOrEmptyJpegFailsCleanly) {
  TagSet t;
  t.position = GeoPosition{1, 2, 3, 4};
  std::string error;
  std::vector<std::uint8_t> empty;
  EXPECT_FALSE(writeTags(empty, t, error));
  EXPECT_FALSE(error.empty());

  std::vector<std::uint8_t> junk(1000, 0x5a);
  error.clear();
  EXPECT_FALSE(writeTags(junk, t, error));
  EXPECT_FALSE(error.empty());
  EXPECT_EQ(junk, std::vector<std::uint8_t>(1000, 0x5a));  // untouched

  std::vector<std::uint8_t> truncated = {0xFF, 0xD8, 0xFF, 0xE1, 0x40, 0x00, 'E', 'x'};
  error.clear();
  EXPECT_FALSE(writeTags(truncated, t, error));
  EXPECT_FALSE(error.empty());
}

}  // namespace
}  // namespace keyframed

#pragma GCC diagnostic pop
