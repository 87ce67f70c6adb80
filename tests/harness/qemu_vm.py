"""Booting a throw-away qemu VM (TCG, no KVM) from a kernel and a busybox initramfs,
for the tests that need a kernel of their own: the vivid V4L2 driver
(test_v4l2_vivid.py), libcamera's virtual camera (test_libcamera_virtual.py), systemd
as PID 1 running the installed service (test_systemd_vm.py)."""

from __future__ import annotations

import gzip
import lzma
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from conftest import keyframed_bin


def tools() -> tuple[str, str]:
    """qemu-system-x86_64 and a static busybox, or the test skips saying which is missing."""
    qemu = shutil.which("qemu-system-x86_64")
    if not qemu:
        pytest.skip("qemu-system-x86_64 not found: apt-get install qemu-system-x86")
    busybox = shutil.which("busybox") or "/bin/busybox"
    if not Path(busybox).exists():
        pytest.skip("busybox not found: apt-get install busybox-static")
    if not shutil.which("cpio"):
        pytest.skip("cpio not found: apt-get install cpio")
    return qemu, busybox


def initramfs(root: Path, init: str, out: Path) -> None:
    """root's tree with `init` (the script the kernel runs first) as a newc cpio archive
    (uncompressed: quicker to unpack under TCG)."""
    (root / "init").write_text(init)
    (root / "init").chmod(0o755)
    files = subprocess.run(["find", "."], cwd=root, capture_output=True, check=True).stdout
    with out.open("wb") as f:
        subprocess.run(
            ["cpio", "-o", "-H", "newc", "--quiet"], cwd=root, input=files, stdout=f, check=True
        )


def boot(
    qemu: str,
    kernel: Path,
    initrd: Path,
    *,
    timeout_s: float,
    log: Path,
    extra: list[str] | None = None,
    booted: str = "KF-BOOTED",
    append_extra: str = "",
    memory_mb: int = 1024,
) -> tuple[str, float]:
    """Boots kernel + initrd (its /init powers off when done) with the serial console on
    stdout; returns the console text and the wall time. Fails when the VM hangs or its
    init never prints `booted`; skips when qemu cannot run here at all."""
    cmd = [qemu, "-accel", "tcg", "-m", str(memory_mb), "-smp", "1", "-kernel", str(kernel)]
    append = f"console=ttyS0 rdinit=/init quiet loglevel=3 panic=-1 {append_extra}".strip()
    cmd += ["-initrd", str(initrd), "-append", append]
    cmd += ["-nographic", "-no-reboot", "-nodefaults", "-serial", "stdio", *(extra or [])]
    t0 = time.monotonic()
    try:
        out = subprocess.run(cmd, capture_output=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as e:
        text = (e.stdout or b"").decode(errors="replace")
        pytest.fail(f"VM did not finish in {timeout_s} s; console:\n{text[-4000:]}")
    elapsed = time.monotonic() - t0
    console = out.stdout.decode(errors="replace").replace("\r", "")
    if booted not in console:
        if out.returncode != 0 and not console.strip():
            pytest.skip(f"qemu could not run: {out.stderr.decode(errors='replace')[-500:]}")
        pytest.fail(f"VM did not boot into the test init; console:\n{console[-4000:]}")
    log.write_text(console)
    return console, elapsed


def kernel() -> tuple[Path, Path]:
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


def module_order(moddir: Path, name: str) -> list[str]:
    """A module and its dependencies from modules.dep, dependencies first."""
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


def ninep_modules(moddir: Path) -> tuple[list[str], str | None]:
    """The modules (dependencies first) for a virtio-9p root, or why it cannot be had."""
    dep = (moddir / "modules.dep").read_text()
    builtin_file = moddir / "modules.builtin"
    builtin = builtin_file.read_text() if builtin_file.exists() else ""
    order: list[str] = []
    for name in ("virtio_pci", "9pnet_virtio", "9p"):
        if re.search(rf"/{name}\.ko$", builtin, re.M):
            continue
        if not re.search(rf"/{name}\.ko(\.\w+)?:", dep):
            return [], f"the kernel has no {name} module (modules.dep/modules.builtin in {moddir})"
        order += [m for m in module_order(moddir, name) if m not in order]
    return order, None


def copy_module(src: Path, dst_dir: Path) -> str:
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


def copy_program(src: Path, root: Path, dst: str) -> None:
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


def v4l2_probe_bin() -> Path:
    env = os.environ.get("KEYFRAMED_V4L2_PROBE")
    path = Path(env) if env else keyframed_bin().parent / "keyframed-v4l2-probe"
    if not path.exists():
        pytest.fail(f"{path} not found: build the keyframed-v4l2-probe target")
    return path
