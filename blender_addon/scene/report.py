"""What a Generate did, for people: one line for the status bar and the panel, the
details in a Text datablock ("DiffSHEG report") that the panel opens."""

from __future__ import annotations

import bpy

REPORT_TEXT = "DiffSHEG report"
MAX_LINE = 120


def report_line(result, seconds: float, extra: list[str] = ()) -> str:
    """At most MAX_LINE characters: take, frames, preset, keys, time, warnings (`extra`: the
    caller's own, beside keying's)."""
    warnings = len(warning_lines(result)) + len(extra)
    line = (f"{result.take}: {result.n_frames} frames, {result.n_keys:,} keys, preset {result.preset}, "
            f"{seconds:.1f} s")
    if warnings:
        line += f"; {warnings} warning{'s' if warnings > 1 else ''}, see {REPORT_TEXT}"
    return line if len(line) <= MAX_LINE else line[: MAX_LINE - 3] + "..."


def warning_lines(result) -> list[str]:
    """Everything the animator may want to act on, one line each."""
    lines = [f"bones not on the rig: {', '.join(result.unmatched_bones)}"] if result.unmatched_bones else []
    lines += [f"{mesh}: {len(names)} face channels without a shape key: {', '.join(names)}"
              for mesh, names in result.unmatched_shape_keys.items() if names]
    return lines + list(result.notes)


def model_label(meta: dict) -> str:
    """The model a take was made with, from its metadata: its id, marked when untrained."""
    label = str(meta.get("model_id", "unknown model"))
    if meta.get("trained") is False or meta.get("untrained"):
        label += " - UNTRAINED (random weights, no learned motion)"
    return label


def report_details(result, seconds: float, model: str, meta: dict, extra: list[str] = ()) -> str:
    """The report's Text: its line, the model, the sampling, the style and emotion the take was
    made with (`meta`: what made it, a range's own record), the Actions, the sound strip, the
    preset's notes and the warnings (`extra`: the caller's own, after keying's)."""
    lines = [report_line(result, seconds, extra), "", f"model: {model}", *sampling_lines(meta),
             f"style: {changes_text(meta.get('style_weights') or {}, meta.get('style_at'), 'default')}",
             f"emotion: {changes_text(meta.get('emotion') or {}, meta.get('emotion_at'), 'neutral')}",
             f"actions: {', '.join(result.actions)}",
             f"sound strip: {result.sound_strip or 'none'}", *result.preset_notes]
    warnings = warning_lines(result) + list(extra)
    if warnings:
        lines += ["", "warnings:"] + [f"- {w}" for w in warnings]
    return "\n".join(lines) + "\n"


def sampling_lines(meta: dict) -> list[str]:
    """'sampling: quality, 25 steps' where `meta` records the sampling (Live's takes do not),
    ', by the distilled student' when the model's student made the steps."""
    if not meta.get("sampling"):
        return []
    steps = meta.get("steps")
    return [f"sampling: {meta['sampling']}" + (f", {steps} steps" if steps else "")
            + (", by the distilled student" if meta.get("student") else "")]


def changes_text(weights: dict, changes: list | None, none: str) -> str:
    """'calm 0.7, animated 0.3; from 10 s: sad': a mix of weights by name, then its changes
    over time ([[seconds, weights], ...]); `none` for empty weights."""
    def mix(w: dict) -> str:
        return ", ".join(name if value == 1 else f"{name} {value:g}" for name, value in w.items()) or none

    return "; ".join([mix(weights)] + [f"from {round(seconds, 2):g} s: {mix(w)}" for seconds, w in changes or ()])


def write_report(text: str):
    """The "DiffSHEG report" Text datablock, holding `text` (the previous report replaced)."""
    block = bpy.data.texts.get(REPORT_TEXT) or bpy.data.texts.new(REPORT_TEXT)
    block.clear()
    block.write(text)
    return block
