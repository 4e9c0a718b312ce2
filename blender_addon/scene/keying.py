"""Bulk keyframing into a new Action, on Blender 5.x layered actions or the legacy API.

The API is chosen by feature detection. Actions with slots (4.4+) get a slot for the
datablock, assigned with the Action: without it, 4.4-4.5 key the curves but nothing
moves. F-Curves go into the slot's channelbag where
`bpy_extras.anim_utils.action_ensure_channelbag_for_slot` exists (5.0+), else into
`Action.fcurves` (4.2-4.3; on 4.4-4.5 the legacy API's first slot, the only one here).
A take already playing there is replaced by the new one (see takes.py); a user's Action
is kept and pushed onto an NLA track, never overwritten. Keys go in with `keyframe_points.add` + `foreach_set`: either a channel's
sparse Bezier keys (`diffsheg_core.keyframes`: poses with aligned handles) or one key per
frame. Every key written is typed GENERATED_KEY: GENERATED, Blender's type for keys a tool
made (4.2+); any other type is the animator's. Blender before 4.2 has no GENERATED type (the
legacy zip's Blenders), and there the keys are JITTER, its type for "a filler or baked
keyframe", which an animator there rarely sets by hand.

Type alone does not tell the animator's keys: keying a frame that holds a generated key
keeps its type (Blender 5.0). So a take's Action also records the frame and value of every
key it baked (`record_baked`), and a generated key whose value is no longer the one baked
is the animator's too (`animators_keys`).
"""

from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

import bpy

from diffsheg_core.errors import DiffshegError
from diffsheg_core.keyframes import Keys, handles

from .takes import assign, is_take, playing_action, push_to_nla

try:
    from bpy_extras.anim_utils import action_ensure_channelbag_for_slot
except ImportError:  # Blender 4.2-4.3: legacy actions only
    action_ensure_channelbag_for_slot = None


@dataclass
class Channel:
    """One F-Curve's worth of values, one per frame from the start frame, and its sparse
    keys (values and slopes of this channel alone) where it is keyed sparsely."""

    data_path: str
    index: int
    values: np.ndarray
    group: str = ""
    keys: Keys | None = None


Undo = Callable[[], None]


@contextmanager
def undone_on_error(what: str, undo: list[Undo] | None = None) -> Iterator[list[Undo]]:
    """A list for undo steps (callables restoring what a change replaced; `undo` where the
    caller keeps them, to roll a change back later); if the block raises, they run in
    reverse, so the scene is as it was, and the error is a DiffshegError ("could not write
    `what` into the scene: ...")."""
    undo = [] if undo is None else undo
    try:
        yield undo
    except Exception as exc:
        for step in reversed(undo):
            step()
        if isinstance(exc, DiffshegError):
            raise
        raise DiffshegError(f"could not write {what} into the scene: {exc}") from exc


def has_action_slots() -> bool:
    return "slots" in bpy.types.Action.bl_rna.properties


def _uses_channelbags(slot) -> bool:
    return slot is not None and action_ensure_channelbag_for_slot is not None


def new_action(id_data, name: str, undo: list[Undo]):
    """Create and assign a new Action on `id_data` (an Object or a shape-key Key). A take
    playing there is replaced (it stays in the file); an Action of the user's is pushed to
    the NLA. Each change is recorded in `undo` (callables restoring the previous state,
    run in reverse on failure)."""
    created_anim = id_data.animation_data is None
    anim = id_data.animation_data_create()
    if created_anim:
        undo.append(lambda: id_data.animation_data_clear())
    previous = anim.action
    if is_take(previous):
        undo.append(lambda: assign(id_data, previous))
    elif previous is not None:
        push_to_nla(anim, previous, undo)
    action = bpy.data.actions.new(name)
    undo.append(lambda: bpy.data.actions.remove(action))
    slot = None
    if has_action_slots():
        slot = action.slots.new(id_type=id_data.id_type, name=id_data.name)
    anim.action = action
    if slot is not None:
        anim.action_slot = slot
    return action, slot


def write_channels(action, slot, channels: list[Channel], start_frame: float) -> int:
    """Key every channel from `start_frame`: its sparse keys where it has them, else one
    key per frame. Returns the number of keys written."""
    make = _fcurve_factory(action, slot)
    groups: dict[str, object] = {}
    total = 0
    for ch in channels:
        values = np.asarray(ch.values, dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise DiffshegError(f"the motion holds non-finite values for {ch.data_path}[{ch.index}]: "
                                "try another seed or model")
        fc = make(ch.data_path, ch.index, ch.group, groups)
        total += _write_keys(fc, ch.keys, values, start_frame)
    return total


GENERATED_KEY = "GENERATED" if "GENERATED" in bpy.types.Keyframe.bl_rna.properties["type"].enum_items else "JITTER"


BAKED = "diffsheg_baked"  # on a take's Action: the frame and value of each key it baked (record_baked)
VALUE_TOLERANCE = 1e-4    # a key this near its baked value is the take's (float noise of keying the same pose again)
FRAME_TOLERANCE = 1e-3    # frames: a key this near a baked key's frame is at that frame


def record_baked(action, fcurves: list) -> None:
    """Keep on `action` (a custom property: saved with the .blend, copied with the Action)
    the frame and value of every generated key of `fcurves`, its F-curves, as they are now."""
    generated = _enum("type", GENERATED_KEY)
    curves, counts, keys = [], [], []
    for fc in fcurves:
        co, types = _keys_of(fc)
        curves.append([fc.data_path, fc.array_index])
        counts.append(int(np.count_nonzero(types == generated)))
        keys.append(co[types == generated])
    action[BAKED] = {"curves": json.dumps(curves), "counts": np.array(counts, dtype=np.int32),
                     "keys": np.concatenate(keys or [np.empty((0, 2))]).astype(np.float32).ravel()}


def animators_keys(action, fcurves: list) -> list[np.ndarray]:
    """Per F-curve of `action` in `fcurves`, which of its keys are the animator's: those not
    typed GENERATED, and those typed GENERATED whose frame and value are not one the take
    baked (`record_baked`, moved with the take where the animator moved it: `moved_by`; a
    take made before the record: by type alone). Where one of a property's keys at a frame
    is the animator's, all of them there are: keying keys the whole property (a bone's
    rotation), and the animator keyed that pose."""
    generated = _enum("type", GENERATED_KEY)
    baked = _baked(action)
    keys = [_keys_of(fc) for fc in fcurves]
    shift = np.array([0.0 if baked is None else _shift(baked, fcurves, keys), 0.0], dtype=np.float32)
    frames, found = [], []
    for fc, (co, types) in zip(fcurves, keys):
        theirs = types != generated
        if baked is not None:
            theirs |= ~_matches(co, baked.get((fc.data_path, fc.array_index), np.empty((0, 2), dtype=np.float32)) + shift)
        frames.append(co[:, 0])
        found.append(theirs)
    edited: dict[str, np.ndarray] = {}
    for fc, at, theirs in zip(fcurves, frames, found):
        edited[fc.data_path] = np.union1d(edited.get(fc.data_path, np.empty(0, dtype=np.float32)), at[theirs])
    return [theirs | _near(at, edited[fc.data_path]) for fc, at, theirs in zip(fcurves, frames, found)]


def moved_by(action, fcurves: list) -> float:
    """Frames the take's keys on `fcurves` (F-curves of `action`) were moved by since they were
    baked, as a whole (the Dope Sheet's G on every key): the shift shared by most curves whose
    generated keys are the ones `record_baked` kept, value for value, each moved by one and the
    same amount. 0.0 where they were not moved, or without a record."""
    baked = _baked(action)
    return 0.0 if baked is None else _shift(baked, fcurves, [_keys_of(fc) for fc in fcurves])


def _shift(baked: dict[tuple[str, int], np.ndarray], fcurves: list, keys: list) -> float:
    """`moved_by` for the record `baked` (`_baked`) and each of `fcurves`' keys (`_keys_of`)."""
    generated, votes, curves = _enum("type", GENERATED_KEY), {}, 0
    for fc, (co, types) in zip(fcurves, keys):
        kept = baked.get((fc.data_path, fc.array_index))
        if kept is None or not len(kept):
            continue
        curves += 1
        made = co[types == generated]
        if len(made) != len(kept) or np.abs(made[:, 1] - kept[:, 1]).max() > VALUE_TOLERANCE:
            continue  # edited, keys added or removed: no vote
        offsets = made[:, 0] - kept[:, 0]
        if np.ptp(offsets) <= FRAME_TOLERANCE:
            shift = round(float(offsets.mean()), 3)
            votes[shift] = votes.get(shift, 0) + 1
    if not votes:
        return 0.0
    shift, count = max(votes.items(), key=lambda item: item[1])
    return shift if 2 * count > curves else 0.0


def mark_animators(action, fcurves: list) -> None:
    """Type KEYFRAME the keys of `fcurves` (F-curves of `action`) typed GENERATED that are
    the animator's (`animators_keys`), so the Dope Sheet shows them as such."""
    for fc, theirs in zip(fcurves, animators_keys(action, fcurves)):
        for i in np.flatnonzero(theirs):
            point = fc.keyframe_points[int(i)]
            if point.type == GENERATED_KEY:
                point.type = "KEYFRAME"


def _keys_of(fc) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) frames and values of `fc`'s keys, and their types (enum values)."""
    points = fc.keyframe_points
    co, types = np.empty(2 * len(points), dtype=np.float32), np.empty(len(points), dtype=np.int32)
    points.foreach_get("co", co)
    points.foreach_get("type", types)
    return co.reshape(-1, 2), types


def _baked(action) -> dict[tuple[str, int], np.ndarray] | None:
    """{(data path, index): (n, 2) frames and values baked} of `action`; None where it keeps no record."""
    record = action.get(BAKED)
    if record is None:
        return None
    curves = json.loads(record["curves"])
    ends = np.cumsum(np.array(record["counts"], dtype=np.int64))
    keys = np.array(record["keys"], dtype=np.float32).reshape(-1, 2)
    return {(path, int(index)): keys[end - count: end]
            for (path, index), count, end in zip(curves, np.diff(ends, prepend=0), ends)}


def _matches(co: np.ndarray, baked: np.ndarray) -> np.ndarray:
    """Per key of `co` ((n, 2) frames, values), whether `baked` holds a key at its frame with its value."""
    if len(baked) == 0:
        return np.zeros(len(co), dtype=bool)
    baked = baked[np.argsort(baked[:, 0], kind="stable")]
    i = _nearest(baked[:, 0], co[:, 0])
    return (np.abs(baked[i, 0] - co[:, 0]) <= FRAME_TOLERANCE) & (np.abs(baked[i, 1] - co[:, 1]) <= VALUE_TOLERANCE)


def _near(frames: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Per frame of `frames`, whether one of `wanted` (sorted) lies within FRAME_TOLERANCE of it."""
    if len(wanted) == 0:
        return np.zeros(len(frames), dtype=bool)
    return np.abs(wanted[_nearest(wanted, frames)] - frames) <= FRAME_TOLERANCE


def _nearest(ordered: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Per value of `x`, the index of the nearest value of `ordered` (sorted, not empty)."""
    right = np.minimum(np.searchsorted(ordered, x), len(ordered) - 1)
    left = np.maximum(right - 1, 0)
    return np.where(np.abs(ordered[left] - x) < np.abs(ordered[right] - x), left, right)


def _enum(prop: str, item: str) -> int:
    return bpy.types.Keyframe.bl_rna.properties[prop].enum_items[item].value


def _write_keys(fc, keys: Keys | None, values: np.ndarray, start_frame: float) -> int:
    points = fc.keyframe_points
    if keys is None:
        n = len(values)
        points.add(n)
        points.foreach_set("co", np.column_stack([start_frame + np.arange(n), values]).astype(np.float32).ravel())
    else:
        n = len(keys)
        left, right = handles(keys)
        offset = np.array([start_frame, 0.0])
        points.add(n)
        points.foreach_set("co", np.column_stack([start_frame + keys.frames, keys.values[:, 0]])
                           .astype(np.float32).ravel())
        points.foreach_set("interpolation", [_enum("interpolation", "BEZIER")] * n)
        _align_handles(points)
        points.foreach_set("handle_left", (left[:, 0] + offset).astype(np.float32).ravel())
        points.foreach_set("handle_right", (right[:, 0] + offset).astype(np.float32).ravel())
    points.foreach_set("type", [_enum("type", GENERATED_KEY)] * n)
    fc.update()
    return n


def _align_handles(points) -> None:
    """ALIGNED handles on every key, so the handles written next are kept (automatic ones are
    computed again). Blender 3.4 ignores foreach_set on the handle types: there key by key."""
    for side in ("handle_left_type", "handle_right_type"):
        points.foreach_set(side, [_enum(side, "ALIGNED")] * len(points))
    if len(points) and points[-1].handle_right_type != "ALIGNED":
        for point in points:
            point.handle_left_type = point.handle_right_type = "ALIGNED"


def _fcurve_factory(action, slot):
    """A function adding a grouped F-Curve to (action, slot), on either API."""
    if _uses_channelbags(slot):
        bag = action_ensure_channelbag_for_slot(action, slot)

        def make(path, index, group, groups):
            fc = bag.fcurves.new(path, index=index)
            if group:
                if group not in groups:
                    groups[group] = bag.groups.new(group)
                fc.group = groups[group]
            return fc

        return make

    def make_legacy(path, index, group, groups):
        return action.fcurves.new(path, index=index, action_group=group)

    return make_legacy


def action_fcurves(action, slot=None) -> list:
    """The F-Curves of `action` for `slot` (None where there are no slots), on either API."""
    if _uses_channelbags(slot):
        from bpy_extras.anim_utils import action_get_channelbag_for_slot
        bag = action_get_channelbag_for_slot(action, slot)
        return list(bag.fcurves) if bag else []
    return list(action.fcurves)


def fcurves_of(id_data, frame: float | None = None) -> list:
    """The F-Curves of the Action (and slot) `id_data` plays, on either API: its active
    Action, else at scene `frame` the take on the sound-strips NLA track (takes.playing_action)."""
    action, slot = playing_action(id_data, frame)
    return [] if action is None else action_fcurves(action, slot)


def rotation_channels(bone: str, rotation_mode: str, quaternions: np.ndarray) -> list[Channel]:
    """Channels for a pose bone's rotation in its own mode: quaternion (continuous
    hemisphere), axis-angle, or Euler in the bone's order (continuous across frames)."""
    from mathutils import Euler, Quaternion

    base = f'pose.bones["{_escape(bone)}"]'
    if rotation_mode == "QUATERNION":
        values = quaternions
        path = base + ".rotation_quaternion"
    elif rotation_mode == "AXIS_ANGLE":
        values = np.array([_axis_angle(Quaternion(q)) for q in quaternions])
        path = base + ".rotation_axis_angle"
    else:
        values = np.empty((len(quaternions), 3))
        previous = Euler((0.0, 0.0, 0.0), rotation_mode)
        for i, q in enumerate(quaternions):
            previous = Quaternion(q).to_euler(rotation_mode, previous)
            values[i] = previous
        path = base + ".rotation_euler"
    return [Channel(path, i, values[:, i], group=bone) for i in range(values.shape[1])]


def _axis_angle(q) -> tuple[float, float, float, float]:
    axis, angle = q.to_axis_angle()
    return (angle, axis.x, axis.y, axis.z)


def _escape(name: str) -> str:
    return name.replace("\\", "\\\\").replace('"', '\\"')


def shape_key_channel(key_name: str, values: np.ndarray) -> Channel:
    return Channel(f'key_blocks["{_escape(key_name)}"].value', 0, values, group="Shape Keys")
