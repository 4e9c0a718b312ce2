"""Generation settings, stored on the Scene (`scene.diffsheg`) so they persist in the .blend."""

from __future__ import annotations

import os
from functools import lru_cache

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

from diffsheg_core.validate import CANDIDATES, GUIDANCE, OVERLAP, SKIP_GUIDANCE, STEPS, STYLE_GUIDANCE

from ..features.generate import CUSTOM_PRESET, DEFAULT_STYLE, NEUTRAL, NO_MIX, SHARED_FACE, model_file
from ..features.live import SOCKET_HOST as LIVE_HOST  # the VMC receiver's default host too
from ..scene import preset

LIVE_HOP, LIVE_HOPS = 2, (1, 16)  # diffsheg_core.live.engine: LiveConfig.hop, HOPS (numpy-free here)

SAMPLING_ITEMS = [
    ("FAST", "Fast", "Five steps a window, each one pass of the model's distilled student: about 5.5 times faster "
                     "than Quality, with its lip-sync, blinks and gesture energy"),
    ("QUALITY", "Quality", "The model's own sampling, 25 steps a window: for final renders and comparisons"),
]
SAMPLING_STEPS = {"FAST": 5, "QUALITY": 25}
"""The steps each sampling takes: diffsheg_core.foppas.FAST_TIMESTEPS, the bundled model's
own (numpy-free here; tests/test_addon_generate.py checks them)."""


def _sampling_changed(settings, _context) -> None:
    """The greyed-out Steps shows the count the chosen Sampling takes (until Set steps is ticked)."""
    if not settings.set_steps:
        settings.steps = SAMPLING_STEPS[settings.sampling]


def _is_armature(_self, obj) -> bool:
    return obj.type == "ARMATURE"


def _is_mesh(_self, obj) -> bool:
    return obj.type == "MESH"


_preset_items_cache: list = []


def _preset_items(_self, _context):
    # Blender keeps only the strings of the last returned list alive: keep a reference.
    _preset_items_cache[:] = [(preset.AUTO, "Auto", "Pick the preset whose bone names the armature has "
                                                    "(the report says which one)")]
    _preset_items_cache.extend((n, n, f"Rig preset presets/{n}.json") for n in preset.available_presets())
    _preset_items_cache.append((CUSTOM_PRESET, "Custom file...", "A preset .json file of your own"))
    return _preset_items_cache


_style_items_cache: dict = {}


def style_names(settings) -> list[str]:
    """The style choices of the panel's model: its style names, else its style indices
    (official checkpoints: one per speaker)."""
    path = model_file(settings)
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


# Names the Language menu shows for the codes a model's faces are stored under (others show their code).
LANGUAGE_NAMES = {"zh": "Mandarin", "yue": "Cantonese", "ja": "Japanese", "ko": "Korean", "en": "English",
                  "es": "Spanish", "fr": "French", "de": "German", "it": "Italian", "pt": "Portuguese",
                  "ru": "Russian", "sv": "Swedish", "ar": "Arabic", "hi": "Hindi"}


@lru_cache(maxsize=16)
def _model_languages(path: str | None, _modified_ns: int) -> tuple[str, ...]:
    from diffsheg_core.checkpoints import stored_face_languages

    return tuple(stored_face_languages(path))


def _language_items(self, _context):
    path = model_file(self)
    try:
        codes = _model_languages(path, _modified(path))
    except Exception:  # as for the styles: the panel or Generate says what is wrong
        codes = ()
    _style_items_cache["language"] = [(SHARED_FACE, "All languages", "The model's shared face, which serves every "
                                                                     "language")] + [
        (c, LANGUAGE_NAMES.get(c, c), f"The model's own face for {LANGUAGE_NAMES.get(c, c)} ({c}), fine-tuned on "
                                      "that language's captured faces: for speech in it") for c in codes]
    return _style_items_cache["language"]


# diffsheg_core.emotion.NAMES, in its order (a test checks): that module needs numpy, which
# the add-on registers without.
EMOTIONS = [
    (NEUTRAL, "Neutral", "No emotion: the face and body as generated"),
    ("happy", "Happy", "Cheeks raised and a smile, livelier gestures, the head up"),
    ("sad", "Sad", "Inner brows up and mouth corners down, less movement, the head and chest lowered"),
    ("angry", "Angry", "Brows down, eyes narrowed, lips pressed, sharper strokes"),
    ("surprised", "Surprised", "Brows up and eyes wide, the head back"),
    ("fearful", "Fearful", "Brows raised together, eyes wide, lips stretched"),
    ("disgusted", "Disgusted", "Nose wrinkled and upper lip raised, the head back"),
]


def _mix_items(self, context):
    _style_items_cache["mix"] = [(NO_MIX, "None", "no second style")] + list(_style_items(self, context))[1:]
    return _style_items_cache["mix"]


class DIFFSHEG_PG_face_mesh(bpy.types.PropertyGroup):
    object: PointerProperty(name="Face mesh", type=bpy.types.Object, poll=_is_mesh,
                            description="A mesh whose shape keys receive the face animation")


# Labels (name=) are short enough to be read whole at the sidebar's default width; they
# follow the add-on's messages ("Range 'Frames'", "'Start from pose'"). Tooltips in plain words.
class DIFFSHEG_PG_settings(bpy.types.PropertyGroup):
    audio_path: StringProperty(name="Audio", subtype="FILE_PATH",
                               description="The speech recording to animate (WAV, FLAC, OGG or MP3)")
    armature: PointerProperty(name="Armature", type=bpy.types.Object, poll=_is_armature,
                              description="The character's rig: it gets the body, hand, head and jaw motion")
    face_meshes: CollectionProperty(type=DIFFSHEG_PG_face_mesh)
    face_index: IntProperty(default=0)
    preset: EnumProperty(name="Preset", items=_preset_items,
                         description="Which of the rig's bones and shape keys the motion goes to")
    preset_file: StringProperty(name="File", subtype="FILE_PATH",
                                description="Your own preset .json file (see presets/ for the format)")
    range_mode: EnumProperty(name="Range", default="WHOLE", items=[
        ("WHOLE", "Whole clip", "Generate the whole audio clip as a new take"),
        ("PREVIEW", "Preview range", "Regenerate the scene's preview range of the take playing"),
        ("FRAMES", "Frames", "Regenerate the frames from Start to End of the take playing")],
        description="Generate the whole clip, or only part of the take playing (kept as a new take)")
    range_start: IntProperty(name="Start", default=1,
                             description="First frame (scene frame) to generate anew")
    range_end: IntProperty(name="End", default=100,
                           description="Last frame (scene frame) to generate anew")
    start_from_pose: BoolProperty(name="Start from pose", default=False,
                                  description="Begin the motion from the pose the character has at the "
                                              "start frame, so a take continues the previous shot")
    model_path: StringProperty(name="Model", subtype="FILE_PATH",
                               description="A model file (.safetensors); empty uses the model that comes with "
                                           "the add-on. Official DiffSHEG checkpoints (.pth) need the GPU "
                                           "support from the add-on's preferences")
    seed: IntProperty(name="Seed", default=0, min=0,
                      description="Same seed, same motion; another seed gives other gestures")
    use_face_seed: BoolProperty(name="Face seed", default=False,
                                description="Give the face (lip-sync, blinks, brows) a seed of its own, so the "
                                            "Seed changes the gestures and the face stays")
    face_seed: IntProperty(name="Face seed", default=0, min=0,
                           description="The seed of the face when the Face seed box is ticked")
    hold_face: BoolProperty(name="Keep face", default=False,
                            description="Regenerating a range: keep the face the take has there, so only the "
                                        "gestures change")
    candidates: IntProperty(name="Candidates", default=1, min=CANDIDATES[0], max=CANDIDATES[1],
                            description="Try each stretch of motion this many times and keep the one that "
                                        "joins best: smoother, but that many times slower")
    sampling: EnumProperty(name="Sampling", items=SAMPLING_ITEMS, default="FAST", update=_sampling_changed,
                           description="How each stretch of motion is sampled: Fast, or the model's own "
                                       "25 steps for final renders")
    set_steps: BoolProperty(name="Set steps", default=False,
                            description="Use your own number of steps instead of the Sampling's own "
                                        f"({SAMPLING_STEPS['FAST']} for Fast, the model's "
                                        f"{SAMPLING_STEPS['QUALITY']} for Quality)")
    steps: IntProperty(name="Steps", default=SAMPLING_STEPS["FAST"], min=STEPS[0], max=STEPS[1],
                       description="Denoising steps when Set steps is ticked (else the Sampling's own): "
                                   "fewer are faster, more follow the model more closely")
    set_overlap: BoolProperty(name="Set overlap", default=False,
                              description="Use your own overlap instead of the model's default")
    overlap: IntProperty(name="Overlap", default=4, min=OVERLAP[0], max=OVERLAP[1],
                         description="Frames each stretch of motion shares with the one before it: "
                                     "more gives smoother joins")
    style: EnumProperty(name="Style", items=_style_items,
                        description="How the character gestures: the model's named styles, or its speakers")
    mix_style: EnumProperty(name="Mix with", items=_mix_items,
                            description="A second style to blend with the first")
    style_mix: FloatProperty(name="Mix", default=0.5, min=0.0, max=1.0, subtype="FACTOR",
                             description="How much of the second style: 0 is only the first, 1 only the second")
    style_strength: FloatProperty(name="Strength", default=1.0, min=STYLE_GUIDANCE[0], max=5.0,
                                  soft_max=3.0,
                                  description="Style strength: 1 is the style as learned, higher exaggerates it "
                                              "(livelier than lively, calmer than calm; models trained to "
                                              "allow it)")
    language: EnumProperty(name="Language", items=_language_items,
                           description="The speech's language, where the model has a face of its own for it "
                                       "(fine-tuned on that language's captured faces): its lips and jaw follow "
                                       "that language's speakers more closely. All languages: the shared face, and "
                                       "Regenerate Range keeps the take's own")
    emotion: EnumProperty(name="Emotion", default=NEUTRAL, items=EMOTIONS,
                          description="A mood laid over the face and body; Neutral: none, and Regenerate "
                                      "Range keeps the take's own. Timeline markers emotion:sad or "
                                      "emotion:sad=0.5 change it from their frame; while Live runs, changing it changes the live face and body")
    emotion_intensity: FloatProperty(name="Intensity", default=1.0, min=0.0, max=1.0, subtype="FACTOR",
                                     description="How strongly the emotion shows: 1 is full, 0 is none")
    set_guidance: BoolProperty(name="Set guidance", default=False,
                               description="Use your own guidance instead of the model's default")
    guidance: FloatProperty(name="Guidance", default=1.0, min=GUIDANCE[0], max=GUIDANCE[1],
                            description="How closely the motion follows the speech; 1 is off")
    set_gesture_energy: BoolProperty(name="Set energy", default=False,
                                     description="Use your own gesture energy instead of the model's default")
    gesture_energy: FloatProperty(name="Energy", default=0.1, min=SKIP_GUIDANCE[0], max=SKIP_GUIDANCE[1],
                                  description="Gesture energy: higher for livelier, bigger gestures; 0 is off")
    start_at_scene_start: BoolProperty(name="Scene start", default=True,
                                       description="Put the first key and the sound at the scene's start frame "
                                                   "(1001 in film pipelines); off: at Start frame")
    start_frame: IntProperty(name="Start frame", default=1,
                             description="Frame of the first key and of the sound strip")

    def start(self) -> int:
        """The frame of the first key and the sound strip (these settings live on the scene)."""
        return self.id_data.frame_start if self.start_at_scene_start else self.start_frame
    device: EnumProperty(name="Device", default="AUTO", items=[
        ("AUTO", "Auto", "A CUDA GPU when the GPU support is installed and finds one, else the CPU"),
        ("CPU", "CPU", "Always the CPU"),
        ("GPU", "GPU", "A CUDA GPU: needs the GPU support from the add-on's preferences")],
        description="Where the model runs")
    upper_body_only: BoolProperty(name="Upper body only", default=False,
                                  description="Leave the hips and legs unkeyed: for seated characters, "
                                              "or legs you key yourself")
    smoothing: FloatProperty(name="Smoothing", default=0.0, min=0.0, max=10.0,
                             description="Smooth the motion over this many frames before keying; 0 is off")
    key_mode: EnumProperty(name="Keys", default="POSES", items=[
        ("POSES", "Poses", "Keys on the motion's turning points with smooth handles, within the error "
                           "below on every frame: easy to edit"),
        ("EVERY_FRAME", "Every frame", "A key on every frame of every channel (baked, for game export)")],
        description="Which frames get keys")
    max_error: FloatProperty(name="Max error", default=1.0, min=0.01, max=30.0, precision=2,
                             description="Largest difference, in degrees, between a bone's keyed and "
                                         "generated rotation on any frame: higher gives fewer keys")
    max_face_error: FloatProperty(name="Face error", default=0.02, min=0.001, max=0.5, precision=3,
                                  description="Largest difference between a shape key's keyed and generated "
                                              "value on any frame: higher gives fewer keys")
    add_sound: BoolProperty(name="Add sound", default=True,
                            description="Add the audio as a sound strip and play back in sync with it")
    set_frame_range: BoolProperty(name="Set frame range", default=True,
                                  description="Make the scene's frame range cover the clip")
    strips_selected_only: BoolProperty(name="Selected only", default=False,
                                       description="Generate for Sound Strips: only the selected sound strips")
    live_source: EnumProperty(name="Source", default="MIC", items=[
        ("MIC", "Microphone", "Your voice, from the microphone below (or the system's default one)"),
        ("FILE", "File", "A speech file played as if it were spoken now (to try Live, or a recorded line)"),
        ("SOCKET", "Socket", f"Speech sent by another program (a TTS engine, an agent) to {LIVE_HOST} on the port "
                             "below: raw 16-bit mono PCM at 16 kHz")],
        description="Where Live hears the speech from")
    live_mic: StringProperty(name="Device", default="",
                             description="The microphone's name (or part of it) or number; empty: the system's "
                                         "default input")
    live_file: StringProperty(name="File", subtype="FILE_PATH", default="",
                              description="The speech file Live plays; empty: the panel's Audio file")
    live_speed: FloatProperty(name="Speed", default=1.0, min=0.25, max=4.0, precision=2,
                              description="Play the file this many times as fast as it was spoken (a demo); "
                                          "a computer that cannot keep up drops audio")
    live_port: IntProperty(name="Port", default=5005, min=1024, max=65535,
                           description=f"The port Live listens on, at {LIVE_HOST} (this computer only)")
    live_hop: IntProperty(name="Hop", default=LIVE_HOP, min=LIVE_HOPS[0], max=LIVE_HOPS[1],
                          description="Frames made at a time: fewer follow the speech sooner but need a faster "
                                      "computer, more need less computing and lag more")
    live_record: BoolProperty(name="Record", default=True,
                              description="On Stop, keep the performance as a take, keyed as Generate keys, with "
                                          "its audio as a sound strip from the frame Live started on")
    live_vmc: BoolProperty(name="VMC out", default=False,
                           description="Also send the motion over the VMC protocol (VSeeFace, Warudo, VNyan)")
    live_vmc_address: StringProperty(name="Address", default=f"{LIVE_HOST}:39539",
                                     description="The VMC receiver as HOST:PORT (avatar apps listen on 39539)")
    model_label: StringProperty(name="Model used", default="",
                                description="The model of the last generation")
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
