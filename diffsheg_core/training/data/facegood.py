"""Real speech with a captured face and no body: the FACEGOOD takes of read Mandarin in
../shared/data/lang_capture/zh_facegood (issue 42), read as face-only takes.

The rig's curves are mapped onto ARKit by metrics.facegood (ARKIT_FROM_RIG) and only the
channels whose mapping holds train (`TRAINED`): the jaw, and the lips' rounding scaled into
the model's units (`ROUNDING_GAIN`). Every other channel, gestures and legs included, is
masked out of the loss, so a take teaches the mouth's timing on that speech and nothing
else. Lip closure is left out: the solve shuts the lips through mouth_press_* and
mouth_suck_* in some takes and not at all in others (p95 0 in three of five takes), which
would teach a mouth that seldom closes at p/b/m.

With `pause` in the data configuration, each take's silences are cut to that length
(metrics.facegood.joined): the words follow one another as in running speech.

The take metrics.facegood.HELD_OUT is the test split (never trained on); the others are
the training split (no validation split: four takes are too few to spare one)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...audio import n_motion_frames
from ...rigs import BEAT
from ..metrics.facegood import HELD_OUT, arkit_curves, joined, read_names, read_take as read_capture, take_names
from .sources import TakeSource
from .take import Take, make_take

if TYPE_CHECKING:
    from .dataset import DataConfig

LAYOUT = BEAT
WHOLE_BODY = True
"""whole_body data: the takes hold no body, so they fit a whole-body model too (its body masked)."""

ROUNDING_GAIN = 0.65
"""The mapped rounding (a sum of the rig's funnel, oh, oo and pucker shapes) over the
model's mouthFunnel / mouthPucker: on takes 01-02 their 95th percentiles are 0.58 and
0.34-0.39 (the bundled model on the same speech), so the sum is scaled to the model's range
and the take teaches when the lips round, not a rounder mouth."""
TRAINED: dict[str, float] = {"jawOpen": 1.0, "mouthFunnel": ROUNDING_GAIN, "mouthPucker": ROUNDING_GAIN}
"""ARKit channel -> gain on its mapped curve, for the channels a take trains."""


def find_takes(root: Path) -> list[TakeSource]:
    return [TakeSource(name, {"audio": root / f"{name}.wav", "face": root / f"bs_value_{name}.npy",
                              "names": root / "bs_names.json"}, 0, "test" if name == HELD_OUT else "train")
            for name in take_names(root)]


def read_take(source: TakeSource, config: DataConfig) -> Take:
    capture = read_capture(source.files["audio"].parent, source.name, read_names(source.files["names"]))
    if config.pause:
        capture = joined(capture, config.pause)
    layout = config.layout
    n = n_motion_frames(capture.audio, config.fps)
    curves = arkit_curves(capture, config.fps, n)
    face = np.zeros((n, layout.expression_dim), np.float32)
    mask = np.zeros(layout.dim, bool)
    for name, gain in TRAINED.items():
        channel = layout.expression_dim - len(layout.face_names) + layout.face_names.index(name)
        face[:, channel] = np.clip(gain * curves[name], 0.0, 1.0)
        mask[layout.gesture_dim + channel] = True
    motion = np.concatenate([np.zeros((n, layout.gesture_dim), np.float32), face], axis=1)
    return make_take(source.name, motion, capture.audio, config.fps, config.style, mask,
                     config.max_length_mismatch)
