"""Benchmark: keys per second and worst error of the add-on's sparse Bezier poses against
the per-channel key reduction it used before and Blender's Graph Editor Decimate. One run
prints every figure side by side, measured on this machine:

    python bench/bench_keys.py [--seconds 60]

The bundled model generates motion once (seed 0) from --seconds of real speech, keyed onto
the BEAT demo rig (BVH import + the ARKit face, preset "beat") in a 24 fps scene: every
frame (the reference), ours at 0.5 / 1 / 2 degrees (face 0.01 / 0.02 / 0.04), "Reduced"
(each F-curve alone: linear keys, split at the worst frame while off by more than a
tolerance) and Decimate (bpy.ops.graph.decimate, ERROR mode, on copies of the every-frame
Actions, headless through a Graph Editor area). Their tolerance / margin start at the bound
and are rescaled (4 tries in numpy for Reduced, 3 in Blender for Decimate, bones and face
apart) to the largest tried whose measured worst error keeps the bound. All are measured
alike: every F-curve evaluated by Blender at every frame against the every-frame bake, a
bone's rotation channels as one rotation (degrees), a shape key as a weight. Keying time:
the bake for ours, the every-frame bake + reduction / decimation for the others.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import soundfile as sf

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]

import bpy  # noqa: E402

import diffsheg_core  # noqa: E402
from addon_fixtures import SPEECH, append_face, import_beat_armature, reset_scene  # noqa: E402
from blender_addon.scene.bake import BakeOptions, bake_motion  # noqa: E402
from blender_addon.scene.keying import fcurves_of  # noqa: E402
from blender_addon.scene.preset import load_preset  # noqa: E402
from diffsheg_core.keyframes import rotation_angle, to_quaternions  # noqa: E402

FPS = 24
BOUNDS = ((0.5, 0.01), (1.0, 0.02), (2.0, 0.04))  # degrees per bone, weight per shape key
MODES = {"rotation_quaternion": "QUATERNION", "rotation_axis_angle": "AXIS_ANGLE"}
Curves = dict[tuple[str, int], np.ndarray]


@dataclass
class Stats:
    rates: list[float]  # keys per second, per bone or per shape key
    worst: float        # degrees or weight, over every frame
    keys: int           # all F-curve keys


@dataclass
class Row:
    method: str
    bound: float  # degrees
    setting: str
    bones: Stats
    face: Stats
    seconds: float


def curves(id_data, frames: np.ndarray) -> dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]:
    """{(data_path, index): (key frames, values Blender evaluates at `frames`)}."""
    out = {}
    for fc in fcurves_of(id_data):
        co = np.empty(2 * len(fc.keyframe_points), dtype=np.float32)
        fc.keyframe_points.foreach_get("co", co)
        out[fc.data_path, fc.array_index] = (co[0::2], np.array([fc.evaluate(f) for f in frames]))
    return out


def bone_mode(armature, path: str) -> str:
    return MODES.get(path.rsplit(".", 1)[1], armature.pose.bones[path.split('"')[1]].rotation_mode)


def bone_worst(armature, want: Curves, got: Curves) -> float:
    """Largest angle (degrees) between `got` and `want` rotations over bones and frames."""
    worst = 0.0
    for path, indices in groups(want).items():
        mode = bone_mode(armature, path)
        a, b = (np.stack([c[path, i] for i in indices], axis=1).astype(np.float64) for c in (got, want))
        worst = max(worst, float(rotation_angle(to_quaternions(a, mode), to_quaternions(b, mode)).max()))
    return worst


def groups(channels) -> dict[str, list[int]]:
    """{data path: its indices} of bone rotation channels."""
    return {path: sorted(i for p, i in channels if p == path) for path, _ in sorted(channels)}


def bone_stats(armature, want: Curves, frames: np.ndarray) -> Stats:
    got = curves(armature, frames)
    rates = [len(np.unique(np.concatenate([got[p, i][0] for i in ix]))) * FPS / len(frames)
             for p, ix in groups(got).items()]
    worst = bone_worst(armature, want, {k: v[1] for k, v in got.items()})
    return Stats(rates, worst, sum(len(v[0]) for v in got.values()))


def face_stats(key, want: Curves, frames: np.ndarray) -> Stats:
    got = curves(key, frames)
    return Stats([len(f) * FPS / len(frames) for f, _ in got.values()],
                 max(float(np.abs(v - want[k]).max()) for k, (_, v) in got.items()),
                 sum(len(f) for f, _ in got.values()))


def reduce_keys(values: np.ndarray, tolerance: float) -> np.ndarray:
    """Indices to key so that linear interpolation is within `tolerance` of every value
    (Douglas-Peucker: keep the ends, split at the worst frame while it is off by more)."""
    keep, stack = {0, len(values) - 1}, [(0, len(values) - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        line = values[a] + (values[b] - values[a]) * np.arange(1, b - a) / (b - a)
        err = np.abs(values[a + 1:b] - line)
        if err.max() > tolerance:
            mid = a + 1 + int(np.argmax(err))
            keep.add(mid)
            stack += [(a, mid), (mid, b)]
    return np.array(sorted(keep))


def reduced_worst(armature, want: Curves, tolerance: float) -> float:
    """The worst bone angle of Reduced at `tolerance`, in numpy (exact at whole frames)."""
    t = np.arange(len(next(iter(want.values()))))
    got = {k: np.interp(t, keep, v[keep]) for k, v in want.items() for keep in [reduce_keys(v, tolerance)]}
    return bone_worst(armature, want, got)


def reduce_in_place(id_data, tolerance: float) -> None:
    linear = bpy.types.Keyframe.bl_rna.properties["interpolation"].enum_items["LINEAR"].value
    for fc in fcurves_of(id_data):
        points = fc.keyframe_points
        co = np.empty(2 * len(points), dtype=np.float32)
        points.foreach_get("co", co)
        co = co.reshape(-1, 2)[reduce_keys(co[1::2].astype(np.float64), tolerance)]
        points.clear()
        points.add(len(co))
        points.foreach_set("co", co.ravel())
        points.foreach_set("interpolation", [linear] * len(co))
        fc.update()


def calibrate(worst_at: Callable[[float], float], start: float, bound: float, tries: int) -> float:
    """The largest of `tries` margins (each rescaled by bound / its worst error) that keeps
    the bound; the smallest tried if none does."""
    tried: dict[float, float] = {}
    margin = start
    for _ in range(tries):
        tried[margin] = worst_at(margin)
        margin *= 0.95 * bound / max(tried[margin], 1e-12)
    ok = [m for m, w in tried.items() if w <= bound]
    return max(ok) if ok else min(tried)


def graph_editor() -> dict:
    """A temp_override context with a Graph Editor showing every object's curves."""
    window = bpy.context.window_manager.windows[0]
    area = max(window.screen.areas, key=lambda a: a.width * a.height)
    area.type = "GRAPH_EDITOR"
    area.spaces.active.dopesheet.show_only_selected = False
    area.spaces.active.dopesheet.show_hidden = True
    region = next(r for r in area.regions if r.type == "WINDOW")
    return {"window": window, "screen": window.screen, "area": area, "region": region}


def decimate(context: dict, targets: list, selected, margin: float) -> float:
    """Decimate the keys of `selected` (one of `targets`) within `margin`; seconds taken."""
    for id_data in targets:
        for fc in fcurves_of(id_data):
            fc.select = id_data is selected
            for flag in ("select_control_point", "select_left_handle", "select_right_handle"):
                fc.keyframe_points.foreach_set(flag, [id_data is selected] * len(fc.keyframe_points))
    start = time.perf_counter()
    with bpy.context.temp_override(**context):
        bpy.ops.graph.decimate(mode="ERROR", remove_error_margin=margin)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    samples, rate = sf.read(str(SPEECH), dtype="float32")
    offset = min(5.0, max(0.0, len(samples) / rate - args.seconds))
    start = time.perf_counter()
    motion = diffsheg_core.generate(samples[int(offset * rate): int((offset + args.seconds) * rate)], rate,
                                    seed=0, device="cpu")
    generated = time.perf_counter() - start
    scene = reset_scene(fps=FPS)
    armature, face = import_beat_armature(), append_face()
    key = face.data.shape_keys

    def bake(**options) -> float:
        start = time.perf_counter()
        bake_motion(scene, motion, None, BakeOptions(armature=armature, face_meshes=[face],
                                                     preset=load_preset("beat"), add_sound=False, **options))
        return time.perf_counter() - start

    def row(method: str, bound: float, setting: str, seconds: float) -> Row:
        return Row(method, bound, setting, bone_stats(armature, want_bones, frames),
                   face_stats(key, want_face, frames), seconds)

    dense_time = bake(every_frame=True)
    frames = np.arange(1, scene.frame_end + 1, dtype=np.float64)
    dense = {armature: armature.animation_data.action, key: key.animation_data.action}
    want_bones = {k: v[1].astype(np.float64) for k, v in curves(armature, frames).items()}
    want_face = {k: v[1].astype(np.float64) for k, v in curves(key, frames).items()}
    rows, failed = [row("every frame", 0.0, "", dense_time)], []
    for degrees, weight in BOUNDS:
        rows.append(row("ours", degrees, f"{degrees:g} deg / {weight:g}",
                        bake(max_error=degrees, max_face_error=weight)))
    for degrees, weight in BOUNDS:
        tolerance = calibrate(lambda t: reduced_worst(armature, want_bones, t), np.radians(degrees), degrees, 4)
        seconds, start = bake(every_frame=True), time.perf_counter()
        reduce_in_place(armature, tolerance)
        reduce_in_place(key, weight)  # one channel: the tolerance is the bound
        rows.append(row("Reduced", degrees, f"{tolerance:.4f} rad / {weight:g}",
                        seconds + time.perf_counter() - start))
    for degrees, weight in BOUNDS:
        trials: dict[float, tuple[Stats, float]] = {}

        def trial(target, want: Curves, stats_of, margin: float) -> float:
            anim = target.animation_data
            anim.action = dense[target].copy()  # one slot, the target's
            anim.action_slot = anim.action.slots[0]
            seconds = decimate(context, [armature, key], target, margin)
            trials[margin] = (stats_of(target, want, frames), seconds)
            return trials[margin][0].worst

        try:
            context = graph_editor()
            bone_margin = calibrate(lambda m: trial(armature, want_bones, bone_stats, m), np.radians(degrees),
                                    degrees, 3)
            face_margin = calibrate(lambda m: trial(key, want_face, face_stats, m), weight, weight, 3)
        except Exception as exc:  # e.g. no window to hold a Graph Editor in this Blender
            failed.append(f"{'Decimate':<12}{degrees:g} deg: could not run headless: {type(exc).__name__}: {exc}")
            continue
        (bones, bone_s), (faces, face_s) = trials[bone_margin], trials[face_margin]
        rows.append(Row("Decimate", degrees, f"{bone_margin:.4f} rad / {face_margin:.4f}", bones, faces,
                        dense_time + bone_s + face_s))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Blender {bpy.app.version_string}; {args.seconds:g} s of {SPEECH.name} generated in "
          f"{generated:.1f} s, keyed at {FPS} fps: {len(frames)} frames, {len(rows[0].bones.rates)} bones "
          f"({bone_mode(armature, next(iter(want_bones))[0])}), {len(rows[0].face.rates)} shape keys")
    report(rows, failed)


def report(rows: list[Row], failed: list[str]) -> None:
    print(f"{'method':<12}{'setting':<24}{'bone keys/s':>12}{'max':>7}{'face keys/s':>12}{'max':>7}"
          f"{'worst deg':>11}{'worst wt':>10}{'keys':>8}{'keying s':>10}")
    for r in rows:
        print(f"{r.method:<12}{r.setting:<24}{np.mean(r.bones.rates):>12.2f}{max(r.bones.rates):>7.2f}"
              f"{np.mean(r.face.rates):>12.2f}{max(r.face.rates):>7.2f}{r.bones.worst:>11.3f}"
              f"{r.face.worst:>10.4f}{r.bones.keys + r.face.keys:>8}{r.seconds:>10.2f}")
    for line in failed:
        print(line)
    print("(bone keys/s: distinct keyed frames of a bone's rotation channels; keys: all F-curve keys)")
    for ours in (r for r in rows if r.method == "ours"):
        for other in (r for r in rows if r.method in ("Reduced", "Decimate") and r.bound == ours.bound):
            print(f"{ours.setting}: keys ours / {other.method}: per bone "
                  f"{np.mean(ours.bones.rates) / np.mean(other.bones.rates):.2f}, per shape key "
                  f"{np.mean(ours.face.rates) / np.mean(other.face.rates):.2f}, all "
                  f"{(ours.bones.keys + ours.face.keys) / (other.bones.keys + other.face.keys):.2f} "
                  f"(worst {ours.bones.worst:.2f} vs {other.bones.worst:.2f} deg, "
                  f"{ours.face.worst:.4f} vs {other.face.worst:.4f})")


if __name__ == "__main__":
    main()
