"""The kernel side of the systemd unit's sandbox, applied to a process started by a
test, without systemd: what its [Service] section says about system calls
(SystemCallFilter=, SystemCallErrorNumber=), address families
(RestrictAddressFamilies=), NoNewPrivileges= and MemoryDenyWriteExecute=, built as
systemd builds them (seccomp filters, through libseccomp) from the unit file itself
and systemd's own lists of system call groups (`systemd-analyze syscall-filter`).

The mount namespace settings (ProtectSystem=, PrivateTmp=, ...) and the user are not
applied: they decide what the process may see and write, which the tests give it
anyway (state in a temporary directory).

Used as a wrapper, so that the filters are loaded in a process of one thread just
before it execs the command (not in a fork of a test process with threads):

    python sandbox.py UNIT COMMAND [ARGS...]      (``sandboxed(unit, command)``)
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

# libseccomp's actions and comparison operators (seccomp.h)
SCMP_ACT_ALLOW = 0x7FFF0000
SCMP_ACT_KILL_PROCESS = 0x80000000
SCMP_CMP_EQ = 4
SCMP_CMP_MASKED_EQ = 7
PROT_EXEC = 0x4
PROT_WRITE = 0x2
SHM_EXEC = 0o100000
PR_SET_NO_NEW_PRIVS = 38


def SCMP_ACT_ERRNO(e: int) -> int:  # noqa: N802 - libseccomp's name
    return 0x00050000 | (e & 0xFFFF)


class ArgCmp(ctypes.Structure):
    _fields_ = [
        ("arg", ctypes.c_uint),
        ("op", ctypes.c_int),
        ("datum_a", ctypes.c_uint64),
        ("datum_b", ctypes.c_uint64),
    ]


def unit_settings(unit: Path) -> dict[str, list[str]]:
    """Each key of the unit file with all its values, in order."""
    settings: dict[str, list[str]] = {}
    for line in unit.read_text().splitlines():
        line = line.strip()
        if "=" in line and not line.startswith(("#", ";", "[")):
            key, value = line.split("=", 1)
            settings.setdefault(key.strip(), []).append(value.strip())
    return settings


def syscall_groups() -> dict[str, list[str]]:
    """systemd's groups (@name -> members, nested groups by name) on this machine."""
    out = subprocess.run(
        ["systemd-analyze", "syscall-filter", "--no-pager"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    groups: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in out.splitlines():
        if line.startswith("@"):
            current = groups.setdefault(line.split()[0], [])
        elif line.strip() and not line.strip().startswith("#") and current is not None:
            current.append(line.split()[0])
    return groups


def expand(names: list[str], groups: dict[str, list[str]]) -> set[str]:
    out: set[str] = set()
    for n in names:
        out |= expand(groups[n], groups) if n.startswith("@") else {n}
    return out


def allowed_syscalls(settings: dict[str, list[str]]) -> set[str]:
    """SystemCallFilter= as systemd reads it: the first line without ~ allows a list
    (and every later allowing line adds to it), a ~ line takes names out."""
    groups = syscall_groups()
    allowed: set[str] = set()
    for value in settings.get("SystemCallFilter", []):
        if value.startswith("~"):
            allowed -= expand(value[1:].split(), groups)
        else:
            allowed |= expand(value.split(), groups)
    return allowed


class _Seccomp:
    def __init__(self) -> None:
        name = ctypes.util.find_library("seccomp")
        if name is None:
            raise OSError("libseccomp not found (Debian: libseccomp2)")
        lib = ctypes.CDLL(name, use_errno=True)
        lib.seccomp_init.restype = ctypes.c_void_p
        lib.seccomp_init.argtypes = [ctypes.c_uint32]
        lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
        lib.seccomp_rule_add_array.argtypes = [
            ctypes.c_void_p,
            ctypes.c_uint32,
            ctypes.c_int,
            ctypes.c_uint,
            ctypes.POINTER(ArgCmp),
        ]
        lib.seccomp_load.argtypes = [ctypes.c_void_p]
        lib.seccomp_attr_set.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint32]
        self.lib = lib

    def number(self, name: str) -> int:
        return int(self.lib.seccomp_syscall_resolve_name(name.encode()))

    def rule(self, ctx: int, action: int, nr: int, *cmps: tuple[int, int, int, int]) -> None:
        arr = (ArgCmp * max(1, len(cmps)))(*[ArgCmp(*c) for c in cmps])
        rc = self.lib.seccomp_rule_add_array(ctx, action, nr, len(cmps), arr)
        if rc < 0:
            raise OSError(-rc, f"seccomp_rule_add_array({nr}): {os.strerror(-rc)}")


def sandbox_preexec(unit: Path) -> Callable[[], None]:
    """A function that puts the calling process under the unit's sandbox (the wrapper
    below calls it, then execs). Everything is worked out first; the function only
    loads the filters."""
    settings = unit_settings(unit)
    one = {k: v[-1] for k, v in settings.items()}
    sc = _Seccomp()
    # A refused call fails with SystemCallErrorNumber=; without it systemd kills.
    name = one.get("SystemCallErrorNumber")
    refuse = SCMP_ACT_ERRNO(getattr(errno, name)) if name else SCMP_ACT_KILL_PROCESS
    allowed = sorted({nr for nr in (sc.number(n) for n in allowed_syscalls(settings)) if nr >= 0})
    if not allowed:
        raise ValueError(f"{unit}: no SystemCallFilter= to apply")
    # Filter 1: the allow list, every other call refused.
    calls = sc.lib.seccomp_init(refuse)
    for nr in allowed:
        sc.rule(calls, SCMP_ACT_ALLOW, nr)
    # Filter 2: what systemd adds per setting, on top (the kernel takes the stricter).
    extra = sc.lib.seccomp_init(SCMP_ACT_ALLOW)
    families = one.get("RestrictAddressFamilies", "").split()
    if families:
        keep = {int(getattr(socket, f)) for f in families}
        for family in range(0, 64):  # AF_MAX is 46 on Linux 6.x: room for more
            if family not in keep:
                sc.rule(
                    extra,
                    SCMP_ACT_ERRNO(errno.EAFNOSUPPORT),
                    sc.number("socket"),
                    (0, SCMP_CMP_EQ, family, 0),
                )
    if one.get("MemoryDenyWriteExecute") == "yes":
        wx = PROT_WRITE | PROT_EXEC
        deny = SCMP_ACT_ERRNO(errno.EPERM)
        sc.rule(extra, deny, sc.number("mmap"), (2, SCMP_CMP_MASKED_EQ, wx, wx))
        for call in ("mprotect", "pkey_mprotect"):
            sc.rule(extra, deny, sc.number(call), (2, SCMP_CMP_MASKED_EQ, PROT_EXEC, PROT_EXEC))
        sc.rule(extra, deny, sc.number("shmat"), (2, SCMP_CMP_MASKED_EQ, SHM_EXEC, SHM_EXEC))
    no_new_privs = one.get("NoNewPrivileges") == "yes"
    libc = ctypes.CDLL(None, use_errno=True)

    def apply() -> None:
        # Loading a filter needs no_new_privs without CAP_SYS_ADMIN; the unit sets it.
        if no_new_privs and libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
            os._exit(120)
        if sc.lib.seccomp_load(extra) != 0 or sc.lib.seccomp_load(calls) != 0:
            os._exit(121)

    return apply


def sandboxed(unit: Path, command: list[str]) -> list[str]:
    """COMMAND run under UNIT's sandbox (this file as the wrapper)."""
    return [sys.executable, str(Path(__file__).resolve()), str(unit), *command]


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: sandbox.py UNIT COMMAND [ARGS...]")
    sandbox_preexec(Path(sys.argv[1]))()
    os.execvp(sys.argv[2], sys.argv[2:])
