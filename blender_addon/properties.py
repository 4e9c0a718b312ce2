"""Generation settings, stored on the Scene (`scene.diffsheg`) so they persist in the .blend."""

from __future__ import annotations

import os
from functools import lru_cache

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

from diffsheg_core.settings import CANDIDATES, GUIDANCE, OVERLAP, SKIP_GUIDANCE, STEPS, STYLE_GUIDANCE

from . import preset

CUSTOM_PRESET = "__custom__"


def _is_armature(_self, obj) -> bool:
    return obj.type == "ARMATURE"


def _is_mesh(_self, obj) -> bool:
    return obj.type == "MESH"


_preset_items_cache: list = []


def _preset_items(_self, _context):
    # Blender keeps only the strings of the last returned list alive: keep a reference.
    _preset_items_cache[:] = [(preset.AUTO, "Auto", "the preset whose bone names the armature has "
                                                    "(the report says which it chose)")]
    _preset_items_cache.extend((n, n, f"rig preset presets/{n}.json") for n in preset.available_presets())
    _preset_items_cache.append((CUSTOM_PRESET, "Custom file...", "a preset .json file of your own"))
    return _preset_items_cache


_style_items_cache: dict = {}
NO_MIX = "__none__"
DEFAULT_STYLE = "__default__"


def style_names(settings) -> list[str]:
    """The style choices of the panel's model: its style names, else its style indices
    (official checkpoints: one per speaker)."""
    raw = settings.model_path.strip()
    path = bpy.path.abspath(raw) if raw else None
    return list(_model_styles(path, _modified(path)))


def _modified(path: str | None) -> int:
    """The file's modification time (ns): a changed file is read again."""
    try:
        return os.stat(path).st_mtime_ns if path else 0
    except OSError:
        return -1


@lru_cache(maxsize=16)
def _model_styles(path: str | None, _modified_ns: int) -> tuple[str, ...]:
    """Read once per path and version of the file: the menu asks on every redraw."""
    from diffsheg_core.checkpoints import stored_style_count, stored_style_names

    names = stored_style_names(path)
    return tuple(names or (str(i) for i in range(stored_style_count(path) or 1)))


def _style_items(self, _context):
    # Blender keeps only the strings of the last returned list alive: keep a reference.
    try:
        names = style_names(self)
    except Exception:  # a menu that raises fails every redraw: the runtime packages are
        names = ["0"]  # missing (the panel says so) or the file is unusable (Generate says why)
    _style_items_cache["style"] = [(DEFAULT_STYLE, "Default", "the model's default style")] + [
        (n, n if not n.isdigit() else f"Style {n}", "") for n in names]
    return _style_items_cache["style"]


def _mix_items(self, context):
    _style_items_cache["mix"] = [(NO_MIX, "None", "no second style")] + list(_style_items(self, context))[1:]
    return _style_items_cache["mix"]


class DIFFSHEG_PG_face_mesh(bpy.types.PropertyGroup):
    object: PointerProperty(name="Face mesh", type=bpy.types.Object, poll=_is_mesh,
                            description="a mesh whose shape keys receive the face weights")


class DIFFSHEG_PG_settings(bpy.types.PropertyGroup):
    audio_path: StringProperty(name="Audio", subtype="FILE_PATH",
                               description="speech recording (WAV, FLAC, OGG or MP3)")
    armature: PointerProperty(name="Armature", type=bpy.types.Object, poll=_is_armature,
                              description="the rig receiving body, hand, head and jaw rotations")
    face_meshes: CollectionProperty(type=DIFFSHEG_PG_face_mesh)
    face_index: IntProperty(default=0)
    preset: EnumProperty(name="Rig preset", items=_preset_items,
                         description="which bones and shape keys the model's channels go to")
    preset_file: StringProperty(name="Preset file", subtype="FILE_PATH",
                                description="your own preset .json (see presets/ for the format)")
    model_path: StringProperty(name="Model", subtype="FILE_PATH",
                               description="a model file (.safetensors); empty = the bundled default model. "
                                           "Official DiffSHEG checkpoints (.pth) need the GPU support (torch)")
    seed: IntProperty(name="Seed", default=0, min=0, description="same seed, same motion")
    keep_face: BoolProperty(name="Keep face", default=False,
                            description="keep the face (lip-sync, blinks, brows) of the face seed while the "
                                        "seed changes the gestures")
    face_seed: IntProperty(name="Face seed", default=0, min=0,
                           description="the seed the face is sampled with when Keep face is on")
    candidates: IntProperty(name="Candidates", default=1, min=CANDIDATES[0], max=CANDIDATES[1],
                            description="sample every window after the first this many times and keep the one "
                                        "that best continues the motion (smoother seams; costs that many times "
                                        "the time)")
    steps: IntProperty(name="Steps", default=25, min=STEPS[0], max=STEPS[1],
                       description="diffusion steps: fewer are faster, 25 is the model's default")
    set_overlap: BoolProperty(name="Set overlap", default=False,
                              description="use your own overlap instead of the model's default")
    overlap: IntProperty(name="Overlap", default=4, min=OVERLAP[0], max=OVERLAP[1],
                         description="frames shared by consecutive windows")
    style: EnumProperty(name="Style", items=_style_items,
                        description="the gesture style of the model (its named styles, or speaker indices)")
    mix_style: EnumProperty(name="Mix with", items=_mix_items,
                            description="a second style to blend with the first")
    style_mix: FloatProperty(name="Mix", default=0.5, min=0.0, max=1.0, subtype="FACTOR",
                             description="share of the second style: 0 is the first style, 1 the second")
    style_strength: FloatProperty(name="Style strength", default=1.0, min=STYLE_GUIDANCE[0], max=5.0,
                                  soft_max=3.0,
                                  description="style guidance: 1 is the style as trained, above 1 goes beyond "
                                              "it (livelier than animated, calmer than calm); models trained "
                                              "with a null style")
    set_guidance: BoolProperty(name="Set guidance", default=False,
                               description="use your own guidance scale instead of the model's default")
    guidance: FloatProperty(name="Guidance", default=1.0, min=GUIDANCE[0], max=GUIDANCE[1],
                            description="classifier-free guidance scale; 1 = off")
    set_gesture_energy: BoolProperty(name="Set gesture energy", default=False,
                                     description="use your own gesture energy instead of the model's default")
    gesture_energy: FloatProperty(name="Gesture energy", default=0.1, min=SKIP_GUIDANCE[0], max=SKIP_GUIDANCE[1],
                                  description="skip-guidance scale of the gestures: higher gives larger, "
                                              "livelier gestures; 0 = off")
    start_at_scene_start: BoolProperty(name="Scene start", default=True,
                                       description="key from the scene's start frame (1001 in film pipelines); "
                                                   "off: from the start frame below")
    start_frame: IntProperty(name="Start frame", default=1, description="frame of the first key and the sound strip")

    def start(self) -> int:
        """The frame of the first key and the sound strip (these settings live on the scene)."""
        return self.id_data.frame_start if self.start_at_scene_start else self.start_frame
    device: EnumProperty(name="Device", default="AUTO", items=[
        ("AUTO", "Auto", "a CUDA GPU when the GPU support (torch) is installed and finds one, "
                         "else the CPU (onnxruntime)"),
        ("CPU", "CPU", "always the CPU"),
        ("GPU", "GPU", "a CUDA GPU: needs the GPU support (torch with CUDA) from the preferences")])
    smoothing: FloatProperty(name="Smoothing", default=0.0, min=0.0, max=10.0,
                             description="Gaussian smoothing of the keys, sigma in frames; 0 = off")
    key_mode: EnumProperty(name="Keys", default="POSES", items=[
        ("POSES", "Poses", "keys on the motion's turning points with smooth handles, within the error "
                           "bounds on every frame: easy to edit"),
        ("EVERY_FRAME", "Every frame", "one key per frame on every channel (baked curves for game export)")])
    max_error: FloatProperty(name="Max error", default=1.0, min=0.01, max=30.0, precision=2,
                             description="largest angle in degrees between a bone's keyed rotation and the "
                                         "generated one, on any frame: higher gives fewer keys")
    max_face_error: FloatProperty(name="Face max error", default=0.02, min=0.001, max=0.5, precision=3,
                                  description="largest difference of a shape key's keyed value from the "
                                              "generated one, on any frame: higher gives fewer keys")
    add_sound: BoolProperty(name="Add sound strip", default=True)
    set_frame_range: BoolProperty(name="Set frame range", default=True,
                                  description="make the scene's frame range cover the clip")
    model_label: StringProperty(name="Model used", default="",
                                description="the model of the last generation")
    last_report: StringProperty(default="")
    last_failed: BoolProperty(default=False, description="the last Generate keyed nothing (last_report says why)")

    def face_objects(self) -> list:
        return [item.object for item in self.face_meshes if item.object is not None]

    def device_arg(self) -> str:
        return {"AUTO": "auto", "CPU": "cpu", "GPU": "cuda"}[self.device]


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(
    (DIFFSHEG_PG_face_mesh, DIFFSHEG_PG_settings))


def register() -> None:
    _register_classes()
    bpy.types.Scene.diffsheg = PointerProperty(type=DIFFSHEG_PG_settings)


def unregister() -> None:
    del bpy.types.Scene.diffsheg
    _unregister_classes()
