"""The View3D sidebar tab "DiffSHEG" with the panel "Generate from audio"."""

from __future__ import annotations

import sys

import bpy

from .preferences import draw_problems, runtime_problems, torch_installed
from .properties import CUSTOM_PRESET, NO_MIX


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


def draw_takes(layout, settings) -> None:
    """One button per take of the panel's character; the one playing is pressed."""
    from . import takes

    targets = [settings.armature] + [ob.data.shape_keys for ob in settings.face_objects()]
    names = takes.takes_of(targets)
    if not names:
        return
    current = next((t for t in map(takes.playing, targets) if t is not None), None)
    col = layout.column(align=True)
    col.label(text="Takes:")
    for name in names:
        col.operator("diffsheg.use_take", text=name, depress=name == current,
                     icon="PLAY" if name == current else "ACTION").take = name


class DIFFSHEG_UL_face_meshes(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        layout.prop(item, "object", text="", emboss=False, icon="MESH_DATA")


class DIFFSHEG_PT_generate(bpy.types.Panel):
    bl_label = "Generate from audio"
    bl_idname = "DIFFSHEG_PT_generate"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "DiffSHEG"

    def draw(self, context):
        layout = self.layout
        s = context.scene.diffsheg
        problems = runtime_problems()
        if problems:
            draw_problems(layout.box(), problems)

        layout.prop(s, "audio_path")
        layout.prop(s, "armature")
        layout.label(text="Face meshes:")
        row = layout.row()
        row.template_list("DIFFSHEG_UL_face_meshes", "", s, "face_meshes", s, "face_index", rows=2)
        col = row.column(align=True)
        col.operator("diffsheg.face_add", text="", icon="ADD")
        col.operator("diffsheg.face_remove", text="", icon="REMOVE")
        layout.prop(s, "preset")
        if s.preset == CUSTOM_PRESET:
            layout.prop(s, "preset_file")

        col = layout.column(align=True)
        col.prop(s, "model_path")
        row = col.row(align=True)
        row.prop(s, "seed")
        row.operator("diffsheg.new_seed", text="", icon="FILE_REFRESH")
        row = col.row(align=True)
        row.prop(s, "keep_face")
        sub = row.row(align=True)
        sub.active = s.keep_face
        sub.prop(s, "face_seed")
        col.prop(s, "steps")
        col.prop(s, "candidates")
        col.prop(s, "style")
        row = col.row(align=True)
        row.prop(s, "mix_style")
        sub = row.row(align=True)
        sub.active = s.mix_style != NO_MIX
        sub.prop(s, "style_mix")
        col.prop(s, "style_strength")
        for toggle, value in (("set_overlap", "overlap"), ("set_guidance", "guidance"),
                              ("set_gesture_energy", "gesture_energy")):
            row = col.row(align=True)
            row.prop(s, toggle, text="")
            sub = row.row(align=True)
            sub.active = getattr(s, toggle)
            sub.prop(s, value)
        col.prop(s, "device")
        col.label(text=f"Runs on: {device_label(s.device)}")

        col = layout.column(align=True)
        row = col.row(align=True)
        row.prop(s, "start_at_scene_start")
        sub = row.row(align=True)
        sub.active = not s.start_at_scene_start
        sub.prop(s, "start_frame")
        col.prop(s, "smoothing")
        col.prop(s, "key_mode")
        if s.key_mode == "POSES":
            col.prop(s, "max_error")
            col.prop(s, "max_face_error")
        col.prop(s, "add_sound")
        col.prop(s, "set_frame_range")

        layout.operator("diffsheg.generate", icon="PLAY_SOUND")
        draw_takes(layout, s)
        if s.model_label:
            untrained = "UNTRAINED" in s.model_label
            layout.label(text=f"Model: {s.model_label}", icon="ERROR" if untrained else "INFO")
        if s.last_report:
            row = layout.row()
            row.label(text=s.last_report, icon="ERROR" if s.last_failed else "NONE")
            if not s.last_failed:
                row.operator("diffsheg.show_report", text="", icon="TEXT")


CLASSES = (DIFFSHEG_UL_face_meshes, DIFFSHEG_PT_generate)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
