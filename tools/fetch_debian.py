#!/usr/bin/env python3
"""Fetches packages of another Debian release from deb.debian.org and unpacks them
into a directory (no apt sources touched, nothing installed on this machine).

The libcamera tests use it: Debian 12 ships libcamera 0.0.3, while a Raspberry Pi
runs newer releases. `--suite trixie libcamera0.4 ...` gives libcamera 0.4 (the first
with a kernel-free virtual camera) with the C/C++ runtime it needs, run under qemu
with trixie's kernel (`--kernel amd64 --modules 9p,9pnet_virtio`), which has the
dma-buf heaps that camera allocates from and virtio-9p to reach this machine's
files; `--suite sid libcamera-dev` gives the newest headers to compile against.

    fetch_debian.py --suite S --dest DIR [--arch ARCH] [--kernel FLAVOUR [--modules M,...]]
                    [--no-deps] PACKAGE...

Unpacks each package and its dependencies (first alternative of each, transitively)
into DIR/root; with --kernel, the kernel image of linux-image-FLAVOUR into
DIR/vmlinuz, and with --modules the modules named (and their dependencies) into
DIR/modules, uncompressed, in load order in DIR/modules/order. DIR/complete records
what was fetched: a second run with the same arguments does nothing (no network).
Exit status 1 with a one-line reason when the mirror cannot be reached.
"""

from __future__ import annotations

import argparse
import json
import lzma
import re
import shutil
import subprocess
import sys
import tempfile
import urllib.request
from pathlib import Path

MIRROR = "http://deb.debian.org/debian"
# Provided by the host or irrelevant to running a library: not fetched.
SKIP = {"debconf", "debconf-2.0", "dpkg", "libc-bin", "perl-base", "install-info", "tzdata"}


def packages_index(suite: str, arch: str = "amd64") -> dict[str, dict[str, str]]:
    url = f"{MIRROR}/dists/{suite}/main/binary-{arch}/Packages.xz"
    with urllib.request.urlopen(url, timeout=120) as r:
        text = lzma.decompress(r.read()).decode("utf-8", "replace")
    index: dict[str, dict[str, str]] = {}
    provides: dict[str, str] = {}
    for stanza in text.split("\n\n"):
        fields: dict[str, str] = {}
        for line in stanza.splitlines():
            if line and not line[0].isspace() and ":" in line:
                key, value = line.split(":", 1)
                fields[key] = value.strip()
        name = fields.get("Package")
        if not name:
            continue
        index.setdefault(name, fields)
        for p in fields.get("Provides", "").split(","):
            p = p.strip().split(" ")[0]
            if p:
                provides.setdefault(p, name)
    for virtual, real in provides.items():
        index.setdefault(virtual, index[real])
    return index


def dependency_names(fields: dict[str, str]) -> list[str]:
    names = []
    for key in ("Pre-Depends", "Depends"):
        for alternatives in fields.get(key, "").split(","):
            first = alternatives.split("|")[0].strip()
            if first:
                names.append(first.split(" ")[0].split(":")[0])
    return names


def closure(index: dict[str, dict[str, str]], roots: list[str]) -> list[dict[str, str]]:
    seen: dict[str, dict[str, str]] = {}
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in SKIP or name not in index:
            if name in roots:
                raise SystemExit(f"fetch_debian: no package {name}")
            continue
        fields = index[name]
        if fields["Package"] in seen:
            continue
        seen[fields["Package"]] = fields
        todo.extend(dependency_names(fields))
    return sorted(seen.values(), key=lambda f: f["Package"])


def download(filename: str, into: Path) -> Path:
    out = into / Path(filename).name
    with urllib.request.urlopen(f"{MIRROR}/{filename}", timeout=600) as r, out.open("wb") as f:
        shutil.copyfileobj(r, f)
    return out


def module_bytes(path: Path) -> bytes:
    data = path.read_bytes()
    return lzma.decompress(data) if path.name.endswith(".xz") else data


def copy_modules(kernel_tree: Path, names: list[str], out: Path) -> None:
    """The modules named and their dependencies (from each module's own modinfo: Debian's
    package ships no modules.dep), uncompressed (busybox insmod reads plain .ko), with
    `order` listing them dependencies first."""
    found = {}
    for ko in kernel_tree.glob("**/lib/modules/*/kernel/**/*.ko*"):
        found[ko.name.split(".ko")[0].replace("-", "_")] = ko
    out.mkdir(parents=True)
    order: list[str] = []

    def add(name: str) -> None:
        name = name.replace("-", "_")
        if name in order:
            return
        if name not in found:
            raise SystemExit(f"fetch_debian: no kernel module {name} (built in?)")
        data = module_bytes(found[name])
        m = re.search(rb"depends=([^\0]*)\0", data)
        for dep in m.group(1).decode().split(",") if m else []:
            if dep:
                add(dep)
        (out / f"{name}.ko").write_bytes(data)
        order.append(name)

    for n in names:
        add(n)
    (out / "order").write_text("".join(f"{n}.ko\n" for n in order))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", required=True)
    ap.add_argument("--dest", required=True, type=Path)
    ap.add_argument("--kernel", help="also fetch linux-image-FLAVOUR's kernel image")
    ap.add_argument(
        "--modules",
        default="",
        help="with --kernel: these modules (comma-separated) and what they depend on",
    )
    ap.add_argument("--arch", default="amd64", help="Debian architecture (arm64: a Pi's)")
    ap.add_argument("--no-deps", action="store_true", help="only the packages named (headers)")
    ap.add_argument("packages", nargs="+")
    args = ap.parse_args()

    request = {
        "suite": args.suite,
        "kernel": args.kernel,
        "packages": args.packages,
        "deps": not args.no_deps,
        "modules": args.modules,
        "arch": args.arch,
    }
    done = args.dest / "complete"
    if done.is_file() and json.loads(done.read_text()).get("request") == request:
        return 0
    try:
        index = packages_index(args.suite, args.arch)
        if args.no_deps:
            missing = [p for p in args.packages if p not in index]
            if missing:
                raise SystemExit(f"fetch_debian: no package {missing[0]}")
            wanted = [index[p] for p in args.packages]
        else:
            wanted = closure(index, args.packages)
        kernel = None
        if args.kernel:
            meta = index.get(f"linux-image-{args.kernel}")
            if meta is None:
                raise SystemExit(f"fetch_debian: no kernel flavour {args.kernel} in {args.suite}")
            kernel = index[dependency_names(meta)[0]]
        if args.dest.exists():
            shutil.rmtree(args.dest)
        root = args.dest / "root"
        root.mkdir(parents=True)
        with tempfile.TemporaryDirectory() as tmp:
            for fields in wanted:
                deb = download(fields["Filename"], Path(tmp))
                subprocess.run(["dpkg-deb", "-x", str(deb), str(root)], check=True)
                deb.unlink()
            if kernel is not None:
                deb = download(kernel["Filename"], Path(tmp))
                unpacked = Path(tmp) / "kernel"
                subprocess.run(["dpkg-deb", "-x", str(deb), str(unpacked)], check=True)
                (image,) = (unpacked / "boot").glob("vmlinuz-*")
                shutil.copy(image, args.dest / "vmlinuz")
                if args.modules:
                    copy_modules(unpacked, args.modules.split(","), args.dest / "modules")
    except OSError as e:  # URLError is an OSError
        print(f"fetch_debian: cannot fetch from {MIRROR} ({args.suite}): {e}", file=sys.stderr)
        return 1
    done.write_text(
        json.dumps(
            {
                "request": request,
                "packages": {f["Package"]: f["Version"] for f in wanted},
                "kernel": kernel["Package"] if kernel else None,
            },
            indent=1,
        )
        + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
