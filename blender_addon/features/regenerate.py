"""Regenerate a range of the take playing, around the animator's own keys.

The animator picks scene frames [first, last] (the preview range, or frames in the
panel). `prepare_range` (main thread) finds the take playing on the character, the
Motion it was made from (takes.source_of), the model frames whose change reaches only
those scene frames, and the pins: every key of the animator's (`keying.animators_keys`:
any type but GENERATED, or a generated key whose value the animator changed) on a driven
bone inside the range, turned back through the retargeting into a pose of the model's
joint. `diffsheg_core.regenerate` then samples the range anew off the main thread, and
`apply_range` (main thread) makes the result a new take: a copy of the take's Actions
(the animator's keys there typed KEYFRAME) in which only the keys inside the range are
replaced. Each F-curve is cut exactly at the frames just outside the range (`_cut`), so the
curves outside it, and every key there, stay as they were; the animator's keys inside
stay as set; new GENERATED keys are fitted between them (`keyframes.fit_span`) within
the error bound, continuing the curves at both cuts with their own slopes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import bpy
import numpy as np

from diffsheg_core.errors import DiffshegError
from diffsheg_core.keyframes import Keys, fit_span, handles, to_quaternions
from diffsheg_core.lower_body import upper_body
from diffsheg_core.motion import Motion
from diffsheg_core.pipeline import Pin
from diffsheg_core.rotations import axis_angle_to_matrix, convert

from ..scene import takes
from ..scene.bake import BakeOptions, BakeResult, Group, auto_preset, group_values, plan_keys, scene_fps
from ..scene.keying import (GENERATED_KEY, Undo, action_fcurves, animators_keys, fcurves_of, mark_animators,
                            moved_by, record_baked, undone_on_error)
from ..scene.retarget import joint_rotation, map_armature, passed_rotation

REACH = 2  # model frames on either side that one scene frame's value depends on (PCHIP face weights)


@dataclass
class RangeRequest:
    """A range of take `take` to generate anew: scene frames [first, last], model frames
    [start, end) of its source, and the pins the new motion passes through."""

    take: str
    source: takes.TakeSource
    first: int
    last: int
    start: int
    end: int
    pins: tuple[Pin, ...] = ()
    notes: list[str] = field(default_factory=list)


def scene_range(settings, scene) -> tuple[int, int]:
    """The scene frames the panel's Range asks for: the preview range or its own frames."""
    if settings.range_mode == "PREVIEW":
        if not scene.use_preview_range:
            raise DiffshegError("Range is 'Preview range' but the scene has none: set one in the timeline "
                                "(View > Set Preview Range, or Ctrl+P) or choose Range 'Frames'")
        return scene.frame_preview_start, scene.frame_preview_end
    return settings.range_start, settings.range_end


def playing_take(targets, frame: int) -> str:
    """The take the character plays at scene `frame` (its armature, else a face); refused
    where that take plays from an NLA strip moved off its own frames."""
    name = takes.first_playing(targets, frame)
    if name is not None:
        for target in targets:
            takes.check_in_place(target, name)
        return name
    raise DiffshegError("the character plays no take: generate the whole clip first (Range 'Whole clip'), "
                        "or pick a take in the panel's take list")


def model_range(first: int, last: int, source: takes.TakeSource, fps: float) -> tuple[int, int]:
    """Model frames [start, end) of the source whose change reaches scene frames inside
    [first, last] only (each scene frame depends on the REACH model frames either side)."""
    motion, s = source.motion, source.start_frame
    n_scene = max(1, int(round(motion.duration * fps)))
    final = s + n_scene - 1
    if not (s <= first <= last <= final):
        raise DiffshegError(f"the range {first}-{last} must lie within the take's frames {s}-{final}")
    ratio = motion.fps / fps
    start = 0 if first == s else math.floor((first - 1 - s) * ratio) + REACH + 1
    end = motion.n_frames if last == final else math.floor((last + 1 - s) * ratio) - REACH + 1
    if end - start < 2:
        need = math.ceil((2 * REACH + 3) / ratio)
        raise DiffshegError(f"the range {first}-{last} is too short to generate anew: choose at least {need} "
                            "frames")
    return max(start, 0), min(end, motion.n_frames)


def take_shift(targets, take: str, frame: int) -> int:
    """Whole frames the keys of take `take` were moved by since it was made (the Dope Sheet's
    G over the take: keying.moved_by), the same for every one of `targets` that plays it at
    scene `frame`. Refused where they were moved apart or by part of a frame: the take's
    frames could not be matched to the speech's."""
    shifts = {}
    for target in targets:
        action, slot = takes.playing_action(target, frame) if target is not None else (None, None)
        if action is not None and takes.is_take(action) and action[takes.TAKE] == take:
            owner = getattr(target, "user", None) or target  # a face's shape keys: its mesh
            shifts[owner.name] = moved_by(action, action_fcurves(action, slot))
    moved = set(shifts.values())
    if len(moved) > 1:
        apart = ", ".join(f"{name} by {shift:g}" for name, shift in shifts.items())
        raise DiffshegError(f"the keys of take '{take}' were moved apart ({apart} frames): move them by the same "
                            "frames on the armature and the faces to regenerate a range of it")
    shift = moved.pop() if moved else 0.0
    if shift != round(shift):
        raise DiffshegError(f"the keys of take '{take}' were moved by {shift:g} frames: move them by whole frames "
                            "to regenerate a range of it")
    return int(round(shift))


def prepare_range(scene, options: BakeOptions, first: int, last: int) -> RangeRequest:
    """Everything regenerating [first, last] needs from the scene (main thread only). A take
    whose keys the animator moved in time as a whole is regenerated where it is now."""
    targets = [options.armature] + [m.data.shape_keys for m in options.face_meshes]
    take = playing_take(targets, first)
    source = takes.source_of(take)
    shift = take_shift(targets, take, first)
    if shift:
        source = replace(source, start_frame=source.start_frame + shift)
    start, end = model_range(first, last, source, scene_fps(scene))
    request = RangeRequest(take, source, first, last, start, end)
    if options.armature is not None:
        pins, notes = animator_pins(scene, options, request)
        request = replace(request, pins=pins, notes=notes)
    return request


# ---------------------------------------------------------------- pins

def animator_pins(scene, options: BakeOptions, request: RangeRequest) -> tuple[tuple[Pin, ...], list[str]]:
    """Pins from the animator's keys on the armature inside the range; notes on keys that
    cannot be pins (a bone the model does not drive, a key too near the range's edge)."""
    armature, source = options.armature, request.source
    by_bone = {t.bone: t for t in _mapping(options, source.motion).targets}
    keyed = _animator_keys(armature, request.first, request.last)
    ratio = source.motion.fps / scene_fps(scene)
    pins, notes = [], []
    for bone, frame in keyed:
        target = by_bone.get(bone)
        if target is None or not target.joints:
            notes.append(f"your key on {bone} at frame {frame:g}: the model does not drive that bone, "
                         "so it is kept but steers nothing")
            continue
        t = (frame - source.start_frame) * ratio
        k = math.floor(t + 1e-6)
        w = t - k if t - k > 1e-6 else 0.0
        if k < request.start or k + (w > 0) >= request.end:
            notes.append(f"your key on {bone} at frame {frame:g} is too near the range's edge, where the motion "
                         "joins the frames outside, to steer it: it is kept as set")
            continue
        local = convert(_bone_quaternion(armature, bone, frame), "quaternion", "matrix")
        joint = target.joints[-1]
        pose = joint_rotation(target, local, passed_rotation(target, source.motion, k))
        pins += _pins_at(source.motion, joint, pose, k, w)
    return tuple(pins), notes


def _mapping(options: BakeOptions, motion: Motion):
    """The options' armature matched to the model's joints (Auto: the preset its names fit):
    not the hips and legs, which the model does not make and a pin cannot steer."""
    preset = options.preset or auto_preset(motion.rig, options.armature, options.face_meshes)[0]
    return map_armature(options.armature, preset, upper_body(motion))


def _animator_keys(armature, first: int, last: int) -> list[tuple[str, float]]:
    """(bone, frame) of every key of the animator's (keying.animators_keys) on a bone's
    rotation inside [first, last]."""
    action, slot = takes.playing_action(armature, first)
    fcurves = [fc for fc in (action_fcurves(action, slot) if action is not None else [])
               if fc.data_path.startswith("pose.bones[") and ".rotation_" in fc.data_path]
    found = set()
    for fc, theirs in zip(fcurves, animators_keys(action, fcurves)):
        bone = fc.data_path.split('"')[1].replace('\\"', '"')
        for i in np.flatnonzero(theirs):
            frame = float(fc.keyframe_points[int(i)].co[0])
            if first <= frame <= last:
                found.add((bone, frame))
    return sorted(found, key=lambda item: (item[1], item[0]))


def _bone_quaternion(armature, bone: str, frame: float) -> np.ndarray:
    """(4,) the bone's rotation at `frame` as its playing F-curves give it (rest where unkeyed)."""
    pose_bone = armature.pose.bones[bone]
    mode = pose_bone.rotation_mode
    attr = {"QUATERNION": "rotation_quaternion", "AXIS_ANGLE": "rotation_axis_angle"}.get(mode, "rotation_euler")
    values = np.array(getattr(pose_bone, attr), dtype=np.float64)
    path = f'pose.bones["{bone}"].{attr}'
    for fc in fcurves_of(armature, frame):
        if fc.data_path == path and fc.array_index < len(values):
            values[fc.array_index] = fc.evaluate(frame)
    return to_quaternions(values[None], mode)[0]


def _pins_at(motion: Motion, joint: str, pose: np.ndarray, k: int, w: float) -> list[Pin]:
    """Pins that make the motion, resampled, pass through `pose` at model time k + w: one at
    frame k where w is 0, else two around it whose slerp at w is the pose, moving as the
    motion moved there (R_k = P d^-w, R_k+1 = P d^(1-w), d the motion's step k -> k+1)."""
    if w == 0.0:
        return [Pin(k, joint, tuple(float(v) for v in pose))]
    j = motion.joint_names.index(joint)
    a, b = axis_angle_to_matrix(motion.rotations[k, j]), axis_angle_to_matrix(motion.rotations[k + 1, j])
    step = convert(a.T @ b, "matrix", "axis_angle")
    p = axis_angle_to_matrix(pose)
    before = convert(p @ axis_angle_to_matrix(-w * step), "matrix", "axis_angle")
    after = convert(p @ axis_angle_to_matrix((1.0 - w) * step), "matrix", "axis_angle")
    return [Pin(k, joint, tuple(float(v) for v in before)), Pin(k + 1, joint, tuple(float(v) for v in after))]


def pose_pins(scene, options: BakeOptions, motion_layout: Motion) -> tuple[Pin, ...]:
    """Pins at the first frame holding the armature's pose at the start frame ("start from
    the pose"): every driven joint as the character stands there now."""
    armature = options.armature
    pins = []
    for target in _mapping(options, motion_layout).targets:
        if not target.joints:
            continue
        local = convert(_bone_quaternion(armature, target.bone, options.start_frame), "quaternion", "matrix")
        pins.append(Pin(0, target.joints[-1], tuple(float(v) for v in joint_rotation(target, local))))
    return tuple({p.joint: p for p in pins}.values())  # a joint spread over a chain: its last bone's


# ---------------------------------------------------------------- the new take

def apply_range(scene, request: RangeRequest, motion: Motion, options: BakeOptions) -> BakeResult:
    """Make `motion` (the take's source with the range generated anew) a new take: a copy of
    the take playing with the keys inside the range replaced. Scene unchanged on error."""
    options = replace(options, start_frame=request.source.start_frame)
    plan = plan_keys(scene, motion, options)
    was = plan_keys(scene, request.source.motion, plan.options)  # the same groups, as the take has them
    old = {a.get(takes.TARGET): a for a in bpy.data.actions
           if takes.is_take(a) and a[takes.TAKE] == request.take}
    audio = Path(request.source.audio_path).stem or "speech"
    number = takes.next_number(audio)
    take = takes.take_name(audio, number)
    notes = list(request.notes)
    with undone_on_error("the regenerated range") as undo:
        actions, replaced, n_keys = [], [], 0
        for (id_data, groups), (_, old_groups) in zip(plan.targets, was.targets):
            source_action = old.get(id_data)
            if source_action is None:
                notes.append(f"{getattr(id_data, 'name', id_data)} is not part of take '{request.take}': "
                             "not keyed (generate the whole clip to key it)")
                continue
            action = _copy_take(source_action, take, audio, number, id_data, undo)
            slot = action.slots[0] if len(getattr(action, "slots", ())) else None
            fcurves = action_fcurves(action, slot)
            mark_animators(action, fcurves)  # from here on, GENERATED keys are the take's
            n_keys += sum(splice_group(fcurves, group, request, plan.options)
                          for group, old_group in zip(groups, old_groups) if _changed(group, old_group, request))
            record_baked(action, fcurves)
            actions.append(action)
            replaced.append(source_action)
        if not actions:
            raise DiffshegError(f"none of the chosen armature and faces plays take '{request.take}'")
        takes.store_source(actions[0], takes.TakeSource(motion, request.source.audio_path,
                                                        request.source.start_frame))
        for action, old_action in zip(actions, replaced):
            takes.replace_playing(action[takes.TARGET], old_action, action, undo)
    return BakeResult(take=take, preset=plan.options.preset.name, actions=[a.name for a in actions],
                      n_frames=request.last - request.first + 1, n_keys=n_keys,
                      unmatched_bones=plan.unmatched_bones, unmatched_shape_keys=plan.unmatched_shape_keys,
                      sound_strip=None, preset_notes=plan.preset_notes, notes=notes + plan.notes)


def _copy_take(action, take: str, audio: str, number: int, id_data, undo: list[Undo]):
    """A copy of one Action of a take, made part of the new take (without the old source)."""
    copy = action.copy()
    undo.append(lambda: bpy.data.actions.remove(copy))
    copy.name = takes.action_name(take, id_data)
    takes.mark(copy, take, audio, number, id_data)
    if takes.SOURCE in copy:
        del copy[takes.SOURCE]
    return copy


# ---------------------------------------------------------------- splicing keys

def _changed(group: Group, old: Group, request: RangeRequest) -> bool:
    """Whether the group's values in the range differ from the take's (a kept face does not)."""
    span = slice(request.first - request.source.start_frame, request.last - request.source.start_frame + 1)
    return not np.array_equal(group_values(group)[span], group_values(old)[span])


@dataclass
class _Curve:
    """One F-curve's keys as arrays: frames, values, handles, whether each is generated."""

    fc: object
    frames: np.ndarray
    values: np.ndarray
    left: np.ndarray
    right: np.ndarray
    generated: np.ndarray


def splice_group(fcurves: list, group: Group, request: RangeRequest, options: BakeOptions) -> int:
    """Replace the group's generated keys inside the range with keys fitted to its new
    values; returns the number of keys written. Curves the take lacks are skipped."""
    by_path = {(fc.data_path, fc.array_index): fc for fc in fcurves}
    found = [by_path.get((ch.data_path, ch.index)) for ch in group.channels]
    if any(fc is None for fc in found):
        return 0
    s = request.source.start_frame
    final = s + len(group.channels[0].values) - 1
    lo = request.first - 1 if request.first > s else request.first  # a cut outside the range, or the take's end
    hi = request.last + 1 if request.last < final else request.last
    for fc in found:
        for cut in {lo, hi} - {request.first, request.last}:
            _cut(fc, cut)
    curves = [_read(fc) for fc in found]
    values = group_values(group)[lo - s: hi - s + 1]
    fixed = _fixed_keys(curves, values, lo, hi, request)
    if options.every_frame:
        keys = Keys(np.arange(len(values)), values, np.gradient(values, axis=0))
    else:
        full = group_values(group)
        error = group.error(full)
        keys = fit_span(values, lambda v, f: error(v, f + (lo - s)), group.bound, fixed)
    return _write_span(curves, keys, lo, hi, request)


def _cut(fc, frame: float) -> None:
    """Put a key at `frame` on `fc` without changing the curve (none there yet): Blender
    subdivides a Bezier segment's handles where a key goes into it (de Casteljau), once
    the keys around it stop recomputing their handles from their neighbours."""
    points = fc.keyframe_points
    frames = np.array([p.co[0] for p in points])
    if len(frames) == 0 or np.any(np.abs(frames - frame) < 1e-4):
        return
    after = int(np.searchsorted(frames, frame))
    for key in points[max(after - 1, 0): after + 1]:  # their handles stay where they are now
        if key.handle_left_type in {"AUTO", "AUTO_CLAMPED", "VECTOR"}:
            key.handle_left_type = key.handle_right_type = "ALIGNED"
    points.insert(frame, fc.evaluate(frame), options={"FAST"}, keyframe_type=GENERATED_KEY)
    fc.update()


def _read(fc) -> _Curve:
    points = fc.keyframe_points
    n = len(points)
    co, left, right = np.empty(2 * n), np.empty(2 * n), np.empty(2 * n)
    points.foreach_get("co", co)
    points.foreach_get("handle_left", left)
    points.foreach_get("handle_right", right)
    generated = np.array([p.type == GENERATED_KEY for p in points], dtype=bool)
    co, left, right = co.reshape(n, 2), left.reshape(n, 2), right.reshape(n, 2)
    return _Curve(fc, co[:, 0], co[:, 1], left, right, generated)


def _slope(point: np.ndarray, handle: np.ndarray) -> float:
    dx = handle[0] - point[0]
    return float((handle[1] - point[1]) / dx) if abs(dx) > 1e-9 else 0.0


def _fixed_keys(curves: list[_Curve], values: np.ndarray, lo: int, hi: int, request: RangeRequest) -> dict:
    """{frame in the span: (values, slopes)} of the keys that stay: the cuts outside the
    range (with the curves' own slopes there) and the animator's keys inside it (its
    values; the new motion's slopes). The span's ends where they are the take's ends
    take the new motion's values."""
    slopes = np.gradient(values, axis=0) if len(values) > 1 else np.zeros_like(values)
    fixed = {0: (values[0].copy(), slopes[0].copy()), len(values) - 1: (values[-1].copy(), slopes[-1].copy())}
    for c, curve in enumerate(curves):
        for i, frame in enumerate(curve.frames):
            if not lo <= frame <= hi or abs(frame - round(frame)) > 1e-4:
                continue
            f = int(round(frame)) - lo
            cut = (frame == lo and lo < request.first) or (frame == hi and hi > request.last)
            if not cut and curve.generated[i]:
                continue
            value, slope = fixed.setdefault(f, (values[f].copy(), slopes[f].copy()))
            value[c] = curve.values[i]
            if cut:
                point = np.array([frame, curve.values[i]])
                slope[c] = _slope(point, curve.right[i] if frame == lo else curve.left[i])
    return fixed


def _write_span(curves: list[_Curve], keys: Keys, lo: int, hi: int, request: RangeRequest) -> int:
    """Write `keys` (span frames from `lo`) into the curves: the generated keys inside the
    range replaced, the kept keys at the cuts given handles spaced for their new neighbours.
    New keys are appended and sorted by `update` (inserting one would subdivide the handles
    of the keys around it)."""
    left, right = handles(keys)
    offset = np.array([lo, 0.0])
    written = 0
    for c, curve in enumerate(curves):
        points = curve.fc.keyframe_points
        for i in reversed(range(len(curve.frames))):  # generated keys inside the range go
            if curve.generated[i] and request.first <= curve.frames[i] <= request.last:
                points.remove(points[i], fast=True)
        kept = {int(round(p.co[0])) for p in points if lo <= p.co[0] <= hi}
        new = [k for k, f in enumerate(keys.frames) if lo + int(f) not in kept]
        first_new = len(points)
        points.add(len(new))  # moves the keys in memory: look them up only from here on
        for point, k in zip(list(points)[first_new:], new):
            point.co = (lo + float(keys.frames[k]), float(keys.values[k, c]))
            point.interpolation = "BEZIER"
            point.type = GENERATED_KEY
            point.handle_left_type = point.handle_right_type = "ALIGNED"
            point.handle_left, point.handle_right = left[k, c] + offset, right[k, c] + offset
        kept = {int(round(p.co[0])): p for p in list(points)[:first_new] if lo <= p.co[0] <= hi}
        for k, f in enumerate(keys.frames):
            point = kept.get(lo + int(f))
            if point is None or point.type != GENERATED_KEY:
                continue  # the animator's key stays as set
            if f == 0 and len(keys) > 1:  # the cut before the range: only its handle into it moves
                point.handle_right = right[k, c] + offset
            if lo + f == hi and len(keys) > 1:
                point.handle_left = left[k, c] + offset
        written += len(new)
        curve.fc.update()
    return written

