#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <numbers>
#include <tuple>
#include <vector>

#include <sys/stat.h>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "tagging/camera_model.h"
#include "tagging/camera_model_toml.h"
#include "tagging/camera_mount.h"
#include "tagging/pix4d_fisheye.h"
#include "telemetry/pose_store.h"
#include "temp_dir.h"

namespace keyframed {
namespace {

namespace fs = std::filesystem;

fs::path tempDir() {
  return test::processTempDir("keyframed-camera");
}

fs::path tempFile(const std::string& name, const std::string& text) {
  const fs::path p = tempDir() / name;
  std::ofstream(p) << text;
  return p;
}

TEST(CameraModel, AnotherAspectRatioIsACropAndSaidSo) {
  CameraModel c;
  c.width = 4056;
  c.height = 3040;                                     // a 4:3 sensor
  EXPECT_EQ(c.aspectMismatch(2028, 1520), "");         // binned: the same picture, scaled
  EXPECT_EQ(c.aspectMismatch(2026, 1520), "");         // within 0.5 %
  const std::string w = c.aspectMismatch(1920, 1080);  // a 16:9 crop
  EXPECT_NE(w.find("4056x3040"), std::string::npos) << w;
  EXPECT_NE(w.find("1920x1080"), std::string::npos) << w;
  EXPECT_EQ(w.find('\n'), std::string::npos);
  EXPECT_EQ(CameraModel{}.aspectMismatch(1920, 1080), "");  // no calibrated size
}

TEST(CameraModel, WithoutIntrinsicsKeepsOnlyWhatACropLeavesTrue) {
  CameraModel c;
  c.make = "Acme";
  c.model = "Eye";
  c.width = 4056;
  c.height = 3040;
  c.fx = c.fy = 3000.0;
  c.cx = 2027.5;
  c.cy = 1519.5;
  c.distortion = {-0.1, 0.02, 0.0, 0.0};
  c.sensorWidthMm = 6.287;
  c.sensorHeightMm = 4.712;
  c.focalLengthMm = 4.74;
  ASSERT_TRUE(c.calibrated());
  const CameraModel u = c.withoutIntrinsics();
  EXPECT_FALSE(u.calibrated());
  EXPECT_EQ(u.make, "Acme");
  EXPECT_EQ(u.model, "Eye");
  EXPECT_DOUBLE_EQ(u.focalLengthMm, 4.74);   // the lens's, whatever the sensor mode
  EXPECT_TRUE(std::isnan(u.sensorWidthMm));  // the crop's active area is unknown
  EXPECT_TRUE(std::isnan(u.focalLength35mm()));
  EXPECT_TRUE(u.distortion.empty());
  EXPECT_FALSE(u.lensModel().active());
}

TEST(CameraModel, ReadsOpenCvCalibrationYaml) {
  const fs::path p = tempDir() / "calib.yaml";
  {
    cv::FileStorage out(p.string(), cv::FileStorage::WRITE);
    out << "image_width" << 1280 << "image_height" << 720;
    out << "camera_matrix" << (cv::Mat_<double>(3, 3) << 1000, 0, 640.5, 0, 1002, 360.25, 0, 0, 1);
    out << "distortion_coefficients" << (cv::Mat_<double>(1, 5) << -0.1, 0.05, 0.001, -0.002, 0.01);
    out << "sensor_width_mm" << 6.4;
  }
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(p.string(), m, error)) << error;
  EXPECT_TRUE(m.calibrated());
  EXPECT_EQ(m.width, 1280);
  EXPECT_EQ(m.height, 720);
  EXPECT_DOUBLE_EQ(m.fx, 1000);
  EXPECT_DOUBLE_EQ(m.fy, 1002);
  EXPECT_DOUBLE_EQ(m.cx, 640.5);
  EXPECT_DOUBLE_EQ(m.cy, 360.25);
  ASSERT_EQ(m.distortion.size(), 5u);
  EXPECT_DOUBLE_EQ(m.distortion[3], -0.002);
  EXPECT_NEAR(m.focalLengthMm, 1000 * 6.4 / 1280, 1e-12);                // derived
  EXPECT_NEAR(m.sensorHeightMm, 6.4 * 720 / 1280 * 1000 / 1002, 1e-12);  // fy kept in it
  EXPECT_EQ(m.make, "");  // the file names no camera: none is made up
}

TEST(CameraModel, CalibrateCameraOutputGetsItsSensorFromTheFocalLengthInMm) {
  // calibrateCamera writes pixels only: a lens's focal length in mm gives the pixel
  // pitch, so the sensor size (and each axis's own focal length survives in it).
  const auto write = [](const fs::path& p, bool withFocal) {
    cv::FileStorage out(p.string(), cv::FileStorage::WRITE);
    out << "image_width" << 1280 << "image_height" << 720;
    out << "camera_matrix" << (cv::Mat_<double>(3, 3) << 1000, 0, 640.5, 0, 1002, 360.25, 0, 0, 1);
    out << "distortion_coefficients" << (cv::Mat_<double>(1, 5) << -0.1, 0.05, 0, 0, 0);
    if (withFocal) out << "focal_length_mm" << 4.0;
  };
  CameraModel m;
  std::string error;
  const fs::path withFocal = tempDir() / "calib-focal.yaml";
  write(withFocal, true);
  ASSERT_TRUE(loadCameraModel(withFocal.string(), m, error)) << error;
  EXPECT_NEAR(m.sensorWidthMm, 4.0 * 1280 / 1000, 1e-12);
  EXPECT_NEAR(m.sensorHeightMm, 4.0 * 720 / 1002, 1e-12);
  EXPECT_EQ(m.physicalSizeWarning(), "");

  const fs::path pixelsOnly = tempDir() / "calib-pixels.yaml";
  write(pixelsOnly, false);
  CameraModel p;
  ASSERT_TRUE(loadCameraModel(pixelsOnly.string(), p, error)) << error;
  EXPECT_TRUE(std::isnan(p.sensorWidthMm));
  const std::string w = p.physicalSizeWarning();
  EXPECT_NE(w.find("sensor_width_mm or focal_length_mm"), std::string::npos) << w;
  EXPECT_EQ(CameraModel{}.physicalSizeWarning(), "");  // no calibration: another warning
}

TEST(CameraModel, ReadsTheShippedExample) {
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(KEYFRAMED_SOURCE_DIR "/config/camera-example.yaml", m, error))
      << error;
  EXPECT_TRUE(m.calibrated());
  EXPECT_EQ(m.make, "ExampleCam");
  EXPECT_DOUBLE_EQ(m.focalLengthMm, 4.41);
  EXPECT_DOUBLE_EQ(m.sensorHeightMm, 3.47);
  EXPECT_EQ(m.lens, CameraModel::Lens::Pinhole);

  CameraModel f;
  ASSERT_TRUE(loadCameraModel(KEYFRAMED_SOURCE_DIR "/config/camera-fisheye-example.yaml", f, error))
      << error;
  EXPECT_EQ(f.lens, CameraModel::Lens::Fisheye);
  EXPECT_EQ(f.distortion.size(), 4u);
  EXPECT_EQ(f.lensModel().kind, LensModel::Kind::Fisheye);
  EXPECT_STREQ(f.lensModel().invalidReason(), "");
  EXPECT_EQ(m.lensModel().kind, LensModel::Kind::Pinhole);  // its k1..k3 are not zero
}

TEST(CameraModel, ReadsSynthIntrinsicsJson) {
  const fs::path p = tempFile("intrinsics.json", R"({
  "width": 960, "height": 540, "fx": 685.5, "fy": 685.5, "cx": 479.5, "cy": 269.5,
  "distortion": [0.0, 0.0, 0.0, 0.0, 0.0], "model": "pinhole",
  "sensor_width_mm": 6.17, "sensor_height_mm": 3.470625, "focal_length_mm": 4.405,
  "fps": 30.0, "mount_pitch_deg": -90.0
})");
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(p.string(), m, error)) << error;
  EXPECT_TRUE(m.calibrated());
  EXPECT_EQ(m.width, 960);
  EXPECT_DOUBLE_EQ(m.cy, 269.5);
  EXPECT_EQ(m.model, "");  // "model" there is the projection, not the camera name
  EXPECT_DOUBLE_EQ(m.focalLengthMm, 4.405);
  EXPECT_NEAR(m.focalLength35mm(), 685.5 * 36 / 960, 1e-12);
}

TEST(CameraModel, ReadsTomlAndDerivesFocalLength) {
  const fs::path p = tempFile("cam.toml", R"([camera]
make = "Acme"
model = "Eye 2"
width = 4000
height = 3000
fx = 2800
fy = 2800.5
cx = 1999.5
cy = 1499.5
distortion = [0.01, -0.02, 0.0, 0.0]
sensor_width_mm = 6.4
)");
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(p.string(), m, error)) << error;
  EXPECT_EQ(m.make, "Acme");
  EXPECT_EQ(m.model, "Eye 2");
  EXPECT_DOUBLE_EQ(m.fy, 2800.5);
  EXPECT_EQ(m.distortion.size(), 4u);
  EXPECT_NEAR(m.focalLengthMm, 2800 * 6.4 / 4000, 1e-12);
  EXPECT_NEAR(m.focalLength35mm(), 2800 * 36.0 / 4000, 1e-12);
}

TEST(CameraModel, TomlUnknownKeyNamesFileLineAndKey) {
  const fs::path p = tempFile("typo.toml", "[camera]\nwidth = 640\nheight = 480\nfocal_mm = 4\n");
  CameraModel m;
  std::string error;
  EXPECT_FALSE(loadCameraModel(p.string(), m, error));
  EXPECT_NE(error.find("typo.toml:4:"), std::string::npos) << error;
  EXPECT_NE(error.find("camera.focal_mm"), std::string::npos) << error;
}

TEST(CameraModel, UncalibratedTomlKeepsOnlyWhatIsKnown) {
  const fs::path p =
      tempFile("lens.toml", "[camera]\nfocal_length_mm = 4.5\nsensor_width_mm = 6.0\n");
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(p.string(), m, error)) << error;
  EXPECT_FALSE(m.calibrated());
  EXPECT_NEAR(m.focalLength35mm(), 4.5 * 36 / 6.0, 1e-12);
}

TEST(CameraModel, BadFilesGiveAOneLineErrorNotACrash) {
  std::string dotted = "[";  // [a.a.a. ... .a]: a table 20,001 keys deep
  for (int i = 0; i < 20000; ++i) dotted += "a.";
  dotted += "a]\n";
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"empty.yaml", ""},
      {"garbage.yaml", "%YAML:1.0\ncamera_matrix: [1, 2\n  ::: }"},
      {"garbage.json", "{ \"fx\": "},
      {"nokeys.yaml", "%YAML:1.0\nfoo: 1\n"},
      {"badmatrix.yaml", "%YAML:1.0\nimage_width: 10\nimage_height: 10\ncamera_matrix: 3\n"},
      {"bad.toml", "[camera\nwidth = 1"},
      {"badtype.toml", "[camera]\nwidth = \"wide\"\n"},
      {"partial.toml", "[camera]\nwidth = 640\nheight = 480\nfx = 500\n"},
      {"binary.xml", std::string("\x01\x02\xff\xfe<<", 6)},
      // a number written as a string: not "uncalibrated", an error
      {"stringfx.json",
       R"({"width": 480, "height": 270, "fx": "228.5", "fy": 228.5, "cx": 240, "cy": 135})"},
      {"stringsensor.json",
       R"({"width": 480, "height": 270, "fx": 228.5, "fy": 228.5, "cx": 240, "cy": 135,
           "sensor_width_mm": "6.4"})"},
      // nested far deeper than any calibration: refused before a parser recurses
      {"deep.toml", std::string(50000, '[') + "camera" + std::string(50000, ']')},
      {"deepdots.toml", dotted},
      {"deep.json", std::string(100000, '[') + std::string(100000, ']')},
      {"big.yaml", "%YAML:1.0\n# " + std::string(2 << 20, 'x') + "\n"},
  };
  for (const auto& [name, text] : cases) {
    CameraModel m;
    std::string error;
    EXPECT_FALSE(loadCameraModel(tempFile(name, text).string(), m, error)) << name;
    EXPECT_FALSE(error.empty()) << name;
    EXPECT_EQ(error.find('\n'), std::string::npos) << name << ": " << error;
  }
  CameraModel m;
  std::string error;
  EXPECT_FALSE(loadCameraModel("/nonexistent/cam.yaml", m, error));
  EXPECT_NE(error.find("cannot open"), std::string::npos);
  // Said in words, not as the name of an OpenCV check ("buf", "parseValue").
  for (const auto& [name, text, words] :
       std::vector<std::tuple<std::string, std::string, std::string>>{
           {"blank.yaml", " \n\n", "empty"},
           {"syntax.yaml", "%YAML:1.0\ncamera_matrix: [1, 2\n  ::: }",
            "not a calibration OpenCV can read"},
           {"floatsize.json",
            R"({"width": 480.0, "height": 270, "fx": 228.5, "fy": 228.5, "cx": 240, "cy": 135})",
            "width must be an integer"},
           // TOML's nan: named, with its line, not "fx, fy, cx, cy go together"
           {"nan.toml",
            "[camera]\nwidth = 960\nheight = 540\nfx = 600\nfy = 600\ncx = 479.5\ncy = nan\n",
            ":7: camera.cy must be a finite number"},
           {"partial-line.toml", "[camera]\nwidth = 640\nheight = 480\nfx = 500\n",
            ":1: camera.fx, fy, cx, cy go together"}}) {
    EXPECT_FALSE(loadCameraModel(tempFile(name, text).string(), m, error)) << name;
    EXPECT_NE(error.find(words), std::string::npos) << name << ": " << error;
  }
}

TEST(CameraModel, ImplausibleIntrinsicsAreRefusedNotTagged) {
  // An intrinsics.json with one value changed: each is refused, naming the rule.
  const auto json = [](const std::string& field, const std::string& value) {
    std::map<std::string, std::string> v = {{"width", "960"},
                                            {"height", "540"},
                                            {"fx", "685.5"},
                                            {"fy", "685.5"},
                                            {"cx", "479.5"},
                                            {"cy", "269.5"},
                                            {"make", "\"Acme\""},
                                            {"sensor_width_mm", "6.17"},
                                            {"focal_length_mm", "4.405"}};
    if (value.empty())
      v.erase(field);
    else
      v[field] = value;
    std::string text = "{";
    for (const auto& [k, x] : v) text += (text.size() > 1 ? ", \"" : "\"") + k + "\": " + x;
    return text + "}";
  };
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(tempFile("ok.json", json("fx", "685.5")).string(), m, error))
      << error;
  EXPECT_EQ(m.lensWarning(), "");
  const std::vector<std::tuple<std::string, std::string, std::string>> cases = {
      {"cx", "", "go together"},           // left out: not "uncalibrated"
      {"cx", ".nan", "go together"},       // NaN in the file
      {"fx", ".nan", "go together"},       //
      {"cx", "1e300", "principal point"},  // a principal point of 1e62 mm in the tags
      {"cy", "-600", "principal point"},   //
      {"fx", "1e300", "fx and fy"},        //
      {"fy", "1e-300", "fx and fy"},       //
      {"sensor_width_mm", "1e308", "sensor sizes"},
      {"focal_length_mm", "50000", "focal length in mm"},
      {"width", "2147483647", "image size"},
      {"distortion", "[-1e300, 0, 0, 0, 0]", "distortion terms must be within"},
      {"distortion", "[0.1, 2e6, 0, 0]", "distortion terms must be within"},
  };
  for (const auto& [field, value, words] : cases) {
    SCOPED_TRACE(field + " = " + value);
    const fs::path p = tempFile("bad.json", json(field, value));
    error.clear();
    EXPECT_FALSE(loadCameraModel(p.string(), m, error));
    EXPECT_NE(error.find(words), std::string::npos) << error;
    EXPECT_EQ(error.find('\n'), std::string::npos) << error;
  }
  // The same in OpenCV's calibrateCamera layout: a NaN in the camera matrix, and a
  // make or model EXIF cannot hold (as --make and tagging.make refuse it).
  const auto yaml = [](const std::string& cx, const std::string& make) {
    return "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\nmake: \"" + make +
           "\"\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
           "   data: [ 500., 0., " +
           cx + ", 0., 500., 240., 0., 0., 1. ]\n";
  };
  EXPECT_FALSE(loadCameraModel(tempFile("nan.yaml", yaml(".nan", "Acme")).string(), m, error));
  EXPECT_NE(error.find("go together"), std::string::npos) << error;
  for (const std::string& make : {std::string(64, 'A'), std::string("Cam\xc3\xa9ra")}) {
    EXPECT_FALSE(loadCameraModel(tempFile("make.yaml", yaml("320.", make)).string(), m, error))
        << make;
    EXPECT_NE(error.find("make must be at most 63 printable ASCII"), std::string::npos) << error;
  }
}

TEST(CameraModel, ADistortionThatFoldsBeforeTheCornersIsWarnedAbout) {
  CameraModel c;
  c.width = 480;
  c.height = 270;
  c.fx = c.fy = 300.0;
  c.cx = 239.5;
  c.cy = 134.5;
  c.distortion = {-0.3, 0.1, 0.0, 0.0, 0.0};  // a wide lens, monotonic across the image
  EXPECT_EQ(c.lensWarning(), "");
  c.distortion = {-10.0, 0.0, 0.0, 0.0, 0.0};  // folds at r = 0.18, the corners at 0.9
  const std::string w = c.lensWarning();
  EXPECT_NE(w.find("folds back"), std::string::npos) << w;
  // A fold so close to the centre that the first step past it throws the point across
  // the centre (the distorted radius comes out negative): folded, not far out.
  c.distortion = {-1e6, 0.0, 0.0, 0.0, 0.0};
  EXPECT_NE(c.lensWarning().find("folds back 0 %"), std::string::npos) << c.lensWarning();
  EXPECT_EQ(CameraModel{}.lensWarning(), "");  // no calibration, nothing to say
}

TEST(CameraModel, AFifoOrADirectoryIsRefusedUnread) {
  const fs::path fifo = tempDir() / "calib.fifo";
  fs::remove(fifo);
  ASSERT_EQ(mkfifo(fifo.c_str(), 0600), 0);  // no writer: an open would wait forever
  CameraModel m;
  std::string error;
  EXPECT_FALSE(loadCameraModel(fifo.string(), m, error));
  EXPECT_NE(error.find("not a regular file"), std::string::npos) << error;
  EXPECT_FALSE(loadCameraModel(tempDir().string(), m, error));
  EXPECT_NE(error.find("not a regular file"), std::string::npos) << error;
  fs::remove(fifo);
}

TEST(CameraModel, FisheyeCalibrationReadsAsFisheye) {
  // OpenCV's calibration sample with a fisheye lens: k1-k4 of the equidistant model,
  // which taken as k1, k2, p1, p2 would tag every keyframe with a wrong lens.
  const fs::path p = tempDir() / "fisheye.yaml";
  {
    cv::FileStorage out(p.string(), cv::FileStorage::WRITE);
    out << "image_width" << 1280 << "image_height" << 720;
    out << "camera_matrix" << (cv::Mat_<double>(3, 3) << 600, 0, 640, 0, 600, 360, 0, 0, 1);
    out << "distortion_coefficients" << (cv::Mat_<double>(4, 1) << 0.05, -0.01, 0.002, -0.0005);
    out << "fisheye_model" << 1;
  }
  CameraModel m;
  std::string error;
  ASSERT_TRUE(loadCameraModel(p.string(), m, error)) << error;
  EXPECT_EQ(m.lens, CameraModel::Lens::Fisheye);
  EXPECT_EQ(m.distortion, (std::vector<double>{0.05, -0.01, 0.002, -0.0005}));
  EXPECT_DOUBLE_EQ(m.fx, 600);
  // Scaling keeps the lens and its (angle-based) distortion.
  const CameraModel half = m.scaledTo(640, 360);
  EXPECT_EQ(half.lens, CameraModel::Lens::Fisheye);
  EXPECT_DOUBLE_EQ(half.fx, 300);
  EXPECT_EQ(half.distortion, m.distortion);

  // A fisheye has exactly k1..k4: five terms are a mistake, not a crop.
  {
    cv::FileStorage out(p.string(), cv::FileStorage::WRITE);
    out << "image_width" << 1280 << "image_height" << 720;
    out << "camera_matrix" << (cv::Mat_<double>(3, 3) << 600, 0, 640, 0, 600, 360, 0, 0, 1);
    out << "distortion_coefficients" << (cv::Mat_<double>(5, 1) << 0.05, -0.01, 0, 0, 0.001);
    out << "fisheye_model" << 1;
  }
  CameraModel five;
  EXPECT_FALSE(loadCameraModel(p.string(), five, error));
  EXPECT_NE(error.find("k1, k2, k3, k4"), std::string::npos) << error;
  EXPECT_NE(error.find("fisheye.yaml"), std::string::npos) << error;

  // The same file from a pinhole calibration (fisheye_model: 0) reads as a pinhole.
  {
    cv::FileStorage out(p.string(), cv::FileStorage::WRITE);
    out << "image_width" << 1280 << "image_height" << 720;
    out << "camera_matrix" << (cv::Mat_<double>(3, 3) << 600, 0, 640, 0, 600, 360, 0, 0, 1);
    out << "distortion_coefficients" << (cv::Mat_<double>(5, 1) << 0.05, -0.01, 0, 0, 0.001);
    out << "fisheye_model" << 0;
  }
  CameraModel pin;
  EXPECT_TRUE(loadCameraModel(p.string(), pin, error)) << error;
  EXPECT_EQ(pin.lens, CameraModel::Lens::Pinhole);

  const fs::path j = tempFile("fisheye.json", R"({"width": 960, "height": 540, "fx": 400,
    "fy": 400, "cx": 480, "cy": 270, "model": "fisheye", "distortion": [0.1, 0, 0, 0]})");
  CameraModel n;
  ASSERT_TRUE(loadCameraModel(j.string(), n, error)) << error;
  EXPECT_EQ(n.lens, CameraModel::Lens::Fisheye);
  const fs::path o = tempFile("omni.json", R"({"width": 960, "height": 540, "fx": 400,
    "fy": 400, "cx": 480, "cy": 270, "model": "omnidirectional"})");
  EXPECT_FALSE(loadCameraModel(o.string(), n, error));
  EXPECT_NE(error.find("\"omnidirectional\" is not supported"), std::string::npos) << error;

  const fs::path t = tempFile("fisheye.toml", R"([camera]
lens = "fisheye"
width = 1280
height = 720
fx = 600.0
fy = 600.0
cx = 640.0
cy = 360.0
distortion = [0.05, -0.01, 0.002, -0.0005]
)");
  CameraModel tm;
  ASSERT_TRUE(loadCameraModel(t.string(), tm, error)) << error;
  EXPECT_EQ(tm.lens, CameraModel::Lens::Fisheye);
  const fs::path bad = tempFile("bad-lens.toml", "[camera]\nlens = \"fish\"\n");
  EXPECT_FALSE(loadCameraModel(bad.string(), tm, error));
  EXPECT_NE(error.find("bad-lens.toml:2: camera.lens must be \"pinhole\" or \"fisheye\""),
            std::string::npos)
      << error;
}

TEST(CameraModel, TomlTextRoundTripsTheWholeModel) {
  // What a flight record keeps of the camera, read back as the same model: a replay
  // tags with the flight's make, model, sensor size and lens.
  CameraModel m;
  m.make = "Acme \"Aero\"";  // quotes survive TOML's escaping
  m.model = "X\\1";
  m.lens = CameraModel::Lens::Fisheye;
  m.width = 1280;
  m.height = 720;
  m.fx = 600.125;
  m.fy = 599.875;
  m.cx = 640.5;
  m.cy = 360.25;
  m.distortion = {0.05, -0.01, 0.002, -0.0005};
  m.sensorWidthMm = 6.17;
  m.sensorHeightMm = 3.47;
  m.focalLengthMm = 2.9;
  CameraModel back;
  std::string error;
  ASSERT_TRUE(cameraFromTomlText("[camera]\n" + cameraTomlKeys(m), "record", back, error))
      << error << "\n"
      << cameraTomlKeys(m);
  EXPECT_EQ(back.make, m.make);
  EXPECT_EQ(back.model, m.model);
  EXPECT_EQ(back.lens, m.lens);
  EXPECT_EQ(back.width, 1280);
  EXPECT_EQ(back.height, 720);
  EXPECT_EQ(back.fx, m.fx);  // exactly: the shortest text that reads back the same
  EXPECT_EQ(back.fy, m.fy);
  EXPECT_EQ(back.cx, m.cx);
  EXPECT_EQ(back.cy, m.cy);
  EXPECT_EQ(back.distortion, m.distortion);
  EXPECT_EQ(back.sensorWidthMm, m.sensorWidthMm);
  EXPECT_EQ(back.sensorHeightMm, m.sensorHeightMm);
  EXPECT_EQ(back.focalLengthMm, m.focalLengthMm);

  // Make and model alone (no calibration) stay uncalibrated.
  CameraModel named;
  named.make = "Acme";
  ASSERT_TRUE(cameraFromTomlText("[camera]\n" + cameraTomlKeys(named), "record", back, error))
      << error;
  EXPECT_FALSE(back.calibrated());
  EXPECT_EQ(back.make, "Acme");

  // Anyone's file: what is not a [camera] table alone is an error naming the origin,
  // never a crash (nor a recursion as deep as the text nests).
  for (const std::string& bad :
       {std::string("[camera]\nfx = 1\n"), std::string("[camera]\nsize = 3\n"),
        std::string("[other]\nmake = \"a\"\n"), std::string("[camera\n"),
        std::string("[camera]\nmake = \"a\"\n[more]\n"), "x = " + std::string(100000, '[')}) {
    error.clear();
    EXPECT_FALSE(cameraFromTomlText(bad, "the record's camera", back, error)) << bad;
    EXPECT_EQ(error.rfind("the record's camera", 0), 0u) << error;
  }
}

TEST(CameraModel, ScaledToKeepsTheFieldOfView) {
  CameraModel m;
  m.width = 1920;
  m.height = 1080;
  m.fx = m.fy = 1400;
  m.cx = 959.5;
  m.cy = 539.5;
  const CameraModel h = m.scaledTo(960, 540);
  EXPECT_DOUBLE_EQ(h.fx, 700);
  EXPECT_DOUBLE_EQ(h.cx, 479.5);  // still the centre in OpenCV's pixel-centre convention
  EXPECT_DOUBLE_EQ(h.cy, 269.5);
  EXPECT_DOUBLE_EQ(h.focalLength35mm(), m.focalLength35mm());
}

// ---------------------------------------------------------------- mount / Pix4D angles

Quaternion headingQ(double yawDeg) {
  const double h = yawDeg * std::numbers::pi / 360.0;
  return {std::cos(h), 0, 0, std::sin(h)};  // rotation about NED down: heading
}

double angleDiff(double a, double b) {
  return std::remainder(a - b, 360.0);
}

TEST(CameraMount, Pix4dAnglesRoundTrip) {
  for (const Pix4dAngles a : {Pix4dAngles{10, 20, 30}, Pix4dAngles{350, -45, 5},
                              Pix4dAngles{181, 60, -170}, Pix4dAngles{0.5, 0, 0}}) {
    const Pix4dAngles b = pix4dAngles(fromPix4dAngles(a));
    EXPECT_NEAR(angleDiff(b.yawDeg, a.yawDeg), 0, 1e-9);
    EXPECT_NEAR(b.pitchDeg, a.pitchDeg, 1e-9);
    EXPECT_NEAR(angleDiff(b.rollDeg, a.rollDeg), 0, 1e-9);
  }
}

TEST(CameraMount, NadirCameraHeadingNorthIsAllZero) {
  // Pix4D: yaw 0, pitch 0, roll 0 = nadir, image top to the north.
  const Pix4dAngles a = pix4dAngles(cameraToNed(Quaternion{}, CameraMount{}));
  EXPECT_NEAR(angleDiff(a.yawDeg, 0), 0, 1e-9);
  EXPECT_NEAR(a.pitchDeg, 0, 1e-9);
  EXPECT_NEAR(a.rollDeg, 0, 1e-9);
}

TEST(CameraMount, HeadingEastTurnsYawBy90) {
  const Pix4dAngles a = pix4dAngles(cameraToNed(headingQ(90), CameraMount{}));
  EXPECT_NEAR(a.yawDeg, 90, 1e-9);  // image top to the east
  EXPECT_NEAR(a.pitchDeg, 0, 1e-9);
  const Pix4dAngles w = pix4dAngles(cameraToNed(headingQ(-90), CameraMount{}));
  EXPECT_NEAR(w.yawDeg, 270, 1e-9);  // Pix4D's own example: 270 = top to the west
}

TEST(CameraMount, GimbalAttitudeIsTheCamerasWhateverTheBody) {
  // A gimbal 55 deg down, heading 200: the same camera as a fixed 55 deg mount on a
  // level body heading 200, and independent of how the body is tilted.
  const Quaternion gimbal =
      quaternionFromEuler(0, -55 * std::numbers::pi / 180, 200 * std::numbers::pi / 180);
  const Pix4dAngles g = pix4dAngles(cameraToNed(gimbal, CameraMount{0, 0, 0}));
  const Pix4dAngles f = pix4dAngles(cameraToNed(headingQ(200), CameraMount{0, -55, 0}));
  EXPECT_NEAR(g.pitchDeg, f.pitchDeg, 1e-9);
  EXPECT_NEAR(angleDiff(g.yawDeg, f.yawDeg), 0, 1e-9);
  EXPECT_NEAR(angleDiff(g.rollDeg, f.rollDeg), 0, 1e-9);
  // Straight down with the gimbal's nose north: Pix4D's all-zero.
  const Pix4dAngles n = pix4dAngles(
      cameraToNed(quaternionFromEuler(0, -std::numbers::pi / 2, 0), CameraMount{0, 0, 0}));
  EXPECT_NEAR(n.pitchDeg, 0, 1e-6);
  EXPECT_NEAR(angleDiff(n.yawDeg, 0), 0, 1e-6);
}

TEST(CameraMount, ForwardCameraHasPitch90AndObliqueInBetween) {
  const Pix4dAngles f = pix4dAngles(cameraToNed(headingQ(30), CameraMount{0, 0, 0}));
  EXPECT_NEAR(f.pitchDeg, 90, 1e-6);
  EXPECT_NEAR(f.yawDeg, 30, 1e-6);
  // synth's orbit: camera 55 deg down from the horizon -> Pix4D pitch 35.
  const Pix4dAngles o = pix4dAngles(cameraToNed(headingQ(200), CameraMount{0, -55, 0}));
  EXPECT_NEAR(o.pitchDeg, 35, 1e-9);
  EXPECT_NEAR(o.yawDeg, 200, 1e-9);
  EXPECT_NEAR(o.rollDeg, 0, 1e-9);
}

TEST(CameraMount, CameraAxesFollowTheMountConvention) {
  // Nadir mount: the optical axis (camera z) points down (NED +z) and the image top
  // (camera -y) toward the nose (north when heading north).
  const Quaternion q = cameraToNed(Quaternion{}, CameraMount{});
  const auto rotate = [&](double x, double y, double z) {
    // v' = q v q^-1 via the matrix form
    const double w = q.w, a = q.x, b = q.y, c = q.z;
    return std::array<double, 3>{
        (1 - 2 * (b * b + c * c)) * x + 2 * (a * b - w * c) * y + 2 * (a * c + w * b) * z,
        2 * (a * b + w * c) * x + (1 - 2 * (a * a + c * c)) * y + 2 * (b * c - w * a) * z,
        2 * (a * c - w * b) * x + 2 * (b * c + w * a) * y + (1 - 2 * (a * a + b * b)) * z};
  };
  const auto axis = rotate(0, 0, 1);
  EXPECT_NEAR(axis[2], 1, 1e-12);
  const auto up = rotate(0, -1, 0);
  EXPECT_NEAR(up[0], 1, 1e-12);
  // A vehicle rolled right by 10 deg tilts the nadir camera: Pix4D roll follows.
  const double r = 10 * std::numbers::pi / 360.0;
  const Pix4dAngles a = pix4dAngles(cameraToNed({std::cos(r), std::sin(r), 0, 0}, CameraMount{}));
  EXPECT_NEAR(a.rollDeg, 10, 1e-9);
  EXPECT_NEAR(a.pitchDeg, 0, 1e-9);
}

// A fisheye camera as cv::fisheye::calibrate leaves it.
CameraModel fisheyeCamera(int w, int h, double fx, double fy, std::vector<double> k) {
  CameraModel c;
  c.lens = CameraModel::Lens::Fisheye;
  c.width = w;
  c.height = h;
  c.fx = fx;
  c.fy = fy;
  c.cx = (w - 1) / 2.0 + 1.75;
  c.cy = (h - 1) / 2.0 - 0.75;
  c.distortion = std::move(k);
  return c;
}

// The largest distance, over rays spread across the image, between where OpenCV's
// fisheye model projects a ray (cv::fisheye::projectPoints) and where Pix4D's published
// model does with the tags' values. The corners' directions are among them.
double pix4dProjectionError(const CameraModel& cam, const Pix4dFisheye& p) {
  std::vector<double> phis;
  for (int i = 0; i < 72; ++i) phis.push_back(2.0 * std::numbers::pi * i / 72.0);
  for (const double u : {-0.5, cam.width - 0.5}) {
    for (const double v : {-0.5, cam.height - 0.5})
      phis.push_back(std::atan2((v - cam.cy) / cam.fy, (u - cam.cx) / cam.fx));
  }
  std::vector<cv::Point3d> rays;
  std::vector<std::pair<double, double>> angles;  // theta, phi
  const double maxTheta = std::min(p.maxAngleDeg, 89.9) * std::numbers::pi / 180.0;
  for (int i = 1; i <= 100; ++i) {
    const double theta = maxTheta * i / 100.0;
    for (const double phi : phis) {
      rays.emplace_back(std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi),
                        std::cos(theta));
      angles.emplace_back(theta, phi);
    }
  }
  const cv::Matx33d k(cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
  const cv::Vec4d d(cam.distortion[0], cam.distortion[1], cam.distortion[2], cam.distortion[3]);
  std::vector<cv::Point2d> px;
  cv::fisheye::projectPoints(rays, px, cv::Vec3d(), cv::Vec3d(), k, d);
  double worst = 0.0;
  for (std::size_t i = 0; i < px.size(); ++i) {
    if (px[i].x < -0.5 - 1e-6 || px[i].y < -0.5 - 1e-6 || px[i].x > cam.width - 0.5 + 1e-6 ||
        px[i].y > cam.height - 0.5 + 1e-6)
      continue;  // outside the image
    const auto [theta, phi] = angles[i];
    const double t = 2.0 / std::numbers::pi * theta;
    const auto& q = p.polynomial;
    const double rho = q[0] + t * (q[1] + t * (q[2] + t * q[3]));
    const double xh = rho * std::cos(phi), yh = rho * std::sin(phi);
    const cv::Point2d back(p.affine[0] * xh + p.affine[1] * yh + cam.cx,
                           p.affine[2] * xh + p.affine[3] * yh + cam.cy);
    worst = std::max(worst, cv::norm(back - px[i]));
  }
  return worst;
}

TEST(Pix4dFisheye, TheFittedModelProjectsAsOpenCvsWithinItsStatedError) {
  // 120 degrees across a 16:9 frame with fx != fy, a 4:3 one, a 1080p one reaching 89
  // degrees in its corners.
  for (const CameraModel& cam :
       {fisheyeCamera(480, 270, 220.0, 221.0, {0.032, -0.0081, 0.0017, -0.0003}),
        fisheyeCamera(320, 240, 120.0, 120.0, {0.031, -0.0072, 0.0011, -0.00019}),
        fisheyeCamera(1920, 1080, 700.0, 700.0, {0.012, -0.004, 0.0009, -0.0001})}) {
    const auto p = pix4dFisheye(cam);
    ASSERT_TRUE(p) << cam.width;
    EXPECT_EQ(p->polynomial[0], 0.0);
    EXPECT_EQ(p->polynomial[1], 1.0);
    EXPECT_EQ(p->affine[1], 0.0);
    EXPECT_EQ(p->affine[2], 0.0);
    // C ~ the image circle's radius at 90 degrees: fx * pi / 2 for an equidistant lens.
    EXPECT_NEAR(p->affine[0] / (cam.fx * std::numbers::pi / 2), 1.0, 0.1) << cam.width;
    EXPECT_NEAR(p->affine[3] / p->affine[0], cam.fy / cam.fx, 1e-12);
    const double measured = pix4dProjectionError(cam, *p);
    EXPECT_LT(measured, 0.5) << cam.width;
    // The error the fit states is what the projection shows.
    EXPECT_NEAR(measured, p->maxErrorPx, 0.02 + 0.1 * p->maxErrorPx) << cam.width;
    EXPECT_EQ(pix4dFisheyeWarning(cam), "") << cam.width;
  }
}

TEST(Pix4dFisheye, ALensTheCubicCannotFollowIsSaidAndOthersGetNone) {
  // Strong higher-order terms out to 90 degrees: the cubic is pixels out, and said.
  const CameraModel wide = fisheyeCamera(1920, 1080, 500.0, 500.0, {0.1, -0.05, 0.02, -0.004});
  const auto p = pix4dFisheye(wide);
  ASSERT_TRUE(p);
  EXPECT_GT(p->maxErrorPx, 2.0);
  EXPECT_NEAR(pix4dProjectionError(wide, *p), p->maxErrorPx, 0.1 * p->maxErrorPx);
  const std::string w = pix4dFisheyeWarning(wide);
  EXPECT_NE(w.find("Pix4D's fisheye model"), std::string::npos) << w;
  EXPECT_NE(w.find("px only"), std::string::npos) << w;
  // A pinhole, an uncalibrated fisheye, one whose polynomial folds back before the
  // corners: no Pix4D fisheye model.
  CameraModel pinhole = wide;
  pinhole.lens = CameraModel::Lens::Pinhole;
  EXPECT_FALSE(pix4dFisheye(pinhole));
  CameraModel bare = wide;
  bare.fx = NAN;
  EXPECT_FALSE(pix4dFisheye(bare));
  EXPECT_FALSE(pix4dFisheye(fisheyeCamera(1920, 1080, 300.0, 300.0, {-0.3, 0.0, 0.0, 0.0})));
  EXPECT_EQ(pix4dFisheyeWarning(pinhole), "");
}

}  // namespace
}  // namespace keyframed
