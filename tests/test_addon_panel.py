"""The sidebar panel (issue 25, item 6): the main panel, its collapsed sub-panels "Sampling"
and "Keys", Blender's layout conventions, labels short enough for the default sidebar width,
the button named by the range, and long texts wrapped to the sidebar.

What it looks like in a real Blender window: tools/panel_screenshot.py."""

from __future__ import annotations

from types import SimpleNamespace

from addon_fixtures import bpy, reset_scene
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

from blender_addon.ui import widgets
from blender_addon.ui.panel import DIFFSHEG_PT_generate, DIFFSHEG_PT_keys, DIFFSHEG_PT_sampling
from blender_addon.ui.properties import DIFFSHEG_PG_settings
from blender_addon.ui.widgets import wrapped_label

# Measured at Blender 3.4's default sidebar width (229 px at UI scale 1.04): a label in the
# label column of `use_property_split` shows about 11 characters, a checkbox's about 13.
LABEL_COLUMN, CHECKBOX = 11, 13


class Layout:
    """Records what a draw() puts where: labels, operators, and each property with the text it shows."""

    def __init__(self, log, split=False, heading=""):
        self.log, self.use_property_split, self.heading = log, split, heading
        self.use_property_decorate = True
        self.active, self.scale_y, self.alignment = True, 1.0, "EXPAND"

    def _child(self, heading=""):
        return Layout(self.log, self.use_property_split, heading or self.heading)

    def row(self, align=False, heading="", **kw):
        return self._child(heading)

    def column(self, align=False, heading="", **kw):
        return self._child(heading)

    def box(self):
        return self._child()

    def split(self, factor=0.5, align=False):
        return self._child()

    def label(self, text="", icon="NONE"):
        self.log.append(("label", text))

    def operator(self, idname, text=None, **kw):
        self.log.append(("operator", idname, text))
        return SimpleNamespace()

    def prop(self, data, name, text=None, expand=False, **kw):
        self.log.append(("prop", name, text, self.use_property_split, self.heading))

    def template_list(self, *a, **kw):
        self.log.append(("list",))


def draw(cls, context=None):
    log = []
    layout = Layout(log)
    cls.draw(SimpleNamespace(layout=layout), context or bpy.context)
    assert layout.use_property_split and not layout.use_property_decorate
    return log


def test_the_new_settings_and_their_defaults():
    s = reset_scene().diffsheg
    assert (s.range_mode, s.start_from_pose, s.set_steps) == ("WHOLE", False, False)
    assert isinstance(s.range_start, int) and isinstance(s.range_end, int)
    modes = DIFFSHEG_PG_settings.bl_rna.properties["range_mode"].enum_items
    assert [(m.identifier, m.name) for m in modes] == [("WHOLE", "Whole clip"), ("PREVIEW", "Preview range"),
                                                        ("FRAMES", "Frames")]


def test_the_main_panel_and_its_collapsed_sub_panels():
    s = reset_scene().diffsheg
    main = [e[1] for e in draw(DIFFSHEG_PT_generate) if e[0] == "prop"]
    assert main[:3] == ["audio_path", "armature", "preset"] and "range_mode" in main
    assert {"language", "style", "mix_style", "style_mix", "start_from_pose"} <= set(main)
    assert not {"steps", "seed", "device", "max_error", "key_mode"} & set(main)  # in the sub-panels
    for cls in (DIFFSHEG_PT_sampling, DIFFSHEG_PT_keys):
        assert cls.bl_parent_id == "DIFFSHEG_PT_generate" and "DEFAULT_CLOSED" in cls.bl_options
    sampling = {e[1] for e in draw(DIFFSHEG_PT_sampling) if e[0] == "prop"}
    assert sampling == {"model_path", "seed", "sampling", "set_steps", "steps", "candidates", "set_overlap", "overlap",
                        "set_guidance", "guidance", "set_gesture_energy", "gesture_energy", "style_strength",
                        "use_face_seed", "face_seed", "device"}
    keys = {e[1] for e in draw(DIFFSHEG_PT_keys) if e[0] == "prop"}
    assert keys == {"key_mode", "max_error", "max_face_error", "smoothing", "start_at_scene_start",
                    "start_frame", "add_sound", "set_frame_range", "upper_body_only"}
    assert any(e[0] == "label" and e[1].startswith("Runs on: ") for e in draw(DIFFSHEG_PT_sampling))

    def generate_button():
        return [e[2] for e in draw(DIFFSHEG_PT_generate) if e[:2] == ("operator", "diffsheg.generate")]

    assert generate_button() == ["Generate"]
    for mode in ("PREVIEW", "FRAMES"):
        s.range_mode = mode
        drawn = [e[1] for e in draw(DIFFSHEG_PT_generate) if e[0] == "prop"]
        assert generate_button() == ["Regenerate Range"]
        assert ("range_start" in drawn) == (mode == "FRAMES") and "start_from_pose" not in drawn


def test_every_label_fits_the_default_sidebar_width():
    s = reset_scene().diffsheg
    s.range_mode, s.preset = "FRAMES", "__custom__"
    rna = DIFFSHEG_PG_settings.bl_rna.properties
    for cls in (DIFFSHEG_PT_generate, DIFFSHEG_PT_sampling, DIFFSHEG_PT_keys):
        for kind, *rest in draw(cls):
            if kind != "prop":
                continue
            name, text, split, heading = rest
            shown = rna[name].name if text is None else text
            assert len(heading) <= LABEL_COLUMN, heading
            if rna[name].type == "BOOLEAN":
                assert len(shown) <= CHECKBOX, (name, shown)
            elif split:
                assert len(shown) <= LABEL_COLUMN, (name, shown)
    for name in ("range_mode", "range_start", "range_end", "start_from_pose", "sampling", "set_steps", "gesture_energy",
                 "style_strength", "steps", "device", "max_error", "max_face_error"):
        description = rna[name].description
        assert description and description[0].isupper() and not description.endswith("."), name
    assert rna["gesture_energy"].description.startswith("Gesture energy: higher for livelier, bigger gestures")


def test_long_texts_wrap_to_the_sidebar():
    context = SimpleNamespace(region=SimpleNamespace(width=229),
                              preferences=SimpleNamespace(system=SimpleNamespace(ui_scale=1.0)))
    report = ("talk take 2: 288 frames, preset readyplayerme, 41/41 joints, 1,204 keys, 3.1 s, "
              "4 warnings: see DiffSHEG report")
    log = []
    wrapped_label(Layout(log), context, report, icon="INFO", beside_px=28)
    lines = [e[1] for e in log]
    assert len(lines) > 3 and " ".join(lines) == report
    assert max(map(len, lines)) <= widgets._chars_per_line(context, indent_px=48) < 30
    log = []
    wrapped_label(Layout(log), SimpleNamespace(region=None), report)  # headless: one label, as it is
    assert log == [("label", report)]
