"""Reading what the daemon logs on stderr (`HH:MM:SS.mmm L category: message`, local
time of the realtime clock)."""

from __future__ import annotations

import re
import time


def _seconds_of_day(stamp: str) -> float:
    h, m, s = stamp.split(":")
    return int(h) * 3600 + int(m) * 60 + float(s)


def logged_stop_s(stderr: str, since: float | None = None) -> float | None:
    """How long the daemon took to stop, by its log: from `since` (a time.time() of
    this machine, the moment the signal was sent) or else from its line saying it
    took the signal ("SIGTERM: stopping"), to its last line ("stopped (": everything
    flushed and closed). None when it logged no such lines."""
    took = re.search(r"^(\d\d:\d\d:\d\d\.\d{3}) .*SIG(?:TERM|INT): stopping", stderr, re.M)
    done = re.findall(r"^(\d\d:\d\d:\d\d\.\d{3}) .*stopped \(", stderr, re.M)
    if not done or (took is None and since is None):
        return None
    if since is not None:
        t = time.localtime(since)
        start = t.tm_hour * 3600 + t.tm_min * 60 + t.tm_sec + since % 1.0
        start = int(start * 1000) / 1000  # the log's stamps are cut to the millisecond
    else:
        assert took is not None
        start = _seconds_of_day(took.group(1))
    return (_seconds_of_day(done[-1]) - start) % 86400
