"""Score a keyframe selection against a synthetic flight's ground truth.

    python -m keyframed.evaluate FLIGHT_DIR OUT_DIR [--band LO,HI] [--json]

FLIGHT_DIR is what ``keyframed.synth`` wrote; OUT_DIR is what ``keyframed select``
wrote (``decisions.csv`` or ``decisions.jsonl``). Reports the ground-truth
overlap between consecutive keyframes, the share inside the band, kept frames
labelled blurry, keyframes added while hovering, and, where the keyframe index
(``keyframes.csv``) holds geotags, how far each is from where the flight was.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .synth import load_flight


@dataclass
class Evaluation:
    frames: int
    keyframes: list[int]
    pair_overlaps: list[float] = field(default_factory=list)
    in_band: float = 0.0  # fraction of consecutive pairs inside the band
    min_overlap: float = 1.0
    blurry_kept: int = 0
    blurry_kept_fraction: float = 0.0
    hover_keyframes: int = 0  # redundant keyframes in a hover (see evaluate())
    band: tuple[float, float] = (0.60, 0.85)
    # Horizontal distance (m) of each geotagged keyframe's position from the flight's
    # at that frame, in keyframes.csv order.
    geotag_errors_m: list[float] = field(default_factory=list)


def read_decisions(out_dir: Path) -> list[dict[str, str]]:
    csv_path = out_dir / "decisions.csv"
    if csv_path.exists():
        with csv_path.open(newline="") as f:
            return list(csv.DictReader(f))
    rows = []
    with (out_dir / "decisions.jsonl").open() as f:
        for line in f:
            d = json.loads(line)
            rows.append(
                {k: ("1" if v is True else "0" if v is False else str(v)) for k, v in d.items()}
            )
    return rows


def keyframe_index_rows(out_dir: Path) -> list[dict[str, str]]:
    """The keyframe index (``keyframes.csv``: beside the decisions for ``select``, in
    ``keyframes/`` for a daemon's flight), or no rows when there is none."""
    for index in (out_dir / "keyframes.csv", out_dir / "keyframes" / "keyframes.csv"):
        if index.exists():
            with index.open(newline="") as f:
                return list(csv.DictReader(f))
    return []


def kept_frames(out_dir: Path) -> list[int]:
    """The keyframes' frame indices: the rows kept, the candidates a later row promoted
    (after a long wait a candidate's row is written before it is promoted, and shows
    as kept only in the promoting row's ``promoted`` column), and whatever the
    keyframe index lists (``keyframes.csv``, beside the decisions for ``select``, in
    ``keyframes/`` for a daemon's flight: the promotions at the end of the stream)."""
    keys: set[int] = set()
    for r in read_decisions(out_dir):
        if r["kept"] == "1":
            keys.add(int(r["index"]))
        if r.get("promoted") not in (None, "", "None"):
            keys.add(int(str(r["promoted"])))
    keys.update(int(row["index"]) for row in keyframe_index_rows(out_dir))
    return sorted(keys)


def geotag_errors(flight_dir: Path, out_dir: Path) -> list[float]:
    """Horizontal error (m) of each geotagged row of the keyframe index against the
    ground truth's position at its frame (local flat earth: metres at this scale)."""
    rows = keyframe_index_rows(out_dir)
    if not rows:
        return []
    with (flight_dir / "groundtruth.csv").open(newline="") as f:
        truth = {int(r["index"]): (float(r["lat"]), float(r["lon"])) for r in csv.DictReader(f)}
    errors = []
    for row in rows:
        if not row.get("lat") or not row.get("lon") or int(row["index"]) not in truth:
            continue
        lat, lon = truth[int(row["index"])]
        north = math.radians(float(row["lat"]) - lat) * 6_371_000.0
        east = math.radians(float(row["lon"]) - lon) * 6_371_000.0 * math.cos(math.radians(lat))
        errors.append(math.hypot(north, east))
    return errors


def evaluate(
    flight_dir: Path, out_dir: Path, band: tuple[float, float] = (0.60, 0.85)
) -> Evaluation:
    flight = load_flight(flight_dir)
    keys = kept_frames(out_dir)
    ev = Evaluation(frames=len(flight.blurry), keyframes=keys, band=band)
    ev.pair_overlaps = [float(flight.overlap(a, b)) for a, b in zip(keys, keys[1:], strict=False)]
    if ev.pair_overlaps:
        inside = [band[0] <= o <= band[1] for o in ev.pair_overlaps]
        ev.in_band = sum(inside) / len(inside)
        ev.min_overlap = min(ev.pair_overlaps)
    ev.blurry_kept = sum(1 for k in keys if flight.blurry[k])
    ev.blurry_kept_fraction = ev.blurry_kept / len(keys) if keys else 0.0
    # A hover may need one keyframe as the vehicle arrives; more is redundancy: a
    # keyframe in a hover counts when the one before it is in the same hover, or when
    # it overlaps the one before it by more than the band's top (nothing new seen).
    hover = flight.hover
    for prev, k in zip(keys, keys[1:], strict=False):
        if not hover[k]:
            continue
        same_hover = all(hover[i] for i in range(prev, k + 1))
        if same_hover or flight.overlap(prev, k) > band[1]:
            ev.hover_keyframes += 1
    ev.geotag_errors_m = geotag_errors(flight_dir, out_dir)
    return ev


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m keyframed.evaluate", description=__doc__)
    p.add_argument("flight_dir", type=Path)
    p.add_argument("out_dir", type=Path)
    p.add_argument("--band", default="0.60,0.85")
    p.add_argument("--json", action="store_true", help="print the evaluation as JSON")
    a = p.parse_args(argv)
    try:
        lo, hi = (float(x) for x in a.band.split(","))
        ev = evaluate(a.flight_dir, a.out_dir, (lo, hi))
    except (OSError, ValueError, KeyError) as e:
        print(f"keyframed.evaluate: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(asdict(ev)))
        return 0
    ov = ev.pair_overlaps
    median = sorted(ov)[len(ov) // 2] if ov else float("nan")
    print(
        f"{len(ev.keyframes)} keyframes from {ev.frames} frames; ground-truth overlap of "
        f"consecutive keyframes: median {median:.2f}, min {ev.min_overlap:.2f}, "
        f"{100 * ev.in_band:.0f}% inside {ev.band[0]:.2f}-{ev.band[1]:.2f}; "
        f"blurry kept {ev.blurry_kept} ({100 * ev.blurry_kept_fraction:.1f}%); "
        f"extra keyframes while hovering {ev.hover_keyframes}"
    )
    if ev.geotag_errors_m:
        errs = sorted(ev.geotag_errors_m)
        print(
            f"geotags of {len(errs)} keyframes against the flight's positions: "
            f"median {errs[len(errs) // 2]:.2f} m, max {errs[-1]:.2f} m"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
