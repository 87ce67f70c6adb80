"""The README's first command, tools/demo.sh, run as written on the tree the suite
has just set up and built (KEYFRAMED_DEMO_SKIP_SETUP=1 skips only its set-up and
build steps, which tools/test.sh has run): it makes the sample flight, flies it with
the daemon, the fake autopilot and the ground station, and says where everything
went. The paths it prints must hold what it says they hold."""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
from pathlib import Path

import pytest
from conftest import ROOT


def test_demo_flies_the_sample_and_shows_where_the_keyframes_went() -> None:
    daemon = ROOT / "build/release/daemon/keyframed"
    ground = ROOT / ".venv/bin/keyframed-ground"
    if not daemon.exists() or not ground.exists():
        pytest.fail(f"{daemon} or {ground} missing: tools/demo.sh runs this tree's build")
    p = subprocess.run(
        ["tools/demo.sh"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
        env={**os.environ, "KEYFRAMED_DEMO_SKIP_SETUP": "1"},
    )
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    out = p.stdout
    print(out[-1500:])
    where = dict(re.findall(r"^([a-zA-Z/ ]+):\s+(\S+)", out, re.M))
    keyframes = Path(where["keyframes"]).parent
    with (keyframes / "keyframes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) >= 10
    assert sorted(p.name for p in keyframes.glob("*.jpg")) == sorted(r["file"] for r in rows)
    assert all(r["geotag"] == "ok" for r in rows), [r["geotag"] for r in rows]
    summary = json.loads(Path(where["summary"]).read_text())
    assert summary["written"] == len(rows) and summary["frames_dropped"] == 0, summary
    assert Path(where["decisions"]).stat().st_size > 0
    assert Path(where["flight record"]).stat().st_size > 0
    dataset = Path(where["COLMAP/ODM"])
    images = sorted(p.name for p in (dataset / "images").glob("*.jpg"))
    assert len(images) == len(rows), (len(images), len(rows))
    for name in ("cameras.txt", "pairs.txt", "geo.txt", "cameras.json"):
        assert (dataset / name).stat().st_size > 0, name
    # the report: the run's numbers and the ground station's
    assert f"{len(rows)} keyframes, {len(rows)} geotagged" in out, out[-2000:]
    assert f"ground station: {len(rows)} keyframes of vehicle demo-nadir" in out, out[-2000:]
    # Where each keyframe was tagged against where the flight was at its frame: the
    # autopilot's replay follows the video's first frame (0.00-0.01 m here; a replay
    # that ran 2 s ahead of the video put every tag 15 m up the track).
    tagged = re.search(r"geotags of (\d+) keyframes .*: median ([\d.]+) m, max ([\d.]+) m", out)
    assert tagged, out[-2000:]
    assert int(tagged[1]) == len(rows)
    assert float(tagged[3]) < 0.5, tagged[0]
