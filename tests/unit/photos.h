#pragma once

#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>
#ifdef KEYFRAMED_PHOTO_PGM
#include <fstream>
#else
#include <opencv2/imgcodecs.hpp>
#endif

namespace keyframed::test {

#ifdef KEYFRAMED_PHOTO_PGM
// The arm64 build of the core's tests (tests/arm64) has no OpenCV image codecs: the
// same photographs come decoded to grey on the build machine, as binary PGM (P5).
inline cv::Mat photo(const std::string& name) {
  const std::string path = std::string(KEYFRAMED_PHOTO_DIR) + "/" + name + ".pgm";
  std::ifstream in(path, std::ios::binary);
  std::string magic;
  int w = 0, h = 0, maxval = 0;
  in >> magic >> w >> h >> maxval;
  in.get();  // the one whitespace byte before the pixels
  cv::Mat m;
  if (in && magic == "P5" && w > 0 && h > 0 && maxval == 255) {
    m.create(h, w, CV_8UC1);
    in.read(reinterpret_cast<char*>(m.data), static_cast<std::streamsize>(w) * h);
    if (!in) m.release();
  }
  if (m.empty()) ADD_FAILURE() << "missing or bad test photo " << path;
  return m;
}
#else
// Real photographs shipped by Debian's opencv-doc package (installed by tools/setup.sh).
inline cv::Mat photo(const std::string& name, int flags = cv::IMREAD_GRAYSCALE) {
  const std::string path = std::string(KEYFRAMED_PHOTO_DIR) + "/" + name;
  cv::Mat m = cv::imread(path, flags);
  if (m.empty()) ADD_FAILURE() << "missing test photo " << path << " (run tools/setup.sh)";
  return m;
}
#endif

inline std::vector<std::string> photoNames() {
  return {"aero1.jpg", "aero3.jpg",     "baboon.jpg", "building.jpg", "fruits.jpg",
          "home.jpg",  "butterfly.jpg", "messi5.jpg", "graf1.png",    "leuvenA.jpg"};
}

}  // namespace keyframed::test

namespace keyframed::test {

// A wide grey strip of real photographs side by side (about 2400 x 480): the
// "ground" a test camera pans over.
inline cv::Mat photoStrip() {
  std::vector<cv::Mat> parts;
  for (const char* n : {"aero1.jpg", "aero3.jpg", "building.jpg", "baboon.jpg", "fruits.jpg"}) {
    cv::Mat p = photo(n);
    if (p.empty()) return {};
    cv::Mat r;
    cv::resize(p, r, cv::Size(p.cols * 480 / p.rows, 480), 0, 0, cv::INTER_AREA);
    parts.push_back(r);
  }
  cv::Mat strip;
  cv::hconcat(parts, strip);
  return strip;
}

// The view of a camera panned x pixels along the strip (size w x h, top row y0).
inline cv::Mat viewAt(const cv::Mat& strip, double x, int w = 480, int h = 270, int y0 = 100) {
  const cv::Matx23d shift(1, 0, -x, 0, 1, -y0);
  cv::Mat out;
  cv::warpAffine(strip, out, shift, cv::Size(w, h), cv::INTER_LINEAR, cv::BORDER_REFLECT);
  return out;
}

}  // namespace keyframed::test
