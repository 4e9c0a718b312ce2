"""Takes: each generation is a numbered take ("talk take 2") of one Action per target.

A take's Actions (the armature's body, one per face mesh) carry custom properties that
name the take, its audio and the datablock it animates, and keep a fake user so that a
take not playing is still saved with the file. Generating again assigns the new take in
place of the one playing: no `.001` copies and no NLA track per run. An Action that is
not a take is the animator's: keying never changes it (it is pushed onto the NLA once,
as before, so it is kept and still plays beneath the take).

The take's first Action also keeps what the take was made from (`store_source`): the
generated Motion at the model's rate, the audio file and the scene frame of its first
frame, so that a range of it can be generated anew (regenerate.py) after the file was
saved and opened again.

Only bpy data are read and written here; call from Blender's main thread.
"""

from __future__ import annotations

import json
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


def playing(id_data) -> str | None:
    """The take `id_data` plays, if its Action is one."""
    anim = getattr(id_data, "animation_data", None)
    action = anim.action if anim is not None else None
    return action[TAKE] if is_take(action) else None


def first_playing(targets) -> str | None:
    """The take the first of `targets` (Objects or Keys; None skipped) that plays one plays."""
    return next((t for t in (playing(x) for x in targets if x is not None) if t is not None), None)


def use_take(take: str) -> list[str]:
    """Assign every Action of take `take` to the datablock it animates; returns their names."""
    actions = [a for a in bpy.data.actions if is_take(a) and a[TAKE] == take]
    if not actions:
        raise DiffshegError(f"there is no take '{take}' in this file: choose one of the takes the panel lists")
    for action in actions:
        target = action.get(TARGET)
        if target is None:
            raise DiffshegError(f"take '{take}': the object that Action '{action.name}' animated is gone")
        assign(target, action)
    return [a.name for a in actions]


def assign(id_data, action) -> None:
    """Play `action` on `id_data` (with its first slot, on Blender 4.4+)."""
    anim = id_data.animation_data_create()
    anim.action = action
    if hasattr(anim, "action_slot") and len(getattr(action, "slots", ())):
        anim.action_slot = action.slots[0]


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
                        meta=json.loads(rec["meta"]))
        return TakeSource(motion, str(rec["audio_path"]), int(rec["start_frame"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise DiffshegError(f"the record of take '{action[TAKE]}' in Action '{action.name}' is damaged ({exc}): "
                            "generate the whole clip again") from None
