"""Takes: each generation is a numbered take ("talk take 2") of one Action per target.

A take's Actions (the armature's body, one per face mesh) carry custom properties that
name the take, its audio and the datablock it animates, and keep a fake user so that a
take not playing is still saved with the file. Generating again assigns the new take in
place of the one playing: no `.001` copies and no NLA track per run. An Action that is
not a take is the animator's: keying never changes it (it is pushed onto the NLA once,
as before, so it is kept and still plays beneath the take).

A take plays either as the active Action (Generate, Live) or, for Generate for Sound
Strips, from a strip on the "DiffSHEG sound strips" NLA track at its own frames, named
after its sound strip, so that one take per line plays, line after line. The take
playing at a frame is the active Action's where there is one (it plays over the NLA),
else the sound-strips track's strip under that frame.

The take's first Action also keeps what the take was made from (`store_source`): the
generated Motion at the model's rate, the audio file and the scene frame of its first
frame, so that a range of it can be generated anew (regenerate.py) after the file was
saved and opened again.

Only bpy data are read and written here; call from Blender's main thread.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import bpy

from diffsheg_core.errors import DiffshegError

if TYPE_CHECKING:
    from diffsheg_core.motion import Motion

TAKE = "diffsheg_take"        # the take's name, on each of its Actions
AUDIO = "diffsheg_audio"      # the take's audio name (the stem of its file)
NUMBER = "diffsheg_take_number"
TARGET = "diffsheg_target"    # the Object or shape-key Key the Action animates
SOURCE = "diffsheg_source"    # what the take was made from (see TakeSource)


def is_take(action) -> bool:
    return action is not None and TAKE in action


def take_name(audio: str, number: int) -> str:
    return f"{audio} take {number}"


def action_name(take: str, id_data) -> str:
    """The Action's name within a take: the take's for an armature, the mesh's added for a face."""
    if isinstance(id_data, bpy.types.Key):  # (ID.id_type is 4.x's: Blender 3.4 has none)
        owner = getattr(id_data, "user", None)
        return f"{take} ({owner.name if owner is not None else id_data.name})"
    return take


def next_number(audio: str) -> int:
    """The number of the next take of `audio`: one above every take of it, and above any
    Action already named like one (so Blender never has to add `.001`)."""
    pattern = re.compile(re.escape(take_name(audio, 0))[:-1] + r"(\d+)\b")
    used = [int(a[NUMBER]) for a in bpy.data.actions if is_take(a) and a.get(AUDIO) == audio]
    used += [int(m.group(1)) for a in bpy.data.actions if (m := pattern.match(a.name))]
    return 1 + max(used, default=0)


def mark(action, take: str, audio: str, number: int, id_data) -> None:
    """Make `action` part of take `take` animating `id_data`."""
    action[TAKE], action[AUDIO], action[NUMBER], action[TARGET] = take, audio, number, id_data
    action.use_fake_user = True


def takes_of(targets) -> list[str]:
    """The names of the takes that animate any of `targets` (Objects or Keys), in the order made."""
    wanted = {t for t in targets if t is not None}
    found = {(a.get(AUDIO, ""), int(a.get(NUMBER, 0)), a[TAKE]) for a in bpy.data.actions
             if is_take(a) and a.get(TARGET) in wanted}
    return [name for _, _, name in sorted(found)]


def playing_action(id_data, frame: float | None = None) -> tuple[object | None, object | None]:
    """The Action `id_data` plays and its slot (None on Blender before 4.4): its active
    Action, else, at scene `frame`, the take on a sound-strips track (None, None where none)."""
    anim = getattr(id_data, "animation_data", None)
    if anim is None:
        return None, None
    if anim.action is not None:
        return anim.action, getattr(anim, "action_slot", None)
    strip = sequence_strip_at(anim, frame) if frame is not None else None
    return (strip.action, getattr(strip, "action_slot", None)) if strip is not None else (None, None)


def playing(id_data, frame: float | None = None) -> str | None:
    """The take `id_data` plays (at scene `frame`, where takes play from the NLA), if any."""
    action = playing_action(id_data, frame)[0]
    return action[TAKE] if is_take(action) else None


def first_playing(targets, frame: float | None = None) -> str | None:
    """The take the first of `targets` (Objects or Keys; None skipped) that plays one plays."""
    return next((t for t in (playing(x, frame) for x in targets if x is not None) if t is not None), None)


def use_take(take: str, scene=None) -> list[str]:
    """Play take `take` on every datablock it animates; returns its Actions' names. A take on
    the sound-strips track plays from there (the active Action is cleared so the track
    plays, and `scene` moves to its first frame); any other is assigned as the active Action.
    An Action of the animator's that was playing keeps a fake user, so it stays in the file."""
    actions = [a for a in bpy.data.actions if is_take(a) and a[TAKE] == take]
    if not actions:
        raise DiffshegError(f"there is no take '{take}' in this file: choose one of the takes the panel lists")
    for action in actions:
        target = action.get(TARGET)
        if target is None:
            raise DiffshegError(f"take '{take}': the object that Action '{action.name}' animated is gone")
        current = getattr(target.animation_data, "action", None)
        if current is not None and not is_take(current):
            current.use_fake_user = True  # the animator's own Action, unassigned: kept in the file
        strip = _sequence_strip_of(target, action)
        if strip is None:
            assign(target, action)
            continue
        target.animation_data.action = None
        if scene is not None:
            scene.frame_set(int(strip.frame_start))
    return [a.name for a in actions]


def assign(id_data, action) -> None:
    """Play `action` on `id_data` (with its first slot, on Blender 4.4+)."""
    anim = id_data.animation_data_create()
    anim.action = action
    if hasattr(anim, "action_slot") and len(getattr(action, "slots", ())):
        anim.action_slot = action.slots[0]


# ---------------------------------------------------------------- the sound-strips track

SEQUENCE_TRACK = "DiffSHEG sound strips"  # NLA tracks playing Generate for Sound Strips' takes


def _sequence_tracks(anim) -> list:
    return [t for t in anim.nla_tracks if t.name.startswith(SEQUENCE_TRACK)]


def sequence_strip_at(anim, frame: float):
    """The unmuted strip of the topmost sound-strips track under scene `frame`, or None."""
    for track in reversed(_sequence_tracks(anim)):
        if track.mute:
            continue
        for strip in track.strips:
            if not strip.mute and strip.frame_start <= frame <= strip.frame_end:
                return strip
    return None


def _sequence_strips(id_data) -> list:
    """The strips of `id_data`'s sound-strips tracks (none where it has no animation)."""
    anim = getattr(id_data, "animation_data", None)
    return [s for t in (_sequence_tracks(anim) if anim is not None else []) for s in t.strips]


def _sequence_strip_of(id_data, action):
    return next((s for s in _sequence_strips(id_data) if s.action == action), None)


def _keep_active(anim, undo: list) -> None:
    """Add to `undo` the step that puts `anim`'s active Action (and slot) back as they are now."""
    action, slot = anim.action, getattr(anim, "action_slot", None)

    def restore() -> None:
        anim.action = action
        if slot is not None:
            anim.action_slot = slot
    undo.append(restore)


def nla_strip(track, name: str, action, slot=None):
    """A strip on `track` playing `action` (and `slot`, on 4.4+) at its own frames."""
    strip = track.strips.new(name, int(math.floor(action.frame_range[0])), action)
    strip.name = name  # (Blender 3.4 names it after the Action)
    if slot is not None and hasattr(strip, "action_slot"):
        strip.action_slot = slot
    return strip


def play_in_sequence(id_data, name: str, undo: list) -> None:
    """Move the take `id_data` plays as its active Action onto the sound-strips track, as a
    strip named `name` (its sound strip's) at its own frames, so that it plays beside the
    other lines' takes. A strip of that name from an earlier run is taken off (its take stays
    in the file). The strip goes on the lowest sound-strips track with room for it (a new one
    above where none has); there it holds its last pose until the next line, on a higher
    track (lines that overlap) it plays only its own frames. `undo` gets the steps back."""
    anim = id_data.animation_data
    action, slot = anim.action, getattr(anim, "action_slot", None)
    for track in _sequence_tracks(anim):
        for old in [s for s in track.strips if s.name == name]:
            _remove_strip(track, old, undo)
    first, last = action.frame_range
    tracks = _sequence_tracks(anim)
    track = next((t for t in tracks if all(s.frame_end < first or s.frame_start > last for s in t.strips)), None)
    if track is None:
        track = anim.nla_tracks.new(prev=tracks[-1] if tracks else None)
        track.name = SEQUENCE_TRACK
        undo.append(lambda: anim.nla_tracks.remove(track))
    strip = nla_strip(track, name, action, slot)
    strip.extrapolation = "HOLD_FORWARD" if track == _sequence_tracks(anim)[0] else "NOTHING"
    undo.append(lambda: track.strips.remove(strip))
    _keep_active(anim, undo)
    anim.action = None


def _remove_strip(track, strip, undo: list) -> None:
    name, action, slot, extrapolation = strip.name, strip.action, getattr(strip, "action_slot", None), \
        strip.extrapolation
    track.strips.remove(strip)

    def restore() -> None:
        nla_strip(track, name, action, slot).extrapolation = extrapolation
    undo.append(restore)


def push_to_nla(anim, action, undo: list) -> None:
    """Keep the animator's `action` playing from an NLA track of its own (it is no take, so
    it has no fake user: unassigned, it would be lost on save); `undo` gets the step back."""
    _keep_active(anim, undo)
    track = anim.nla_tracks.new()
    track.name = action.name
    undo.append(lambda: anim.nla_tracks.remove(track))
    nla_strip(track, action.name, action, getattr(anim, "action_slot", None))
    anim.action = None


def replace_playing(id_data, old, new, undo: list) -> None:
    """Play Action `new` (a regenerated copy of `old`) in the sound-strips track's strip of
    `old` where `old` plays from there and is not overridden by an active Action, else as
    `id_data`'s active Action."""
    anim = id_data.animation_data_create()
    strip = _sequence_strip_of(id_data, old) if anim.action is None else None
    if strip is None:
        _keep_active(anim, undo)
        assign(id_data, new)
        return
    slot = getattr(strip, "action_slot", None)
    strip.action = new
    if slot is not None:
        strip.action_slot = new.slots[0]

    def restore() -> None:
        strip.action = old
        if slot is not None:
            strip.action_slot = slot
    undo.append(restore)


def check_in_place(id_data, take: str) -> None:
    """Refuse where `id_data` plays take `take` from a sound-strips strip that no longer
    plays it at its own frames (moved, scaled or repeated in the NLA): regenerating a range
    maps scene frames to the take's."""
    for strip in _sequence_strips(id_data):
        if not is_take(strip.action) or strip.action[TAKE] != take:
            continue
        first, last = strip.action.frame_range
        if (strip.frame_start, strip.frame_end) != (first, last) or strip.scale != 1 or strip.repeat != 1:
            raise DiffshegError(f"the NLA strip '{strip.name}' of take '{take}' was moved or scaled: put it back "
                                f"at frame {first:g} (scale 1, repeat 1) to regenerate a range of it")


@dataclass
class TakeSource:
    """What a take was made from: the Motion at the model's rate, the audio file, and the
    scene frame its first frame was keyed on."""

    motion: "Motion"
    audio_path: str
    start_frame: int


def store_source(action, source: TakeSource) -> None:
    """Keep `source` in `action` (custom properties: saved with the .blend)."""
    import numpy as np  # here, not at the top: the panel lists takes also where numpy is missing

    m = source.motion
    action[SOURCE] = {
        "fps": float(m.fps), "rig": m.rig, "joint_names": json.dumps(m.joint_names),
        "face_names": json.dumps(m.face_names), "frames": m.n_frames,
        "rotations": m.rotations.astype(np.float64).ravel().tolist(),
        "face": m.face.astype(np.float64).ravel().tolist(),
        "meta": json.dumps(m.meta, default=str), "audio_path": source.audio_path,
        "start_frame": int(source.start_frame),
    }
    if m.root_translation is not None:
        action[SOURCE]["root_translation"] = m.root_translation.astype(np.float64).ravel().tolist()


def source_of(take: str) -> TakeSource:
    """The source of take `take`; DiffshegError if no Action of it keeps one."""
    for action in bpy.data.actions:
        if is_take(action) and action[TAKE] == take and SOURCE in action:
            return _read_source(action)
    raise DiffshegError(f"take '{take}' keeps no record of the motion it was made from (it was made by an "
                        "older version of the add-on): generate the whole clip again to regenerate ranges of it")


def _read_source(action) -> TakeSource:
    import numpy as np  # see store_source

    from diffsheg_core.motion import Motion

    rec = action[SOURCE]
    try:
        joints, faces, n = json.loads(rec["joint_names"]), json.loads(rec["face_names"]), int(rec["frames"])
        motion = Motion(fps=float(rec["fps"]), rig=str(rec["rig"]), joint_names=joints,
                        rotations=np.asarray(rec["rotations"], dtype=np.float64).reshape(n, len(joints), 3),
                        face_names=faces, face=np.asarray(rec["face"], dtype=np.float64).reshape(n, len(faces)),
                        root_translation=(np.asarray(rec["root_translation"], dtype=np.float64).reshape(n, 3)
                                          if "root_translation" in rec else None),
                        meta=json.loads(rec["meta"]))
        return TakeSource(motion, str(rec["audio_path"]), int(rec["start_frame"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise DiffshegError(f"the record of take '{action[TAKE]}' in Action '{action.name}' is damaged ({exc}): "
                            "generate the whole clip again") from None
