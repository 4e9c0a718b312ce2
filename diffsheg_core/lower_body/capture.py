"""The capture material and the offline lower body.

For a model whose layout stops at the waist (`beat`: v8 and the official BEAT checkpoint),
`add_lower_body` adds what a standing talker's hips and legs do: weight shifts, sway and
turns cut from the real full-body capture of BEAT2 take 2_scott_0_1_1 (SMPL-X, with root
translation), stored beside the model (`assets/lower_body.npz`, a few thousand numbers:
`LowerBodyLibrary`, made by `build`, `python -m diffsheg_core.lower_body`). That flow is
one way, as DiffSHEG's expression-to-gesture flow: the upper body the model made drives the
lower body, never the reverse, so the upper body and face are the model's to the bit.

The lower body is cut from that capture as the teacher's gestures are cut from the BEAT
take: motion matching. The take is built segment by segment (1.5-4 s, drawn with the
generation's seed); each segment is the stretch of the capture (less its last 20 s, held
out as the gesture material is) whose arm energy (wrist speed, layout-free, `kinematics`)
best matches the generated arms' over the same time and whose first pose best continues
the last one, chosen at random among the few best; segments are cross-faded over half a
second and the hips' translation continues across each join. So real weight shifts,
sways, turns and steps come with the gestures that go with them. The hips' translation is
kept within the capture's range (`settle`) and the contact feet are pinned (`feet`).

A whole-body model (layout `beat_body`, with a lower-body branch: the bundled model) makes
the hips, legs and the hips' translation itself: `plant` low-passes them, settles the hips
as the capture's are and lets the feet stand or step (`feet.FootSteps`).
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable
from pathlib import Path

import numpy as np

from ..errors import DiffshegError
from ..kinematics import wrist_positions
from ..motion import Motion, smooth_frames
from ..rotations import (axis_angle_to_quaternion, quaternion_conjugate, quaternion_product,
                         quaternion_sequence_continuous, quaternion_to_axis_angle, resample_positions,
                         resample_weights, slerp_resample)
from .body import (JOINTS, _apply, _check_whole_body, _lowest, _world, foot_positions, lower_rotations,
                   upper_body, with_lower_body)
from .feet import plant_feet, step_feet

SMPLX_INDEX = (0, 2, 5, 8, 11, 1, 4, 7, 10)  # pelvis, right hip, knee, ankle, foot, then left
ASSET = Path(__file__).parents[1] / "assets" / "lower_body.npz"
LAYOUTS = ("beat",)

HELD_OUT_S = 20.0    # the capture's last seconds, left out of the fit (as the gesture material)
SEGMENT = (1.5, 4.0)  # seconds: the shortest and longest segment cut from the capture
FADE_S = 0.5         # seconds of cross-fade between segments
CHOICES = 4          # a segment is drawn among this many best matches
DRIFT_S = 4.0        # Gaussian sigma (s) of the hips' slow drift across joins, taken out
GROUND_S = 0.25     # Gaussian sigma (s) of the lowest foot point the body is lowered onto the floor by
TRAVEL_M = 0.15      # metres a segment's hips travel that cost as much as a poor energy match
ENERGY_S = 1.0       # Gaussian sigma of the arms' energy the segments are matched on
MODEL_SMOOTH_S = 0.2    # Gaussian sigma (s) a whole-body model's hips and legs are low-passed by before planting


@dataclass(frozen=True)
class LowerBodyLibrary:
    """The capture's lower body to cut segments from, at `fps`: rotations (N, 9, 3),
    hips translation (N, 3, metres about the standing hips) and arm energy (N,)."""

    rotations: np.ndarray
    translation: np.ndarray
    energy: np.ndarray
    fps: float

    def save(self, path: Path) -> Path:
        np.savez(path, rotations=self.rotations.astype(np.float32), translation=self.translation.astype(np.float32),
                 energy=self.energy.astype(np.float32), fps=np.float64(self.fps))
        return path

    @classmethod
    def load(cls, path: Path = ASSET) -> "LowerBodyLibrary":
        try:
            with np.load(path) as z:
                return cls(z["rotations"].astype(np.float64), z["translation"].astype(np.float64),
                           z["energy"].astype(np.float64), float(z["fps"]))
        except (OSError, KeyError, ValueError) as exc:
            raise DiffshegError(f"the lower-body library {path} cannot be read ({exc}): reinstall the package, "
                                "or generate with upper_body_only") from None

    @property
    def translation_low(self) -> np.ndarray:
        return self.translation.min(axis=0)

    @property
    def translation_high(self) -> np.ndarray:
        return self.translation.max(axis=0)

    @property
    def centre(self) -> np.ndarray:
        """(2,) where the capture's hips stand on average, x and z."""
        return self.translation[:, [0, 2]].mean(axis=0)


# ---------------------------------------------------------------- the capture

def read_capture(path: Path, fps: float) -> tuple[np.ndarray, np.ndarray, Motion]:
    """A BEAT2 SMPL-X take as (T, 9, 3) lower-body rotations, (T, 3) hips translation
    (metres, canonical axes, about the standing hips) and its upper body as a Motion, at
    `fps`, turned so that the speaker faces +z on average."""
    from ..rigs import SMPLX_JOINTS

    with np.load(path, allow_pickle=True) as z:
        poses, trans, rate = z["poses"].astype(np.float64), z["trans"].astype(np.float64), float(z["mocap_frame_rate"])
    joints = poses.reshape(len(poses), -1, 3)
    n = len(resample_positions(len(poses), rate, fps))
    rotations = slerp_resample(joints, rate, fps, n)
    trans = resample_weights(trans, rate, fps, "linear", n)
    # face +z on average: turn the world about y by minus the pelvis's mean heading
    forward = _apply(axis_angle_to_quaternion(rotations[:, 0]), np.array([0.0, 0.0, 1.0]))
    heading = float(np.arctan2(forward[:, 0].mean(), forward[:, 2].mean()))
    turn = np.array([np.cos(-heading / 2), 0.0, np.sin(-heading / 2), 0.0])
    rotations[:, 0] = quaternion_to_axis_angle(quaternion_product(turn, axis_angle_to_quaternion(rotations[:, 0])))
    trans = _apply(np.broadcast_to(turn, (n, 4)), trans)
    lower = rotations[:, list(SMPLX_INDEX)]
    # the hips upright on average (the upper body sits on them): their mean tilt goes to the
    # thighs, whose world orientation is unchanged
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(lower))
    tilt = q[:, 0].mean(axis=0)
    tilt /= np.linalg.norm(tilt)
    q[:, 0] = quaternion_product(q[:, 0], quaternion_conjugate(tilt)[None])
    for thigh in ("RightUpLeg", "LeftUpLeg"):
        q[:, JOINTS.index(thigh)] = quaternion_product(tilt[None], q[:, JOINTS.index(thigh)])
    lower = quaternion_to_axis_angle(q)
    upper = Motion(fps=fps, rig="smplx", joint_names=list(SMPLX_JOINTS[:len(rotations[0])]), rotations=rotations,
                   face_names=[], face=np.zeros((n, 0)))
    # about the standing hips: x and z about their mean; y from the floor (the soles' low
    # point over the take) less the canonical body's standing hips height
    soles = foot_positions(lower, np.zeros((n, 3)))  # with the hips at their standing height
    lowest = np.minimum(soles["right"][1][:, 1], soles["left"][1][:, 1])
    floor = np.percentile(trans[:, 1] + lowest, 5)
    trans = np.stack([trans[:, 0] - trans[:, 0].mean(), trans[:, 1] - floor,
                      trans[:, 2] - trans[:, 2].mean()], axis=1)
    return lower, trans, upper


def arm_energy(motion: Motion) -> np.ndarray:
    """(T,) the wrists' speed (arm lengths/s), smoothed: what drives the hips."""
    wrists = wrist_positions(motion)
    speed = np.linalg.norm(np.diff(wrists, axis=0, prepend=wrists[:1]), axis=-1).mean(axis=-1) * motion.fps
    return smooth_frames(speed[:, None], ENERGY_S * motion.fps)[:, 0]


def build(path: Path, fps: float = 15.0) -> LowerBodyLibrary:
    """The lower-body library of a BEAT2 SMPL-X take, less its last HELD_OUT_S seconds."""
    lower, trans, upper = read_capture(path, fps)
    keep = len(lower) - int(HELD_OUT_S * fps)
    if keep < 4 * SEGMENT[1] * fps:
        raise DiffshegError(f"{path} holds {len(lower) / fps:.1f} s: the lower body needs at least "
                            f"{4 * SEGMENT[1] + HELD_OUT_S:.0f} s of capture")
    return LowerBodyLibrary(lower[:keep], trans[:keep], arm_energy(upper)[:keep], fps)


# ---------------------------------------------------------------- generating

class _Planner:
    """Cuts segments from the library one after another: each the stretch (SEGMENT seconds,
    drawn) whose arm energy best matches the energy asked for and whose first pose best
    continues the last, chosen at random among the CHOICES best, cross-faded over FADE_S
    with the hips going on from where they are. Offline and live lower bodies share it."""

    def __init__(self, library: LowerBodyLibrary, seed: int):
        self.library = library
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 29]))
        self.fade = int(round(FADE_S * library.fps))
        self.lengths = (int(SEGMENT[0] * library.fps), int(SEGMENT[1] * library.fps))
        self.q = quaternion_sequence_continuous(axis_angle_to_quaternion(library.rotations))
        self.pose = library.rotations.reshape(len(self.q), -1)
        self.rotations, self.trans = np.zeros((0, len(JOINTS), 4)), np.zeros((0, 3))

    def add(self, want: Callable[[int, int], float], leash: float = 0.0) -> None:
        """One more segment; `want(first, span)` is the arm energy it should match over its
        frames [first, first + span). `leash` (0-1): the share of the hips' distance from the
        capture's centre that the segment takes back over its length (a live stream cannot
        take out drift afterwards)."""
        library, q, fade = self.library, self.q, self.fade
        length = int(self.rng.integers(self.lengths[0], self.lengths[1] + 1))
        span = min(length + fade, len(q) - 1)
        t0 = max(0, len(self.rotations) - fade)
        starts = np.arange(len(q) - span)
        windows = np.convolve(library.energy, np.ones(span) / span, mode="valid")[:len(starts)]
        cost = np.abs(windows - want(t0, span)) / (library.energy.std() + 1e-9)
        # a talker mostly stands: a segment that walks off costs as much as a poor energy match
        travel = np.linalg.norm(library.translation[starts + span - 1][:, [0, 2]]
                                - library.translation[starts][:, [0, 2]], axis=1)
        cost = cost + travel / TRAVEL_M
        if len(self.rotations):
            last = quaternion_to_axis_angle(self.rotations[t0]).reshape(-1)
            cost = cost + np.linalg.norm(self.pose[starts] - last, axis=1) / 0.2
        s0 = int(self.rng.choice(np.argsort(cost)[:CHOICES]))
        seg_q, seg_t = q[s0:s0 + span].copy(), library.translation[s0:s0 + span].copy()
        if len(self.rotations):
            here = self.trans[t0, [0, 2]]
            seg_t[:, [0, 2]] += here - seg_t[0, [0, 2]]  # the hips go on from where they are
            if leash:
                ease = np.linspace(0.0, 1.0, span)[:, None]
                seg_t[:, [0, 2]] += leash * ease * ease * (3 - 2 * ease) * (self.library.centre - here)
            w = np.linspace(0.0, 1.0, fade + 2)[1:-1][:, None]
            old_q, old_t = self.rotations[t0:], self.trans[t0:]
            overlap = len(old_q)
            flip = np.sign(np.sum(old_q * seg_q[:overlap], axis=-1, keepdims=True))
            blended = (1 - w[:overlap, :, None]) * old_q + w[:overlap, :, None] * seg_q[:overlap] * flip
            seg_q[:overlap] = blended / np.linalg.norm(blended, axis=-1, keepdims=True)
            seg_t[:overlap] = (1 - w[:overlap]) * old_t + w[:overlap] * seg_t[:overlap]
        self.rotations = np.concatenate([self.rotations[:t0], seg_q])
        self.trans = np.concatenate([self.trans[:t0], seg_t])


def _on_floor(lower: np.ndarray, trans: np.ndarray, fps: float) -> np.ndarray:
    """`trans` lowered or raised so the lowest foot point is on the floor (smoothed over
    GROUND_S): segments stood a little higher or lower in the capture than its floor."""
    out = trans.copy()
    out[:, 1] -= smooth_frames(_lowest(_world(lower, trans))[:, None], GROUND_S * fps)[:, 0]
    return out


def sample(library: LowerBodyLibrary, energy: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, 9, 3) lower-body rotations and (T, 3) hips translation for the arms' `energy`
    (arm_energy of the take), cut from `library` with `seed`; the translation's slow drift
    taken out and kept within the capture's range, then the body set on the floor."""
    n, fps = len(energy), library.fps
    planner = _Planner(library, seed)
    while len(planner.rotations) < n:
        planner.add(lambda t0, span: energy[t0:t0 + span].mean() if t0 < n else energy[-1])
    lower = quaternion_to_axis_angle(planner.rotations[:n])
    return lower, settle(lower, planner.trans[:n], library)


def settle(lower: np.ndarray, trans: np.ndarray, library: LowerBodyLibrary) -> np.ndarray:
    """`trans` (T, 3) of the hips under `lower` (T, 9, 3) wandering no further than the
    capture did: its slow drift (DRIFT_S) taken out about the capture's centre, kept within
    the capture's range, then lowered or raised so the feet are on the floor."""
    fps = library.fps
    trans = trans.copy()
    trans[:, [0, 2]] -= smooth_frames(trans[:, [0, 2]], DRIFT_S * fps) - library.centre
    trans = np.clip(trans, library.translation_low, library.translation_high)
    return _on_floor(lower, trans, fps)


def legs_source(rig: str, whole_body: bool) -> str | None:
    """Where generated motion's hips and legs come from: "model" (a whole-body model's own,
    planted), "capture" (cut from the capture to go with the arms, for a model whose layout
    stops at the waist on the BEAT skeleton), or None (a layout legs cannot be added to)."""
    if whole_body:
        return "model"
    return "capture" if rig in LAYOUTS else None


def add_lower_body(motion: Motion, seed: int, library: LowerBodyLibrary | None = None) -> Motion:
    """`motion` (a `beat` upper body) with the hips and legs (JOINTS) after its joints,
    `root_translation` (metres about the standing hips), and in its meta the hips' rest
    height ("hips_height", metres) and the contact spans ("contacts", model frames)."""
    library = _library_for(motion, library)
    lower, trans = sample(library, arm_energy(motion), seed)
    lower, spans = plant_feet(lower, trans, motion.fps)
    return with_lower_body(motion, lower, trans, spans)


def plant(motion: Motion, library: LowerBodyLibrary | None = None) -> Motion:
    """`motion` (a `beat` Motion whose hips, legs and root translation a whole-body model
    made) with the hips and legs low-passed (MODEL_SMOOTH_S: the network's frame-to-frame
    wobble would read as feet that never stand still), the hips settled as the capture's are
    (`settle`) and the feet standing or stepping (`FootSteps`); the spans each foot stands
    and the hips' rest height go into its meta."""
    library = _library_for(motion, library)
    _check_whole_body(motion)
    sigma = MODEL_SMOOTH_S * motion.fps
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(lower_rotations(motion)))
    q = smooth_frames(q, sigma)
    lower = quaternion_to_axis_angle(q / np.linalg.norm(q, axis=-1, keepdims=True))
    trans = settle(lower, smooth_frames(motion.root_translation.astype(np.float64), sigma), library)
    lower, trans, spans = step_feet(lower, trans, motion.fps)
    return with_lower_body(upper_body(motion), lower, trans, spans)


def _library_for(motion: Motion, library: LowerBodyLibrary | None) -> LowerBodyLibrary:
    if motion.rig not in LAYOUTS:
        raise DiffshegError(f"the lower body is known for the {', '.join(LAYOUTS)} layout, not '{motion.rig}': "
                            "generate with upper_body_only")
    return _library_at(motion.fps, library)


def _library_at(fps: float, library: LowerBodyLibrary | None) -> LowerBodyLibrary:
    library = library or _bundled_library()
    if abs(library.fps - fps) > 1e-6:
        raise DiffshegError(f"the lower-body library runs at {library.fps:g} fps, the motion at {fps:g}")
    return library


@lru_cache(maxsize=1)
def _bundled_library() -> LowerBodyLibrary:
    """The library shipped with the package, read once per process (batches generate many takes)."""
    return LowerBodyLibrary.load()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core.lower_body",
                                     description="Build the lower-body library from a BEAT2 SMPL-X take.")
    parser.add_argument("--capture", required=True, type=Path, help="a BEAT2 smplxflame_30 .npz with trans")
    parser.add_argument("--out", type=Path, default=ASSET)
    args = parser.parse_args(argv)
    print(build(args.capture).save(args.out))
    return 0
