"""Reading what the daemon logs on stderr (`HH:MM:SS.mmm L category: message`)."""

from __future__ import annotations

import re


def logged_stop_s(stderr: str) -> float | None:
    """The daemon's own time from taking the signal ("SIGTERM: stopping") to its last
    line ("stopped (": everything flushed and closed), from the stamps of its log."""

    def stamp(line: str) -> float:
        h, m, s = line[:12].split(":")
        return int(h) * 3600 + int(m) * 60 + float(s)

    took = re.search(r"^(\d\d:\d\d:\d\d\.\d{3}) .*SIG(?:TERM|INT): stopping", stderr, re.M)
    done = re.findall(r"^(\d\d:\d\d:\d\d\.\d{3}) .*stopped \(", stderr, re.M)
    if took is None or not done:
        return None
    return (stamp(done[-1]) - stamp(took.group(1))) % 86400
