"""Drawing helpers the panel and the preferences share: text wrapped to the region's width,
a list of problems."""

from __future__ import annotations

import textwrap


def _chars_per_line(context, indent_px: float = 0.0) -> int | None:
    """About how many characters of the UI font fit on one line of the sidebar; None when
    no region is drawn (a headless draw)."""
    region = getattr(context, "region", None)
    if region is None or region.width <= 1:
        return None
    scale = context.preferences.system.ui_scale
    # panel margins and a label's icon, then Blender's UI font: about 7 px a character (wide letters included)
    usable = region.width - (44 + indent_px) * scale
    return max(12, int(usable / (7.0 * scale)))


def wrapped_label(layout, context, text: str, icon: str = "NONE", beside_px: float = 0.0) -> None:
    """`text` as one label per line of the sidebar's width (less `beside_px` taken by buttons
    beside it), the icon on the first."""
    width = _chars_per_line(context, indent_px=beside_px + (0 if icon == "NONE" else 20))
    lines = [text] if width is None else (textwrap.wrap(text, width) or [""])
    col = layout.column(align=True)
    for i, line in enumerate(lines):
        row = col.row()
        row.scale_y = 0.8 if i else 1.0
        # later lines indented by the icon's width, so they line up under the first
        row.label(text=line, icon=icon if i == 0 else ("BLANK1" if icon != "NONE" else "NONE"))


def draw_problems(layout, lines: list[str]) -> None:
    """`lines` as labels, the first marked as an error."""
    for i, line in enumerate(lines):
        layout.label(text=line, icon="ERROR" if i == 0 else "NONE")
