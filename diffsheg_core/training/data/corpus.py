"""The project's synthetic speech corpus (`python -m diffsheg_core.training.corpus build`):
`manifest.jsonl` at the root lists every utterance, its `.wav` and the teacher motion
`.npz` in the `beat` layout (with `whole_body`, `beat_body`: the hips, legs and hips'
translation too). Utterances the builder failed on are reported and skipped.
The corpus has no split file: utterances are split by name (`val_fraction`). Each gets
the style class of its teacher's named gesture style (teacher.STYLE_NAMES); utterances of a
corpus made before named styles get the style class of the data configuration."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...audio import load_audio
from ..corpus.build import read_manifest
from ..corpus.teacher import STYLE_NAMES, load_utterance
from ...errors import DiffshegError
from ...rigs import BEAT
from .sources import TakeSource
from .take import Take, TakeError, decimate, make_take

if TYPE_CHECKING:
    from .dataset import DataConfig

LAYOUT = BEAT
WHOLE_BODY = True
"""whole_body data: the corpus holds the hips, legs and hips' translation (teacher v4 and later)."""


def find_takes(root: Path) -> list[TakeSource]:
    if not (root / "manifest.jsonl").is_file():
        raise DiffshegError(f"{root} has no manifest.jsonl: build the corpus there first "
                            "(python -m diffsheg_core.training.corpus build --out ...)")
    sources = []
    for index, record in sorted(read_manifest(root).items()):
        if "error" in record:
            sources.append(TakeSource(f"{index:06d}", {}, 0, None,
                                      [f"its audio and motion (the build failed: {record['error']})"]))
            continue
        files = {"audio": root / record["wav"], "motion": root / record["npz"]}
        sources.append(TakeSource(Path(record["wav"]).stem, files, 0, None))
    return sources


def read_take(source: TakeSource, config: DataConfig) -> Take:
    try:
        motion, _, info = load_utterance(source.files["motion"])
    except DiffshegError as exc:
        raise TakeError(str(exc)) from exc
    layout = config.layout
    if layout.root_translation and motion.root_translation is None:
        raise TakeError(f"{source.files['motion']}: the utterance holds no lower body (teacher "
                        f"v{info.get('teacher_version', '?')}): whole_body needs a corpus built with teacher v4 or later")
    joints = len(layout.gesture_joints)
    values = decimate(layout.join(motion.rotations[:, :joints], motion.face, motion.root_translation), motion.fps,
                      config.fps, str(source.files["motion"]))
    style = STYLE_NAMES.index(info["style"]) if "style" in info else config.style
    return make_take(source.name, values, load_audio(source.files["audio"]), config.fps,
                     style, np.ones(layout.dim, bool), config.max_length_mismatch)
