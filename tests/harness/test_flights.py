"""Selection quality on the synthetic flights, against their ground truth.

The geometric mode must keep consecutive keyframes inside the overlap band, keep
(almost) no blurry frame and add nothing while hovering. The paper's mode runs on
the same flights and its figures are reported beside them (see the terminal
summary and build/reports/flight_quality.md).

Selection runs at a lower priority (nice 10): it is CPU-bound, and another test
running at the same time (pytest -n 2) may be replaying a flight in real time.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from flights import ROOT, flight
from keyframed.evaluate import Evaluation, evaluate

# One JSON row per (flight, mode), written by whichever worker ran it and read by the
# terminal summary; conftest.py clears them when a session starts.
ROWS = ROOT / "build" / "reports" / "flight_quality"


def select(kf_bin: Path, video: Path, out: Path, *args: str) -> dict:
    p = subprocess.run(
        ["nice", "-n", "10", str(kf_bin), "select", str(video), "--out", str(out), "--quiet"]
        + list(args),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert p.returncode == 0, p.stderr
    return json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="module", params=["nadir", "orbit"])
def sample(request: pytest.FixtureRequest) -> tuple[str, Path]:
    return request.param, flight(request.param)


def test_geometric_mode_meets_the_quality_bar(kf_bin: Path, sample, tmp_path):
    name, fdir = sample
    summary = select(kf_bin, fdir / "video.avi", tmp_path / "geo")
    ev = evaluate(fdir, tmp_path / "geo")
    record(name, "geometric", ev)
    assert summary["frames_read"] == ev.frames
    # About what the README reports (25 on both; 23-25 on other seeds): neither a
    # keyframe every few frames nor a handful.
    assert 15 <= len(ev.keyframes) <= 40, ev.keyframes
    median = sorted(ev.pair_overlaps)[len(ev.pair_overlaps) // 2]
    assert 0.62 <= median <= 0.78, ev.pair_overlaps  # around the 0.70 target
    assert ev.in_band >= 0.90, ev.pair_overlaps
    assert ev.min_overlap >= 0.5, ev.pair_overlaps
    assert ev.blurry_kept_fraction < 0.02, ev.keyframes
    assert ev.hover_keyframes == 0


def test_hover_adds_no_keyframes(kf_bin: Path, tmp_path):
    fdir = flight("nadir")
    select(kf_bin, fdir / "video.avi", tmp_path / "geo")
    ev = evaluate(fdir, tmp_path / "geo")
    from keyframed.synth import load_flight

    hover = load_flight(fdir).hover
    assert hover.sum() > 60  # the flight does hover
    inside = [k for k in ev.keyframes if hover[k]]
    assert inside == [], inside  # not even the frame where it arrived


# t = 50 is the paper's value for a Bebop; t = 29 is what gives 0.70 overlap on the
# nadir flight (read off its ground truth): the paper's threshold has to be tuned per
# source, which is the weakness the geometric mode removes.
@pytest.mark.parametrize("threshold", [50, 29])
def test_paper_mode_runs_on_the_same_flights(kf_bin: Path, sample, tmp_path, threshold: int):
    name, fdir = sample
    out = tmp_path / "paper"
    summary = select(
        kf_bin, fdir / "video.avi", out, "--mode", "paper", "--paper-threshold", str(threshold)
    )
    ev = evaluate(fdir, out)
    record(name, f"paper t={threshold}", ev)
    assert summary["frames_read"] == ev.frames
    assert len(ev.keyframes) >= 2  # reported, not held to the geometric bar


def test_python_selection_matches_the_command_line(kf_bin: Path, tmp_path):
    import keyframed

    fdir = flight("nadir")
    select(kf_bin, fdir / "video.avi", tmp_path / "cli")
    s = keyframed.select_video(str(fdir / "video.avi"), str(tmp_path / "py"))
    assert s["error"] == ""
    cli = sorted(p.name for p in (tmp_path / "cli").glob("*.jpg"))
    py = sorted(p.name for p in (tmp_path / "py").glob("*.jpg"))
    assert cli == py


def record(name: str, mode: str, ev: Evaluation) -> None:
    ov = sorted(ev.pair_overlaps)
    row = {
        "flight": name,
        "mode": mode,
        "keyframes": len(ev.keyframes),
        "median": ov[len(ov) // 2] if ov else float("nan"),
        "min": ev.min_overlap,
        "in_band": ev.in_band,
        "blurry": ev.blurry_kept,
        "blurry_fraction": ev.blurry_kept_fraction,
    }
    ROWS.mkdir(parents=True, exist_ok=True)
    (ROWS / f"{name}-{mode.replace(' ', '_')}.json").write_text(json.dumps(row))


def write_report() -> str:
    rows = sorted(
        (json.loads(f.read_text()) for f in ROWS.glob("*.json")),
        key=lambda r: (r["flight"], r["mode"]),
    )
    if not rows:
        return ""
    lines = [
        "| flight | mode | keyframes | overlap median | min | in band | blurry kept |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['flight']} | {r['mode']} | {r['keyframes']} | {r['median']:.2f} | "
            f"{r['min']:.2f} | {100 * r['in_band']:.0f}% | {r['blurry']} "
            f"({100 * r['blurry_fraction']:.1f}%) |"
        )
    text = "\n".join(lines) + "\n"
    (ROWS.parent / "flight_quality.md").write_text(text)
    return text


def test_the_evaluation_counts_promotions_written_after_their_row(tmp_path: Path) -> None:
    """A candidate whose row was written before it was promoted (a wait over 900
    rows) is a keyframe all the same: the evaluation reads it from the promoting
    row, and an end-of-stream promotion from keyframes.csv."""
    from keyframed.evaluate import kept_frames

    head = "index,timestamp_ns,kept,reason,candidate,promoted\n"
    rows = ["0,0,1,first,0,", "1,1,0,overlap,1,", "2,2,0,overlap,0,", "3,3,1,gap_fill,0,1"]
    (tmp_path / "decisions.csv").write_text(head + "\n".join(rows) + "\n")
    assert kept_frames(tmp_path) == [0, 1, 3]
    (tmp_path / "keyframes.csv").write_text("sequence,index,file\n0,0,a\n1,1,b\n2,3,c\n3,2,d\n")
    assert kept_frames(tmp_path) == [0, 1, 2, 3]
