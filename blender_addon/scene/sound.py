"""The audio as a sound strip in the scene's sequencer, at the animation's start frame."""

from __future__ import annotations

from pathlib import Path

import bpy

from diffsheg_core.errors import DiffshegError
from diffsheg_core.files import resolve_path

from .keying import Undo

NO_AUDIO_NOTE = "no sound strip: this Blender build has no audio support (e.g. the bpy 4.x module from PyPI)"


def audio_supported() -> bool:
    """Whether this Blender can hold sound strips: builds without Audaspace refuse them."""
    return bool(bpy.app.build_options.audaspace)


def _strips(editor):
    # Blender 5.0 has `strips` only, 4.x `sequences`. An empty collection is falsy,
    # so the choice is by attribute, never by `or`.
    return editor.strips if hasattr(editor, "strips") else editor.sequences


CHANNELS = 128  # the sequencer's channels
MARK = "diffsheg_audio"  # custom property on the strips this add-on adds: the audio file they play


def _audio_key(audio_path: str) -> str:
    return str(resolve_path(audio_path, "audio file"))


def strips_added_for(scene, audio_path: str) -> list:
    """The sound strips this add-on added for `audio_path` (a user's own strips are not)."""
    key = _audio_key(audio_path)
    return [s for s in sound_strips(scene) if s.get(MARK) == key]


def remove_strips(scene, strips: list) -> None:
    for strip in strips:
        _strips(scene.sequence_editor).remove(strip)


def add_sound_strip(scene, audio_path: str, frame_start: int, undo: list[Undo]):
    """Add `audio_path` as a sound strip starting at `frame_start` on the lowest
    channel free over the clip, marked as this add-on's, and play the scene back in sync
    with the audio; returns the strip."""
    created = scene.sequence_editor is None
    editor = scene.sequence_editor_create()
    if created:
        undo.append(lambda: scene.sequence_editor_clear())
    strips = _strips(editor)
    used = {s.channel for s in strips if s.frame_final_end > frame_start}
    channel = next((c for c in range(1, CHANNELS + 1) if c not in used), None)
    if channel is None:
        raise DiffshegError(f"no channel for the sound strip: all {CHANNELS} channels of the sequencer are in "
                            f"use at frame {frame_start} or later. Free one by deleting or moving a strip in the "
                            "Video Sequencer, or turn off 'Add sound strip'")
    strip = strips.new_sound(Path(audio_path).stem, str(audio_path), channel=channel, frame_start=int(frame_start))
    strip[MARK] = _audio_key(audio_path)
    if not created:
        undo.append(lambda: strips.remove(strip))
    sync = scene.sync_mode
    undo.append(lambda: setattr(scene, "sync_mode", sync))
    scene.sync_mode = "AUDIO_SYNC"  # lip-sync is reviewed at speed: play back in step with the sound
    return strip


def sound_strips(scene) -> list:
    if scene.sequence_editor is None:
        return []
    return [s for s in _strips(scene.sequence_editor) if s.type == "SOUND"]
