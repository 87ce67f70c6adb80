#include <gtest/gtest.h>
#include <stdlib.h>

#include <cstddef>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <string>

#include <toml++/toml.h>

#include "app/config.h"
#include "app/settings.h"

namespace keyframed {
namespace {

namespace fs = std::filesystem;

// Counts an aggregate's members (each member, nested structs included, counts once).
struct AnyValue {
  template <typename T>
  operator T() const;  // never defined: unevaluated use only
};

template <typename T, typename... A>
constexpr std::size_t memberCount() {
  if constexpr (requires { T{A{}..., AnyValue{}}; })
    return memberCount<T, A..., AnyValue>();
  else
    return sizeof...(A);
}

class TempDir {
 public:
  TempDir() {
    char tmpl[] = "/tmp/keyframed-config-XXXXXX";
    path_ = mkdtemp(tmpl);
  }
  ~TempDir() { fs::remove_all(path_); }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  [[nodiscard]] std::string path() const { return path_.string(); }
  std::string write(const std::string& name, const std::string& text) const {
    const fs::path p = path_ / name;
    fs::create_directories(p.parent_path());
    std::ofstream(p) << text;
    return p.string();
  }

 private:
  fs::path path_;
};

ConfigLoadResult loadDir(const TempDir& dir, std::vector<std::string> overrides = {}) {
  ConfigSources s;
  s.configDir = dir.path();
  s.overrides = std::move(overrides);
  return loadConfig(s);
}

ConfigLoadResult loadText(const TempDir& dir, const std::string& text) {
  ConfigSources s;
  s.files = {dir.write("test.toml", text)};
  return loadConfig(s);
}

std::string joined(const std::vector<std::string>& lines) {
  std::string out;
  for (const auto& l : lines) out += l + "\n";
  return out;
}

// One error, exactly this text after the file name.
void expectOneError(const TempDir& dir, const std::string& text, const std::string& expected) {
  const ConfigLoadResult r = loadText(dir, text);
  ASSERT_EQ(r.errors.size(), 1u) << joined(r.errors);
  EXPECT_EQ(r.errors[0], dir.path() + "/test.toml:" + expected);
}

const std::string kSource = KEYFRAMED_SOURCE_DIR;

TEST(Config, DefaultsAreValidAndEmptyDirectoryGivesThem) {
  TempDir dir;
  const ConfigLoadResult r = loadDir(dir);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(toToml(r.config), toToml(DaemonConfig{}));
  EXPECT_EQ(r.layers, std::vector<std::string>{"built-in defaults"});
}

TEST(Config, SelectionSettingsRoundTripAsOverrides) {
  DaemonConfig c;
  c.selection.target = 0.78;
  c.selection.bandHigh = 0.9;
  c.selection.overlap.mode = OverlapMode::Paper;
  const std::string lines = selectionOverrides(c.selection);
  EXPECT_NE(lines.find("selection.target=0.78\n"), std::string::npos) << lines;
  const ConfigLoadResult r = loadSelectionOverrides(lines);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(toToml(r.config), toToml(c));
  // What does not load is an error naming it, not a crash or a silent default.
  EXPECT_FALSE(loadSelectionOverrides("camera.source=file\n").ok());
  const ConfigLoadResult bad = loadSelectionOverrides("selection.target=7\n");
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(joined(bad.errors).find("selection.target"), std::string::npos) << joined(bad.errors);
}

TEST(Config, TaggingSettingsRoundTripAsOverrides) {
  DaemonConfig c;
  c.tagging.make = "Acme";
  c.tagging.model = "Cam \"1\"";
  c.tagging.mountGimbal = true;
  c.tagging.mountRollDeg = 1.5;
  c.tagging.mountPitchDeg = -45;
  c.tagging.mountYawDeg = 10;
  c.camera.timeOffsetMs = -12.5;
  const std::string lines = taggingOverrides(c.tagging, c.camera.timeOffsetMs);
  EXPECT_NE(lines.find("camera.time_offset_ms=-12.5\n"), std::string::npos) << lines;
  // What shapes a keyframe's tags only: not the JPEG quality, nor a file path.
  EXPECT_EQ(lines.find("jpeg_quality"), std::string::npos) << lines;
  EXPECT_EQ(lines.find("calibration"), std::string::npos) << lines;
  const ConfigLoadResult r = loadTaggingOverrides(lines);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(toToml(r.config), toToml(c));
  for (const char* bad : {"tagging.jpeg_quality=50\n", "selection.target=0.7\n", "tagging.make\n",
                          "camera.fps=25\n", "tagging.=1\n", "tagging.mount_pitch=\"x\"\n"}) {
    EXPECT_FALSE(loadTaggingOverrides(bad).ok()) << bad;
  }
}

TEST(Config, ShippedFileIsExactlyTheDefaultsAndListsEveryKey) {
  ConfigSources s;
  s.files = {kSource + "/config/keyframed.toml"};
  const ConfigLoadResult r = loadConfig(s);
  ASSERT_TRUE(r.ok()) << joined(r.errors);  // unknown keys would be errors
  EXPECT_EQ(toToml(r.config), toToml(DaemonConfig{}));

  const toml::table doc = toml::parse_file(kSource + "/config/keyframed.toml");
  std::set<std::string> inFile;
  for (auto&& [section, table] : doc) {
    ASSERT_TRUE(table.is_table());
    for (auto&& [key, value] : *table.as_table())
      inFile.insert(std::string(section.str()) + "." + std::string(key.str()));
  }
  for (const std::string& key : configKeys()) EXPECT_TRUE(inFile.count(key)) << key;
  EXPECT_EQ(inFile.size(), configKeys().size());
}

TEST(Config, EveryKeyIsDocumented) {
  std::ifstream in(kSource + "/docs/configuration.md");
  std::stringstream doc;
  doc << in.rdbuf();
  for (const std::string& key : configKeys())
    EXPECT_NE(doc.str().find("`" + key + "`"), std::string::npos) << key << " not in docs";
}

// The schema must cover every member: a field added to a config struct without a
// key fails here.
TEST(Config, SchemaCoversEveryMember) {
  auto keysIn = [](const std::string& section) {
    std::size_t n = 0;
    for (const std::string& k : configKeys()) n += k.rfind(section + ".", 0) == 0;
    return n;
  };
  EXPECT_EQ(memberCount<DaemonConfig>(), configSections().size());
  EXPECT_EQ(memberCount<DaemonConfig::Camera>(), keysIn("camera"));
  // The selector's own members hold the two nested structs; the overlap's lens is no
  // [selection] key but the calibration's (tagging.calibration).
  EXPECT_EQ(memberCount<SelectorConfig>() - 2 + memberCount<SharpnessConfig>() +
                memberCount<OverlapConfig>() - 1,
            keysIn("selection"));
  // [telemetry] is TelemetryServiceConfig (its decoder: TelemetryConfig, with a
  // PoseStore::Config and a ClockMapper::Config) plus two waits; telemetry.autopilot
  // sets both the system and the component; waitForSerialDevice is no key (`run` waits
  // for a serial device, `select` does not).
  EXPECT_EQ(memberCount<DaemonConfig::Telemetry>() - 1 + memberCount<TelemetryServiceConfig>() - 2 +
                memberCount<TelemetryConfig>() - 2 + memberCount<PoseStore::Config>() +
                memberCount<ClockMapper::Config>() - 1,
            keysIn("telemetry"));
  // ... and the [tagging.camera] table (IntrinsicsInlineInTaggingCamera).
  EXPECT_EQ(memberCount<DaemonConfig::Tagging>() - 1, keysIn("tagging"));
  EXPECT_EQ(memberCount<DaemonConfig::Output>(), keysIn("output"));
  EXPECT_EQ(memberCount<DaemonConfig::Zenoh>(), keysIn("zenoh"));
  // level, target, and one key per category.
  EXPECT_EQ(memberCount<LogConfig>() - 1 + kLogCategories, keysIn("log"));
}

TEST(Config, LayersApplyInOrder) {
  TempDir dir;
  dir.write("keyframed.toml", "[camera]\nfps = 10\nwidth = 640\n[zenoh]\nvehicle = \"main\"\n");
  dir.write("conf.d/20-b.toml", "[camera]\nfps = 20\n");
  dir.write("conf.d/10-a.toml", "[camera]\nfps = 15\nheight = 480\n[zenoh]\nvehicle = \"a\"\n");
  ConfigLoadResult r = loadDir(dir);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(r.config.camera.fps, 20.0);            // conf.d/20-b over 10-a over the main file
  EXPECT_EQ(r.config.camera.width, 640);           // main file only
  EXPECT_EQ(r.config.camera.height, 480);          // 10-a only
  EXPECT_EQ(r.config.zenoh.vehicle, "a");          // conf.d over the main file
  EXPECT_EQ(r.config.camera.pixelFormat, "auto");  // default
  EXPECT_EQ(r.layers, (std::vector<std::string>{"built-in defaults", dir.path() + "/keyframed.toml",
                                                dir.path() + "/conf.d/10-a.toml",
                                                dir.path() + "/conf.d/20-b.toml"}));
  r = loadDir(dir, {"camera.fps=25", "zenoh.vehicle=cli"});
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(r.config.camera.fps, 25.0);  // --set over everything
  EXPECT_EQ(r.config.zenoh.vehicle, "cli");
  EXPECT_EQ(r.layers.back(), "--set zenoh.vehicle=cli");
}

TEST(Config, DropInsSortByNameAndOnlyTomlFilesCount) {
  TempDir dir;
  dir.write("conf.d/9-b.toml", "[zenoh]\nvehicle = \"nine\"\n");
  dir.write("conf.d/10-a.toml", "[zenoh]\nvehicle = \"ten\"\n");  // "10-a" < "9-b"
  dir.write("conf.d/99-z.toml.dpkg-old", "[zenoh]\nvehicle = \"old\"\n");
  dir.write("conf.d/.99-editor.toml", "[zenoh]\nvehicle = \"hidden\"\n");
  dir.write("conf.d/README", "not toml at all [");
  const ConfigLoadResult r = loadDir(dir);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(r.config.zenoh.vehicle, "nine");
  EXPECT_EQ(r.layers.size(), 3u);
}

TEST(Config, AConfDThatCannotBeReadIsAnErrorNotDefaults) {
  TempDir dir;
  dir.write("keyframed.toml", "[zenoh]\nvehicle = \"main\"\n");
  dir.write("conf.d", "a file where the drop-in directory should be\n");
  const ConfigLoadResult r = loadDir(dir);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(joined(r.errors).find(dir.path() + "/conf.d: cannot read"), std::string::npos)
      << joined(r.errors);
}

TEST(Config, ADropInThatIsNoFileOrNestsTooDeepIsAnError) {
  TempDir dir;
  dir.write("keyframed.toml", "[zenoh]\nvehicle = \"main\"\n");
  dir.write("conf.d/10-ok.toml", "[selection]\ntarget = 0.75\n");
  std::filesystem::create_directories(dir.path() + "/conf.d/20-dir.toml");
  std::filesystem::create_symlink(dir.path() + "/gone.toml", dir.path() + "/conf.d/30-link.toml");
  std::string deep = "[";
  for (int i = 0; i < 20000; ++i) deep += "a.";
  dir.write("conf.d/40-deep.toml", deep + "a]\n");
  dir.write("conf.d/notes.txt", "ignored: not .toml\n");
  const ConfigLoadResult r = loadDir(dir);
  ASSERT_FALSE(r.ok());
  const std::string all = joined(r.errors);
  EXPECT_NE(all.find("/conf.d/20-dir.toml: not a regular file"), std::string::npos) << all;
  EXPECT_NE(all.find("/conf.d/30-link.toml: no such file"), std::string::npos) << all;
  EXPECT_NE(all.find("/conf.d/40-deep.toml: nested more than 64 levels deep"), std::string::npos)
      << all;
  EXPECT_EQ(all.find("notes.txt"), std::string::npos) << all;
  // A main file that is a dangling symlink: an error too, not the defaults.
  TempDir other;
  std::filesystem::create_symlink(other.path() + "/nowhere", other.path() + "/keyframed.toml");
  const ConfigLoadResult r2 = loadDir(other);
  ASSERT_FALSE(r2.ok());
  EXPECT_NE(joined(r2.errors).find("keyframed.toml: no such file"), std::string::npos)
      << joined(r2.errors);
}

TEST(Config, DirectoryFromTheEnvironmentAndMissingDirectories) {
  TempDir dir;
  dir.write("keyframed.toml", "[camera]\nwidth = 800\n");
  ::setenv("KEYFRAMED_CONFIG_DIR", dir.path().c_str(), 1);
  EXPECT_EQ(defaultConfigDir(), dir.path());
  ConfigLoadResult r = loadConfig({});
  ::unsetenv("KEYFRAMED_CONFIG_DIR");
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(r.config.camera.width, 800);
  // Built in from the install prefix: /etc/keyframed for /usr.
  EXPECT_TRUE(defaultConfigDir().ends_with("/keyframed")) << defaultConfigDir();
  EXPECT_NE(defaultConfigDir(), dir.path());

  ConfigSources s;
  s.configDir = dir.path() + "/nope";
  r = loadConfig(s);
  ASSERT_EQ(r.errors.size(), 1u);
  EXPECT_EQ(r.errors[0], dir.path() + "/nope: no such directory");
  s = {};
  s.files = {dir.path() + "/missing.toml"};
  r = loadConfig(s);
  ASSERT_EQ(r.errors.size(), 1u);
  EXPECT_EQ(r.errors[0], dir.path() + "/missing.toml: no such file");
}

TEST(Config, SetOverridesTakeTomlValuesAndBareStrings) {
  TempDir dir;
  const ConfigLoadResult r =
      loadDir(dir, {"camera.source=file", "camera.path=/data/flight 1.mp4", "camera.realtime=false",
                    "telemetry.url=", "selection.target=0.65", "selection.blur_floor=12",
                    "tagging.calibration=", "zenoh.vehicle=\"quoted\"", "telemetry.autopilot=1:1",
                    "log.capture=debug", "camera.fps=29.97"});
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(r.config.camera.source, DaemonConfig::Source::File);
  EXPECT_EQ(r.config.camera.path, "/data/flight 1.mp4");
  EXPECT_FALSE(r.config.camera.realtime);
  EXPECT_DOUBLE_EQ(r.config.selection.target, 0.65);
  EXPECT_DOUBLE_EQ(r.config.selection.blur.floor, 12.0);  // an integer for a float key
  EXPECT_EQ(r.config.zenoh.vehicle, "quoted");
  EXPECT_EQ(r.config.telemetry.link.decoder.autopilotSystem, 1);
  EXPECT_EQ(r.config.telemetry.link.decoder.autopilotComponent, 1);
  EXPECT_EQ(r.config.log.categories[static_cast<int>(LogCategory::Capture)], LogLevel::Debug);
  EXPECT_DOUBLE_EQ(r.config.camera.fps, 29.97);
}

TEST(Config, SetErrorsNameTheOverride) {
  TempDir dir;
  const ConfigLoadResult r = loadDir(dir, {"camera.fps=500", "camera.width=abc", "camera",
                                           "camra.fps=1", "camera.fsp=1", "camera.realtime=1"});
  EXPECT_EQ(joined(r.errors),
            "--set camera.fps=500: camera.fps: must be between 1 and 240 (got 500)\n"
            "--set camera.width=abc: camera.width: expected an integer (got \"abc\")\n"
            "--set camera: expected --set SECTION.KEY=VALUE\n"
            "--set camra.fps=1: camra: unknown section (did you mean 'camera'?)\n"
            "--set camera.fsp=1: camera.fsp: unknown key (did you mean 'fps'?)\n"
            "--set camera.realtime=1: camera.realtime: expected true or false, got an integer\n");
}

TEST(Config, UnknownKeyNamesFileLineAndKey) {
  TempDir dir;
  expectOneError(dir, "[camera]\nfps = 30\n\nframerate = 30\n", "4: camera.framerate: unknown key");
  expectOneError(dir, "[camera]\nwidht = 640\n",
                 "2: camera.widht: unknown key (did you mean 'width'?)");
  expectOneError(dir, "[camera]\n[camera.extra]\nx = 1\n", "2: camera.extra: unknown key");
}

TEST(Config, UnknownSectionAndKeysOutsideSections) {
  TempDir dir;
  expectOneError(dir, "\n[cameras]\nfps = 30\n",
                 "2: cameras: unknown section (did you mean 'camera'?)");
  expectOneError(dir, "[video]\nfps = 30\n", "1: video: unknown section");
  expectOneError(dir, "fps = 30\n", "1: fps: key outside any section (did you mean [camera]?)");
  expectOneError(dir, "camera = 3\n", "1: camera: expected a [camera] table, got an integer");
}

TEST(Config, WrongTypes) {
  TempDir dir;
  expectOneError(dir, "[camera]\nwidth = \"640\"\n",
                 "2: camera.width: expected an integer, got a string");
  expectOneError(dir, "[camera]\nwidth = 640.0\n",
                 "2: camera.width: expected an integer, got a float");
  expectOneError(dir, "[selection]\ntarget = [0.7]\n",
                 "2: selection.target: expected a number, got an array");
  expectOneError(dir, "[output]\nmcap = \"yes\"\n",
                 "2: output.mcap: expected true or false, got a string");
  expectOneError(dir, "[zenoh]\nvehicle = 7\n",
                 "2: zenoh.vehicle: expected a string, got an integer");
}

TEST(Config, ControlCharactersInAStringAreRefused) {
  // TOML's "\u0000" would cut a path short at the C library (a state directory that
  // exists already, taken for the one named: a start that never ends).
  TempDir dir;
  expectOneError(dir, "[output]\nstate_dir = \"/tmp/x\\u0000y\"\n",
                 "2: output.state_dir: must not contain control characters (a NUL, a newline, a "
                 "tab, ...)");
  expectOneError(dir, "[camera]\npath = \"/data/a.avi\\njunk\"\n",
                 "2: camera.path: must not contain control characters (a NUL, a newline, a tab, "
                 "...)");
  const ConfigLoadResult r = loadDir(dir, {std::string("output.state_dir=/tmp/a\x01b")});
  ASSERT_EQ(r.errors.size(), 1u) << joined(r.errors);
  EXPECT_NE(r.errors[0].find("control characters"), std::string::npos) << r.errors[0];
}

TEST(Config, OutOfRangeAndBadValues) {
  TempDir dir;
  expectOneError(dir, "[camera]\n\n\nfps = 500\n",
                 "4: camera.fps: must be between 1 and 240 (got 500)");
  expectOneError(dir, "[selection]\ntarget = 1.5\n",
                 "2: selection.target: must be between 0.01 and 0.99 (got 1.5)");
  expectOneError(dir, "[tagging]\njpeg_quality = 101\n",
                 "2: tagging.jpeg_quality: must be between 1 and 100 (got 101)");
  expectOneError(dir, "[tagging]\nmodel = \"tab\\there\"\n",
                 "2: tagging.model: must not contain control characters (a NUL, a newline, a "
                 "tab, ...)");
  expectOneError(dir, "[tagging]\nmount = \"gimbal2\"\n",
                 "2: tagging.mount: must be one of fixed, gimbal (got \"gimbal2\")");
  expectOneError(dir, "[output]\npreview_format = \"vp9\"\n",
                 "2: output.preview_format: must be jpeg or h264 (got \"vp9\")");
  // Debian's libavcodec (tools/setup.sh) has libx264: "h264" passes the check for it.
  EXPECT_TRUE(loadText(dir, "[output]\npreview_format = \"h264\"\n").ok());
  expectOneError(dir, "[selection]\nmode = \"fast\"\n",
                 "2: selection.mode: must be one of geometric, paper (got \"fast\")");
  expectOneError(dir, "[camera]\nsource = \"usb\"\n",
                 "2: camera.source: must be one of v4l2, libcamera, file (got \"usb\")");
  expectOneError(dir, "[camera]\npixel_format = \"yuyv422\"\n",
                 "2: camera.pixel_format: must be \"auto\" or one of NV12, YUV420 (YU12, I420), "
                 "YUYV (YUY2), MJPEG (MJPG), GREY (GRAY, GRAY8) (got \"yuyv422\")");
  // A well-formed FourCC that no backend decodes is as wrong as a typo.
  expectOneError(dir, "[camera]\npixel_format = \"H264\"\n",
                 "2: camera.pixel_format: must be \"auto\" or one of NV12, YUV420 (YU12, I420), "
                 "YUYV (YUY2), MJPEG (MJPG), GREY (GRAY, GRAY8) (got \"H264\")");
  // A video file is delivered as decoded or as a camera's YUV, never as YUYV or MJPEG.
  expectOneError(dir, "[camera]\nsource = \"file\"\npath = \"/v.avi\"\npixel_format = \"YUYV\"\n",
                 "4: camera.pixel_format: source \"file\" delivers \"auto\" (BGR, as decoded), "
                 "YUV420 or NV12 (got \"YUYV\")");
  EXPECT_TRUE(loadText(dir,
                       "[camera]\nsource = \"file\"\npath = \"/v.avi\"\n"
                       "pixel_format = \"i420\"\n")
                  .ok());
  // libcamera gives YUV only (what the camera offers is checked again when it opens).
  expectOneError(dir, "[camera]\nsource = \"libcamera\"\npixel_format = \"MJPEG\"\n",
                 "3: camera.pixel_format: source \"libcamera\" delivers \"auto\", NV12, YUV420 or "
                 "YUYV (got \"MJPEG\")");
  EXPECT_TRUE(loadText(dir, "[camera]\nsource = \"libcamera\"\npixel_format = \"yuyv\"\n").ok());
  EXPECT_EQ(filePixelFormat("i420"), PixelFormat::YUV420);
  EXPECT_EQ(filePixelFormat("NV12"), PixelFormat::NV12);
  EXPECT_EQ(filePixelFormat("auto"), PixelFormat::BGR24);
  EXPECT_FALSE(filePixelFormat("MJPEG"));
  expectOneError(dir, "[telemetry]\nurl = \"tcp:1.2.3.4\"\n",
                 "2: telemetry.url: bad MAVLink link 'tcp:1.2.3.4': unknown scheme 'tcp'");
  expectOneError(dir, "[telemetry]\nautopilot = \"1:300\"\n",
                 "2: telemetry.autopilot: expected SYS[:COMP] with ids 1..255 (got \"1:300\")");
  expectOneError(dir, "[output]\nstate_dir = \"var/lib\"\n",
                 "2: output.state_dir: must be an absolute path (got \"var/lib\")");
  expectOneError(dir, "[zenoh]\nvehicle = \"a/b\"\n",
                 "2: zenoh.vehicle: may hold only letters, digits, '-', '_' and '.', 1 to 64 of "
                 "them (got \"a/b\")");
  expectOneError(dir, "[log]\ntelemetry = \"loud\"\n",
                 "2: log.telemetry: must be \"\" (follow log.level) or one of debug, info, "
                 "notice, warning, error (got \"loud\")");
  expectOneError(dir, "[tagging]\ncalibration = \"/nonexistent/cam.yaml\"\n",
                 "2: tagging.calibration: /nonexistent/cam.yaml: cannot open");
}

TEST(Config, CrossChecksNameTheLastKeySet) {
  TempDir dir;
  expectOneError(dir, "[selection]\nband_low = 0.75\n",
                 "2: selection.band_low: selection.band_low (0.75) must not exceed "
                 "selection.target (0.7)");
  expectOneError(dir, "[selection]\nband_low = 0.5\ntarget = 0.55\nmin_overlap = 0.52\n",
                 "4: selection.min_overlap: selection.min_overlap (0.52) must not exceed "
                 "selection.band_low (0.5)");
  expectOneError(dir, "[camera]\nsource = \"file\"\n",
                 "2: camera.source: source \"file\" needs camera.path");
  expectOneError(dir, "[telemetry]\nurl = \"flight.tlog\"\n",
                 "2: telemetry.url: a tlog replays a recorded flight: it needs camera.source = "
                 "\"file\" and camera.start_time");
  // A file read as fast as it decodes with the default live link (udpin:0.0.0.0:14550).
  expectOneError(dir, "[camera]\nsource = \"file\"\npath = \"f.avi\"\nrealtime = false\n",
                 "4: camera.realtime: a live telemetry link needs camera.realtime = true (a file "
                 "read as fast as it decodes is on the video's clock; replay its tlog instead, or "
                 "set telemetry.url = \"\")");
  // The video placed by its motion: only a file with its tlog.
  expectOneError(dir, "[camera]\nsource = \"file\"\npath = \"f.avi\"\nstart_time = \"auto\"\n",
                 "4: camera.start_time: camera.start_time = \"auto\" places a video in its tlog by "
                 "their motion: it needs camera.source = \"file\" and a tlog as telemetry.url");
  EXPECT_TRUE(loadText(dir,
                       "[camera]\nsource = \"file\"\npath = \"f.avi\"\nstart_time = \"auto\"\n"
                       "[telemetry]\nurl = \"tlog:f.tlog\"\n")
                  .ok());
  expectOneError(dir, "[camera]\nstart_time = \"soon\"\n",
                 "2: camera.start_time: expected a UTC time like \"2026-06-01T10:00:00Z\", unix "
                 "seconds or \"auto\" (got \"soon\")");
}

TEST(Config, ZeroOrAtLeastSettingsNameTheirOwnKeyAndLine) {
  // 0 switches these off (or means full size); other values have a minimum. The key
  // and line named are the bad one's, whatever is set after it.
  TempDir dir;
  expectOneError(dir, "[selection]\nanalysis_width = 32\ntarget = 0.7\n",
                 "2: selection.analysis_width: must be 0 (full) or >= 64 (got 32)");
  expectOneError(dir, "[selection]\nblur_width = 20\ntarget = 0.7\n",
                 "2: selection.blur_width: must be 0 (full) or >= 32 (got 20)");
  expectOneError(dir, "[selection]\nmotion_ratio = 0.5\ntarget = 0.7\n",
                 "2: selection.motion_ratio: must be 0 (off) or >= 1 (got 0.5)");
  // A preview a pixel wide would be no picture at all.
  expectOneError(dir, "[output]\npreview_width = 1\n",
                 "2: output.preview_width: must be 0 (no preview) or >= 16 (got 1)");
  TempDir ok;
  for (const char* text : {"[selection]\nanalysis_width = 0\nblur_width = 0\nmotion_ratio = 0\n"
                           "[output]\npreview_width = 0\n",
                           "[selection]\nanalysis_width = 64\nblur_width = 32\nmotion_ratio = 1\n"
                           "[output]\npreview_width = 16\n"}) {
    const ConfigLoadResult r = loadText(ok, text);
    EXPECT_TRUE(r.ok()) << text << joined(r.errors);
  }
}

TEST(Config, SmallValuesLowerTheDefaultsThatDependOnThem) {
  TempDir dir;
  const ConfigLoadResult r = loadText(dir, "[selection]\nmax_tracks = 30\nblur_window = 2\n");
  ASSERT_TRUE(r.errors.empty()) << joined(r.errors);
  // Two fifths of max_tracks, but not under min_inliers (15): fewer tracks than that
  // would lose the track before they are replenished.
  EXPECT_EQ(r.config.selection.overlap.minTracks, 15);
  EXPECT_EQ(r.config.selection.blur.warmup, 2);
  // Set explicitly, a conflict is still reported.
  expectOneError(dir, "[selection]\nmax_tracks = 30\nmin_tracks = 40\n",
                 "3: selection.min_tracks: selection.min_tracks must not exceed "
                 "selection.max_tracks");
  expectOneError(dir, "[selection]\nmin_tracks = 20\nmin_inliers = 25\n",
                 "3: selection.min_inliers: selection.min_inliers must not exceed "
                 "selection.min_tracks (tracks are replenished only below it)");
  expectOneError(dir, "[selection]\nmode = \"paper\"\npaper_min_matches = 5000\n",
                 "3: selection.paper_min_matches: selection.paper_min_matches must not exceed "
                 "selection.orb_features");
}

TEST(Config, ADependentKeyFromAnEarlierFileFollowsALaterOne) {
  // The shipped keyframed.toml spells out min_tracks = 80 and blur_warmup = 5; a
  // drop-in that lowers max_tracks or blur_window alone lowers them as it would
  // the defaults.
  TempDir dir;
  std::ifstream shipped(kSource + "/config/keyframed.toml");
  std::stringstream text;
  text << shipped.rdbuf();
  dir.write("keyframed.toml", text.str());
  dir.write("conf.d/10-small.toml", "[selection]\nmax_tracks = 50\nblur_window = 3\n");
  const ConfigLoadResult r = loadDir(dir);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  EXPECT_EQ(r.config.selection.overlap.minTracks, 20);  // 2/5 of 50
  EXPECT_EQ(r.config.selection.blur.warmup, 3);
  // Set again in the later file, the conflict is the user's and is reported.
  dir.write("conf.d/10-small.toml", "[selection]\nmax_tracks = 50\nmin_tracks = 80\n");
  const ConfigLoadResult both = loadDir(dir);
  ASSERT_EQ(both.errors.size(), 1u) << joined(both.errors);
  EXPECT_NE(both.errors[0].find("10-small.toml:3: selection.min_tracks"), std::string::npos)
      << both.errors[0];
  // And --set counts as a later layer than any file.
  dir.write("conf.d/10-small.toml", "");
  const ConfigLoadResult set = loadDir(dir, {"selection.max_tracks=40"});
  ASSERT_TRUE(set.ok()) << joined(set.errors);
  EXPECT_EQ(set.config.selection.overlap.minTracks, 16);
}

TEST(Config, MalformedTomlGivesTheLine) {
  TempDir dir;
  const ConfigLoadResult r = loadText(dir, "[camera]\nfps = 30\nwidth = = 3\n");
  ASSERT_EQ(r.errors.size(), 1u);
  EXPECT_EQ(r.errors[0].rfind(dir.path() + "/test.toml:3: ", 0), 0u) << r.errors[0];
  const ConfigLoadResult dup = loadText(dir, "[camera]\nfps = 30\nfps = 31\n");
  ASSERT_EQ(dup.errors.size(), 1u);
  EXPECT_EQ(dup.errors[0].rfind(dir.path() + "/test.toml:3: ", 0), 0u) << dup.errors[0];
}

TEST(Config, EveryErrorIsReportedInFileOrder) {
  TempDir dir;
  const ConfigLoadResult r =
      loadText(dir, "[zenoh]\nvehicle = 1\n[camera]\nwidth = 0\nfps = 0\n[log]\nlevel = \"x\"\n");
  ASSERT_EQ(r.errors.size(), 4u) << joined(r.errors);
  EXPECT_NE(r.errors[0].find(":2: zenoh.vehicle"), std::string::npos);
  EXPECT_NE(r.errors[1].find(":4: camera.width"), std::string::npos);
  EXPECT_NE(r.errors[2].find(":5: camera.fps"), std::string::npos);
  EXPECT_NE(r.errors[3].find(":7: log.level"), std::string::npos);
}

TEST(Config, PrintedConfigLoadsBackTheSame) {
  TempDir dir;
  // A file name that needs TOML's escapes (the Zenoh configuration must exist).
  const std::string zenoh = dir.write("z \"q\".json5", "{}");
  const ConfigLoadResult a =
      loadDir(dir, {"camera.source=libcamera", "camera.fps=24.5", "selection.mode=paper",
                    "selection.blur_threshold=1e9", "telemetry.autopilot=7",
                    "telemetry.stale_ms=300", "telemetry.history_s=60", "zenoh.config=" + zenoh,
                    "log.level=debug", "log.output=error", "output.mcap_rotate_s=0"});
  ASSERT_TRUE(a.ok()) << joined(a.errors);
  const std::string text = toToml(a.config);
  EXPECT_NE(toToml(DaemonConfig{}), text);
  ConfigSources s;
  s.files = {dir.write("printed.toml", text)};
  const ConfigLoadResult b = loadConfig(s);
  ASSERT_TRUE(b.ok()) << joined(b.errors);
  EXPECT_EQ(toToml(b.config), text);
  EXPECT_EQ(b.config.telemetry.link.decoder.store.maxHoldNs, 300'000'000);
  EXPECT_EQ(b.config.telemetry.link.decoder.store.historyNs, 60'000'000'000);
}

TEST(Config, IntrinsicsInlineInTaggingCamera) {
  TempDir dir;
  const std::string table =
      "[tagging.camera]\nmake = \"Arducam\"\nmodel = \"IMX477 6mm\"\nwidth = 4056\n"
      "height = 3040\nfx = 3712.5\nfy = 3712.5\ncx = 2027.5\ncy = 1519.5\n"
      "distortion = [-0.11, 0.09, 0.0, 0.0, 0.0]\nsensor_width_mm = 6.287\n";
  const ConfigLoadResult r = loadText(dir, table);
  ASSERT_TRUE(r.ok()) << joined(r.errors);
  ASSERT_TRUE(r.config.tagging.camera.has_value());
  const CameraModel& c = *r.config.tagging.camera;
  EXPECT_EQ(c.model, "IMX477 6mm");
  EXPECT_TRUE(c.calibrated());
  EXPECT_NEAR(c.focalLengthMm, 3712.5 * 6.287 / 4056, 1e-9);  // derived as for a file
  // printed back as TOML, it loads back the same
  ConfigSources s;
  s.files = {dir.write("printed.toml", toToml(r.config))};
  const ConfigLoadResult b = loadConfig(s);
  ASSERT_TRUE(b.ok()) << joined(b.errors);
  EXPECT_EQ(toToml(b.config), toToml(r.config));
  EXPECT_EQ(b.config.tagging.camera->distortion, c.distortion);
  // A fisheye stays a fisheye (the lens is printed too).
  const ConfigLoadResult fish =
      loadText(dir,
               "[tagging.camera]\nlens = \"fisheye\"\nwidth = 1280\nheight = 960\nfx = 330.0\n"
               "fy = 330.0\ncx = 640.0\ncy = 480.0\ndistortion = [0.05, -0.01, 0.002, -0.0003]\n");
  ASSERT_TRUE(fish.ok()) << joined(fish.errors);
  s.files = {dir.write("printed.toml", toToml(fish.config))};
  const ConfigLoadResult fishBack = loadConfig(s);
  ASSERT_TRUE(fishBack.ok()) << joined(fishBack.errors);
  EXPECT_EQ(fishBack.config.tagging.camera->lens, CameraModel::Lens::Fisheye);

  expectOneError(dir, "[tagging.camera]\nfz = 1.0\n", "2: unknown key 'tagging.camera.fz'");
  expectOneError(dir, "[tagging.camera]\nwidth = 640\nheight = 480\nfx = 500.0\n",
                 "1: tagging.camera.fx, fy, cx, cy go together");
  // The checks every calibration passes name the table's line and the table.
  expectOneError(dir, "[tagging.camera]\nwidth = 640\nheight = 480\ndistortion = [1.0]\n",
                 "1: tagging.camera: distortion needs 4 or 5 terms");
  expectOneError(dir, "[tagging.camera]\nwidth = 100001\n",
                 "2: tagging.camera.width must be an integer from 1 to 100000");
  expectOneError(dir, "[tagging]\ncamera = 5\n",
                 "2: tagging.camera: expected a [tagging.camera] table, got an integer");
  const std::string yaml = kSource + "/config/camera-example.yaml";
  expectOneError(dir, "[tagging]\ncalibration = \"" + yaml + "\"\n\n" + table,
                 "4: tagging.calibration and [tagging.camera] are both set: give the "
                 "intrinsics one way");
}

TEST(Config, TakeConfigArgsLeavesTheRest) {
  std::vector<std::string> args = {"--config-dir", "/x",    "run",      "--set=camera.fps=5",
                                   "--set",        "a.b=c", "--verbose"};
  ConfigSources s;
  EXPECT_EQ(takeConfigArgs(args, s), "");
  EXPECT_EQ(s.configDir, "/x");
  EXPECT_EQ(s.overrides, (std::vector<std::string>{"camera.fps=5", "a.b=c"}));
  EXPECT_EQ(args, (std::vector<std::string>{"run", "--verbose"}));
  std::vector<std::string> bad = {"--set"};
  EXPECT_EQ(takeConfigArgs(bad, s), "option --set needs a value");
}

TEST(ParseUtcTime, IsoAndUnixSecondsWithinTheRangeAnInt64OfNanosecondsHolds) {
  std::int64_t ns = 0;
  ASSERT_TRUE(parseUtcTime("2026-12-02T23:15:00.25Z", ns));
  EXPECT_EQ(ns, 1'796'253'300'250'000'000);
  ASSERT_TRUE(parseUtcTime("2026-12-02T23:15:00+00:00", ns));
  EXPECT_EQ(ns, 1'796'253'300'000'000'000);
  ASSERT_TRUE(parseUtcTime("1796253300.5", ns));
  EXPECT_EQ(ns, 1'796'253'300'500'000'000);
  ASSERT_TRUE(parseUtcTime("2099-12-31T23:59:59Z", ns));
  // A typo'd year past 2262 overflowed the nanoseconds; before 1970 is no video's.
  for (const char* bad :
       {"2300-01-01T00:00:00Z", "9999-12-31T23:59:59Z", "1969-12-31T23:59:59Z",
        "2026-12-02T-1:15:00Z", "2026-12-02T23:-5:00Z", "2026-13-02T23:15:00Z",
        "2026-12-02T23:15:00+01:00", "2026-12-02", "-5", "5e9", "2026-02-30T00:00:00Z",
        "2026-02-29T00:00:00Z", "2100-02-29T00:00:00Z", "2026-04-31T00:00:00Z"}) {
    EXPECT_FALSE(parseUtcTime(bad, ns)) << bad;
  }
  EXPECT_TRUE(parseUtcTime("2028-02-29T12:00:00Z", ns));  // a leap day
  EXPECT_TRUE(parseUtcTime("2000-02-29T12:00:00Z", ns));
}

}  // namespace
}  // namespace keyframed
