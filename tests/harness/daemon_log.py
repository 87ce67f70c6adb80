"""Reading what the daemon logs on stderr (`HH:MM:SS.mmm L category: message`)."""

from __future__ import annotations

import re


def _seconds_of_day(stamp: str) -> float:
    h, m, s = stamp.split(":")
    return int(h) * 3600 + int(m) * 60 + float(s)


def logged_stop_s(stderr: str) -> float | None:
    """How long the daemon took to stop, by its log: from its line saying it took the
    signal ("SIGTERM: stopping") to its last line ("stopped (": everything flushed and
    closed). None when it logged no such lines."""
    took = re.search(r"^(\d\d:\d\d:\d\d\.\d{3}) .*SIG(?:TERM|INT): stopping", stderr, re.M)
    done = re.findall(r"^(\d\d:\d\d:\d\d\.\d{3}) .*stopped \(", stderr, re.M)
    if took is None or not done:
        return None
    return (_seconds_of_day(done[-1]) - _seconds_of_day(took.group(1))) % 86400
