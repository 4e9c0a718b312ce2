"""Screenshot the sidebar panel "Generate from audio" in a real Blender window.

    python -c "import build_addon, pathlib; build_addon.build_legacy(pathlib.Path('dist'))"
    xvfb-run -s "-screen 0 1600x1000x24" blender --factory-startup \
        --python tools/panel_screenshot.py -- dist/diffsheg-0.1.0-legacy.zip OUT.png [--open] [--range]

Blender 3.4 and Xvfb on Debian: `bash tools/install_system_packages.sh --screenshots`.
Installs and enables the add-on zip in that Blender (3.4+; into the user's add-ons folder),
makes a character (armature, face mesh, two takes, a report), shows the 3D view's sidebar at
its default width with the panel (before 4.1 on the first tab, see show_tab) and saves the
3D view area as OUT.png, then quits. With --open the
sub-panels (Sampling, Keys, Live) are registered open (Blender has no Python switch for a
panel's open state); with --range the other choices are drawn (a range of frames, a custom
preset, a style mix, an emotion (Sad at 0.6), the Mandarin face, Quality sampling, GPU; Live from
a socket with VMC out).
Open sub-panels need a taller screen (1600x1900) to be seen whole.
"""

import sys
from pathlib import Path

import bpy

SAMPLE = Path(__file__).resolve().parents[1] / "diffsheg_core" / "samples" / "sample_speech.wav"

argv = sys.argv[sys.argv.index("--") + 1:]
ZIP, OUT, OPEN, RANGE = argv[0], argv[1], "--open" in argv, "--range" in argv

bpy.ops.preferences.addon_install(filepath=ZIP, overwrite=True)
bpy.ops.preferences.addon_enable(module="diffsheg")
addon = sys.modules["diffsheg"]

SUB_PANELS = (addon.ui.panel.DIFFSHEG_PT_sampling, addon.ui.panel.DIFFSHEG_PT_keys, addon.ui.panel.DIFFSHEG_PT_live)

if OPEN:
    for cls in SUB_PANELS:
        bpy.utils.unregister_class(cls)
        cls.bl_options = set()
        bpy.utils.register_class(cls)


def character():
    scene = bpy.context.scene
    rig = bpy.data.objects.new("Avatar", bpy.data.armatures.new("Avatar"))
    face = bpy.data.objects.new("Wolf3D_Head", bpy.data.meshes.new("Wolf3D_Head"))
    for ob in (rig, face):
        scene.collection.objects.link(ob)
    face.shape_key_add(name="Basis")
    s = scene.diffsheg
    s.audio_path = "//audio/talk_interview_take3.wav"
    s.armature = rig
    s.face_meshes.add().object = face
    from diffsheg.scene import takes
    for number in (1, 2):
        name = takes.take_name("talk", number)
        action = bpy.data.actions.new(name)
        takes.mark(action, name, "talk", number, rig)
    rig.animation_data_create().action = bpy.data.actions["talk take 2"]
    editor = scene.sequence_editor_create()  # a sound strip: the panel offers Generate for Strips
    strips = editor.strips if hasattr(editor, "strips") else editor.sequences
    strips.new_sound("talk", str(SAMPLE), channel=1, frame_start=1)
    s.last_report = ("talk take 2: 288 frames, preset readyplayerme, 41/41 joints, 1,204 keys, 3.1 s, "
                     "4 warnings: see DiffSHEG report")
    s.model_label = "diffsheg-beat-small 0.1.0 (bundled)"
    if RANGE:  # the other choices drawn: a range of frames, a custom preset, a style mix, an emotion
        s.range_mode, s.range_start, s.range_end = "FRAMES", 1048, 1120
        s.preset, s.preset_file = "__custom__", "//presets/my_rig.json"
        for style in ("animated", "0"):  # the bundled model's style names, or indices where they are unknown
            try:
                s.mix_style = style
                break
            except TypeError:
                continue
        s.style_mix = 0.3
        s.emotion, s.emotion_intensity = "sad", 0.6
        try:
            s.language = "zh"  # the bundled model's own face for Mandarin
        except TypeError:  # the menu reads the model's faces with safetensors, one of the runtime's packages
            pass
        s.device, s.key_mode, s.use_face_seed, s.hold_face = "GPU", "EVERY_FRAME", True, True
        s.sampling = "QUALITY"  # the greyed-out Steps shows its 25
        s.live_source, s.live_vmc = "SOCKET", True


def sidebar():
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
    area.spaces[0].show_region_ui = True
    area.tag_redraw()


def show_tab():
    """Blender before 4.1 has no Python switch for the sidebar's tab (and simulated clicks on a
    tab did nothing under Xvfb): with no active object the first tab is "Tool", and the add-on's
    panels are registered on it again, before Blender's own ("Tool" and "View" registered again
    after them).
    The tab strip stays, so the panel has the width it has on its own tab."""
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
    region = next(r for r in area.regions if r.type == "UI")
    if hasattr(region, "active_panel_category"):  # Blender 4.1+
        region.active_panel_category = "DiffSHEG"
    else:
        bpy.context.view_layer.objects.active = None  # no "Item" tab
        ours = [addon.ui.panel.DIFFSHEG_PT_generate, *SUB_PANELS]
        tool = [cls for cls in bpy.types.Panel.__subclasses__()
                if getattr(cls, "bl_space_type", "") == "VIEW_3D" and getattr(cls, "bl_region_type", "") == "UI"
                and getattr(cls, "bl_category", "") in ("Tool", "View") and cls.is_registered and cls not in ours]
        tool.sort(key=lambda cls: (cls.bl_category != "Tool", bool(getattr(cls, "bl_parent_id", ""))))
        for cls in reversed(ours + tool):
            bpy.utils.unregister_class(cls)
        for cls in ours:
            cls.bl_category = "Tool"
        for cls in ours + tool:
            bpy.utils.register_class(cls)
    area.tag_redraw()


def shoot():
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
    region = next(r for r in area.regions if r.type == "UI")
    print("sidebar width", region.width, "ui scale", bpy.context.preferences.system.ui_scale, flush=True)
    with bpy.context.temp_override(window=window, area=area):
        bpy.ops.screen.screenshot_area(filepath=OUT)
    print("saved", OUT, flush=True)
    bpy.ops.wm.quit_blender()


def setup():
    character()
    sidebar()
    bpy.app.timers.register(show_tab, first_interval=1.0)
    bpy.app.timers.register(shoot, first_interval=2.5)


bpy.app.timers.register(setup, first_interval=1.0)
