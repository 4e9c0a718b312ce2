"""The result of generation: `Motion`, its `.npz` form, frame-rate resampling, and
face-curve files (the official DiffSHEG ARKit JSON, Live Link Face CSV).

Everything a client (the add-on, a writer, a script) needs is here; nothing in it
refers to the model that made it. BVH lives in `diffsheg_core.bvh`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.lib import format as npy_format

from .errors import DiffshegError
from .files import atomic_write
from .rigs import ARKIT51, ARKIT52
from .rotations import resample_weights, slerp_resample


def write_npz(fh, arrays: dict[str, np.ndarray]) -> None:
    """`arrays` as an .npz archive into the open file `fh`, as np.savez writes it, the
    archive closed even when a write fails (np.savez leaves it open to the garbage
    collector, which prints "Exception ignored in ZipFile.__del__" on a full disk)."""
    with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                npy_format.write_array(member, np.asanyarray(value), allow_pickle=False)


@dataclass
class Motion:
    """Joint rotations and face weights sampled at `fps`.

    rotations: (T, J, 3) axis-angle radians, each joint in its parent's frame.
    face: (T, K) blendshape weights (ARKit, nominally 0..1) or expression coefficients.
    root_translation: optional (T, 3) metres in the layout's canonical axes (x left, y up, z
    forward), the root's displacement from where it stands at rest.
    meta: model id, seed, audio file, sample rate, software version, ...
    """

    fps: float
    rig: str
    joint_names: list[str]
    rotations: np.ndarray
    face_names: list[str]
    face: np.ndarray
    root_translation: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.joint_names = list(self.joint_names)
        self.face_names = list(self.face_names)
        self.rotations = np.asarray(self.rotations, dtype=np.float32)
        self.face = np.asarray(self.face, dtype=np.float32)
        if self.root_translation is not None:
            self.root_translation = np.asarray(self.root_translation, dtype=np.float32)
        self.validate()

    def validate(self) -> None:
        t = self.n_frames
        if self.fps <= 0:
            raise DiffshegError(f"Motion fps must be positive, got {self.fps}")
        if self.rotations.shape != (t, len(self.joint_names), 3):
            raise DiffshegError(
                f"Motion rotations have shape {self.rotations.shape}, expected "
                f"({t}, {len(self.joint_names)}, 3) for {len(self.joint_names)} joints")
        if self.face.shape != (t, len(self.face_names)):
            raise DiffshegError(
                f"Motion face weights have shape {self.face.shape}, expected "
                f"({t}, {len(self.face_names)})")
        if self.root_translation is not None and self.root_translation.shape != (t, 3):
            raise DiffshegError(
                f"Motion root_translation has shape {self.root_translation.shape}, expected ({t}, 3)")

    @property
    def n_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration(self) -> float:
        """Seconds covered: frame i is at time i / fps."""
        return self.n_frames / self.fps

    def save_npz(self, path: str | Path) -> Path:
        path = Path(path)
        arrays = {
            "fps": np.float64(self.fps),
            "rig": np.str_(self.rig),
            "joint_names": np.array(self.joint_names, dtype=np.str_),
            "rotations": self.rotations,
            "face_names": np.array(self.face_names, dtype=np.str_),
            "face": self.face,
            "meta": np.str_(json.dumps(self.meta, default=str)),
        }
        if self.root_translation is not None:
            arrays["root_translation"] = self.root_translation
        with atomic_write(path) as fh:
            write_npz(fh, arrays)
        return path

    @classmethod
    def load_npz(cls, path: str | Path) -> "Motion":
        path = Path(path)
        if not path.is_file():
            raise DiffshegError(f"{path}: no such motion file")
        try:
            with np.load(path, allow_pickle=False) as z:
                return cls(
                    fps=float(z["fps"]),
                    rig=str(z["rig"]),
                    joint_names=[str(n) for n in z["joint_names"]],
                    rotations=z["rotations"],
                    face_names=[str(n) for n in z["face_names"]],
                    face=z["face"],
                    root_translation=z["root_translation"] if "root_translation" in z else None,
                    meta=json.loads(str(z["meta"])),
                )
        except (KeyError, ValueError, OSError) as exc:
            raise DiffshegError(
                f"{path}: not a motion file written by diffsheg_core ({exc})") from exc


def nominal_fps(fps: float) -> float:
    """Snap a measured rate (1 / frame time, often rounded) to the integer or NTSC
    (N * 1000 / 1001) rate it stands for when within 1e-4 of it; else return it as is."""
    for candidate in (round(fps), round(fps * 1.001) * 1000 / 1001):
        if candidate > 0 and abs(fps - candidate) <= 1e-4 * candidate:
            return float(candidate)
    return float(fps)


def resample_motion(motion: Motion, fps: float, face_kind: str = "cubic") -> Motion:
    """The same motion sampled at `fps` (a Blender scene rate such as 24 or 29.97).

    Rotations are slerped per joint; face weights and root translation use PCHIP
    (`face_kind='cubic'`, no overshoot) or linear interpolation. The duration is kept
    to within half an output frame: the output has round(duration * fps) frames and
    any frames past the last source frame's time hold its pose. `meta['source_fps']`
    records the rate the motion was generated at.
    """
    if not fps > 0:
        raise DiffshegError(f"target fps must be positive, got {fps}")
    if motion.n_frames == 0:
        raise DiffshegError("cannot resample a motion with no frames")
    n_out = max(1, int(round(motion.duration * fps)))
    src = motion.fps
    if motion.rotations.shape[1]:
        rotations = slerp_resample(motion.rotations, src, fps, n_out)
    else:
        rotations = np.zeros((n_out, 0, 3))
    if motion.face.shape[1]:
        face = resample_weights(motion.face, src, fps, face_kind, n_out)
    else:
        face = np.zeros((n_out, 0))
    root = None
    if motion.root_translation is not None:
        root = resample_weights(motion.root_translation, src, fps, face_kind, n_out)
    meta = dict(motion.meta)
    meta.setdefault("source_fps", src)
    return Motion(fps=float(fps), rig=motion.rig, joint_names=motion.joint_names,
                  rotations=rotations, face_names=motion.face_names, face=face,
                  root_translation=root, meta=meta)


LIVELINK_BLENDSHAPES: tuple[str, ...] = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft",
    "EyeSquintLeft", "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight",
    "EyeLookOutRight", "EyeLookUpRight", "EyeSquintRight", "EyeWideRight",
    "JawForward", "JawRight", "JawLeft", "JawOpen", "MouthClose", "MouthFunnel", "MouthPucker",
    "MouthRight", "MouthLeft", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft",
    "MouthStretchRight", "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper",
    "MouthPressLeft", "MouthPressRight", "MouthLowerDownLeft", "MouthLowerDownRight",
    "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft", "BrowDownRight", "BrowInnerUp",
    "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft", "CheekSquintRight",
    "NoseSneerLeft", "NoseSneerRight", "TongueOut",
)
"""The 52 blendshape columns of a Live Link Face CSV, in the app's order and spelling."""

LIVELINK_HEAD: tuple[str, ...] = (
    "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
    "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
)
"""The head and eye rotation columns that follow the blendshapes in a Live Link Face CSV."""

_ARKIT_BY_KEY = {n.lower(): n for n in ARKIT52}
_TIMECODE = re.compile(r"^(\d+):(\d\d):(\d\d):(\d+(?:\.\d*)?)$")


def arkit_name(name: str) -> str | None:
    """The ARKit blendshape a column or shape-key name stands for, or None.

    Matches ignore case, so ARKit's 'eyeBlinkLeft' and Live Link Face's 'EyeBlinkLeft'
    agree; '_L' / '_R' suffixes ('eyeBlink_L') read as Left / Right.
    """
    key = name.strip().lower()
    if key.endswith(("_l", "_r")):
        key = key[:-2] + ("left" if key[-1] == "l" else "right")
    return _ARKIT_BY_KEY.get(key)


class FaceCurves(NamedTuple):
    """Blendshape curves read from a file, on a uniform time grid starting at 0.

    names: canonical ARKit names in ARKit's alphabetical order (51, or 52 with
    tongueOut); weights: (T, len(names)) float32.
    """

    fps: float
    names: list[str]
    weights: np.ndarray


def _face_curves(times: np.ndarray, names: list[str], weights: np.ndarray, where: str) -> FaceCurves:
    """Pick the ARKit columns out of timed samples and put them on a uniform grid."""
    columns: dict[str, int] = {}
    for k, name in enumerate(names):
        canonical = arkit_name(name)
        if canonical is None:
            continue
        if canonical in columns:
            raise DiffshegError(f"{where}: blendshape '{canonical}' appears twice "
                                f"(columns '{names[columns[canonical]]}' and '{name}')")
        columns[canonical] = k
    missing = [n for n in ARKIT51 if n not in columns]
    if missing:
        raise DiffshegError(
            f"{where}: missing ARKit blendshape columns: {', '.join(missing[:6])}"
            f"{' ...' if len(missing) > 6 else ''} ({len(missing)} of 51); the file must hold "
            "all 51 ARKit weights (tongueOut optional), named as in ARKit or Live Link Face")
    out_names = list(ARKIT52 if "tongueOut" in columns else ARKIT51)
    values = weights[:, [columns[n] for n in out_names]].astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if bad.size:
        raise DiffshegError(f"{where}: frame {bad[0]} holds NaN or infinite weights")
    if len(times) < 2:
        raise DiffshegError(f"{where}: needs at least two frames to tell the frame rate")
    steps = np.diff(times)
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise DiffshegError(
            f"{where}: time does not increase at frame {k} ({times[k - 1]:.6f} s then "
            f"{times[k]:.6f} s); frames must be in time order without repeats")
    fps = nominal_fps(1.0 / float(np.median(steps)))
    times = times - times[0]
    if np.max(np.abs(steps - 1.0 / fps)) > 0.25 / fps:
        grid = np.arange(int(math.floor(times[-1] * fps + 1e-6)) + 1) / fps
        values = np.stack([np.interp(grid, times, values[:, k]) for k in range(values.shape[1])], axis=1)
    return FaceCurves(fps=fps, names=out_names, weights=values.astype(np.float32))


def _arkit_face(motion: Motion, what: str) -> dict[str, np.ndarray]:
    """The motion's face curves by canonical ARKit name; all 51 must be there."""
    curves = {}
    for k, name in enumerate(motion.face_names):
        canonical = arkit_name(name)
        if canonical is not None:
            curves[canonical] = motion.face[:, k]
    missing = [n for n in ARKIT51 if n not in curves]
    if missing:
        raise DiffshegError(
            f"{what} needs the 51 ARKit blendshape weights, but this '{motion.rig}' motion lacks "
            f"{len(missing)} of them (e.g. {missing[0]}); SMPL-X motion carries FLAME "
            "expression coefficients instead: save it as .npz")
    return curves


def write_arkit_json(motion: Motion, path: str | Path) -> Path:
    """Face weights in the official DiffSHEG JSON form:
    {"names": [...], "frames": [{"weights": [...], "time": seconds}, ...]}."""
    curves = _arkit_face(motion, "ARKit JSON export")
    names = [n for n in ARKIT52 if n in curves]
    weights = np.round(np.stack([curves[n] for n in names], axis=1).astype(np.float64), 6)
    frames = [{"weights": w, "time": round(i / motion.fps, 6)} for i, w in enumerate(weights.tolist())]
    path = Path(path)
    with atomic_write(path, "w", encoding="utf-8") as fh:
        fh.write(json.dumps({"names": names, "frames": frames}))
    return path


def read_arkit_json(path: str | Path) -> FaceCurves:
    """Read an ARKit JSON (the DiffSHEG / BEAT form written by `write_arkit_json`)."""
    path = Path(path)
    if not path.is_file():
        raise DiffshegError(f"{path}: no such ARKit JSON file")
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
        names = [str(n) for n in payload["names"]]
        frames = payload["frames"]
        times = np.array([float(f["time"]) for f in frames], dtype=np.float64)
        weights = np.array([f["weights"] for f in frames], dtype=np.float64)
    except (ValueError, KeyError, TypeError) as exc:
        raise DiffshegError(
            f"{path}: not an ARKit JSON file ({exc!r}); expected "
            '{"names": [...], "frames": [{"weights": [...], "time": seconds}, ...]}') from None
    if weights.ndim != 2 or weights.shape[1] != len(names):
        raise DiffshegError(
            f"{path}: every frame must hold one weight per name ({len(names)} names)")
    return _face_curves(times, names, weights, str(path))


def _timecodes(n_frames: int, fps: float) -> list[str]:
    """Live Link Face timecodes HH:MM:SS:FF.fff, FF counted at the rate rounded up."""
    rate = int(math.ceil(fps - 1e-6))
    millis = np.round(np.arange(n_frames) / fps * rate * 1000).astype(np.int64)
    seconds, rest = np.divmod(millis, rate * 1000)
    return [f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}:{r // 1000:02d}.{r % 1000:03d}"
            for s, r in zip(seconds.tolist(), rest.tolist())]


def write_livelink_csv(motion: Motion, path: str | Path) -> Path:
    """Face weights as a Live Link Face CSV (Timecode, BlendShapeCount, 52 blendshapes,
    9 head/eye rotations). TongueOut is 0 unless the motion has it; the head and eye
    rotation columns are written as 0 (the face part of a Motion has no head pose)."""
    curves = _arkit_face(motion, "Live Link Face CSV export")
    zeros = np.zeros(motion.n_frames, dtype=np.float32)
    blend = [curves.get(arkit_name(n), zeros) for n in LIVELINK_BLENDSHAPES]
    block = np.stack(blend + [zeros] * len(LIVELINK_HEAD), axis=1)
    body = io.StringIO()
    np.savetxt(body, block, fmt="%.6f", delimiter=",")
    count = len(LIVELINK_BLENDSHAPES) + len(LIVELINK_HEAD)
    lines = [",".join(("Timecode", "BlendShapeCount") + LIVELINK_BLENDSHAPES + LIVELINK_HEAD)]
    lines += [f"{tc},{count},{row}" for tc, row in
              zip(_timecodes(motion.n_frames, motion.fps), body.getvalue().splitlines())]
    path = Path(path)
    with atomic_write(path, "w", encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")
    return path


def _timecode_seconds(codes: list[str], rate: float | None, where: str) -> np.ndarray:
    parts = []
    for k, code in enumerate(codes):
        m = _TIMECODE.match(code.strip())
        if m is None:
            raise DiffshegError(f"{where}: row {k + 1}: Timecode '{code}' is not HH:MM:SS:FF(.fff)")
        h, mi, s, ff = m.groups()
        parts.append((int(h) * 3600 + int(mi) * 60 + int(s), float(ff)))
    whole = np.array([p[0] for p in parts], dtype=np.float64)
    frame = np.array([p[1] for p in parts], dtype=np.float64)
    if rate is None:
        if np.all(whole == whole[0]):
            raise DiffshegError(
                f"{where}: the recording is shorter than a second, so the timecode's frame rate "
                "cannot be told from it; pass timecode_rate=... (Live Link Face: 60 by default)")
        rate = math.floor(frame.max()) + 1
    return whole + frame / rate


def read_livelink_csv(path: str | Path, timecode_rate: float | None = None) -> FaceCurves:
    """Read a Live Link Face CSV (or any CSV with a Timecode column and ARKit-named
    blendshape columns in either camelCase or PascalCase).

    The timecode's frame field counts at `timecode_rate`; by default the rate is read
    off the data (the highest frame number + 1, seen once a second boundary passes).
    Recordings with dropped frames are put on a uniform grid by linear interpolation.
    """
    path = Path(path)
    if not path.is_file():
        raise DiffshegError(f"{path}: no such CSV file")
    with open(path, newline="", encoding="utf-8-sig") as fh:
        rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    if len(rows) < 2:
        raise DiffshegError(f"{path}: the CSV holds no data rows")
    header = [h.strip() for h in rows[0]]
    lower = [h.lower() for h in header]
    if "timecode" not in lower:
        raise DiffshegError(f"{path}: no Timecode column; is this a Live Link Face CSV?")
    short = [k for k, r in enumerate(rows[1:], start=1) if len(r) != len(header)]
    if short:
        raise DiffshegError(
            f"{path}: row {short[0]} has {len(rows[short[0]])} fields, the header has {len(header)}")
    t_col = lower.index("timecode")
    wanted = [k for k, h in enumerate(header) if arkit_name(h) is not None]
    try:
        weights = np.array([[float(r[k]) for k in wanted] for r in rows[1:]], dtype=np.float64)
    except ValueError as exc:
        raise DiffshegError(f"{path}: a blendshape value is not a number ({exc})") from None
    times = _timecode_seconds([r[t_col] for r in rows[1:]], timecode_rate, str(path))
    return _face_curves(times, [header[k] for k in wanted], weights.reshape(len(rows) - 1, -1), str(path))


def write_talkshow_npz(motion: Motion, path: str | Path) -> Path:
    """SMPL-X motion in the TalkSHOW parameter layout, as the official SHOW model's
    statistics use it: `pose` (T, 165) = jaw 3, left eye 3, right eye 3, global 3,
    body 63 (SMPL-X joints 1..21), hands 90 (left then right, 15 joints each), all
    axis-angle; `expression` (T, 100) FLAME coefficients; `fps`. Joints the motion
    does not drive are zero (rest pose)."""
    from .rigs import SMPLX_JOINTS

    if motion.rig != "smplx":
        raise DiffshegError(f"the TalkSHOW layout holds SMPL-X motion; this motion uses the "
                            f"'{motion.rig}' layout (save it as .npz or BVH instead)")
    order = ("jaw", "left_eye_smplhf", "right_eye_smplhf", "pelvis") + SMPLX_JOINTS[1:22] + SMPLX_JOINTS[25:55]
    pose = np.zeros((motion.n_frames, len(order), 3), dtype=np.float32)
    index = {name: k for k, name in enumerate(order)}
    for j, name in enumerate(motion.joint_names):
        pose[:, index[name]] = motion.rotations[:, j]
    expression = np.zeros((motion.n_frames, 100), dtype=np.float32)
    n_exp = min(100, motion.face.shape[1])
    expression[:, :n_exp] = motion.face[:, :n_exp]
    path = Path(path)
    with atomic_write(path) as fh:
        write_npz(fh, {"pose": pose.reshape(motion.n_frames, -1), "expression": expression,
                       "fps": np.float64(motion.fps)})
    return path


def smooth_frames(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along time (axis 0) with a sigma of `sigma` frames, edges held."""
    radius = max(1, int(np.ceil(3 * sigma)))
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([np.repeat(values[:1], radius, 0), values, np.repeat(values[-1:], radius, 0)])
    out = np.empty(values.shape, dtype=np.float64)
    flat_in = padded.reshape(len(padded), -1)
    flat_out = out.reshape(len(values), -1)
    for c in range(flat_in.shape[1]):
        flat_out[:, c] = np.convolve(flat_in[:, c], kernel, mode="valid")
    return out
