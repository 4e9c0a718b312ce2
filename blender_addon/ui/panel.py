"""The View3D sidebar tab "DiffSHEG": the panel "Generate from audio" with what most runs
need (audio, character, style, emotion, range, Generate, Generate for Strips where the scene
has sound strips, takes, the report), and three collapsed sub-panels, "Sampling" (the model's
options), "Keys" (how the motion is keyed) and "Live" (the character animated as the speech
arrives, recorded as a take).

Blender's conventions: labels in a column on the left (`use_property_split`), no
keyframe decorators, labels short enough for the sidebar's default width; texts that
can be long (the report, the model, where it runs) wrap to the sidebar's width.
"""

from __future__ import annotations

import sys

import bpy

from ..environment import microphone_problem, runtime_problems, torch_installed
from ..features.generate import CUSTOM_PRESET, NEUTRAL, NO_MIX
from .widgets import wrapped_label


def device_label(choice: str) -> str:
    """Which device a run will use; torch is only asked once it is loaded."""
    torch = sys.modules.get("torch")
    if choice == "CPU":
        return "CPU"
    if torch is None and not torch_installed():
        return "CPU (GPU support not installed)" if choice == "AUTO" else \
            "GPU needs GPU support: see the add-on's preferences"
    if torch is None:
        return "GPU (CUDA) if available, else CPU" if choice == "AUTO" else "GPU (CUDA)"
    has_cuda = torch.cuda.is_available()
    if choice == "GPU":
        return "GPU (CUDA)" if has_cuda else "no CUDA GPU found: choose Auto or CPU"
    return "GPU (CUDA)" if has_cuda else "CPU (no CUDA GPU found)"


def _labelled(layout, text: str):
    """A row with `text` in the label column, like `use_property_split` draws a property
    (for a property drawn beside a button)."""
    split = layout.split(factor=0.4, align=True)
    left = split.row()
    left.alignment = "RIGHT"
    left.label(text=text)
    return split.row(align=True)


def _toggled(layout, settings, toggle: str, value: str, label: str) -> None:
    """A value the model has a default for: the toggle on, the value is used (greyed out, the
    model's default)."""
    row = layout.row(align=True, heading=label)
    row.prop(settings, toggle, text="")
    sub = row.row(align=True)
    sub.active = getattr(settings, toggle)
    sub.prop(settings, value, text="")


def draw_takes(layout, settings, frame: int) -> None:
    """One button per take of the panel's character; the one playing at `frame` is pressed."""
    from ..scene import takes

    targets = [settings.armature] + [ob.data.shape_keys for ob in settings.face_objects()]
    names = takes.takes_of(targets)
    if not names:
        return
    current = takes.first_playing(targets, frame)
    col = layout.column(align=True)
    col.label(text="Takes:")
    for name in names:
        col.operator("diffsheg.use_take", text=name, depress=name == current,
                     icon="PLAY" if name == current else "ACTION").take = name


def has_sound_strips(scene) -> bool:
    """Whether the scene's Video Sequencer holds a sound strip (no numpy needed: the panel draws
    where the runtime is missing; sound.py's helpers import keying)."""
    editor = scene.sequence_editor
    if editor is None:
        return False
    strips = editor.strips if hasattr(editor, "strips") else editor.sequences  # 5.0, 4.x
    return any(s.type == "SOUND" for s in strips)


def draw_strips(layout, context, settings) -> None:
    """Generate for Sound Strips and its 'Selected only', where the scene has sound strips."""
    if not has_sound_strips(context.scene):
        return
    col = layout.column()
    col.operator("diffsheg.generate_strips", text="Generate for Strips",
                 icon="SEQUENCE").selected_only = settings.strips_selected_only
    col.row(heading="Strips").prop(settings, "strips_selected_only", text="Selected only")


def draw_report(layout, context, settings) -> None:
    """The last Generate's one-line report (wrapped to the sidebar), the button that opens the
    "DiffSHEG report" Text with the details, and the model it used."""
    if settings.last_report:
        row = layout.row()
        wrapped_label(row, context, settings.last_report, icon="ERROR" if settings.last_failed else "INFO",
                      beside_px=0 if settings.last_failed else 28)
        if not settings.last_failed:
            row.operator("diffsheg.show_report", text="", icon="TEXT")
    if settings.model_label:
        untrained = "UNTRAINED" in settings.model_label
        wrapped_label(layout, context, f"Model: {settings.model_label}", icon="ERROR" if untrained else "NONE")


class DIFFSHEG_UL_face_meshes(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        layout.prop(item, "object", text="", emboss=False, icon="MESH_DATA")


class _Panel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "DiffSHEG"


def _split(layout):
    """Blender's layout: labels in a column on the left, no keyframe decorators."""
    layout.use_property_split = True
    layout.use_property_decorate = False
    return layout


class DIFFSHEG_PT_generate(_Panel, bpy.types.Panel):
    bl_label = "Generate from audio"
    bl_idname = "DIFFSHEG_PT_generate"

    def draw(self, context):
        layout = _split(self.layout)
        s = context.scene.diffsheg
        problems = runtime_problems()
        if problems:
            box = layout.box()
            for i, line in enumerate(problems):
                wrapped_label(box, context, line, icon="ERROR" if i == 0 else "NONE")

        layout.prop(s, "audio_path")

        col = layout.column()
        col.prop(s, "armature")
        col.label(text="Face meshes:")
        row = col.row()  # the whole width: mesh names are long
        row.template_list("DIFFSHEG_UL_face_meshes", "", s, "face_meshes", s, "face_index", rows=2)
        ops = row.column(align=True)
        ops.operator("diffsheg.face_add", text="", icon="ADD")
        ops.operator("diffsheg.face_remove", text="", icon="REMOVE")
        col.prop(s, "preset")
        if s.preset == CUSTOM_PRESET:
            col.prop(s, "preset_file")

        col = layout.column()
        col.prop(s, "language")
        col.prop(s, "style")
        sub = col.column(align=True)
        sub.prop(s, "mix_style")
        mix = sub.row(align=True)
        mix.active = s.mix_style != NO_MIX
        mix.prop(s, "style_mix")
        sub = col.column(align=True)
        sub.prop(s, "emotion")
        intensity = sub.row(align=True)
        intensity.active = s.emotion != NEUTRAL
        intensity.prop(s, "emotion_intensity", slider=True)

        col = layout.column()
        col.prop(s, "range_mode")
        if s.range_mode == "FRAMES":
            frames = col.column(align=True)
            frames.prop(s, "range_start")
            frames.prop(s, "range_end")
        if s.range_mode != "WHOLE":
            col.prop(s, "hold_face")
        if s.range_mode == "WHOLE":  # a range starts from the take's own frames
            col.row(heading="Start").prop(s, "start_from_pose", text="From pose")

        row = layout.row()
        row.scale_y = 1.4
        row.operator("diffsheg.generate", icon="PLAY_SOUND",
                     text="Generate" if s.range_mode == "WHOLE" else "Regenerate Range")
        draw_strips(layout, context, s)
        draw_takes(layout, s, context.scene.frame_current)
        draw_report(layout, context, s)


class DIFFSHEG_PT_sampling(_Panel, bpy.types.Panel):
    bl_label = "Sampling"
    bl_idname = "DIFFSHEG_PT_sampling"
    bl_parent_id = "DIFFSHEG_PT_generate"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = _split(self.layout)
        s = context.scene.diffsheg
        layout.prop(s, "model_path")

        col = layout.column()
        row = _labelled(col, "Seed")
        row.prop(s, "seed", text="")
        row.operator("diffsheg.new_seed", text="", icon="FILE_REFRESH")
        col.row().prop(s, "sampling", expand=True)
        _toggled(col, s, "set_steps", "steps", "Steps")
        col.prop(s, "candidates")
        _toggled(col, s, "set_overlap", "overlap", "Overlap")
        _toggled(col, s, "set_guidance", "guidance", "Guidance")
        _toggled(col, s, "set_gesture_energy", "gesture_energy", "Energy")
        col.prop(s, "style_strength")

        col = layout.column()
        _toggled(col, s, "use_face_seed", "face_seed", "Face seed")

        col = layout.column()
        col.row().prop(s, "device", expand=True)
        wrapped_label(col, context, f"Runs on: {device_label(s.device)}")


class DIFFSHEG_PT_keys(_Panel, bpy.types.Panel):
    bl_label = "Keys"
    bl_idname = "DIFFSHEG_PT_keys"
    bl_parent_id = "DIFFSHEG_PT_generate"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = _split(self.layout)
        s = context.scene.diffsheg
        col = layout.column()
        col.prop(s, "key_mode")
        errors = col.column(align=True)
        errors.active = s.key_mode == "POSES"
        errors.prop(s, "max_error")
        errors.prop(s, "max_face_error")
        col.prop(s, "smoothing")
        body = layout.column(heading="Body")  # "Upper body only" is cut at the sidebar's default width
        body.prop(s, "upper_body_only", text="Upper only")

        col = layout.column(heading="Start")
        col.prop(s, "start_at_scene_start")
        sub = col.row()
        sub.active = not s.start_at_scene_start
        sub.prop(s, "start_frame", text="Frame")
        col = layout.column(heading="Scene")
        col.prop(s, "add_sound")
        col.prop(s, "set_frame_range", text="Frame range")


class DIFFSHEG_PT_live(_Panel, bpy.types.Panel):
    """The character animated as the speech arrives (live.py): the source, Record, VMC out,
    Start or Stop, and the session's status line while it runs."""

    bl_label = "Live"
    bl_idname = "DIFFSHEG_PT_live"
    bl_parent_id = "DIFFSHEG_PT_generate"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        from ..features import live

        layout = _split(self.layout)
        s = context.scene.diffsheg
        run = live.current()
        col = layout.column()
        col.enabled = run is None  # a running session keeps the settings it started with
        col.prop(s, "live_source")
        if s.live_source == live.MIC:
            _prop(col, s, "live_mic", placeholder="System default")
            problem = microphone_problem()
            if problem:
                wrapped_label(col, context, problem[0].upper() + problem[1:], icon="ERROR")
        elif s.live_source == live.FILE:
            _prop(col, s, "live_file", placeholder="The Audio above")
            col.prop(s, "live_speed")
        else:
            col.prop(s, "live_port")
            rate = f"{live.SOCKET_RATE / 1000:g}\u00a0kHz"  # a non-breaking space: "16 kHz" on one line
            wrapped_label(col, context, f"Listens on {live.SOCKET_HOST}:{s.live_port} for 16-bit mono PCM at {rate}")
        col.prop(s, "live_hop")
        col.row(heading="Take").prop(s, "live_record")
        col.row(heading="VMC").prop(s, "live_vmc", text="Send")
        if s.live_vmc:  # the whole width: an address is longer than the value column shows
            address = col.row()
            address.use_property_split = False
            address.prop(s, "live_vmc_address", text="To")

        row = layout.row()
        row.scale_y = 1.4
        if run is None:
            row.operator("diffsheg.live_start", text="Start Live", icon="REC" if s.live_record else "PLAY")
        else:
            row.alert = True
            row.operator("diffsheg.live_stop", text="Stop", icon="PAUSE")
            wrapped_label(layout, context, run.status(), icon="REC" if run.record else "PLAY")


def _prop(layout, data, name: str, placeholder: str) -> None:
    """`layout.prop` with the grey text an empty field shows (`placeholder`: Blender 4.1 and
    later; before, the field is drawn without it)."""
    if bpy.app.version >= (4, 1, 0):
        layout.prop(data, name, placeholder=placeholder)
    else:
        layout.prop(data, name)


CLASSES = (DIFFSHEG_UL_face_meshes, DIFFSHEG_PT_generate, DIFFSHEG_PT_sampling, DIFFSHEG_PT_keys, DIFFSHEG_PT_live)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
