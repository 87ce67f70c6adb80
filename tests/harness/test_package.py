"""Installation layout and the Debian package, built from the tested build tree.

`cpack` re-installs the build tree into a staging directory and runs dpkg-shlibdeps:
about 2 s here. The build must be configured with the /usr prefix (the default).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from conftest import ROOT, build_dir, cached, host_package_lock


def test_install_layout(tmp_path: Path):
    stage = tmp_path / "stage"
    p = subprocess.run(
        ["cmake", "--install", str(build_dir())],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "DESTDIR": str(stage)},
    )
    assert p.returncode == 0, p.stderr
    prefix = cached("CMAKE_INSTALL_PREFIX").lstrip("/")  # /usr unless configured otherwise
    etc = cached("KEYFRAMED_CONFIG_DIR").lstrip("/")  # /etc/keyframed for /usr
    for f in (
        f"{prefix}/bin/keyframed",
        f"{prefix}/lib/systemd/system/keyframed.service",
        f"{prefix}/lib/sysusers.d/keyframed.conf",
        f"{etc}/keyframed.toml",
        f"{prefix}/share/doc/keyframed/configuration.md",
        f"{prefix}/share/doc/keyframed/README.md",
    ):
        assert (stage / f).is_file(), f
    assert (stage / etc / "conf.d").is_dir()
    assert not list(stage.rglob("_core*")), "the Python extension installed with the daemon"
    assert os.access(stage / prefix / "bin/keyframed", os.X_OK)
    unit = (stage / prefix / "lib/systemd/system/keyframed.service").read_text()
    assert f"ExecStart=/{prefix}/bin/keyframed run" in unit  # follows the prefix
    assert (stage / etc / "keyframed.toml").read_text() == (
        ROOT / "config/keyframed.toml"
    ).read_text()


def test_debian_package(deb: Path, tmp_path: Path):
    arch = subprocess.check_output(["dpkg", "--print-architecture"], text=True).strip()
    version = subprocess.check_output(["dpkg-deb", "-f", str(deb), "Version"], text=True).strip()
    assert deb.name == f"keyframed_{version}_{arch}.deb"
    print(f"{deb.name}: {deb.stat().st_size} bytes")

    files = subprocess.check_output(["dpkg-deb", "-c", str(deb)], text=True)
    paths = {line.split()[-1] for line in files.splitlines()}
    for f in (
        "./usr/bin/keyframed",
        "./usr/lib/systemd/system/keyframed.service",
        "./usr/lib/sysusers.d/keyframed.conf",
        "./etc/keyframed/keyframed.toml",
        "./etc/keyframed/conf.d/",
        "./usr/share/doc/keyframed/configuration.md",
        "./usr/share/doc/keyframed/deploy.md",
        "./usr/share/doc/keyframed/capture.md",
    ):
        assert f in paths, f
    # The Python extension, built in the same tree, is the wheel's, not the daemon's.
    assert not [p for p in paths if "_core" in p or "python" in p], sorted(paths)

    control = tmp_path / "control"
    subprocess.run(["dpkg-deb", "-e", str(deb), str(control)], check=True)
    assert (control / "conffiles").read_text().split() == ["/etc/keyframed/keyframed.toml"]
    for script in ("postinst", "prerm", "postrm"):
        assert os.access(control / script, os.X_OK), script
        subprocess.run(["sh", "-n", str(control / script)], check=True)  # parses
    postinst = (control / "postinst").read_text()
    assert "systemd-sysusers keyframed.conf" in postinst
    assert "adduser --system" in postinst
    assert "systemctl daemon-reload" in postinst

    info = subprocess.check_output(["dpkg-deb", "-I", str(deb)], text=True)
    depends = subprocess.check_output(["dpkg-deb", "-f", str(deb), "Depends"], text=True)
    # Computed by dpkg-shlibdeps from the binary's libraries.
    for lib in ("libc6", "libsystemd0", "libtomlplusplus3", "libopencv-core"):
        assert lib in depends, depends
    # what postinst makes the user with
    assert "systemd | adduser" in depends, depends
    assert "Package: keyframed" in info
    # a Pi camera does not start without libcamera's IPA modules (Debian only suggests them)
    if "libcamera" in depends:
        recommends = subprocess.check_output(["dpkg-deb", "-f", str(deb), "Recommends"], text=True)
        assert "libcamera-ipa" in recommends, recommends


def _dpkg(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["dpkg", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"},
    )


def test_debian_package_installs_runs_and_purges(deb: Path, tmp_path: Path):
    """The package for real: dpkg runs its maintainer scripts (system user), the
    installed daemon reads the installed configuration, removal keeps the conffile
    and purge removes it. Needs root and a machine where keyframed is not installed
    otherwise (CI's throw-away machine)."""
    if os.geteuid() != 0:
        pytest.skip("installing a .deb needs root")
    with host_package_lock():
        _install_run_and_purge(deb)


def _install_run_and_purge(deb: Path) -> None:
    if _dpkg("-s", "keyframed").returncode == 0:
        pytest.skip("keyframed is already installed as a package here: not touching it")
    if Path("/usr/bin/keyframed").exists() or Path("/etc/keyframed").exists():
        pytest.skip("/usr/bin/keyframed or /etc/keyframed exists outside dpkg: not touching it")
    try:
        p = _dpkg("-i", str(deb))
        assert p.returncode == 0, p.stdout + p.stderr
        user = subprocess.run(["getent", "passwd", "keyframed"], capture_output=True, text=True)
        assert user.returncode == 0, "postinst made no keyframed user"
        groups = subprocess.check_output(["id", "-nG", "keyframed"], text=True).split()
        assert {"keyframed", "video", "dialout"} <= set(groups), groups
        # the installed binary with the installed configuration, as the unit runs it
        p = subprocess.run(
            ["/usr/bin/keyframed", "check-config"], capture_output=True, text=True, timeout=30
        )
        assert p.returncode == 0, p.stdout + p.stderr
        assert "/etc/keyframed/keyframed.toml" in p.stdout + p.stderr
        conf = Path("/etc/keyframed/keyframed.toml")
        conf.write_text(conf.read_text() + "\n# edited by the operator\n")
        # enabled by the operator (systemctl edits the links without a running systemd)
        wants = Path("/etc/systemd/system/multi-user.target.wants/keyframed.service")
        enable = subprocess.run(
            ["systemctl", "enable", "keyframed.service"], capture_output=True, text=True
        )
        assert enable.returncode == 0 and wants.is_symlink(), enable.stdout + enable.stderr
        p = _dpkg("-r", "keyframed")
        assert p.returncode == 0, p.stdout + p.stderr
        assert not Path("/usr/bin/keyframed").exists()
        # no enable link left dangling, to start a reinstalled daemon unasked
        assert not wants.is_symlink()
        assert "edited by the operator" in conf.read_text()  # a conffile survives removal
        p = _dpkg("-P", "keyframed")
        assert p.returncode == 0, p.stdout + p.stderr
        assert not conf.exists()
    finally:
        _dpkg("-P", "keyframed")


def test_python_wheel_holds_the_package_only():
    """The installed keyframed distribution is the Python package, its metadata and
    the keyframed-ground script: not the daemon, its unit or configuration, which
    the same CMake installs for a system."""
    from importlib.metadata import files

    installed = [str(f) for f in files("keyframed") or []]
    assert any(f.startswith("keyframed/_core") for f in installed), installed
    outside = [
        f
        for f in installed
        if not f.startswith(("keyframed/", "keyframed-")) and not f.endswith("bin/keyframed-ground")
    ]
    assert not outside, outside
