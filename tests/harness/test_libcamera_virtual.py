"""libcamera capture against real libcamera releases newer than Debian 12's 0.0.3.

A Raspberry Pi runs libcamera 0.4 to 0.7; the daemon builds against Debian 12's 0.0.3
and guards the API differences (daemon/capture/libcamera_compat.h). tools/setup.sh
unpacks, under build/debian (tools/fetch_debian.py, nothing installed), Debian 13's
libcamera 0.4 with the C/C++ runtime it needs and Debian 13's cloud kernel, and Debian
sid's newest libcamera headers. Here:

- the daemon's libcamera sources compile, warnings as errors, against both releases;
- keyframed-libcamera-probe, the daemon's own LibcameraSource built against 0.4, runs
  under qemu on libcamera's virtual camera: a kernel-free pipeline handler (new in 0.4)
  that renders colour bars into dma-buf heap buffers (the cloud kernel has the heaps;
  Debian 12's kernel has not). It checks camera listing, stream configuration, request
  recycling over many more frames than buffers, sensor timestamps, the NV12 pixels
  (the bars' BT.601 luma along a row), and clear errors for a format the camera does
  not offer and an unknown camera id.

Skipped, saying why, where g++, qemu or busybox is missing or setup could not fetch
the releases.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import qemu_vm
from daemon_log import logged_stop_s

ROOT = Path(__file__).resolve().parents[2]
TRIXIE = ROOT / "build" / "debian" / "trixie"
SID = ROOT / "build" / "debian" / "sid"
BOOT_TIMEOUT_S = 240

# The cameras the virtual pipeline handler reads from its configuration file.
VIRTUAL_YAML = """\
%YAML 1.1
---
"Virtual0":
  supported_formats:
    - width: 640
      height: 480
      frame_rates:
        - 15
        - 30
  test_pattern: "bars"
  model: "keyframed test camera"
"""

# probe arguments per case; the VM runs them in order.
CASES = {
    "list": "--list",
    "stream": "--frames 40 --size 640x480 --fps 30 --buffers 4",
    "other_size": "--frames 5 --size 1920x1080",
    "viewfinder": "--frames 5 --viewfinder",
    "yuyv": "--frames 5 --format YUYV",
    "unknown": "--camera nope",
}

INIT = """#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin LIBCAMERA_LOG_LEVELS=*:ERROR
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
echo KF-BOOTED
@CASES@
@DAEMON@
poweroff -f
"""

# The whole daemon, built against libcamera 0.4 (keyframed-libcamera-alt): this
# machine's root comes in read-only over virtio-9p for the libraries it shares with
# the daemon (OpenCV, exiv2, ...); it runs under Debian 13's loader and C/C++ runtime
# (the initramfs's own /usr), in the initramfs, where the virtual camera's
# configuration is. Once it is ready it runs a few seconds, then gets SIGTERM.
DAEMON = r"""
echo "KF-CASE daemon"
for m in $(cat /modules/order); do insmod /modules/$m || echo "KF-INSMOD-FAIL $m"; done
mkdir -p /host /scratch/etc/conf.d
: > /scratch/etc/keyframed.toml
if mount -t 9p -o trans=virtio,version=9p2000.L,ro,cache=loose,msize=512000 hostroot /host
then
  log=/scratch/daemon.log
  /lib64/ld-linux-x86-64.so.2 --library-path /usr/lib/x86_64-linux-gnu:@HOSTLIBS@ \
    /host@ALT@ run --config-dir /scratch/etc @SETS@ > $log 2>&1 &
  pid=$!
  n=0
  while ! grep -q 'ready: first frame' $log && kill -0 $pid 2>/dev/null && [ $n -lt 600 ]
  do sleep 0.1; n=$((n+1)); done
  echo "KF-DAEMON-READY $(cut -d' ' -f1 /proc/uptime)"
  sleep @RUN_S@
  # At least a dozen frames decided before SIGTERM, however slow the emulation (the
  # virtual camera's frames come slower when the host is busy): up to 30 s more.
  n=0
  while [ "$(cat /scratch/state/flights/*/decisions.csv 2>/dev/null | wc -l)" -lt 13 ] &&
        kill -0 $pid 2>/dev/null && [ $n -lt 300 ]
  do sleep 0.1; n=$((n+1)); done
  kill -TERM $pid && echo "KF-DAEMON-TERM $(cut -d' ' -f1 /proc/uptime)"
  wait $pid
  rc=$?
  echo "KF-DAEMON-EXIT $(cut -d' ' -f1 /proc/uptime)"
  sed 's/^/KF-LOG /' $log
  flight=$(ls -d /scratch/state/flights/* | head -1)
  echo "KF-SUMMARY $(tr -d '\n' < $flight/summary.json)"
  tail -n +2 $flight/decisions.csv | cut -d, -f4 | sort | uniq -c | sed 's/^ */KF-REASON /'
  first=$(ls $flight/keyframes/*.jpg 2>/dev/null | head -1)
  if [ -n "$first" ]; then
    echo "KF-JPEG-BEGIN"; base64 $first; echo "KF-JPEG-END"
  fi
  echo "KF-RC $rc"
else
  echo "KF-9P-MOUNT-FAIL"
  echo "KF-RC 99"
fi
"""
DAEMON_RUN_S = 4

# Colour bars at 100 %: white, yellow, cyan, green, magenta, red, blue, black, as
# BT.601 limited-range luma (Y = 16 + 219 * (0.299 R + 0.587 G + 0.114 B)).
BAR_LUMA = [235, 210, 170, 145, 106, 81, 41, 16]


def alt_bin() -> Path:
    """The daemon linked against libcamera 0.4 (daemon/CMakeLists.txt)."""
    default = ROOT / "build/release/daemon/keyframed-libcamera-alt"
    return Path(os.environ.get("KEYFRAMED_LIBCAMERA_ALT_BIN", default))


def host_library_dirs() -> list[str]:
    """Where this machine's loader finds libraries (its ld.so.cache), in that order."""
    out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True).stdout
    dirs: list[str] = []
    for line in out.splitlines():
        if "=> " in line and "x86-64" in line:
            d = str(Path(line.split("=> ", 1)[1].strip()).parent)
            if d not in dirs:
                dirs.append(d)
    return dirs or ["/usr/lib/x86_64-linux-gnu"]


def probe_sources() -> list[Path]:
    """The probe's sources, as daemon/CMakeLists.txt lists them."""
    text = (ROOT / "daemon" / "CMakeLists.txt").read_text()
    m = re.search(r"set\(KEYFRAMED_LIBCAMERA_PROBE_SOURCES\s+([^)]*)\)", text)
    assert m, "KEYFRAMED_LIBCAMERA_PROBE_SOURCES not found in daemon/CMakeLists.txt"
    return [ROOT / "daemon" / s for s in m.group(1).split()]


def libcamera_root(release: Path) -> Path:
    if not (release / "complete").is_file():
        pytest.skip(f"{release} missing: tools/setup.sh could not fetch it from deb.debian.org")
    return release / "root"


def compile_probe(root: Path, out: Path | None) -> subprocess.CompletedProcess[str]:
    """Compiles the probe against the libcamera under root: linked into `out`, or only
    checked (-fsyntax-only) when out is None."""
    cxx = shutil.which("g++")
    if cxx is None:
        pytest.skip("g++ not found")
    cmd = [cxx, "-std=c++20", "-O2", "-Wall", "-Wextra", "-Wpedantic", "-Wshadow"]
    cmd += ["-Wconversion", "-Wno-sign-conversion", "-Wold-style-cast", "-Werror"]
    cmd += ["-DKEYFRAMED_WITH_LIBCAMERA=1", f"-I{ROOT / 'daemon'}"]
    cmd += ["-isystem", str(root / "usr/include/libcamera"), "-isystem", "/usr/include/opencv4"]
    cmd += [str(s) for s in probe_sources()]
    if out is None:
        cmd += ["-fsyntax-only"]
    else:
        lib = root / "usr/lib/x86_64-linux-gnu"
        # libcamera's own dependencies are resolved at run time, in the VM, against
        # the newer C library it was built for.
        cmd += ["-o", str(out), f"-L{lib}", "-lcamera", "-lcamera-base", "-pthread"]
        cmd += ["-Wl,--allow-shlib-undefined"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def version_of(root: Path) -> str:
    h = (root / "usr/include/libcamera/libcamera/version.h").read_text()
    parts = [re.search(rf"LIBCAMERA_VERSION_{k}\s+(\d+)", h) for k in ("MAJOR", "MINOR", "PATCH")]
    return ".".join(p.group(1) if p else "?" for p in parts)


@pytest.mark.parametrize("release", [TRIXIE, SID], ids=["trixie", "sid"])
def test_libcamera_sources_compile_against_newer_releases(release: Path) -> None:
    root = libcamera_root(release)
    r = compile_probe(root, None)
    assert r.returncode == 0, f"against libcamera {version_of(root)}:\n{r.stderr[-4000:]}"
    print(f"compiled against libcamera {version_of(root)}")


@pytest.fixture(scope="module")
def vm(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    lc = libcamera_root(TRIXIE)
    qemu, busybox = qemu_vm.tools()
    work = tmp_path_factory.mktemp("libcamera-vm")
    probe = work / "keyframed-libcamera-probe"
    r = compile_probe(lc, probe)
    assert r.returncode == 0, r.stderr[-4000:]

    # The initramfs: Debian 13's runtime as its whole root, the probe, the virtual
    # camera's configuration where libcamera looks for it.
    root = work / "root"
    shutil.copytree(lc / "usr", root / "usr", symlinks=True)
    for unused in ("usr/share/doc", "usr/share/locale", "usr/share/man", "usr/include"):
        shutil.rmtree(root / unused, ignore_errors=True)
    os.symlink("usr/lib", root / "lib")
    os.symlink("usr/lib64", root / "lib64")
    for d in ("bin", "proc", "sys", "dev", "tmp"):
        (root / d).mkdir(exist_ok=True)
    shutil.copy(busybox, root / "bin" / "busybox")
    shutil.copy(probe, root / "probe")
    conf = root / "usr/share/libcamera/pipeline/virtual"
    conf.mkdir(parents=True)
    (conf / "virtual.yaml").write_text(VIRTUAL_YAML)
    cases = "\n".join(
        f'echo "KF-CASE {name}"\n/probe {args}\necho "KF-RC $?"' for name, args in CASES.items()
    )
    # The daemon section, when the daemon was built against this release and qemu
    # has virtio-9p (the VM reads the host's libraries through it).
    alt = alt_bin()
    devices = subprocess.run([qemu, "-device", "help"], capture_output=True, text=True)
    daemon_skip = None
    if not alt.exists():
        daemon_skip = f"{alt} not built (tools/build.sh builds it once setup fetched libcamera)"
    elif "virtio-9p-pci" not in devices.stdout + devices.stderr:
        daemon_skip = f"{qemu} has no virtio-9p-pci device (no virtfs support)"
    daemon = ""
    if daemon_skip is None:
        shutil.copytree(TRIXIE / "modules", root / "modules")
        # Debian's alternatives (BLAS, LAPACK, ...) are absolute links through
        # /etc/alternatives into subdirectories of the library directory: lead both
        # to the host's copies.
        (root / "etc").mkdir(exist_ok=True)
        os.symlink("/host/etc/alternatives", root / "etc" / "alternatives")
        libdir = Path("/usr/lib/x86_64-linux-gnu")
        for sub in libdir.iterdir():
            target = root / "usr/lib/x86_64-linux-gnu" / sub.name
            if sub.is_dir() and not sub.is_symlink() and not target.exists():
                os.symlink(f"/host{sub}", target)
        sets = [
            "camera.source=libcamera",
            "camera.width=640",
            "camera.height=480",
            "camera.fps=30",
            "output.state_dir=/scratch/state",
            "telemetry.url=",
            "zenoh.enabled=false",
        ]
        daemon = (
            DAEMON.replace("@ALT@", str(alt.resolve()))
            .replace("@SETS@", " ".join(f"--set {x}" for x in sets))
            .replace("@RUN_S@", str(DAEMON_RUN_S))
            .replace("@HOSTLIBS@", ":".join(f"/host{d}" for d in host_library_dirs()))
        )
    initrd = work / "initrd.cpio"
    qemu_vm.initramfs(root, INIT.replace("@CASES@", cases).replace("@DAEMON@", daemon), initrd)
    virtfs = "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap"
    console, elapsed = qemu_vm.boot(
        qemu,
        TRIXIE / "vmlinuz",
        initrd,
        timeout_s=BOOT_TIMEOUT_S,
        log=work / "console.log",
        extra=[] if daemon_skip else ["-virtfs", virtfs],
    )
    print(f"libcamera VM: {elapsed:.1f} s wall, console {work / 'console.log'}")

    sections: dict[str, dict] = {}
    current: dict | None = None
    for line in console.splitlines():
        if line.startswith("KF-CASE "):
            current = {"events": [], "rc": None, "text": []}
            sections[line.split(" ", 1)[1].strip()] = current
        elif current is not None and line.startswith("KF-RC "):
            current["rc"] = int(line.split()[1])
            current = None
        elif current is not None:
            current["text"].append(line)
            if line.startswith("{"):
                current["events"].append(json.loads(line))
    if daemon_skip:
        sections["daemon"] = {"skip": daemon_skip}
    return sections


def events(case: dict, kind: str) -> list[dict]:
    return [e for e in case["events"] if e["event"] == kind]


def test_virtual_camera_is_listed(vm: dict[str, dict]) -> None:
    case = vm["list"]
    assert case["rc"] == 0, case["text"]
    assert [e["id"] for e in events(case, "camera")] == ["Virtual0"]


def test_streams_nv12_with_recycled_requests_and_sensor_timestamps(vm: dict[str, dict]) -> None:
    case = vm["stream"]
    assert case["rc"] == 0, case["text"]
    (stream,) = events(case, "stream")
    assert (stream["format"], stream["width"], stream["height"]) == ("NV12", 640, 480), stream
    assert stream["stride"] >= 640 and stream["info_fps"] == 30, stream
    (s,) = events(case, "summary")
    # 40 frames through 4 buffers: each request went back to the camera ten times.
    assert s["frames"] == 40 and s["indexed"] and s["monotonic"], s
    assert s["sensor_timestamps"], s  # controls::SensorTimestamp, not the buffer's time
    # libcamera 0.4's virtual camera leaves the buffers' FrameMetadata::status
    # unset (fixed in later releases), so some come back "failed": they are counted
    # and requeued, never handed on.
    print(f"failed (uninitialised status) buffers: {s['failed_frames']}")
    assert events(case, "closed"), case["text"]  # stopped and released without a crash


def test_nv12_pixels_are_the_colour_bars(vm: dict[str, dict]) -> None:
    (stream,) = events(vm["stream"], "stream")
    row = stream["luma_row"]
    assert len(row) == 32
    # 32 samples across 8 bars: 4 a bar, each the bar's luma.
    bars = [row[4 * i : 4 * i + 4] for i in range(8)]
    for want, got in zip(BAR_LUMA, bars, strict=True):
        assert all(abs(v - want) <= 2 for v in got), (BAR_LUMA, row)


def test_size_and_role_the_camera_does_not_offer(vm: dict[str, dict]) -> None:
    # Only 640x480 is offered: a request for 1080p gets the nearest size (the daemon
    # logs the difference), the viewfinder role the same stream.
    for name in ("other_size", "viewfinder"):
        case = vm[name]
        assert case["rc"] == 0, case["text"]
        (stream,) = events(case, "stream")
        assert (stream["width"], stream["height"]) == (640, 480), stream
        (s,) = events(case, "summary")
        assert s["frames"] == 5 and s["monotonic"], s


def test_clear_errors_for_a_missing_format_and_an_unknown_camera(vm: dict[str, dict]) -> None:
    yuyv = vm["yuyv"]
    assert yuyv["rc"] == 1, yuyv["text"]
    (err,) = events(yuyv, "error")
    assert "does not offer YUYV" in err["message"] and "NV12" in err["message"], err
    unknown = vm["unknown"]
    assert unknown["rc"] == 1, unknown["text"]
    (err,) = events(unknown, "error")
    assert err["message"] == "camera 'nope' not found (available: Virtual0)", err


def daemon_run(vm: dict[str, dict]) -> dict:
    d = vm["daemon"]
    if d.get("skip"):
        pytest.skip(d["skip"])
    text = d["text"]
    assert "KF-9P-MOUNT-FAIL" not in text, "mounting the host root over 9p failed"
    assert not [x for x in text if x.startswith("KF-INSMOD-FAIL")], text
    log = [x[len("KF-LOG ") :] for x in text if x.startswith("KF-LOG ")]
    summary = [json.loads(x[len("KF-SUMMARY ") :]) for x in text if x.startswith("KF-SUMMARY ")]
    marks = {x.split()[0]: float(x.split()[1]) for x in text if x.startswith("KF-DAEMON-")}
    jpeg = b""
    if "KF-JPEG-BEGIN" in text:
        lines = text[text.index("KF-JPEG-BEGIN") + 1 : text.index("KF-JPEG-END")]
        jpeg = base64.b64decode("".join(lines))
    return {
        "rc": d["rc"],
        "log": log,
        "summary": summary,
        "marks": marks,
        "jpeg": jpeg,
        "text": text,
    }


def test_daemon_runs_on_libcamera_and_stops_cleanly(vm: dict[str, dict]) -> None:
    d = daemon_run(vm)
    log = "\n".join(d["log"])
    assert d["rc"] == 0, log
    assert "capturing from libcamera" in log and "640x480" in log, log
    assert "ready: first frame received" in log, log
    marks = d["marks"]
    # SIGTERM ends it within a second, outputs flushed: by the daemon's own log (its
    # last line comes after the summary and the record are closed) and the process gone.
    stop = logged_stop_s(log)
    assert stop is not None and stop < 1.0, log
    assert marks["KF-DAEMON-EXIT"] - marks["KF-DAEMON-TERM"] < 1.0, marks
    (s,) = d["summary"]
    assert s["state"] == "stopped" and (s["width"], s["height"]) == (640, 480), s
    assert "Virtual0" in s["source"], s
    assert s["frames_read"] >= 10 and s["kept"] >= 1, s
    # Nothing complains but about the calibration (none given).
    complaints = [x for x in d["log"] if re.search(r"\d [EW] \w+:", x)]
    assert all("no tagging.calibration" in x for x in complaints), complaints
    # A static test pattern, striped without corners: one keyframe, then nothing new
    # to measure (each frame a keyframe of its own before the selector knew better).
    reasons = {x.split()[2]: int(x.split()[1]) for x in d["text"] if x.startswith("KF-REASON ")}
    assert s["kept"] == 1 and reasons.get("first") == 1, (s, reasons)
    assert reasons.get("featureless", 0) >= s["frames_read"] - 1 - s["rejected_blur"], reasons
    print(f"daemon on libcamera 0.4: {s['frames_read']} frames read, {s['kept']} kept")


def test_daemon_keyframe_is_the_colour_bars(vm: dict[str, dict]) -> None:
    d = daemon_run(vm)
    assert d["jpeg"], "no keyframe written"
    import cv2
    import numpy as np

    img = cv2.imdecode(np.frombuffer(d["jpeg"], np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (480, 640, 3), None if img is None else img.shape
    # white, yellow, cyan, green, magenta, red, blue, black (BGR)
    bars = [(255, 255, 255), (0, 255, 255), (255, 255, 0), (0, 255, 0)]
    bars += [(255, 0, 255), (0, 0, 255), (255, 0, 0), (0, 0, 0)]
    for i, want in enumerate(bars):
        got = img[240, 40 + 80 * i].astype(int)
        assert np.abs(got - np.array(want)).max() <= 40, (i, got.tolist(), want)
