"""Sample flights for the tests, generated once and cached by generator version."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from pathlib import Path
from typing import Any

from keyframed import synth

ROOT = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("KEYFRAMED_FLIGHT_CACHE", ROOT / "build" / "flights"))


def flight(
    name: str,
    *,
    width: int = 960,
    height: int = 540,
    seconds: float | None = None,
    fps: float = 30.0,
) -> Path:
    """The directory of a generated flight; regenerated when synth.py changes."""
    version = hashlib.sha256(Path(synth.__file__).read_bytes()).hexdigest()[:12]
    rate = "" if fps == 30.0 else f"-{fps:g}fps"
    # seconds=3 and seconds=3.0 are one flight.
    length = "default" if seconds is None else f"{float(seconds):g}"
    key = f"{name}-{width}x{height}{rate}-{length}-{version}"
    out = CACHE / key
    if (out / "meta.json").exists():
        return out
    # pytest-xdist workers may want the same flight at once: one makes it, the
    # others wait on the lock and find it made.
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / (key + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (out / "meta.json").exists():
            tmp = CACHE / (key + ".partial")
            shutil.rmtree(tmp, ignore_errors=True)
            synth.generate(name, tmp, width=width, height=height, fps=fps, seconds=seconds, seed=0)
            tmp.rename(out)
    return out


# The flights the suite uses, the dearest to make first (about 2.5 minutes of CPU in
# all on this machine): tools/test.sh makes them ahead, at the lowest priority, beside
# the C++ tests, which leave a core idle at times. A test asking for one that is being
# made waits for it (the lock above); one asking for another makes it itself.
SUITE_FLIGHTS: list[tuple[str, dict[str, Any]]] = [
    ("nadir", {}),
    ("orbit", {}),
    ("nadir", {"seconds": 20.0}),
    ("nadir", {"width": 480, "height": 270}),
    ("orbit", {"width": 480, "height": 270}),
    ("nadir", {"width": 1920, "height": 1080, "seconds": 2.0, "fps": 60.0}),
    ("nadir", {"width": 480, "height": 270, "seconds": 8.0}),
    ("orbit", {"width": 480, "height": 270, "seconds": 6.0}),
    ("nadir", {"width": 480, "height": 270, "seconds": 6.0}),
]

if __name__ == "__main__":
    for name, options in SUITE_FLIGHTS:
        print(flight(name, **options), flush=True)
