"""Benchmark: a dialogue library on Ray, lines per minute with one worker and with two, and
the per-line overhead that each worker's reuse of the model and the character keeps out.

    python bench/bench_studio.py [--lines 8] [--seconds 4]

Makes a character file (the BEAT rig imported from BVH and the ARKit face) and a manifest
of --lines lines of --seconds of real speech each (outputs blend and npz), then runs
`batch_render.py --manifest` on a new local Ray with --workers 1 and with --workers 2, in a
network namespace of its own (`unshare -n`, where Ray can only use 127.0.0.1) when this
runs as root on Linux. Wall time includes starting Ray. The per-line overhead that reuse
keeps out is a worker's first line against the median line: the first opens the character
file, loads the model and warms onnxruntime, which a run without reuse would do for every
line.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]

import bpy  # noqa: E402

from addon_fixtures import SPEECH, SPEECH_2, append_face, cut_speech, import_beat_armature, reset_scene  # noqa: E402


def make_library(work: Path, lines: int, seconds: float) -> Path:
    reset_scene(fps=24)
    import_beat_armature()
    append_face()
    bpy.ops.wm.save_as_mainfile(filepath=str(work / "character.blend"))
    rows = ["id,audio,seed,blend,preset,outputs"]
    for i in range(lines):
        cut_speech(work, seconds=seconds, source=SPEECH if i % 2 else SPEECH_2, offset=2.0 + seconds * (i // 2),
                   name=f"l{i}.wav")
        rows.append(f"line{i},l{i}.wav,{i},character.blend,beat,blend;npz")
    (work / "lines.csv").write_text("\n".join(rows) + "\n")
    return work / "lines.csv"


def run(manifest: Path, out: Path, workers: int) -> float:
    command = [sys.executable, str(REPO / "batch_render.py"), "--manifest", str(manifest), "--output", str(out),
               "--workers", str(workers)]
    if shutil.which("unshare") and os.geteuid() == 0:
        command = ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$@"', "sh", *command]
    started = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})
    if proc.returncode != 0:
        raise SystemExit(f"the batch failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return time.perf_counter() - started


def line_seconds(out: Path) -> list[float]:
    with open(out / "report.csv", newline="") as fh:
        return [float(row["seconds"]) for row in csv.DictReader(fh) if row["status"] == "done"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lines", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=4.0)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-studio-"))
    try:
        manifest = make_library(work, args.lines, args.seconds)
        print(f"machine: {platform.machine()}, {os.cpu_count()} cores; {args.lines} lines of {args.seconds:g} s "
              f"of real speech, outputs blend + npz")
        walls = {}
        for workers in (1, 2):
            wall = run(manifest, work / f"out{workers}", workers)
            times = sorted(line_seconds(work / f"out{workers}"))
            walls[workers] = wall
            print(f"{workers} worker{'s' if workers > 1 else ' '}: {wall:6.1f} s wall (Ray start included), "
                  f"{60 * args.lines / wall:5.1f} lines/min; per line median {times[len(times) // 2]:.2f} s, "
                  f"slowest {times[-1]:.2f} s (a worker's first line: it opens the character, loads the model)")
        print(f"two workers / one: {walls[1] / walls[2]:.2f}x the throughput")
        times = sorted(line_seconds(work / "out1"))
        print(f"per-line overhead kept out by reuse (first line - median, one worker): "
              f"{times[-1] - times[len(times) // 2]:.2f} s of {times[-1]:.2f} s")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
