"""Booting a throw-away qemu VM (TCG, no KVM) from a kernel and a busybox initramfs,
for the tests that need a kernel of their own: the vivid V4L2 driver
(test_v4l2_vivid.py), libcamera's virtual camera (test_libcamera_virtual.py)."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest


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


def initramfs(root: Path, out: Path) -> None:
    """root's tree as a newc cpio archive (uncompressed: quicker to unpack under TCG)."""
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
) -> tuple[str, float]:
    """Boots kernel + initrd (its /init powers off when done) with the serial console on
    stdout; returns the console text and the wall time. Fails when the VM hangs or its
    init never prints `booted`; skips when qemu cannot run here at all."""
    cmd = [qemu, "-accel", "tcg", "-m", "1024", "-smp", "1", "-kernel", str(kernel)]
    append = "console=ttyS0 rdinit=/init quiet loglevel=3 panic=-1"
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
