"""The installed service under a real systemd: PID 1 in a qemu VM (TCG, no KVM).

test_systemd.py checks the unit file, its notify protocol and its sandbox from
outside; this runs it as an operator would. The VM boots Debian's kernel with a
busybox initramfs that mounts this machine's root read-only over virtio-9p under a
tmpfs overlay (writes stay in the VM), hides its /tmp, and switches to
/lib/systemd/systemd with `systemd.unit=kf-test.target`: only the units the test
needs start. The test unit (as root, in the VM) loads vivid (the kernel's virtual
camera; udev gives /dev/video0 to group video), installs the package built from this
tree with dpkg (postinst makes the keyframed user), points the camera at vivid in a
conf.d drop-in, and then:

- `systemctl start keyframed` returns once the daemon said READY=1 (Type=notify,
  after the first frame); it runs as user keyframed with groups video and dialout,
  under the unit's sandbox (seccomp, no new privileges, read-only /, a writable
  StateDirectory), its log in the journal and its STATUS= in `systemctl show`;
- `systemctl reload` (SIGHUP) applies a changed selection setting;
- the camera stalls (vivid drops every buffer): the daemon stops feeding the
  watchdog, systemd stops it after WatchdogSec (SIGTERM: it flushes its flight)
  and restarts it, and it is ready again once frames come back;
- `systemctl stop` stops it cleanly; each start left a complete flight, owned by
  keyframed, in /var/lib/keyframed; `systemd-analyze security` rates the running
  unit as test_systemd.py does offline;
- `dpkg -r keyframed` stops the running service (prerm), flushing its flight, and
  leaves every flight in place.

Results come back through a second, writable 9p share. Skipped with the reason when
qemu, virtio-9p, the kernel's 9p/overlay/vivid modules, busybox or cpio are missing.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import qemu_vm
from conftest import host_package_lock

BOOT_TIMEOUT_S = 480
WIDTH, HEIGHT, FPS = 640, 360, 30

INIT = r"""#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
echo "KF-BOOTED $(cut -d' ' -f1 /proc/uptime)"
for m in $(cat /modules.order); do insmod /modules/$m || echo "KF-INSMOD-FAIL $m"; done
fail() { echo "KF-INIT-FAIL $1"; poweroff -f; }
mount -t 9p -o trans=virtio,version=9p2000.L,ro,cache=loose,msize=512000 hostroot /lower ||
  fail "9p root"
mount -t tmpfs -o size=512m rw /rw
mkdir -p /rw/upper /rw/work
mount -t overlay -o lowerdir=/lower,upperdir=/rw/upper,workdir=/rw/work overlay /newroot ||
  fail overlay
mkdir -p /newroot/kf
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 kfshare /newroot/kf || fail share
# This machine's /tmp and /var/tmp hidden: systemd-tmpfiles would empty them at boot,
# file by file through the overlay.
mount -t tmpfs -o size=64m,mode=1777 tmp /newroot/tmp
mount -t tmpfs -o size=64m,mode=1777 vartmp /newroot/var/tmp
cp -a /newroot/kf/in/units/. /newroot/etc/systemd/system/
# A container image's marker would make systemd boot as in a container (and ignore
# the kernel command line).
rm -f /newroot/.dockerenv /newroot/run/.containerenv
echo "KF-SWITCH $(cut -d' ' -f1 /proc/uptime)"
umount /proc /sys
mount --move /dev /newroot/dev || umount /dev
exec switch_root /newroot /lib/systemd/systemd
"""

TARGET = """[Unit]
Description=keyframed VM test
Requires=kf-test.service
After=kf-test.service
AllowIsolate=yes
"""

TEST_SERVICE = """[Unit]
Description=keyframed VM test script
Requires=basic.target
After=basic.target

[Service]
Type=oneshot
ExecStart=/bin/sh /kf/in/test.sh
StandardOutput=file:/kf/out/test.log
StandardError=inherit
"""

# As root under systemd in the VM. Each step's evidence goes to /kf/out; the host
# side asserts. Marks are CLOCK_BOOTTIME (/proc/uptime), the journal's monotonic
# timestamps the same clock in a VM that never suspends.
TEST_SH = r"""
set -x
out=/kf/out
mark() { echo "$1 $(cut -d' ' -f1 /proc/uptime)" >> $out/marks; }
show() {
  systemctl show keyframed -p ActiveState -p SubState -p MainPID -p StatusText \
    -p NRestarts -p Result -p ExecMainStatus -p ExecMainCode > $out/show-$1.txt
}
prop() { systemctl show keyframed -p "$1" --value; }
# Waits up to $1 tenths of a second for the command that follows to succeed.
wait_for() { n=0; lim=$1; shift; until "$@"; do
  n=$((n+1)); [ $n -ge $lim ] && return 1; sleep 0.1; done; }
restarted() { [ "$(prop NRestarts)" -ge 1 ]; }
frames_flowing() { prop StatusText | grep -Eq '^[1-9][0-9.]* fps|^0\.[1-9][0-9]* fps'; }

mark test-start
systemd-detect-virt > $out/virt.txt
modprobe vivid n_devs=1 node_types=0x1
udevadm settle
stat -c '%G %a' /dev/video0 > $out/video0.txt
DEBIAN_FRONTEND=noninteractive dpkg -i /kf/in/keyframed.deb > $out/dpkg.txt 2>&1
echo $? > $out/dpkg.rc
id keyframed > $out/id.txt
cp /kf/in/50-vivid.toml /etc/keyframed/conf.d/
keyframed check-config > $out/check-config.txt 2>&1
echo $? > $out/check-config.rc
# The emulated CPU loads the daemon's ~260 libraries over 9p: start-up takes
# longer than systemd's default 90 s allows on a slow host.
mkdir -p /etc/systemd/system/keyframed.service.d
printf '[Service]\nTimeoutStartSec=300\n' > /etc/systemd/system/keyframed.service.d/vm.conf
systemctl daemon-reload

mark start
systemctl start keyframed
echo $? > $out/start.rc
mark started
show started
pid=$(prop MainPID)
cat /proc/$pid/status > $out/proc-status.txt
cat /proc/$pid/mountinfo > $out/mountinfo.txt
wait_for 600 frames_flowing
show running

# A changed selection setting, applied by SIGHUP.
printf '[selection]\ntarget = 0.72\n' > /etc/keyframed/conf.d/60-reload.toml
mark reload
systemctl reload keyframed
echo $? > $out/reload.rc
sleep 2

# The camera stalls: no frame, so no watchdog ping; systemd stops and restarts it.
mark stall
/kf/in/probe --device /dev/video0 --set-ctrl "percentage of dropped buffers=100"
wait_for 1200 restarted
mark restarted
show restarted
/kf/in/probe --device /dev/video0 --set-ctrl "percentage of dropped buffers=0"
mark frames-back
wait_for 3000 systemctl is-active --quiet keyframed
mark active-again
wait_for 600 frames_flowing
show again

mark stop
systemctl stop keyframed
echo $? > $out/stop.rc
mark stopped
show stopped
find /var/lib/keyframed /var/log/keyframed -printf '%u %g %m %y %p\n' > $out/state.txt
n=0
for f in /var/lib/keyframed/flights/*/summary.json; do
  n=$((n+1)); cp "$f" $out/summary-$n.json
done
systemd-analyze security keyframed --no-pager > $out/security.txt 2>&1

# Removing the package stops the running service (prerm) and keeps its flights.
systemctl start keyframed
echo $? > $out/restart.rc
wait_for 600 frames_flowing
mark remove
DEBIAN_FRONTEND=noninteractive dpkg -r keyframed > $out/dpkg-r.txt 2>&1
echo $? > $out/dpkg-r.rc
mark removed
systemctl is-active keyframed > $out/after-remove.txt 2>&1
ls /var/lib/keyframed/flights > $out/flights-after-remove.txt
last=$(ls -d /var/lib/keyframed/flights/* | sort | tail -1)
cp $last/summary.json $out/removed-summary.json
[ -e /usr/bin/keyframed ] && echo present > $out/binary-after-remove.txt ||
  echo gone > $out/binary-after-remove.txt
journalctl -u keyframed -o json --no-pager > $out/journal.json
mark done
sync
systemctl poweroff --force --force
"""

VIVID_TOML = f"""# the VM's virtual camera
[camera]
source = "v4l2"
device = "/dev/video0"
width = {WIDTH}
height = {HEIGHT}
fps = {FPS}
"""


def _share(deb: Path, work: Path) -> Path:
    share = work / "share"
    (share / "out").mkdir(parents=True)
    inp = share / "in"
    (inp / "units").mkdir(parents=True)
    shutil.copy(deb, inp / "keyframed.deb")
    shutil.copy(qemu_vm.v4l2_probe_bin(), inp / "probe")  # static
    (inp / "test.sh").write_text(TEST_SH)
    (inp / "50-vivid.toml").write_text(VIVID_TOML)
    (inp / "units" / "kf-test.target").write_text(TARGET)
    (inp / "units" / "kf-test.service").write_text(TEST_SERVICE)
    return share


@pytest.fixture(scope="module")
def vm(deb: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    qemu, busybox = qemu_vm.tools()
    vmlinuz, moddir = qemu_vm.kernel()
    devices = subprocess.run([qemu, "-device", "help"], capture_output=True, text=True)
    if "virtio-9p-pci" not in devices.stdout + devices.stderr:
        pytest.skip(f"{qemu} has no virtio-9p-pci device (no virtfs support)")
    order, reason = qemu_vm.ninep_modules(moddir)
    if reason:
        pytest.skip(reason)
    order += [m for m in qemu_vm.module_order(moddir, "overlay") if m not in order]
    if not Path("/lib/systemd/systemd").exists() or not shutil.which("udevadm"):
        pytest.skip("systemd or udev not installed: apt-get install systemd udev")

    work = tmp_path_factory.mktemp("systemd-vm")
    root = work / "root"
    for d in ("bin", "proc", "sys", "dev", "modules", "lower", "rw", "newroot"):
        (root / d).mkdir(parents=True)
    qemu_vm.copy_program(Path(busybox), root, "/bin/busybox")
    names = [qemu_vm.copy_module(moddir / m, root / "modules") for m in order]
    (root / "modules.order").write_text("\n".join(names) + "\n")
    initrd = work / "initrd.cpio"
    qemu_vm.initramfs(root, INIT, initrd)
    share = _share(deb, work)
    with host_package_lock():  # the VM's dpkg reads this machine's package state
        console, elapsed = qemu_vm.boot(
            qemu,
            vmlinuz,
            initrd,
            timeout_s=BOOT_TIMEOUT_S,
            log=work / "console.log",
            append_extra="systemd.unit=kf-test.target systemd.show_status=false",
            memory_mb=1536,
            extra=[
                "-virtfs",
                "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap",
                "-virtfs",
                f"local,path={share},mount_tag=kfshare,security_model=none",
            ],
        )
    out = share / "out"
    failed = re.findall(r"KF-INIT-FAIL (.*)", console)
    assert not failed, f"the VM's init failed: {failed}; console:\n{console[-3000:]}"
    assert (out / "marks").exists(), f"the test unit never ran; console:\n{console[-3000:]}"
    print(f"systemd VM: {elapsed:.1f} s wall, results in {out}")
    return {"out": out, "console": console, "elapsed": elapsed}


def _text(vm: dict, name: str) -> str:
    path = vm["out"] / name
    assert path.exists(), f"{name} missing; the test unit's log:\n{_log_tail(vm)}"
    return path.read_text()


def _log_tail(vm: dict) -> str:
    log = vm["out"] / "test.log"
    return log.read_text()[-4000:] if log.exists() else vm["console"][-4000:]


def _marks(vm: dict) -> dict[str, float]:
    return {k: float(v) for k, v in (line.split() for line in _text(vm, "marks").splitlines())}


def _show(vm: dict, when: str) -> dict[str, str]:
    return dict(line.split("=", 1) for line in _text(vm, f"show-{when}.txt").splitlines())


def _journal(vm: dict) -> list[dict]:
    return [json.loads(line) for line in _text(vm, "journal.json").splitlines() if line]


def _messages(entries: list[dict]) -> list[tuple[float, str, dict]]:
    """(boot time in s, message, entry), in order."""
    out = []
    for e in entries:
        msg = e.get("MESSAGE")
        if isinstance(msg, list):  # not UTF-8: journalctl gives the bytes
            msg = bytes(msg).decode(errors="replace")
        out.append((int(e["__MONOTONIC_TIMESTAMP"]) / 1e6, msg or "", e))
    return out


def _status_counts(status: str) -> tuple[float, int, int]:
    m = re.match(r"([\d.]+) fps, (\d+) keyframes, (\d+) dropped", status)
    assert m, status
    return float(m.group(1)), int(m.group(2)), int(m.group(3))


def test_vm_boots_systemd_and_installs_the_package(vm: dict) -> None:
    assert _text(vm, "virt.txt").strip() == "qemu"  # not taken for a container
    assert _text(vm, "dpkg.rc").strip() == "0", _text(vm, "dpkg.txt")
    # udev gives the camera to group video; postinst put keyframed in it.
    assert _text(vm, "video0.txt").split() == ["video", "660"]
    ident = _text(vm, "id.txt")
    assert re.search(r"groups=.*\(video\)", ident) and "(dialout)" in ident, ident
    assert _text(vm, "check-config.rc").strip() == "0", _text(vm, "check-config.txt")


def test_start_returns_once_the_daemon_is_ready(vm: dict) -> None:
    assert _text(vm, "start.rc").strip() == "0", _log_tail(vm)
    s = _show(vm, "started")
    assert (s["ActiveState"], s["SubState"]) == ("active", "running"), s
    marks = _marks(vm)
    msgs = _messages(_journal(vm))
    opened = [t for t, m, e in msgs if "capturing from v4l2:/dev/video0" in m]
    ready = [t for t, m, e in msgs if "ready: first frame received" in m]
    started = [t for t, m, e in msgs if m.startswith("Started keyframed.service")]
    assert opened and ready and started, [m for _, m, _ in msgs][:40]
    # Type=notify: systemd calls the unit started, and `systemctl start` returns, only
    # at the daemon's READY=1, sent once the camera's first frame is in (the daemon's
    # "ready" line and systemd's reach the journal in either order).
    assert marks["start"] < opened[0] < started[0] <= marks["started"] + 0.5
    assert abs(ready[0] - started[0]) < 0.5, (ready[0], started[0])
    s = _show(vm, "running")
    fps, kept, dropped = _status_counts(s["StatusText"])
    assert fps > 0 and kept >= 1, s
    print(
        f"systemctl start to READY: {started[0] - marks['start']:.1f} s (emulated CPU); "
        f"STATUS={s['StatusText']!r}"
    )


def test_daemon_runs_as_its_user_inside_the_sandbox(vm: dict) -> None:
    ident = _text(vm, "id.txt")
    m = re.search(r"uid=(\d+)", ident)
    assert m, ident
    uid = m.group(1)
    groups = dict((name, gid) for gid, name in re.findall(r"(\d+)\((\w+)\)", ident))
    status = dict(
        (k, v.strip())
        for k, v in (line.split(":", 1) for line in _text(vm, "proc-status.txt").splitlines())
    )
    assert status["Uid"].split() == [uid] * 4, status["Uid"]
    assert {groups["video"], groups["dialout"]} <= set(status["Groups"].split()), status
    assert status["NoNewPrivs"] == "1"
    assert status["Seccomp"] == "2"  # SystemCallFilter: a filter is installed
    assert int(status["CapEff"], 16) == 0 and int(status["CapBnd"], 16) == 0, status
    mounts = {}
    for line in _text(vm, "mountinfo.txt").splitlines():
        fields = line.split()
        mounts[fields[4]] = fields[5].split(",")
    assert "ro" in mounts["/"], mounts["/"]  # ProtectSystem=strict
    assert "rw" in mounts["/var/lib/keyframed"], mounts.get("/var/lib/keyframed")
    # ProtectHome=yes: /home, /root and /run/user are empty and unreadable.
    assert any(m in mounts for m in ("/home", "/root")), sorted(mounts)
    assert "/tmp" in mounts  # PrivateTmp


def test_journal_holds_the_daemon_log_by_category(vm: dict) -> None:
    msgs = _messages(_journal(vm))
    daemon = [(m, e) for _, m, e in msgs if e.get("SYSLOG_IDENTIFIER") == "keyframed"]
    assert daemon, [m for _, m, _ in msgs][:40]
    opened = [e for m, e in daemon if "capturing from v4l2:/dev/video0 (vivid: vivid)" in m]
    assert opened and opened[0]["KEYFRAMED_CATEGORY"] == "capture", opened
    assert {"app", "capture"} <= {e["KEYFRAMED_CATEGORY"] for _, e in daemon}
    # Levels map onto journal priorities (a notice is 5, a warning 4).
    prio = {m: int(e["PRIORITY"]) for m, e in daemon}
    ready = next(m for m in prio if "ready: first frame received" in m)
    assert prio[ready] <= 6, (ready, prio[ready])


def test_reload_applies_a_changed_selection_setting(vm: dict) -> None:
    assert _text(vm, "reload.rc").strip() == "0"
    marks = _marks(vm)
    msgs = _messages(_journal(vm))
    after = [m for t, m, _ in msgs if marks["reload"] < t < marks["stall"]]
    assert any("selection settings reloaded" in m for m in after), after
    assert not any("reload: configuration invalid" in m for m in after), after


def test_watchdog_restarts_a_daemon_whose_camera_stalls(vm: dict) -> None:
    marks = _marks(vm)
    msgs = _messages(_journal(vm))
    stalled = [(t, m) for t, m, _ in msgs if marks["stall"] < t <= marks["restarted"] + 1]
    text = "\n".join(m for _, m in stalled)
    watchdog = [t for t, m in stalled if "Watchdog timeout" in m]
    assert watchdog, text
    assert not [m for t, m, _ in msgs if "Watchdog timeout" in m and t < marks["stall"]]
    # WatchdogSec=10 from the last ping; the daemon pings every 5 s while a frame came
    # in the last 2 s: the timeout comes 7 to 12 s after the last frame.
    assert 6.0 <= watchdog[0] - marks["stall"] <= 20.0, (watchdog[0], marks["stall"])
    # WatchdogSignal=SIGTERM: the daemon stops as on `systemctl stop`, flushing.
    assert any("SIGTERM: stopping" in m for t, m in stalled if t >= watchdog[0]), text
    s = _show(vm, "restarted")
    assert int(s["NRestarts"]) >= 1, s
    again = _show(vm, "again")
    assert again["ActiveState"] == "active", again
    fps, _, _ = _status_counts(again["StatusText"])
    assert fps > 0, again
    print(
        f"watchdog: stopped {watchdog[0] - marks['stall']:.1f} s after the stall, "
        f"ready again {marks['active-again'] - marks['frames-back']:.1f} s after frames came back"
    )


def test_stop_is_clean_and_every_flight_is_complete(vm: dict) -> None:
    assert _text(vm, "stop.rc").strip() == "0"
    s = _show(vm, "stopped")
    assert s["ActiveState"] == "inactive" and s["Result"] == "success", s
    assert s["ExecMainStatus"] == "0", s
    summaries = sorted(vm["out"].glob("summary-*.json"))
    assert len(summaries) == 2, summaries  # one before the watchdog's restart, one after
    states = sorted(json.loads(p.read_text())["state"] for p in summaries)
    assert states == ["stopped", "stopped"], states
    state = [line.split(maxsplit=4) for line in _text(vm, "state.txt").splitlines()]
    files = {path: (user, group, mode, kind) for user, group, mode, kind, path in state}
    assert files["/var/lib/keyframed"][:3] == ("keyframed", "keyframed", "750")
    for p in summaries:
        summary = json.loads(p.read_text())
        assert summary["kept"] >= 1 and summary["written"] == summary["kept"], summary
        assert summary["source"].startswith("v4l2:/dev/video0 (vivid: vivid)"), summary
    jpgs = [p for p, v in files.items() if p.endswith(".jpg")]
    assert len(jpgs) == sum(json.loads(p.read_text())["written"] for p in summaries)
    assert all(files[p][:2] == ("keyframed", "keyframed") for p in jpgs)


def test_security_rating_of_the_running_unit(vm: dict) -> None:
    text = _text(vm, "security.txt")
    m = re.search(r"Overall exposure level for keyframed\.service: ([\d.]+) (\w+)", text)
    assert m, text[-2000:]
    assert float(m.group(1)) <= 2.0 and m.group(2) == "OK", m.group(0)


def test_removing_the_package_stops_the_service_and_keeps_its_flights(vm: dict) -> None:
    assert _text(vm, "restart.rc").strip() == "0", _log_tail(vm)
    assert _text(vm, "dpkg-r.rc").strip() == "0", _text(vm, "dpkg-r.txt")
    assert _text(vm, "after-remove.txt").split() == ["inactive"]
    assert _text(vm, "binary-after-remove.txt").split() == ["gone"]
    assert len(_text(vm, "flights-after-remove.txt").split()) == 3  # the third: this start's
    summary = json.loads(_text(vm, "removed-summary.json"))
    assert summary["state"] == "stopped" and summary["written"] == summary["kept"] >= 1, summary
    marks = _marks(vm)
    msgs = [m for t, m, _ in _messages(_journal(vm)) if marks["remove"] < t < marks["removed"]]
    assert any("SIGTERM: stopping" in m for m in msgs), msgs
