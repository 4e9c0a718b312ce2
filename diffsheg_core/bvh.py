"""BVH motion files: read, write, convert to and from `Motion`.

Rotation channels are read as intrinsic Euler angles in the order the channels are
listed: "Xrotation Yrotation Zrotation" means R = Rx @ Ry @ Rz (rotate about X, then
the new Y, then the new Z); in `diffsheg_core.rotations` terms, order 'XYZ' (upper
case = intrinsic). tests/test_bvh.py checks both authorities on this: Blender's BVH
importer puts every joint where `joint_positions` does, and the real take's
axis-angle means sit within 2 std of the official BEAT axis-angle statistics (an
extrinsic reading misses some channels by 10^5 std).

`write_bvh` writes the 75-joint BEAT skeleton the official DiffSHEG BEAT model
outputs. Its hierarchy, offsets, channels and a template pose are embedded as
`beat_skeleton.json` (made by tools/extract_beat_skeleton.py from the BEAT take
2_scott_0_1_1), so writing needs no external file.
"""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .errors import DiffshegError
from .files import atomic_write
from .motion import Motion, nominal_fps
from .rigs import BEAT, Layout, get_layout
from .rotations import axis_angle_to_euler, convert, euler_continuous, euler_to_axis_angle

BEAT_SKELETON_PATH = Path(__file__).with_name("beat_skeleton.json")

_ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
_POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
BVH_UNITS_PER_METRE = 100.0  # the BEAT skeleton is in centimetres; Motion.root_translation in metres
_MOTION_LINE = re.compile(r"^\s*MOTION\s*$", re.MULTILINE)
_FRAMES_LINE = re.compile(r"^\s*Frames:\s*(\d+)\s*$")
_FRAME_TIME_LINE = re.compile(r"^\s*Frame\s+Time:\s*(\S+)\s*$")


@dataclass
class BvhData:
    """A parsed BVH file: a joint hierarchy and one row of channel values per frame.

    Joints are in file (depth-first) order, which is also the order of their
    channels in `frames`. `parents[j]` is -1 for a root. `end_sites` maps a joint
    index to the offset of its End Site. `header_frames` / `header_frame_time` are
    what the file's header claimed; `frame_time` is what is used.
    """

    joint_names: list[str]
    parents: list[int]
    offsets: np.ndarray
    channels: list[tuple[str, ...]]
    end_sites: dict[int, np.ndarray]
    frames: np.ndarray
    frame_time: float
    header_frames: int | None = None
    header_frame_time: float | None = None
    source: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def fps(self) -> float:
        return nominal_fps(1.0 / self.frame_time)

    @property
    def header_mismatch(self) -> bool:
        """True when the header's frame count disagrees with the rows actually present."""
        return self.header_frames is not None and self.header_frames != self.n_frames

    def joint_index(self, name: str) -> int:
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise DiffshegError(f"{self.source or 'BVH'}: no joint named '{name}'") from None

    def _first_column(self, joint: int) -> int:
        return sum(len(c) for c in self.channels[:joint])

    def rotation_columns(self, name: str) -> tuple[np.ndarray, str]:
        """Column indices of a joint's three rotation channels and their Euler order ('XYZ')."""
        j = self.joint_index(name)
        start = self._first_column(j)
        picked = [(start + k, ch[0]) for k, ch in enumerate(self.channels[j]) if ch in _ROTATION_CHANNELS]
        if len(picked) != 3:
            raise DiffshegError(
                f"{self.source or 'BVH'}: joint '{name}' has {len(picked)} rotation channels; "
                "only joints with all three (X, Y, Z) rotations can be converted")
        return np.array([c for c, _ in picked]), "".join(a for _, a in picked)

    def position_columns(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Column indices of a joint's position channels and the axis (0-2) each one moves."""
        j = self.joint_index(name)
        start = self._first_column(j)
        picked = [(start + k, "XYZ".index(ch[0])) for k, ch in enumerate(self.channels[j])
                  if ch in _POSITION_CHANNELS]
        return np.array([c for c, _ in picked], dtype=int), np.array([a for _, a in picked], dtype=int)

    def copy(self) -> "BvhData":
        return BvhData(
            joint_names=list(self.joint_names), parents=list(self.parents),
            offsets=self.offsets.copy(), channels=list(self.channels),
            end_sites={j: o.copy() for j, o in self.end_sites.items()},
            frames=self.frames.copy(), frame_time=self.frame_time,
            header_frames=self.header_frames, header_frame_time=self.header_frame_time,
            source=self.source,
        )


class _Hierarchy:
    """Builds the joint lists from the tokens between HIERARCHY and MOTION."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[list[float] | None] = []
        self.channels: list[tuple[str, ...]] = []
        self.end_sites: dict[int, np.ndarray] = {}

    def fail(self, problem: str) -> DiffshegError:
        return DiffshegError(f"{self.where}: bad BVH hierarchy: {problem}")

    def parse(self, tokens: list[str]) -> None:
        if not tokens or tokens[0] != "HIERARCHY":
            raise self.fail("the file does not start with HIERARCHY")
        stack: list[tuple[str, int]] = []
        i = 1
        while i < len(tokens):
            tok = tokens[i]
            if tok in ("ROOT", "JOINT"):
                i = self._open_joint(tokens, i, stack)
            elif tok == "End":
                if tokens[i + 1: i + 3] != ["Site", "{"] or not stack or stack[-1][0] != "joint":
                    raise self.fail(f"misplaced 'End Site' after joint '{self._last()}'")
                stack.append(("end", stack[-1][1]))
                i += 3
            elif tok == "OFFSET":
                i = self._offset(tokens, i, stack)
            elif tok == "CHANNELS":
                i = self._channels(tokens, i, stack)
            elif tok == "}":
                if not stack:
                    raise self.fail("unbalanced '}'")
                stack.pop()
                i += 1
            else:
                raise self.fail(f"unexpected '{tok}' after joint '{self._last()}'")
        if stack:
            raise self.fail(f"joint '{self.names[stack[-1][1]]}' is not closed with '}}'")
        if not self.names:
            raise self.fail("no ROOT joint")
        missing = [n for n, o in zip(self.names, self.offsets) if o is None]
        if missing:
            raise self.fail(f"joints without OFFSET: {', '.join(missing)}")

    def _last(self) -> str:
        return self.names[-1] if self.names else "(none)"

    def _open_joint(self, tokens: list[str], i: int, stack: list[tuple[str, int]]) -> int:
        kind = tokens[i]
        if i + 2 >= len(tokens) or tokens[i + 2] != "{":
            raise self.fail(f"{kind} needs a name and '{{' (after joint '{self._last()}')")
        name = tokens[i + 1]
        if kind == "JOINT" and (not stack or stack[-1][0] != "joint"):
            raise self.fail(f"JOINT '{name}' has no enclosing joint")
        if kind == "ROOT" and stack:
            raise self.fail(f"ROOT '{name}' inside another joint")
        if name in self.names:
            raise self.fail(f"joint name '{name}' appears twice")
        self.names.append(name)
        self.parents.append(stack[-1][1] if stack else -1)
        self.offsets.append(None)
        self.channels.append(())
        stack.append(("joint", len(self.names) - 1))
        return i + 3

    def _offset(self, tokens: list[str], i: int, stack: list[tuple[str, int]]) -> int:
        if not stack:
            raise self.fail("OFFSET outside a joint")
        try:
            offset = [float(v) for v in tokens[i + 1: i + 4]]
        except ValueError:
            offset = []
        if len(offset) != 3 or not np.all(np.isfinite(offset)):
            raise self.fail(f"OFFSET of '{self.names[stack[-1][1]]}' needs three numbers")
        kind, j = stack[-1]
        if kind == "end":
            self.end_sites[j] = np.array(offset)
        else:
            self.offsets[j] = offset
        return i + 4

    def _channels(self, tokens: list[str], i: int, stack: list[tuple[str, int]]) -> int:
        if not stack or stack[-1][0] != "joint":
            raise self.fail("CHANNELS outside a joint")
        name = self.names[stack[-1][1]]
        try:
            n = int(tokens[i + 1])
        except (ValueError, IndexError):
            raise self.fail(f"CHANNELS of '{name}' needs a count") from None
        chans = tuple(tokens[i + 2: i + 2 + n])
        unknown = [c for c in chans if c not in _ROTATION_CHANNELS + _POSITION_CHANNELS]
        if len(chans) != n or unknown or len(set(chans)) != n:
            raise self.fail(f"CHANNELS of '{name}' are not {n} distinct X/Y/Z position/rotation "
                            f"channels: {' '.join(chans)}")
        self.channels[stack[-1][1]] = chans
        return i + 2 + n


def _parse_motion(text: str, where: str, n_channels: int) -> tuple[int, float, np.ndarray]:
    lines = [ln for ln in text.splitlines() if ln.strip()]
    frames_m = _FRAMES_LINE.match(lines[0]) if lines else None
    time_m = _FRAME_TIME_LINE.match(lines[1]) if len(lines) > 1 else None
    if frames_m is None or time_m is None:
        raise DiffshegError(f"{where}: bad BVH: MOTION must be followed by 'Frames: N' and "
                            "'Frame Time: seconds' lines")
    try:
        header_time = float(time_m.group(1))
    except ValueError:
        raise DiffshegError(f"{where}: bad BVH: Frame Time '{time_m.group(1)}' is not a number") from None
    rows = lines[2:]
    if not rows:
        raise DiffshegError(f"{where}: the BVH file holds no motion rows")
    for k, row in enumerate(rows):
        width = len(row.split())
        if width != n_channels:
            raise DiffshegError(
                f"{where}: motion row {k} has {width} values but the hierarchy declares "
                f"{n_channels} channels; the file is truncated or does not match its header")
    try:
        frames = np.loadtxt(io.StringIO("\n".join(rows)), dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise DiffshegError(f"{where}: motion data is not numeric ({exc})") from None
    bad = np.flatnonzero(~np.all(np.isfinite(frames), axis=1))
    if bad.size:
        raise DiffshegError(f"{where}: motion row {bad[0]} holds NaN or infinite values")
    return int(frames_m.group(1)), header_time, frames


def read_bvh(path: str | Path, fps: float | None = None) -> BvhData:
    """Parse a BVH file. Rows are counted, never taken from the header.

    `fps` overrides the header's frame time. It is required when the header's frame
    count disagrees with the rows present: such a header is stale (BEAT files made for
    DiffSHEG claim 7669 frames at 120 fps but hold 957 rows at 15 fps), so its frame
    time is not trusted either and reading stops with an error that says so.
    """
    path = Path(path)
    if not path.is_file():
        raise DiffshegError(f"{path}: no such BVH file")
    text = path.read_text(encoding="utf-8", errors="replace")
    split = _MOTION_LINE.search(text)
    if split is None:
        raise DiffshegError(f"{path}: not a BVH file (no MOTION section)")
    hierarchy = _Hierarchy(str(path))
    hierarchy.parse(text[: split.start()].split())
    n_channels = sum(len(c) for c in hierarchy.channels)
    header_frames, header_time, frames = _parse_motion(text[split.end():], str(path), n_channels)
    if fps is not None:
        if not fps > 0:
            raise DiffshegError(f"fps must be positive, got {fps}")
        frame_time = 1.0 / fps
    elif header_frames != len(frames):
        raise DiffshegError(
            f"{path}: the header says {header_frames} frames at {header_time} s per frame, but "
            f"the file holds {len(frames)} rows. The header is stale, so its frame time cannot "
            "be trusted either: pass the real rate, read_bvh(path, fps=...) (BEAT files made "
            "for the official DiffSHEG model are 15 fps, with a template pose in row 0)")
    elif not header_time > 0:
        raise DiffshegError(f"{path}: Frame Time must be positive, got {header_time}; pass fps=...")
    else:
        frame_time = header_time
    return BvhData(
        joint_names=hierarchy.names, parents=hierarchy.parents,
        offsets=np.array(hierarchy.offsets, dtype=np.float64), channels=hierarchy.channels,
        end_sites=hierarchy.end_sites, frames=frames, frame_time=frame_time,
        header_frames=header_frames, header_frame_time=header_time, source=str(path),
    )


def _hierarchy_text(data: BvhData) -> str:
    children: dict[int, list[int]] = {j: [] for j in range(-1, len(data.parents))}
    for j, p in enumerate(data.parents):
        children[p].append(j)
    lines = ["HIERARCHY"]
    visited: list[int] = []

    def vec(v: np.ndarray) -> str:
        return " ".join(f"{x:.6f}" for x in v)

    def emit(j: int, depth: int) -> None:
        tab = "\t" * depth
        visited.append(j)
        chans = " ".join((str(len(data.channels[j])),) + data.channels[j])
        lines.extend([f"{tab}{'ROOT' if data.parents[j] < 0 else 'JOINT'} {data.joint_names[j]}",
                      f"{tab}{{", f"{tab}\tOFFSET {vec(data.offsets[j])}", f"{tab}\tCHANNELS {chans}"])
        for c in children[j]:
            emit(c, depth + 1)
        if j in data.end_sites:
            lines.extend([f"{tab}\tEnd Site", f"{tab}\t{{",
                          f"{tab}\t\tOFFSET {vec(data.end_sites[j])}", f"{tab}\t}}"])
        lines.append(f"{tab}}}")

    for root in children[-1]:
        emit(root, 0)
    if visited != list(range(len(data.joint_names))):
        raise DiffshegError("BVH joints must be listed in depth-first order to be written")
    return "\n".join(lines) + "\n"


def write_bvh_data(data: BvhData, path: str | Path) -> Path:
    """Write a `BvhData` as a BVH file (values with 6 decimals, as BEAT's files have)."""
    path = Path(path)
    n_channels = sum(len(c) for c in data.channels)
    if data.frames.ndim != 2 or data.frames.shape[1] != n_channels:
        raise DiffshegError(
            f"BVH frames have shape {data.frames.shape}, expected (T, {n_channels})")
    if not np.all(np.isfinite(data.frames)):
        raise DiffshegError("BVH frames hold NaN or infinite values; nothing written")
    if not data.frame_time > 0:
        raise DiffshegError(f"BVH frame time must be positive, got {data.frame_time}")
    body = io.StringIO()
    np.savetxt(body, data.frames, fmt="%.6f", delimiter=" ")
    with atomic_write(path, "w", encoding="ascii", newline="\n") as fh:
        fh.write(_hierarchy_text(data))
        fh.write(f"MOTION\nFrames: {data.n_frames}\nFrame Time: {data.frame_time:.8f}\n")
        fh.write(body.getvalue())
    return path


def joint_positions(data: BvhData) -> np.ndarray:
    """Forward kinematics: (T, J, 3) joint positions in the file's units and world frame."""
    n_frames, n_joints = data.n_frames, len(data.joint_names)
    positions = np.zeros((n_frames, n_joints, 3))
    world = np.zeros((n_frames, n_joints, 3, 3))
    for j, name in enumerate(data.joint_names):
        if any(ch in _ROTATION_CHANNELS for ch in data.channels[j]):
            cols, order = data.rotation_columns(name)
            local = convert(data.frames[:, cols], "euler", "matrix", order=order)
        else:
            local = np.broadcast_to(np.eye(3), (n_frames, 3, 3))
        shift = np.broadcast_to(data.offsets[j], (n_frames, 3)).copy()
        cols, axes = data.position_columns(name)
        shift[:, axes] += data.frames[:, cols]
        parent = data.parents[j]
        if parent < 0:
            world[:, j], positions[:, j] = local, shift
        else:
            world[:, j] = world[:, parent] @ local
            positions[:, j] = positions[:, parent] + np.einsum("tab,tb->ta", world[:, parent], shift)
    return positions


def _driven_columns(data: BvhData, joints: tuple[str, ...] | list[str]) -> np.ndarray:
    return np.concatenate([data.rotation_columns(n)[0] for n in joints])


def has_template_row(data: BvhData, joints: tuple[str, ...] | list[str]) -> bool:
    """Whether row 0 is a template pose in front of the motion, as in BEAT files for DiffSHEG.

    Those files drive only `joints`; every other channel is constant from row 1 on
    but holds a different (template) value in row 0.
    """
    others = np.setdiff1d(np.arange(data.frames.shape[1]), _driven_columns(data, joints))
    if data.n_frames < 3 or others.size == 0:
        return False
    rest = data.frames[1:, others]
    return bool(np.ptp(rest, axis=0).max() <= 1e-6
                and np.abs(data.frames[0, others] - rest[0]).max() > 1e-6)


def bvh_to_motion(data: BvhData, layout: Layout | str = BEAT, fps: float | None = None,
                  skip_template_row: bool | None = None) -> Motion:
    """The layout's joint rotations as a Motion (axis-angle from intrinsic Euler degrees).

    `fps` defaults to the BvhData's rate. `skip_template_row`: None detects a template
    row 0 (see `has_template_row`). BVH files carry no face channels, so the Motion's
    face part is empty (K = 0) and there is no root translation.
    """
    layout = get_layout(layout) if isinstance(layout, str) else layout
    missing = [n for n in layout.joint_names if n not in data.joint_names]
    if missing:
        raise DiffshegError(
            f"{data.source or 'BVH'}: joints of layout '{layout.name}' missing from the file: "
            f"{', '.join(missing)}")
    skip = has_template_row(data, layout.joint_names) if skip_template_row is None else skip_template_row
    frames = data.frames[1:] if skip else data.frames
    rotations = np.stack([
        euler_to_axis_angle(frames[:, cols], order)
        for cols, order in (data.rotation_columns(n) for n in layout.joint_names)
    ], axis=1)
    return Motion(
        fps=float(fps) if fps is not None else data.fps, rig=layout.name,
        joint_names=list(layout.joint_names), rotations=rotations,
        face_names=[], face=np.zeros((len(frames), 0)),
        meta={"source": data.source, "skipped_template_row": bool(skip)},
    )


def save_skeleton_json(data: BvhData, path: str | Path, template_row: int = 0,
                       note: str = "") -> Path:
    """Store a hierarchy and one template pose (a row of `data.frames`) as JSON."""
    joints = [
        {"name": n, "parent": p, "offset": data.offsets[j].tolist(), "channels": list(c),
         "end_site": data.end_sites[j].tolist() if j in data.end_sites else None}
        for j, (n, p, c) in enumerate(zip(data.joint_names, data.parents, data.channels))
    ]
    lines = [f" {json.dumps(j)}" for j in joints]
    text = (f'{{"note": {json.dumps(note)},\n"joints": [\n' + ",\n".join(lines) + "\n],\n"
            f'"template": {json.dumps(data.frames[template_row].tolist())}\n}}\n')
    path = Path(path)
    with atomic_write(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return path


def load_skeleton_json(path: str | Path, fps: float = BEAT.fps) -> BvhData:
    """A skeleton saved by `save_skeleton_json`, as a one-frame BvhData at `fps`."""
    path = Path(path)
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
        joints = payload["joints"]
        data = BvhData(
            joint_names=[j["name"] for j in joints], parents=[int(j["parent"]) for j in joints],
            offsets=np.array([j["offset"] for j in joints], dtype=np.float64),
            channels=[tuple(j["channels"]) for j in joints],
            end_sites={k: np.array(j["end_site"], dtype=np.float64)
                       for k, j in enumerate(joints) if j["end_site"] is not None},
            frames=np.array([payload["template"]], dtype=np.float64),
            frame_time=1.0 / fps, source=str(path),
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DiffshegError(f"{path}: not a skeleton file written by save_skeleton_json ({exc})") from exc
    if data.frames.shape[1] != sum(len(c) for c in data.channels):
        raise DiffshegError(f"{path}: template pose does not match the skeleton's channels")
    return data


@lru_cache(maxsize=1)
def _beat_skeleton_cached() -> BvhData:
    return load_skeleton_json(BEAT_SKELETON_PATH)


def beat_skeleton() -> BvhData:
    """The 75-joint BEAT skeleton with its template pose as the single frame."""
    return _beat_skeleton_cached().copy()


def motion_to_bvh(motion: Motion, skeleton: BvhData | None = None) -> BvhData:
    """Pose `skeleton` (default: BEAT) with a Motion, one row per frame.

    Joints the Motion does not hold keep the skeleton's template pose. Euler angles are
    kept continuous over time, starting from the branch nearest the template pose.
    A root translation, when present, goes to the root's position channels (in the
    skeleton's units).
    """
    skeleton = beat_skeleton() if skeleton is None else skeleton
    unknown = [n for n in motion.joint_names if n not in skeleton.joint_names]
    if unknown:
        raise DiffshegError(
            f"motion of rig '{motion.rig}' has joints the BVH skeleton lacks: "
            f"{', '.join(unknown[:8])}{' ...' if len(unknown) > 8 else ''}; "
            "BVH export writes the 75-joint BEAT skeleton, so it needs a 'beat' motion "
            "(save other rigs as .npz)")
    template = skeleton.frames[0]
    frames = np.tile(template, (motion.n_frames, 1))
    by_order: dict[str, list[tuple[int, np.ndarray]]] = {}
    for j, name in enumerate(motion.joint_names):
        cols, order = skeleton.rotation_columns(name)
        by_order.setdefault(order, []).append((j, cols))
    for order, group in by_order.items():
        joints = [j for j, _ in group]
        cols = np.stack([c for _, c in group])
        euler = axis_angle_to_euler(motion.rotations[:, joints], order)
        frames[:, cols] = euler_continuous(euler, order, reference=template[cols])
    if motion.root_translation is not None:
        root = skeleton.joint_names[skeleton.parents.index(-1)]
        cols, axes = skeleton.position_columns(root)
        if cols.size != 3:
            raise DiffshegError(f"the skeleton's root '{root}' has no X/Y/Z position channels "
                                "for the motion's root translation")
        frames[:, cols] = template[cols] + motion.root_translation[:, axes] * BVH_UNITS_PER_METRE
    out = skeleton.copy()
    out.frames, out.frame_time = frames, 1.0 / motion.fps
    out.header_frames, out.header_frame_time, out.source = None, None, ""
    return out


def write_bvh(motion: Motion, path: str | Path) -> Path:
    """Write a 'beat' Motion as a BVH of the 75-joint BEAT skeleton at the motion's fps."""
    return write_bvh_data(motion_to_bvh(motion), path)
