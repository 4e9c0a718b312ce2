"""Takes: each generation is a numbered take ("talk take 2") of one Action per target.

A take's Actions (the armature's body, one per face mesh) carry custom properties that
name the take, its audio and the datablock it animates, and keep a fake user so that a
take not playing is still saved with the file. Generating again assigns the new take in
place of the one playing: no `.001` copies and no NLA track per run. An Action that is
not a take is the animator's: keying never changes it (it is pushed onto the NLA once,
as before, so it is kept and still plays beneath the take).

Only bpy data are read and written here; call from Blender's main thread.
"""

from __future__ import annotations

import re

import bpy

from diffsheg_core.errors import DiffshegError

TAKE = "diffsheg_take"        # the take's name, on each of its Actions
AUDIO = "diffsheg_audio"      # the take's audio name (the stem of its file)
NUMBER = "diffsheg_take_number"
TARGET = "diffsheg_target"    # the Object or shape-key Key the Action animates


def is_take(action) -> bool:
    return action is not None and TAKE in action


def take_name(audio: str, number: int) -> str:
    return f"{audio} take {number}"


def action_name(take: str, id_data) -> str:
    """The Action's name within a take: the take's for an armature, the mesh's added for a face."""
    if getattr(id_data, "id_type", "") == "KEY":
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
