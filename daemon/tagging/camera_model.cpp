#include "tagging/camera_model.h"
#include "tagging/camera_model_toml.h"

#include "core/nesting.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include <toml++/toml.h>
#include <opencv2/core.hpp>

namespace keyframed {

bool CameraModel::calibrated() const {
  return width > 0 && height > 0 && std::isfinite(fx) && std::isfinite(fy) && std::isfinite(cx) &&
         std::isfinite(cy);
}

double CameraModel::focalLength35mm() const {
  if (width > 0 && height > 0 && std::isfinite(fx) && std::isfinite(fy)) {
    return width >= height ? fx * 36.0 / width : fy * 36.0 / height;
  }
  if (std::isfinite(focalLengthMm) && std::isfinite(sensorWidthMm)) {
    const double longSide =
        std::isfinite(sensorHeightMm) ? std::max(sensorWidthMm, sensorHeightMm) : sensorWidthMm;
    return focalLengthMm * 36.0 / longSide;
  }
  return NAN;
}

CameraModel CameraModel::scaledTo(int w, int h) const {
  CameraModel out = *this;
  out.width = w;
  out.height = h;
  if (width > 0 && height > 0) {
    const double sx = static_cast<double>(w) / width;
    const double sy = static_cast<double>(h) / height;
    out.fx = fx * sx;
    out.fy = fy * sy;
    out.cx = (cx + 0.5) * sx - 0.5;
    out.cy = (cy + 0.5) * sy - 0.5;
  }
  return out;
}

std::string CameraModel::aspectMismatch(int w, int h) const {
  if (width <= 0 || height <= 0 || w <= 0 || h <= 0) return {};
  const double mine = static_cast<double>(width) / height;
  const double theirs = static_cast<double>(w) / h;
  if (std::fabs(theirs / mine - 1.0) <= 0.005) return {};
  char buf[320];
  std::snprintf(buf, sizeof buf,
                "the calibration is for %dx%d (aspect %.3f), the frames are %dx%d (aspect "
                "%.3f): another sensor mode crops rather than scales, so the intrinsics "
                "scaled to it would be wrong: keyframes are tagged without them; calibrate "
                "in this mode",
                width, height, mine, w, h, theirs);
  return buf;
}

CameraModel CameraModel::withoutIntrinsics() const {
  CameraModel out;
  out.make = make;
  out.model = model;
  out.lens = lens;
  out.focalLengthMm = focalLengthMm;
  return out;
}

std::string CameraModel::physicalSizeWarning() const {
  if (!calibrated() || std::isfinite(sensorWidthMm)) return {};
  return "the calibration gives no sensor_width_mm or focal_length_mm: the principal point, "
         "distortion centre and focal length in mm are not tagged (Pix4D, COLMAP's and ODM's "
         "exact focal need them); add either";
}

std::string CameraModel::lensWarning() const {
  const LensModel lm = lensModel();
  if (!lm.active() || lm.invalidReason()[0] != '\0') return {};
  const double reach = lm.monotonicRadius();
  // How far out, in the corners' directions, the lens still draws rays (on the
  // normalised image plane, distorted), against how far out the corners are.
  double worst = 1e9;
  for (const auto& [u, v] : {std::pair{-0.5, -0.5},
                             {width - 0.5, -0.5},
                             {-0.5, height - 0.5},
                             {width - 0.5, height - 0.5}}) {
    const double dx = (u - cx) / fx, dy = (v - cy) / fy;
    const double corner = std::hypot(dx, dy);
    if (!(corner > 0.0)) continue;
    const cv::Point2d edge =
        lm.distort({cx + reach * fx * dx / corner, cy + reach * fy * dy / corner});
    // How far out along the corner's direction (a point thrown across the centre
    // counts as none, as does one the arithmetic lost).
    const double drawn = ((edge.x - cx) / fx * dx + (edge.y - cy) / fy * dy) / corner;
    worst = std::isfinite(drawn) ? std::min(worst, std::max(0.0, drawn) / corner) : 0.0;
  }
  if (worst >= 0.999) return {};
  char buf[320];
  std::snprintf(buf, sizeof buf,
                "the calibration's distortion folds back %.0f %% of the way to the image's "
                "corners: beyond, the image cannot be undistorted and the overlap analysis "
                "loses it (check the calibration: a k3 fitted without points near the edge "
                "does this)",
                100.0 * worst);
  return buf;
}

LensModel CameraModel::lensModel() const {
  LensModel out;
  const bool distorted =
      std::any_of(distortion.begin(), distortion.end(), [](double d) { return d != 0.0; });
  if (!calibrated() || (lens == Lens::Pinhole && !distorted)) return out;
  out.kind = lens == Lens::Fisheye ? LensModel::Kind::Fisheye : LensModel::Kind::Pinhole;
  out.width = width;
  out.height = height;
  out.fx = fx;
  out.fy = fy;
  out.cx = cx;
  out.cy = cy;
  if (lens == Lens::Fisheye) {
    for (std::size_t i = 0; i < 4 && i < distortion.size(); ++i) out.k[i] = distortion[i];
  } else {
    // OpenCV's k1, k2, p1, p2[, k3], the order LensModel keeps.
    for (std::size_t i = 0; i < 5 && i < distortion.size(); ++i) out.k[i] = distortion[i];
  }
  return out;
}

namespace {

bool endsWith(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && std::equal(suffix.rbegin(), suffix.rend(), s.rbegin(),
                                                 [](unsigned char a, unsigned char b) {
                                                   return std::tolower(a) == std::tolower(b);
                                                 });
}

// Checks shared by every format; fills derived values.
bool finish(const std::string& path, CameraModel& m, std::string& error) {
  const auto bad = [&](const std::string& what) {
    error = path + ": " + what;
    return false;
  };
  if (m.width < 0 || m.height < 0) return bad("negative image size");
  if ((m.width > 0) != (m.height > 0)) return bad("image width and height go together");
  if (m.width > 100000 || m.height > 100000) return bad("image size over 100000 pixels");
  for (double v : {m.fx, m.fy}) {
    if (!std::isnan(v) && !(v > 0.0 && std::isfinite(v))) return bad("focal length must be > 0");
  }
  // Partial intrinsics are a mistake in the file (a NaN in the camera matrix, a key
  // left out), not "uncalibrated": the keyframes would lose the lens without a word.
  const int known =
      std::isfinite(m.fx) + std::isfinite(m.fy) + std::isfinite(m.cx) + std::isfinite(m.cy);
  if (known != 0 && known != 4) return bad("fx, fy, cx, cy go together (four finite numbers)");
  if (known == 4 && m.width == 0) return bad("intrinsics need the image size");
  if (known == 4) {
    // Far beyond any lens: a typo or a unit mix-up, which would reach the tags as is.
    const double side = std::max(m.width, m.height);
    for (double f : {m.fx, m.fy}) {
      if (f < 0.01 * side || f > 1000.0 * side)
        return bad("fx and fy must lie between 1 % and 1000 times the image's longer side");
    }
    if (m.cx < -m.width || m.cx > 2.0 * m.width || m.cy < -m.height || m.cy > 2.0 * m.height)
      return bad("the principal point (cx, cy) must lie within an image size of the image");
  }
  for (double v : {m.sensorWidthMm, m.sensorHeightMm}) {
    if (!std::isnan(v) && !(v > 0.0 && v <= 1000.0))
      return bad("sensor sizes in mm must be > 0 and at most 1000");
  }
  if (!std::isnan(m.focalLengthMm) && !(m.focalLengthMm > 0.0 && m.focalLengthMm <= 10000.0))
    return bad("focal length in mm must be > 0 and at most 10000");
  for (const std::string* text : {&m.make, &m.model}) {
    if (std::string e = exifTextError(*text); !e.empty())
      return bad(std::string(text == &m.make ? "make " : "model ") + e);
  }
  if (m.lens == CameraModel::Lens::Fisheye) {
    // cv::fisheye::calibrate's D is exactly k1..k4.
    if (!m.distortion.empty() && m.distortion.size() != 4) {
      return bad("a fisheye lens's distortion is k1, k2, k3, k4 (4 terms)");
    }
  } else {
    // k1, k2, p1, p2, k3 is what the tags can carry; longer OpenCV vectors (rational
    // or thin-prism models) are accepted only when their extra terms are zero.
    if (!m.distortion.empty() && m.distortion.size() < 4) {
      return bad("distortion needs 4 or 5 terms");
    }
    for (std::size_t i = 5; i < m.distortion.size(); ++i) {
      if (m.distortion[i] != 0.0) return bad("only k1, k2, p1, p2, k3 distortion is supported");
    }
    if (m.distortion.size() > 5) m.distortion.resize(5);
  }
  for (double d : m.distortion) {
    if (!std::isfinite(d)) return bad("distortion terms must be finite");
    // No lens has terms this large; arithmetic on them overflows (calibrateCamera on
    // points that do not constrain them gives tens, hundreds at most).
    if (std::abs(d) > 1e6) return bad("distortion terms must be within -1e6..1e6");
  }
  if (std::isnan(m.focalLengthMm) && std::isfinite(m.fx) && std::isfinite(m.sensorWidthMm)) {
    m.focalLengthMm = m.fx * m.sensorWidthMm / m.width;
  }
  // The focal length in mm and in pixels give the pixel pitch, so the sensor size
  // (OpenCV's calibrateCamera output has neither; a lens's focal length is known).
  if (std::isnan(m.sensorWidthMm) && std::isfinite(m.focalLengthMm) && std::isfinite(m.fx) &&
      std::isfinite(m.fy)) {
    m.sensorWidthMm = m.focalLengthMm * m.width / m.fx;
  }
  // Pixels as tall as fx / fy times their width (one lens, one focal length): the tags'
  // focal plane resolution then gives each axis its own focal length back.
  if (std::isnan(m.sensorHeightMm) && std::isfinite(m.sensorWidthMm) && std::isfinite(m.fx) &&
      std::isfinite(m.fy)) {
    m.sensorHeightMm = m.sensorWidthMm * m.height / m.width * m.fx / m.fy;
  }
  return true;
}

// ---------------------------------------------------------------- OpenCV / JSON

double number(const cv::FileNode& n) {
  return (n.isReal() || n.isInt()) ? static_cast<double>(n) : NAN;
}

bool readFileStorage(const std::string& path, CameraModel& m, std::string& error) {
  cv::FileStorage fs(path, cv::FileStorage::READ);
  if (!fs.isOpened()) {
    error = path + ": not an OpenCV YAML/XML/JSON file";
    return false;
  }
  // Present means a number: "fx": "228.5" must not quietly become "no intrinsics".
  for (const char* key : {"fx", "fy", "cx", "cy", "width", "height", "image_width", "image_height",
                          "sensor_width_mm", "sensor_height_mm", "focal_length_mm"}) {
    const cv::FileNode n = fs[key];
    if (!n.empty() && !n.isReal() && !n.isInt()) {
      error = path + ": " + key + " is not a number";
      return false;
    }
  }
  const auto text = [](const cv::FileNode& n, std::string& dst) {
    if (n.isString()) dst = static_cast<std::string>(n);
  };
  // A size must be an integer: 480.0 is refused by name, not taken for "missing".
  std::string notInteger;
  const auto integer = [&](const cv::FileNode& n) {
    if (n.isReal() && notInteger.empty()) notInteger = n.name();
    return n.isInt() ? static_cast<int>(n) : 0;
  };
  // OpenCV's calibration sample writes fisheye_model: 1 for cv::fisheye::calibrate: its
  // four distortion terms are k1-k4 of the equidistant model, not k1, k2, p1, p2.
  if (const cv::FileNode f = fs["fisheye_model"];
      (f.isInt() && static_cast<int>(f) != 0) ||
      (f.isString() && static_cast<std::string>(f) != "0")) {
    m.lens = CameraModel::Lens::Fisheye;
  }
  const cv::FileNode k = fs["camera_matrix"];
  if (!k.empty()) {
    // cv::calibrateCamera sample layout.
    cv::Mat mat;
    k >> mat;
    if (mat.rows != 3 || mat.cols != 3 || mat.channels() != 1) {
      error = path + ": camera_matrix must be a 3x3 matrix";
      return false;
    }
    mat.convertTo(mat, CV_64F);
    m.fx = mat.at<double>(0, 0);
    m.fy = mat.at<double>(1, 1);
    m.cx = mat.at<double>(0, 2);
    m.cy = mat.at<double>(1, 2);
    cv::Mat d;
    fs["distortion_coefficients"] >> d;
    if (!d.empty()) {
      d.convertTo(d, CV_64F);
      d = d.reshape(1, 1);
      m.distortion.assign(d.ptr<double>(), d.ptr<double>() + d.cols);
    }
    m.width = integer(fs["image_width"]);
    m.height = integer(fs["image_height"]);
    text(fs["make"], m.make);
    text(fs["model"], m.model);
  } else if (!fs["fx"].empty()) {
    // keyframed.synth intrinsics.json; its "model" key is the projection.
    if (const cv::FileNode p = fs["model"]; p.isString()) {
      const auto name = static_cast<std::string>(p);
      if (name == "fisheye") {
        m.lens = CameraModel::Lens::Fisheye;
      } else if (name != "pinhole") {
        error = path + ": projection model \"" + name +
                "\" is not supported (\"pinhole\", with Brown-Conrady distortion, or "
                "\"fisheye\", OpenCV's k1-k4)";
        return false;
      }
    }
    m.width = integer(fs["width"]);
    m.height = integer(fs["height"]);
    m.fx = number(fs["fx"]);
    m.fy = number(fs["fy"]);
    m.cx = number(fs["cx"]);
    m.cy = number(fs["cy"]);
    const cv::FileNode d = fs["distortion"];
    if (d.isSeq()) {
      for (const auto& v : d) m.distortion.push_back(number(v));
    }
  } else {
    error = path + ": no camera_matrix (OpenCV calibration) or fx (intrinsics.json) found";
    return false;
  }
  m.sensorWidthMm = number(fs["sensor_width_mm"]);
  m.sensorHeightMm = number(fs["sensor_height_mm"]);
  m.focalLengthMm = number(fs["focal_length_mm"]);
  if (!notInteger.empty()) {
    error = path + ": " + notInteger + " must be an integer (pixels)";
    return false;
  }
  if (m.width <= 0 || m.height <= 0) {
    error = path + ": image size missing (image_width/image_height or width/height)";
    return false;
  }
  return true;
}

// ---------------------------------------------------------------- TOML

bool readToml(const std::string& path, CameraModel& m, std::string& error) {
  toml::table doc;
  try {
    doc = toml::parse_file(path);
  } catch (const toml::parse_error& e) {
    std::ostringstream s;
    s << path << ":" << e.source().begin.line << ": " << e.description();
    error = s.str();
    return false;
  }
  for (auto&& [key, node] : doc) {
    if (key != "camera") {
      error = path + ":" + std::to_string(node.source().begin.line) + ": unknown key '" +
              std::string(key.str()) + "'";
      return false;
    }
  }
  const toml::table* cam = doc["camera"].as_table();
  if (cam == nullptr) {
    error = path + ": no [camera] table";
    return false;
  }
  return cameraFromTomlTable(*cam, path, "camera", m, error);
}

}  // namespace

bool cameraFromTomlTable(const toml::table& cam, const std::string& path, const std::string& prefix,
                         CameraModel& m, std::string& error) {
  const auto where = [&](const toml::node& n) {
    return path + ":" + std::to_string(n.source().begin.line) + ": ";
  };
  static const std::set<std::string> kKeys = {"make",
                                              "model",
                                              "lens",
                                              "width",
                                              "height",
                                              "fx",
                                              "fy",
                                              "cx",
                                              "cy",
                                              "distortion",
                                              "sensor_width_mm",
                                              "sensor_height_mm",
                                              "focal_length_mm"};
  for (auto&& [key, node] : cam) {
    const std::string k(key.str());
    if (!kKeys.contains(k)) {
      error = where(node) + "unknown key '" + prefix + "." + k + "'";
      return false;
    }
    const auto wrongType = [&](const char* want) {
      error = where(node) + prefix + "." + k + " must be " + want;
      return false;
    };
    if (k == "lens") {
      const auto v = node.value<std::string>();
      if (!v || (*v != "pinhole" && *v != "fisheye"))
        return wrongType("\"pinhole\" or \"fisheye\"");
      m.lens = *v == "fisheye" ? CameraModel::Lens::Fisheye : CameraModel::Lens::Pinhole;
    } else if (k == "make" || k == "model") {
      const auto v = node.value<std::string>();
      if (!v) return wrongType("a string");
      (k == "make" ? m.make : m.model) = *v;
    } else if (k == "width" || k == "height") {
      const auto v = node.value_exact<std::int64_t>();
      if (!v || *v <= 0 || *v > 100000) return wrongType("an integer from 1 to 100000");
      (k == "width" ? m.width : m.height) = static_cast<int>(*v);
    } else if (k == "distortion") {
      const toml::array* a = node.as_array();
      if (a == nullptr) return wrongType("an array of numbers");
      for (const auto& e : *a) {
        const auto v = e.value<double>();
        if (!v || !std::isfinite(*v)) return wrongType("an array of finite numbers");
        m.distortion.push_back(*v);
      }
    } else {
      const auto v = node.value<double>();
      // TOML has nan and inf: not a measurement, and "unknown" is leaving the key out.
      if (!v || !std::isfinite(*v)) return wrongType("a finite number");
      double* dst = k == "fx"                 ? &m.fx
                    : k == "fy"               ? &m.fy
                    : k == "cx"               ? &m.cx
                    : k == "cy"               ? &m.cy
                    : k == "sensor_width_mm"  ? &m.sensorWidthMm
                    : k == "sensor_height_mm" ? &m.sensorHeightMm
                                              : &m.focalLengthMm;
      *dst = *v;
    }
  }
  // Partial intrinsics are a mistake in the file, not "uncalibrated".
  const int known =
      std::isfinite(m.fx) + std::isfinite(m.fy) + std::isfinite(m.cx) + std::isfinite(m.cy);
  if (known != 0 && known != 4) {
    error = where(cam) + prefix + ".fx, fy, cx, cy go together";
    return false;
  }
  // The table's line and name before what the shared checks find wrong in it.
  return finish(where(cam) + prefix, m, error);
}

std::string tomlString(std::string_view s) {
  std::string out = "\"";
  for (const char ch : s) {
    const auto u = static_cast<unsigned char>(ch);
    if (ch == '"' || ch == '\\') {
      out += '\\';
      out += ch;
    } else if (u < 0x20 || u == 0x7f) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", u);
      out += buf;
    } else {
      out += ch;
    }
  }
  return out + "\"";
}

std::string tomlReal(double v) {
  char buf[64];
  const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);
  std::string s(buf, ec == std::errc() ? end : buf);
  if (s.find_first_of(".eEn") == std::string::npos) s += ".0";
  return s;
}

std::string cameraTomlKeys(const CameraModel& m) {
  std::string out = "make = " + tomlString(m.make) + "\nmodel = " + tomlString(m.model) + "\n";
  out += std::string("lens = ") +
         (m.lens == CameraModel::Lens::Fisheye ? "\"fisheye\"" : "\"pinhole\"") + "\n";
  if (m.width > 0 && m.height > 0) {
    out += "width = " + std::to_string(m.width) + "\nheight = " + std::to_string(m.height) + "\n";
  }
  const std::pair<const char*, double> numbers[] = {{"fx", m.fx},
                                                    {"fy", m.fy},
                                                    {"cx", m.cx},
                                                    {"cy", m.cy},
                                                    {"sensor_width_mm", m.sensorWidthMm},
                                                    {"sensor_height_mm", m.sensorHeightMm},
                                                    {"focal_length_mm", m.focalLengthMm}};
  for (const auto& [key, v] : numbers) {
    if (std::isfinite(v)) out.append(key).append(" = ").append(tomlReal(v)).append("\n");
  }
  if (!m.distortion.empty()) {
    out += "distortion = [";
    for (std::size_t i = 0; i < m.distortion.size(); ++i) {
      out += (i > 0 ? ", " : "") + tomlReal(m.distortion[i]);
    }
    out += "]\n";
  }
  return out;
}

bool cameraFromTomlText(const std::string& text, const std::string& origin, CameraModel& out,
                        std::string& error) {
  // A record is anyone's file: toml++ recurses once per level of nesting.
  if (text.size() > (1u << 16) || textNesting(text) > 64) {
    error = origin + ": a [camera] table over 64 KiB or nested past 64 levels";
    return false;
  }
  toml::table doc;
  try {
    doc = toml::parse(text);
  } catch (const toml::parse_error& e) {
    error =
        origin + ":" + std::to_string(e.source().begin.line) + ": " + std::string(e.description());
    return false;
  }
  const toml::table* cam = doc["camera"].as_table();
  if (cam == nullptr || doc.size() != 1) {
    error = origin + ": not a [camera] table alone";
    return false;
  }
  CameraModel m;
  if (!cameraFromTomlTable(*cam, origin, "camera", m, error)) return false;
  out = std::move(m);
  return true;
}

std::string readSmallText(const std::string& path, std::string& text) {
  constexpr std::size_t kMaxBytes = 1 << 20;
  constexpr std::size_t kMaxNesting = 64;
  // A FIFO or a device would block the open, or never end: refused unread.
  std::error_code ec;
  if (std::filesystem::exists(path, ec) && !std::filesystem::is_regular_file(path, ec))
    return "not a regular file";
  std::ifstream in(path, std::ios::binary);
  if (!in.good()) return "cannot open";
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  if (size < 0) return "cannot read";
  if (static_cast<std::size_t>(size) > kMaxBytes) return "larger than 1 MiB: not a settings file";
  text.resize(static_cast<std::size_t>(size));
  in.seekg(0);
  if (!in.read(text.data(), size)) return "cannot read";
  if (textNesting(text) > kMaxNesting) return "nested more than 64 levels deep";
  return {};
}

bool loadCameraModel(const std::string& path, CameraModel& out, std::string& error) {
  // Checked before a parser reads it.
  std::string text;
  if (std::string why = readSmallText(path, text); !why.empty()) {
    error = path + ": " + why;
    return false;
  }
  if (text.find_first_not_of(" \t\r\n") == std::string::npos) {
    error = path + ": empty: no calibration in it";
    return false;
  }
  CameraModel m;
  try {
    const bool ok =
        endsWith(path, ".toml") ? readToml(path, m, error) : readFileStorage(path, m, error);
    if (!ok) return false;
  } catch (const cv::Exception& e) {
    // FileStorage reports syntax errors by throwing, with the name of the check that
    // failed ("parseValue", "isMap()"); keep the first line only.
    std::string what = e.err.empty() ? e.what() : e.err;
    what.erase(std::find(what.begin(), what.end(), '\n'), what.end());
    error = path +
            ": not a calibration OpenCV can read (YAML, XML or JSON as "
            "calibrateCamera writes it, or keyframed's TOML): " +
            what;
    return false;
  } catch (const std::exception& e) {
    error = path + ": " + e.what();
    return false;
  }
  if (!finish(path, m, error)) return false;
  out = std::move(m);
  return true;
}

std::string exifTextError(std::string_view text) {
  const bool printable = std::all_of(text.begin(), text.end(), [](char ch) {
    return static_cast<unsigned char>(ch) >= 0x20 && static_cast<unsigned char>(ch) < 0x7f;
  });
  if (printable && text.size() <= 63) return {};
  return "must be at most 63 printable ASCII characters, as EXIF holds them";
}

bool checkCameraModel(const std::string& origin, CameraModel& m, std::string& error) {
  return finish(origin, m, error);
}

}  // namespace keyframed
