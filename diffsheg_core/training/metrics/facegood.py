"""Lip-sync against a real Mandarin face (issue 42): the FACEGOOD capture in
../shared/data/lang_capture/zh_facegood/ (5 takes 1114_2_01..05 of read Mandarin, 16 kHz,
one speaker, the face solved from video onto FACEGOOD's 116-blendshape rig at 30 fps,
`bs_value_<take>.npy` frames x 116 float32, the names in column order in `bs_names.json`),
mapped onto the ARKit mouth channels the model makes and compared with them.

Reading (`read_take`): the wav, the array (no pickle) and the names are checked against
each other (116 unique names holding every channel the mapping reads, a finite 2-D float
array with a column per name and weights within [0, 1], as many 30 fps frames as the audio
lasts within 0.1 s). `arkit_curves` takes the curves to the model's 15 fps: a triangular
low-pass as wide as the rate ratio ([1/4, 1/2, 1/4] for 30 -> 15) then linear interpolation
at frame times i / fps, so frame i of the model and of the capture stand at the same time
(the capture follows the audio with no offset: its jaw correlates best with the speech
level at shift 0 in 4 takes and one 30 fps frame in the fifth).

The mapping (`ARKIT_FROM_RIG`; each ARKit weight is a weighted sum of rig weights, clipped
to [0, 1]), decided by measurement on the 5 takes: first by how the rig's channels move
together in the capture itself, then by their agreement with the ARKit channels the bundled
model makes on the same speech (seeds 0 and 1, Pearson r at the best shift within
qc.MAX_LAG, whole clip / voiced frames, means over takes and seeds).

  jawOpen          mouth_stretch_c (the rig's jaw opening)                     0.74 / 0.46
  mouthFunnel      lip rounding: mean(mouth_funnel_*) + mouth_oh_c +           0.50 / 0.41
                   mouth_oo_c + mean(mouth_pucker_l, _r)
  mouthPucker      the same lip rounding                                       0.50 / 0.40
  mouthClose       lip closure: mean(mouth_press_l, _r) + mean(mouth_suck_d*)  0.23 / 0.29
                   + mean(mouth_suck_u*)
  mouthPressLeft   mouth_press_l + mouth_suck_dl + mouth_suck_ul (Right: _r)  0.24 / 0.28
  mouthRollLower   mean(mouth_suck_dl, _dr)                                    0.27 / 0.31
  mouthRollUpper   mean(mouth_suck_ul, _ur)                                    0.23 / 0.27
  mouthSmileLeft   mouth_lipCornerPull_l (Right: _r)                           0.03 / 0.01

Per take (voiced frames, means over seeds 0 and 1, takes 1114_2_01..05): jawOpen 0.48, 0.48,
0.47, 0.49, 0.39; mouthFunnel 0.37, 0.45, 0.44, 0.32, 0.46; mouthPucker 0.41, 0.39, 0.36,
0.41, 0.41; mouthClose 0.34, 0.30, 0.24, 0.23, 0.32. For scale: the model's jawOpen agrees
with BEAT2's captured SMPL-X jaw of the English take 2_scott_0_1_1 at 0.52 over voiced
frames and 0.46 over the whole clip (seeds 0 and 1), so Mandarin's jaw is at 0.89x English's
over voiced frames (the held-out 1114_2_05 0.76x). The whole-clip figure (1.61x English's)
is flattered by the takes' pauses: each take is about 100 single syllables or short words
(voiced runs of at most 0.67 s, median 0.47 s) about 0.6 s apart, so only 38-40 % of the frames
are voiced (English's running speech 74 %), and both faces shut the mouth between the
items. Over voiced frames the captured jaw follows the voice's level (qc.voiced_level_correlation)
at 0.51-0.59 where BEAT2's English jaw does at 0.30: an isolated syllable opens and closes
the jaw as its loudness rises and falls, which running speech does not.

How it was decided and how well it holds:
- jawOpen: mouth_stretch_c is the one rig channel that follows the jaw (42 % of frames
  above 0.05, p99 0.50, max 0.71) and the model's jawOpen agrees with it far more than with
  any other (0.74 / 0.46; next best mouth_oh_c, 0.22 / 0.13); adding mouth_oh_c (0.5x) or
  mouth_lowerLipDepress lowers both figures (0.73 / 0.45, 0.72 / 0.40 on takes 1-4).
- The solve does not use the same lip channels in every take: takes 1, 3 and 5 round the
  lips with mouth_oh_c (13-19 % of frames above 0.02, 2 % in takes 2 and 4), takes 2 and 4
  with mouth_oo_c (14-16 %, 0-3 % elsewhere), and takes 3 and 5 never use mouth_pucker_*,
  mouth_press_* or tooth_d_d. So one ARKit channel per rig channel does not hold: mouthPucker
  from mouth_pucker_* alone agrees 0.33 / 0.29 on takes 1-4 and not at all on 1114_2_05 (its
  mouth_pucker_* is zero throughout); the semantic split (funnel + oh -> mouthFunnel,
  pucker + oo -> mouthPucker) fails the same way (pucker + oo: 0.02 and 0.11 voiced on
  takes 3 and 5). Summed, the rounding channels agree with both ARKit channels in every take
  (0.32-0.46 voiced per take), and the model's own mouthFunnel and mouthPucker move
  together (r 0.78 over these takes), so they take the same curve. Likewise mouth_press_* and mouth_suck_*
  are one closure group in the capture (r 0.37-0.76 between them, under 0.05 with every
  other mouth channel) and press is absent from takes 3 and 5: their sum agrees with the
  model's mouthClose and mouthPress in every take (0.23-0.34 voiced), mouth_press_* alone
  0.22 on takes 1-4 and not at all on 3 and 5. Rolling the lips in is what ARKit's
  mouthRoll* are, and mouth_suck_d* / _u* agree with them (best of their rows).
- mouthSmile does not hold: the reader barely smiles (mouth_lipCornerPull_* above 0.02 on
  0-9 % of frames, p99 0.12) and the model's smile in read speech does not follow it
  (0.03 / 0.01). Kept for completeness, not to be read as lip-sync.
- The rig's left and right halves are equal in this capture (press, suck, funnel, corner
  pull identical; pucker within 0.004, upperLipRaise within 0.03), so Left and Right agree
  alike.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ...audio import Audio, load_audio
from ...errors import DiffshegError

CAPTURE_FPS = 30.0
"""Frames per second of the FACEGOOD solve."""
N_CHANNELS = 116
"""Blendshapes of the FACEGOOD rig."""
JAW = "mouth_stretch_c"
"""The rig's jaw opening (column 74)."""
HELD_OUT = "1114_2_05"
"""The take the tests measure (the mapping was chosen on all five; its figures on takes
1-4 and on this one are in the docstring of the module)."""
DURATION_TOLERANCE = 0.1
"""Seconds by which the capture's length may differ from its audio's."""

_FUNNEL = ("mouth_funnel_dl", "mouth_funnel_dr", "mouth_funnel_ul", "mouth_funnel_ur")
ROUNDING = (*((0.25, n) for n in _FUNNEL), (1.0, "mouth_oh_c"), (1.0, "mouth_oo_c"),
            (0.5, "mouth_pucker_l"), (0.5, "mouth_pucker_r"))
"""Lip rounding: the rig's funnel, oh, oo and pucker shapes, which the solve trades between
takes (see the module docstring)."""
CLOSURE = ((0.5, "mouth_press_l"), (0.5, "mouth_press_r"), (0.5, "mouth_suck_dl"), (0.5, "mouth_suck_dr"),
           (0.5, "mouth_suck_ul"), (0.5, "mouth_suck_ur"))
"""Lips shut: pressed together or rolled in."""

ARKIT_FROM_RIG: dict[str, tuple[tuple[float, str], ...]] = {
    "jawOpen": ((1.0, JAW),),
    "mouthFunnel": ROUNDING,
    "mouthPucker": ROUNDING,
    "mouthClose": CLOSURE,
    "mouthPressLeft": ((1.0, "mouth_press_l"), (1.0, "mouth_suck_dl"), (1.0, "mouth_suck_ul")),
    "mouthPressRight": ((1.0, "mouth_press_r"), (1.0, "mouth_suck_dr"), (1.0, "mouth_suck_ur")),
    "mouthRollLower": ((0.5, "mouth_suck_dl"), (0.5, "mouth_suck_dr")),
    "mouthRollUpper": ((0.5, "mouth_suck_ul"), (0.5, "mouth_suck_ur")),
    "mouthSmileLeft": ((1.0, "mouth_lipCornerPull_l"),),
    "mouthSmileRight": ((1.0, "mouth_lipCornerPull_r"),),
}
"""ARKit channel -> (weight, rig channel) pairs whose weighted sum, clipped to [0, 1], is its
weight (the mapping and how well it holds: the module docstring)."""


@dataclass(frozen=True)
class FacegoodTake:
    """One take: its speech and its solved face (frames x channels at `fps`)."""

    name: str
    audio: Audio
    names: tuple[str, ...]
    values: np.ndarray
    fps: float = CAPTURE_FPS

    @property
    def n_frames(self) -> int:
        return len(self.values)

    def channel(self, name: str) -> np.ndarray:
        """(frames,) weight of the rig channel `name` at the capture's own rate."""
        if name not in self.names:
            raise DiffshegError(f"the FACEGOOD take {self.name} has no channel '{name}'")
        return self.values[:, self.names.index(name)].astype(np.float64)


def take_names(directory: str | Path) -> list[str]:
    """Names of the takes in `directory` (each a <name>.wav with a bs_value_<name>.npy)."""
    directory = Path(directory)
    return sorted(p.stem for p in directory.glob("*.wav") if (directory / f"bs_value_{p.stem}.npy").is_file())


def read_names(path: str | Path) -> tuple[str, ...]:
    """The rig's channel names in column order from a bs_names.json, checked."""
    try:
        names = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise DiffshegError(f"cannot read the FACEGOOD channel names {path}: {e}") from e
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise DiffshegError(f"{path} must hold a JSON list of channel names")
    if len(names) != N_CHANNELS or len(set(names)) != len(names):
        raise DiffshegError(f"{path} holds {len(names)} names ({len(set(names))} distinct); the FACEGOOD "
                            f"rig has {N_CHANNELS} distinct ones")
    wanted = {JAW} | {n for pairs in ARKIT_FROM_RIG.values() for _, n in pairs}
    missing = sorted(wanted - set(names))
    if missing:
        raise DiffshegError(f"{path} lacks the channels the ARKit mapping reads: {', '.join(missing)}")
    return tuple(names)


def read_take(directory: str | Path, name: str, names: Optional[tuple[str, ...]] = None) -> FacegoodTake:
    """The take `name` of `directory`: <name>.wav, bs_value_<name>.npy and the directory's
    bs_names.json (or `names`), checked against each other."""
    directory = Path(directory)
    names = read_names(directory / "bs_names.json") if names is None else names
    wav, npy = directory / f"{name}.wav", directory / f"bs_value_{name}.npy"
    for path in (wav, npy):
        if not path.is_file():
            raise DiffshegError(f"the FACEGOOD take {name} has no {path.name} in {directory}")
    try:
        values = np.load(npy, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise DiffshegError(f"cannot read {npy}: {e}") from e
    if values.ndim != 2 or values.shape[1] != len(names) or not np.issubdtype(values.dtype, np.floating):
        raise DiffshegError(f"{npy.name} holds a {values.dtype} array of shape {values.shape}; expected "
                            f"float frames x {len(names)} (one column per name in bs_names.json)")
    if not np.isfinite(values).all():
        raise DiffshegError(f"{npy.name} holds values that are not finite")
    if values.size and (values.min() < -0.01 or values.max() > 1.01):
        raise DiffshegError(f"{npy.name} holds weights from {values.min():.3f} to {values.max():.3f}; "
                            "blendshape weights lie within [0, 1]")
    audio = load_audio(wav)
    seconds = len(values) / CAPTURE_FPS
    if abs(seconds - audio.duration) > DURATION_TOLERANCE:
        raise DiffshegError(f"{npy.name} lasts {seconds:.2f} s at {CAPTURE_FPS:g} fps but {wav.name} "
                            f"{audio.duration:.2f} s")
    return FacegoodTake(name, audio, names, values)


SILENCE_DB = 35.0
"""A capture frame whose speech level (qc.speech_level) lies this far below the take's 95th
percentile is silence: the takes' pauses are gated to digital silence (40-50 % of frames
at the floor), where the captured jaw is shut (95th percentile 0.003 against a median of
0.15 in sound on 1114_2_05)."""


def joined(take: FacegoodTake, pause: float) -> FacegoodTake:
    """`take` with every silence longer than `pause` seconds cut to `pause` (its first and
    last halves kept), the audio and the face cut at the same capture frames: the words,
    read one by one with about 0.6 s between them, follow one another as in running speech
    (issue 42: the takes hold no running speech to learn or measure it on)."""
    from ...qc import speech_level

    if pause <= 0:
        raise DiffshegError(f"a pause to cut silences to must be above 0 s, got {pause}")
    rate, n = take.audio.sample_rate, take.n_frames
    level = speech_level(take.audio.samples, rate, take.fps, n)
    silent = level < np.percentile(level, 95) - SILENCE_DB
    keep = np.ones(n, bool)
    kept = max(2, int(round(pause * take.fps)))
    edges = np.flatnonzero(np.diff(np.concatenate([[0], silent.astype(np.int8), [0]])))
    for start, end in zip(edges[::2], edges[1::2]):
        if end - start > kept:
            keep[start + kept // 2:end - (kept - kept // 2)] = False
    per_frame = rate / take.fps
    bounds = np.minimum(np.round(np.arange(n + 1) * per_frame).astype(np.int64), take.audio.n_samples)
    bounds[-1] = take.audio.n_samples  # the audio's tail past the last frame goes with it
    samples = np.concatenate([take.audio.samples[bounds[i]:bounds[i + 1]] for i in np.flatnonzero(keep)])
    return FacegoodTake(f"{take.name}-joined", Audio(samples, rate), take.names, take.values[keep], take.fps)


def resample_curves(values: np.ndarray, fps: float, to_fps: float, n_frames: int) -> np.ndarray:
    """Per-frame curves (frames, ...) at `fps` -> `n_frames` frames at `to_fps` (frame i at
    i / to_fps): low-passed by a triangle as wide as the rate ratio when going down, then
    linearly interpolated (held at the ends)."""
    values = np.asarray(values, np.float64)
    flat = values.reshape(len(values), -1)
    ratio = fps / to_fps
    if ratio > 1 and len(flat) > 1:
        half = int(math.ceil(ratio)) - 1
        kernel = 1 - np.abs(np.arange(-half, half + 1)) / ratio
        kernel /= kernel.sum()
        padded = np.concatenate([np.repeat(flat[:1], half, 0), flat, np.repeat(flat[-1:], half, 0)])
        flat = np.stack([np.convolve(padded[:, j], kernel, "valid") for j in range(flat.shape[1])], 1)
    source, times = np.arange(len(flat)) / fps, np.arange(n_frames) / to_fps
    out = np.stack([np.interp(times, source, flat[:, j]) for j in range(flat.shape[1])], 1)
    return out.reshape((n_frames,) + values.shape[1:])


def arkit_curves(take: FacegoodTake, fps: float = 15.0, n_frames: Optional[int] = None) -> dict[str, np.ndarray]:
    """ARKit channel -> (n_frames,) weight at `fps` (default: the model's 15), from the rig
    through ARKIT_FROM_RIG; n_frames defaults to the capture's length at `fps`."""
    n = int(take.n_frames / take.fps * fps + 1e-9) if n_frames is None else n_frames
    out = {}
    for arkit, pairs in ARKIT_FROM_RIG.items():
        curve = sum(w * take.channel(name) for w, name in pairs)
        out[arkit] = np.clip(resample_curves(curve, take.fps, fps, n), 0.0, 1.0)
    return out


def agreement(curve: np.ndarray, captured: np.ndarray, fps: float, audio: Audio,
              voiced: Optional[np.ndarray] = None) -> tuple[float, float]:
    """(whole clip, voiced frames) Pearson correlation of a model curve with a captured one
    of the same speech at `fps`, each the best within +-qc.MAX_LAG: over every frame, and
    over the voiced frames only, as the English captured-jaw figure is
    (lipsync.voiced_reference_correlation: qc.voiced_frames of `audio` on the captured
    curve's frames; `voiced` gives them when already known). NaN where the captured curve
    does not move."""
    from ...qc import MAX_LAG, lagged_correlation, voiced_frames

    n = min(len(curve), len(captured))
    a, b = np.asarray(curve[:n], np.float64), np.asarray(captured[:n], np.float64)
    if n < 3 or b.std() < 1e-9:
        return math.nan, math.nan
    if voiced is None:
        voiced = voiced_frames(audio.samples, audio.sample_rate, fps, n)
    shift = int(MAX_LAG * fps + 1e-9)
    return lagged_correlation(a, b, shift), lagged_correlation(a, b, shift, where=voiced[:n])


def measure_take(motion, take: FacegoodTake) -> dict[str, tuple[float, float]]:
    """ARKit channel -> (whole clip, voiced frames) agreement of `motion` (the model's face on
    the take's audio) with the take's captured face mapped onto ARKit."""
    from ...qc import voiced_frames
    from .channels import face_channel

    captured = arkit_curves(take, motion.fps, motion.n_frames)
    voiced = voiced_frames(take.audio.samples, take.audio.sample_rate, motion.fps, motion.n_frames)
    return {name: agreement(face_channel(motion, name), curve, motion.fps, take.audio, voiced)
            for name, curve in captured.items()}
