"""V4L2 capture against a real kernel driver: vivid, under qemu (TCG, no KVM).

The test builds a tiny initramfs (static busybox, the vivid module and the media
modules it needs, the static keyframed-v4l2-probe), boots Debian's kernel with it,
and inside the VM: captures each format vivid offers, checks driver timestamps
(monotonic, at the configured rate), unbinds and removes vivid while capturing
(the "device went away" path) and loads it again (recovery). Results come back
as JSON lines on the serial console.

Skipped only when qemu-system-x86_64, a kernel with vivid.ko, or busybox cannot
be found or run (tools/setup.sh installs them).
"""

from __future__ import annotations

import gzip
import json
import lzma
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from conftest import keyframed_bin

WIDTH, HEIGHT, FPS = 640, 360, 30
# vivid's formats this test captures; MJPEG is checked for and expected absent
# (vivid has no compressed capture formats).
FORMATS = ["YUYV", "NV12", "YUV420", "MJPEG"]
BOOT_TIMEOUT_S = 150


def _probe_bin() -> Path:
    env = os.environ.get("KEYFRAMED_V4L2_PROBE")
    path = Path(env) if env else keyframed_bin().parent / "keyframed-v4l2-probe"
    if not path.exists():
        pytest.fail(f"{path} not found: build the keyframed-v4l2-probe target")
    return path


def _kernel() -> tuple[Path, Path]:
    """The newest /boot/vmlinuz-VER whose /lib/modules/VER holds vivid."""
    want = os.environ.get("KEYFRAMED_VM_KERNEL_VERSION")
    found = []
    for vmlinuz in sorted(Path("/boot").glob("vmlinuz-*")):
        ver = vmlinuz.name[len("vmlinuz-") :]
        moddir = Path("/lib/modules") / ver
        if want and ver != want:
            continue
        if (moddir / "modules.dep").exists() and list(moddir.rglob("vivid.ko*")):
            found.append((vmlinuz, moddir))
    if not found:
        pytest.skip(
            "no kernel with vivid.ko (/boot/vmlinuz-* + /lib/modules/*/.../vivid.ko): "
            "apt-get install linux-image-amd64"
        )
    vmlinuz, moddir = found[-1]
    if not os.access(vmlinuz, os.R_OK):
        pytest.skip(f"{vmlinuz} is not readable by this user")
    return vmlinuz, moddir


def _module_order(moddir: Path, name: str) -> list[str]:
    """vivid and its dependencies from modules.dep, dependencies first."""
    deps: dict[str, list[str]] = {}
    for line in (moddir / "modules.dep").read_text().splitlines():
        mod, _, rest = line.partition(":")
        deps[mod] = rest.split()
    target = next(m for m in deps if re.search(rf"/{name}\.ko(\.\w+)?$", m))
    order: list[str] = []

    def visit(mod: str) -> None:
        if mod in order:
            return
        for d in deps.get(mod, []):
            visit(d)
        order.append(mod)

    visit(target)
    return order


def _copy_module(src: Path, dst_dir: Path) -> str:
    """Copies one module, decompressing .ko.xz/.ko.zst/.ko.gz (busybox insmod wants plain .ko)."""
    base = src.name.split(".ko")[0] + ".ko"
    dst = dst_dir / base
    if src.suffix == ".xz":
        dst.write_bytes(lzma.decompress(src.read_bytes()))
    elif src.suffix == ".gz":
        dst.write_bytes(gzip.decompress(src.read_bytes()))
    elif src.suffix == ".zst":
        if not shutil.which("zstd"):
            pytest.skip("kernel modules are zstd-compressed and zstd is not installed")
        subprocess.run(["zstd", "-q", "-d", "-f", str(src), "-o", str(dst)], check=True)
    else:
        shutil.copyfile(src, dst)
    return base


def _copy_program(src: Path, root: Path, dst: str) -> None:
    """Copies a program, with its shared libraries and loader when it is dynamic."""
    target = root / dst.lstrip("/")
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src, target)
    out = subprocess.run(["ldd", str(src)], capture_output=True, text=True)
    if out.returncode != 0 or "not a dynamic executable" in out.stdout + out.stderr:
        return
    for line in out.stdout.splitlines():
        m = re.search(r"(/\S+)", line.split("=>")[-1])
        if m and Path(m.group(1)).exists():
            lib = Path(m.group(1))
            dest = root / str(lib).lstrip("/")
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(lib, dest)


INIT = r"""#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
mkdir -p /tmp
echo "KF-BOOTED $(cut -d' ' -f1 /proc/uptime)"
for m in $(cat /modules.order); do
  insmod /modules/$m || echo "KF-INSMOD-FAIL $m"
done
VIVID="/modules/vivid.ko n_devs=1 node_types=0x101"
insmod $VIVID || echo "KF-INSMOD-FAIL vivid.ko"
n=0; while [ ! -e /dev/video0 ] && [ $n -lt 50 ]; do sleep 0.1; n=$((n+1)); done
echo "KF-VIVID-LOADED $(cut -d' ' -f1 /proc/uptime)"
/probe --list
for fmt in @FORMATS@; do
  echo "KF-BEGIN $fmt"
  /probe --device /dev/video0 --format $fmt --size @SIZE@ --fps @FPS@ --frames @FRAMES@
  echo "KF-RC $fmt $?"
done
echo "KF-BEGIN notcapture"
/probe --device /dev/video1 --frames 1
echo "KF-RC notcapture $?"
echo "KF-BEGIN missing"
/probe --device /dev/video7 --frames 1
echo "KF-RC missing $?"

# Device going away mid-capture: unbind the driver, then unload it; bring it back.
echo "KF-BEGIN recover"
: > /tmp/recover.log
/probe --device /dev/video0 --format YUYV --size @SIZE@ --fps @FPS@ --frames @RFRAMES@ \
  --reopen-wait 30 --verbose > /tmp/recover.log 2>&1 &
pid=$!
n=0; while [ "$(grep -c '"event":"frame"' /tmp/recover.log)" -lt 20 ] && [ $n -lt 200 ]; do
  sleep 0.1; n=$((n+1)); done
echo "KF-UNBIND $(cut -d' ' -f1 /proc/uptime)"
echo vivid.0 > /sys/bus/platform/drivers/vivid/unbind || echo "KF-UNBIND-FAIL"
n=0; while ! grep -q '"lost":true' /tmp/recover.log && [ $n -lt 100 ]; do
  sleep 0.1; n=$((n+1)); done
rmmod vivid && echo "KF-RMMOD ok" || echo "KF-RMMOD-FAIL"
sleep 1
insmod $VIVID && echo "KF-RELOAD $(cut -d' ' -f1 /proc/uptime)" || echo "KF-INSMOD-FAIL vivid.ko"
wait $pid
rc=$?
cat /tmp/recover.log
echo "KF-RC recover $rc"
echo "KF-DONE $(cut -d' ' -f1 /proc/uptime)"
poweroff -f
"""


@pytest.fixture(scope="module")
def vm_run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    qemu = shutil.which("qemu-system-x86_64")
    if not qemu:
        pytest.skip("qemu-system-x86_64 not found: apt-get install qemu-system-x86")
    busybox = shutil.which("busybox") or "/bin/busybox"
    if not Path(busybox).exists():
        pytest.skip("busybox not found: apt-get install busybox-static")
    if not shutil.which("cpio"):
        pytest.skip("cpio not found: apt-get install cpio")
    vmlinuz, moddir = _kernel()
    probe = _probe_bin()

    work = tmp_path_factory.mktemp("vivid-vm")
    root = work / "root"
    for d in ("bin", "proc", "sys", "dev", "tmp", "modules"):
        (root / d).mkdir(parents=True)
    _copy_program(Path(busybox), root, "/bin/busybox")
    _copy_program(probe, root, "/probe")
    order = _module_order(moddir, "vivid")
    names = [_copy_module(moddir / m, root / "modules") for m in order]
    (root / "modules.order").write_text("\n".join(n for n in names if n != "vivid.ko") + "\n")
    init = (
        INIT.replace("@FORMATS@", " ".join(FORMATS))
        .replace("@SIZE@", f"{WIDTH}x{HEIGHT}")
        .replace("@FPS@", str(FPS))
        .replace("@FRAMES@", "45")
        .replace("@RFRAMES@", "60")
    )
    (root / "init").write_text(init)
    (root / "init").chmod(0o755)
    initrd = work / "initrd.cpio"
    files = subprocess.run(["find", "."], cwd=root, capture_output=True, check=True).stdout
    with initrd.open("wb") as f:
        subprocess.run(
            ["cpio", "-o", "-H", "newc", "--quiet"], cwd=root, input=files, stdout=f, check=True
        )

    cmd = [
        qemu,
        "-accel",
        "tcg",
        "-m",
        "512",
        "-smp",
        "1",
        "-kernel",
        str(vmlinuz),
        "-initrd",
        str(initrd),
        "-append",
        "console=ttyS0 rdinit=/init quiet loglevel=3 panic=-1",
        "-nographic",
        "-no-reboot",
        "-nodefaults",
        "-serial",
        "stdio",
    ]
    t0 = time.monotonic()
    try:
        out = subprocess.run(cmd, capture_output=True, timeout=BOOT_TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        text = (e.stdout or b"").decode(errors="replace")
        pytest.fail(f"VM did not finish in {BOOT_TIMEOUT_S} s; console:\n{text[-4000:]}")
    elapsed = time.monotonic() - t0
    console = out.stdout.decode(errors="replace").replace("\r", "")
    if "KF-BOOTED" not in console:
        if out.returncode != 0 and not console.strip():
            pytest.skip(f"qemu could not run: {out.stderr.decode(errors='replace')[-500:]}")
        pytest.fail(f"VM did not boot into the test init; console:\n{console[-4000:]}")
    (work / "console.log").write_text(console)
    print(f"vivid VM: {elapsed:.1f} s wall, console log {work / 'console.log'}")
    return {"console": console, "elapsed": elapsed, "sections": _sections(console)}


def _sections(console: str) -> dict[str, dict]:
    """Per KF-BEGIN section: its JSON events and the probe's exit code."""
    sections: dict[str, dict] = {"": {"events": [], "rc": None}}
    current = ""
    for line in console.splitlines():
        line = line.strip()
        if line.startswith("KF-BEGIN "):
            current = line.split()[1]
            sections[current] = {"events": [], "rc": None}
        elif line.startswith("KF-RC "):
            _, name, rc = line.split()
            sections[name]["rc"] = int(rc)
        elif line.startswith("{"):
            try:
                sections[current]["events"].append(json.loads(line))
            except json.JSONDecodeError:
                pass  # a kernel message cut into the line
    return sections


def _events(section: dict, kind: str) -> list[dict]:
    return [e for e in section["events"] if e.get("event") == kind]


def test_vivid_listed_as_capture_device(vm_run: dict) -> None:
    devices = _events(vm_run["sections"][""], "device")
    assert devices, vm_run["console"][-3000:]
    vivid = [d for d in devices if d["driver"] == "vivid"]
    assert vivid and vivid[0]["path"] == "/dev/video0"
    assert vivid[0]["capture"] and vivid[0]["streaming"]
    assert {"YUYV", "NV12", "YU12"} <= set(vivid[0]["formats"])
    # node_types=0x101: a video output node beside the capture node
    assert any(d["path"] == "/dev/video1" and not d["capture"] for d in vivid), vivid


def test_clear_errors_for_output_and_missing_nodes(vm_run: dict) -> None:
    sec = vm_run["sections"]["notcapture"]
    assert sec["rc"] == 1
    (err,) = _events(sec, "error")
    assert err["reason"] == "/dev/video1 (vivid: vivid) is not a video capture device", err
    sec = vm_run["sections"]["missing"]
    assert sec["rc"] == 1
    (err,) = _events(sec, "error")
    assert err["reason"] == "no such device: /dev/video7", err


@pytest.mark.parametrize("fmt", ["YUYV", "NV12", "YUV420"])
def test_vivid_capture_format(vm_run: dict, fmt: str) -> None:
    sec = vm_run["sections"].get(fmt)
    assert sec is not None, vm_run["console"][-3000:]
    assert sec["rc"] == 0, sec["events"]
    (opened,) = _events(sec, "open")
    assert (opened["width"], opened["height"]) == (WIDTH, HEIGHT)
    assert opened["fps"] == pytest.approx(FPS)
    (s,) = _events(sec, "summary")
    assert s["ok"] and s["frames"] == 45
    assert s["driver_timestamps"], "vivid stamps buffers on CLOCK_MONOTONIC"
    assert s["monotonic"]
    # Driver time is CLOCK_MONOTONIC: the last frame was stamped close to now
    # (vivid stamps the end of the frame period it schedules: up to a frame ahead).
    assert abs(s["monotonic_now_ns"] - s["last_ts_ns"]) < 1_000_000_000, s
    # Timestamps come at the configured rate. Under TCG vivid may fall behind
    # and drop frames (sequence gaps), so the median delta is checked, and the
    # span against the frames the driver produced.
    assert s["delta_ms_median"] == pytest.approx(1000 / FPS, rel=0.15), s
    produced = s["frames"] - 1 + s["sequence_gaps"]
    span_ms = (s["last_ts_ns"] - s["first_ts_ns"]) / 1e6
    assert span_ms == pytest.approx(produced * 1000 / FPS, rel=0.15), s
    assert 16 < s["mean"] < 240, "the test pattern is neither black nor white"
    print(
        f"{fmt}: {s['fps_measured']:.2f} fps measured, delta median "
        f"{s['delta_ms_median']:.3f} ms, std {s['delta_ms_std']:.3f} ms, "
        f"min {s['delta_ms_min']:.3f} max {s['delta_ms_max']:.3f}, gaps {s['sequence_gaps']}, "
        f"cpu {s['cpu_percent']:.1f} % (TCG)"
    )


def test_vivid_has_no_mjpeg_and_says_so(vm_run: dict) -> None:
    sec = vm_run["sections"]["MJPEG"]
    assert sec["rc"] == 1
    (err,) = _events(sec, "error")
    assert "does not offer MJPG" in err["reason"] and "YUYV" in err["reason"], err


def test_vivid_unbind_and_reload_recovers(vm_run: dict) -> None:
    console = vm_run["console"]
    assert "KF-RMMOD ok" in console, "rmmod vivid failed: the source kept the device open"
    assert "KF-RELOAD" in console
    sec = vm_run["sections"]["recover"]
    lost = [e for e in _events(sec, "error") if e.get("lost")]
    assert lost, sec["events"]
    assert "device lost: /dev/video0" in lost[0]["reason"], lost[0]
    assert lost[0]["frame"] >= 15
    (rec,) = _events(sec, "recovered")
    assert rec["reopens"] == 1
    (s,) = _events(sec, "summary")
    assert sec["rc"] == 0 and s["ok"], s
    assert s["frames"] == 60 and s["reopens"] == 1
    # Frame indices continue across the reopen and timestamps keep increasing.
    frames = _events(sec, "frame")
    assert [f["index"] for f in frames] == list(range(60))
    ts = [f["ts_ns"] for f in frames]
    assert all(b > a for a, b in zip(ts, ts[1:], strict=False))
    print(f"recovered {rec['after_s']:.2f} s after the loss; VM total {vm_run['elapsed']:.1f} s")
