"""The lower body: hips (rotation and translation) and legs under the generated upper body,
with the feet planted.

The diffusion model makes the upper body and face (its layouts stop at the waist). Below
it, this module adds what a standing talker's hips and legs do: weight shifts, sway and
turns, learnt from the real full-body capture of BEAT2 take 2_scott_0_1_1 (SMPL-X, with
root translation) and stored beside the model (`assets/lower_body.npz`, a few thousand
numbers). The flow is one way, as DiffSHEG's expression-to-gesture flow: the upper body
the model made drives the lower body, never the reverse, so the upper body and face are
the model's to the bit.

The lower body is cut from that capture as the teacher's gestures are cut from the BEAT
take: motion matching. The take is built segment by segment (1.5-4 s, drawn with the
generation's seed); each segment is the stretch of the capture (less its last 20 s, held
out as the gesture material is) whose arm energy (wrist speed, layout-free, `kinematics`)
best matches the generated arms' over the same time and whose first pose best continues
the last one, chosen at random among the few best; segments are cross-faded over half a
second and the hips' translation continues across each join. So real weight shifts,
sways, turns and steps come with the gestures that go with them.

Feet: on the BEAT skeleton's legs (the canonical body: x left, y up, z forward; legs
straight down at rest) each foot is in contact while it is low and slow; within a contact
span the ankle's position and the foot's orientation are pinned (eased in and out over a
few frames) and each leg is solved again with two-bone IK, so a contact foot does not
slide. The hips' translation is kept within the capture's range.
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from .errors import DiffshegError
from .kinematics import rest_offsets, wrist_positions
from .leg_ik import pin_goals, two_bone
from .motion import Motion, smooth_frames
from .rotations import (axis_angle_to_quaternion, convert, matrix_to_axis_angle, quaternion_conjugate,
                        quaternion_product, quaternion_sequence_continuous, quaternion_to_axis_angle,
                        resample_positions, resample_weights, slerp_resample)

JOINTS = ("Hips", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
          "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase")
"""The joints added to a `beat` Motion, in its BEAT skeleton names."""
SMPLX_INDEX = (0, 2, 5, 8, 11, 1, 4, 7, 10)  # pelvis, right hip, knee, ankle, foot, then left
LEGS = {"right": ("RightUpLeg", "RightLeg", "RightFoot"), "left": ("LeftUpLeg", "LeftLeg", "LeftFoot")}
ASSET = Path(__file__).with_name("assets") / "lower_body.npz"
LAYOUTS = ("beat",)

HELD_OUT_S = 20.0    # the capture's last seconds, left out of the fit (as the gesture material)
SEGMENT = (1.5, 4.0)  # seconds: the shortest and longest segment cut from the capture
FADE_S = 0.5         # seconds of cross-fade between segments
CHOICES = 4          # a segment is drawn among this many best matches
DRIFT_S = 4.0        # Gaussian sigma (s) of the hips' slow drift across joins, taken out
GROUND_S = 0.25     # Gaussian sigma (s) of the lowest foot point the body is lowered onto the floor by
TRAVEL_M = 0.15      # metres a segment's hips travel that cost as much as a poor energy match
ENERGY_S = 1.0       # Gaussian sigma of the arms' energy the segments are matched on
CONTACT_HEIGHT = 0.03   # m above the floor a contact foot's sole may be
CONTACT_SPEED = 0.15    # m/s a contact foot's ankle may move before pinning
EASE = 3                # frames over which a pin eases in and out
MIN_CONTACT = 4         # frames: a shorter low, slow stretch is a step, not a contact
REACH_SLACK = 0.004     # m a pinned ankle may lie beyond the straight leg (IK stops 4 mm short)


@lru_cache(maxsize=None)
def _offsets() -> dict[str, np.ndarray]:
    """The BEAT skeleton's joint offsets in metres (the canonical body)."""
    return {name: offset / 100.0 for name, offset in rest_offsets("beat").items()}


def _hips_height() -> float:
    """Rest height of the hips above the floor (the sole, at the fore-foot) in metres."""
    return float(-sum(_offsets()[j][1] for j in ("RightLeg", "RightFoot", "RightForeFoot")))


def canonical_leg_length(hips_height: float) -> float:
    """Thigh and shin (hip to ankle) of the canonical body in proportion to one whose hips
    rest `hips_height` metres above the floor (a Motion's meta "hips_height")."""
    off = _offsets()
    return float(hips_height * (np.linalg.norm(off["RightLeg"]) + np.linalg.norm(off["RightFoot"])) / _hips_height())


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


# ---------------------------------------------------------------- the capture

def read_capture(path: Path, fps: float) -> tuple[np.ndarray, np.ndarray, Motion]:
    """A BEAT2 SMPL-X take as (T, 9, 3) lower-body rotations, (T, 3) hips translation
    (metres, canonical axes, about the standing hips) and its upper body as a Motion, at
    `fps`, turned so that the speaker faces +z on average."""
    from .rigs import SMPLX_JOINTS

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


def _apply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors `v` (..., 3) by quaternions `q` (..., 4), broadcast."""
    v4 = np.concatenate([np.zeros(np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (1,)),
                         np.broadcast_to(v, np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (3,))], axis=-1)
    return quaternion_product(quaternion_product(q, v4), quaternion_conjugate(q))[..., 1:]


# ---------------------------------------------------------------- the canonical body's legs

def _world(lower: np.ndarray, trans: np.ndarray) -> dict:
    """World rotations (T, 4) and positions (T, 3) of every lower joint, the fore-foot
    (sole) and the toe's end, on the canonical body standing on the floor y = 0."""
    off = _offsets()
    q = axis_angle_to_quaternion(lower)
    hips = q[:, JOINTS.index("Hips")]
    trans = trans + np.array([0.0, _hips_height(), 0.0])  # the floor at y = 0
    out = {"Hips": (hips, trans)}
    for side, prefix in (("right", "Right"), ("left", "Left")):
        rot, pos = hips, trans
        for joint in (f"{prefix}UpLeg", f"{prefix}Leg", f"{prefix}Foot"):
            pos = pos + _apply(rot, off[joint])
            rot = quaternion_product(rot, q[:, JOINTS.index(joint)])
            out[joint] = (rot, pos)
        sole = pos + _apply(rot, off[f"{prefix}ForeFoot"])
        toe_rot = quaternion_product(rot, q[:, JOINTS.index(f"{prefix}ToeBase")])
        toe = sole + _apply(rot, off[f"{prefix}ToeBase"])
        out[f"{prefix}Sole"] = (rot, sole)
        out[f"{prefix}ToeEnd"] = (toe_rot, toe + _apply(toe_rot, off[f"{prefix}ToeBaseEnd"]))
    return out


def foot_positions(lower: np.ndarray, trans: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{"right"/"left": ((T, 3) ankle, (T, 3) sole)} world positions on the canonical body."""
    return _feet(_world(lower, trans))


def _feet(world: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {side: (world[f"{p}Foot"][1], world[f"{p}Sole"][1]) for side, p in (("right", "Right"), ("left", "Left"))}


def contacts(lower: np.ndarray, trans: np.ndarray, fps: float) -> dict[str, list[tuple[int, int]]]:
    """Per foot, the [first, last] frame spans in which it is on the floor: its sole within
    CONTACT_HEIGHT of the floor (y = 0) and its ankle slower than CONTACT_SPEED."""
    return _contacts(_world(lower, trans), fps)


def _contacts(world: dict, fps: float) -> dict[str, list[tuple[int, int]]]:
    spans = {}
    for side, (ankle, sole) in _feet(world).items():
        speed = np.linalg.norm(np.diff(ankle, axis=0, prepend=ankle[:1]), axis=-1) * fps
        down = (sole[:, 1] < CONTACT_HEIGHT) & (speed < CONTACT_SPEED)
        spans[side] = [(a, b) for a, b in _runs(down) if b - a + 1 >= MIN_CONTACT]
    return spans


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2])]


def foot_skating(lower: np.ndarray, trans: np.ndarray, fps: float, height: float = 0.05,
                 slide: float = 0.025) -> float:
    """The foot-skating ratio (as SpeechAct and GMD report it): the share of frames in which a
    foot whose sole is below `height` m moves more than `slide` m per 1/30 s on the floor."""
    ratios = []
    for ankle, sole in foot_positions(lower, trans).values():
        step = np.linalg.norm(np.diff(sole[:, [0, 2]], axis=0), axis=-1) * fps / 30.0
        low = (sole[1:, 1] < height) & (sole[:-1, 1] < height)
        ratios.append(low & (step > slide))
    return float(np.mean(np.any(ratios, axis=0)))


def plant_feet(lower: np.ndarray, trans: np.ndarray, fps: float) -> tuple[np.ndarray, dict]:
    """`lower` with each contact foot's ankle and orientation pinned over its span (eased in
    and out over EASE frames) by two-bone IK on each leg (leg_ik); returns it and the spans
    pinned. A span is pinned where its foot stood in the middle of it; frames where the leg
    cannot reach that spot split it (the foot steps there)."""
    world = _world(lower, trans)
    spans = _contacts(world, fps)
    world = {name: (convert(q, "quaternion", "matrix"), pos) for name, (q, pos) in world.items()}
    off = _offsets()
    hips = world["Hips"][0]
    out, pinned = lower.copy(), {}
    for side, (up, knee, foot) in LEGS.items():
        thigh, shin = np.linalg.norm(off[knee]), np.linalg.norm(off[foot])
        (thigh_rot, hip), (shin_rot, knee_pos), (foot_rot, ankle) = world[up], world[knee], world[foot]
        pins = [(a, b, spot, foot_rot[(a + b) // 2]) for span in spans[side]
                for a, b, spot in _reachable(ankle, hip, span, thigh + shin + REACH_SLACK)]
        pinned[side] = [(a, b) for a, b, _, _ in pins]
        goal, goal_rot, _ = pin_goals(ankle, foot_rot, pins, EASE)
        turn, bend = two_bone(hip, knee_pos, ankle, goal, thigh, shin, hips[:, :, 0])
        thigh_rot, shin_rot = turn @ thigh_rot, turn @ bend @ shin_rot
        for joint, parent, rotation in ((up, hips, thigh_rot), (knee, thigh_rot, shin_rot), (foot, shin_rot, goal_rot)):
            out[:, JOINTS.index(joint)] = matrix_to_axis_angle(np.transpose(parent, (0, 2, 1)) @ rotation)
    return out, pinned


def _reachable(ankle: np.ndarray, hip: np.ndarray, span: tuple[int, int], reach: float
               ) -> list[tuple[int, int, np.ndarray]]:
    """(first, last, spot) pins within `span`: the ankle's median position there, split
    (and each part pinned anew) where the hip is further from it than the leg reaches."""
    todo, done = [span], []
    for _ in range(3):
        later = []
        for a, b in todo:
            spot = np.median(ankle[a:b + 1], axis=0)
            near = np.linalg.norm(spot - hip[a:b + 1], axis=-1) < reach
            if near.all():
                done.append((a, b, spot))
                continue
            later += [(a + x, a + y) for x, y in _runs(near) if y - x + 1 >= MIN_CONTACT]
        todo = later
    return sorted(done, key=lambda pin: pin[0])


# ---------------------------------------------------------------- generating

def sample(library: LowerBodyLibrary, energy: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, 9, 3) lower-body rotations and (T, 3) hips translation for the arms' `energy`
    (arm_energy of the take), cut from `library` with `seed`; the translation kept within
    the capture's range, then the body lowered or raised so its lowest foot is on the floor."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 29]))
    n, fps = len(energy), library.fps
    fade = int(round(FADE_S * fps))
    lengths = (int(SEGMENT[0] * fps), int(SEGMENT[1] * fps))
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(library.rotations))
    pose = library.rotations.reshape(len(q), -1)
    rotations, trans = np.zeros((0, len(JOINTS), 4)), np.zeros((0, 3))
    while len(rotations) < n:
        length = int(rng.integers(lengths[0], lengths[1] + 1))
        span = min(length + fade, len(q) - 1)
        t0 = max(0, len(rotations) - fade)
        want = energy[t0:t0 + span].mean() if t0 < n else energy[-1]
        starts = np.arange(len(q) - span)
        windows = np.convolve(library.energy, np.ones(span) / span, mode="valid")[:len(starts)]
        cost = np.abs(windows - want) / (library.energy.std() + 1e-9)
        # a talker mostly stands: a segment that walks off costs as much as a poor energy match
        travel = np.linalg.norm(library.translation[starts + span - 1][:, [0, 2]]
                                - library.translation[starts][:, [0, 2]], axis=1)
        cost = cost + travel / TRAVEL_M
        if len(rotations):
            last = quaternion_to_axis_angle(rotations[t0]).reshape(-1)
            cost = cost + np.linalg.norm(pose[starts] - last, axis=1) / 0.2
        best = np.argsort(cost)[:CHOICES]
        s0 = int(rng.choice(best))
        seg_q, seg_t = q[s0:s0 + span].copy(), library.translation[s0:s0 + span].copy()
        if len(rotations):
            seg_t[:, [0, 2]] += trans[t0, [0, 2]] - seg_t[0, [0, 2]]  # the hips go on from where they are
            w = np.linspace(0.0, 1.0, fade + 2)[1:-1][:, None]
            old_q, old_t = rotations[t0:], trans[t0:]
            overlap = len(old_q)
            flip = np.sign(np.sum(old_q * seg_q[:overlap], axis=-1, keepdims=True))
            blended = (1 - w[:overlap, :, None]) * old_q + w[:overlap, :, None] * seg_q[:overlap] * flip
            seg_q[:overlap] = blended / np.linalg.norm(blended, axis=-1, keepdims=True)
            seg_t[:overlap] = (1 - w[:overlap]) * old_t + w[:overlap] * seg_t[:overlap]
            rotations, trans = rotations[:t0], trans[:t0]
        rotations = np.concatenate([rotations, seg_q])
        trans = np.concatenate([trans, seg_t])
    # the hips wander no further than the capture did: slow drift taken out, then the range kept
    drift = smooth_frames(trans[:n, [0, 2]], DRIFT_S * fps) - library.translation[:, [0, 2]].mean(axis=0)
    trans = trans[:n].copy()
    trans[:, [0, 2]] -= drift
    lower = quaternion_to_axis_angle(rotations[:n])
    trans = np.clip(trans, library.translation_low, library.translation_high)
    # on the floor: segments stood a little higher or lower in the capture than its floor
    world = _world(lower, trans)
    lowest = np.min([world[f"{p}{point}"][1][:, 1] for p in ("Right", "Left") for point in ("Sole", "ToeEnd")], axis=0)
    trans[:, 1] -= smooth_frames(lowest[:, None], GROUND_S * fps)[:, 0]
    return lower, trans


def add_lower_body(motion: Motion, seed: int, library: LowerBodyLibrary | None = None) -> Motion:
    """`motion` (a `beat` upper body) with the hips and legs (JOINTS) after its joints,
    `root_translation` (metres about the standing hips), and in its meta the hips' rest
    height ("hips_height", metres) and the contact spans ("contacts", model frames)."""
    if motion.rig not in LAYOUTS:
        raise DiffshegError(f"the lower body is known for the {', '.join(LAYOUTS)} layout, not '{motion.rig}': "
                            "generate with upper_body_only")
    library = library or _bundled_library()
    if abs(library.fps - motion.fps) > 1e-6:
        raise DiffshegError(f"the lower-body library runs at {library.fps:g} fps, the motion at {motion.fps:g}")
    lower, trans = sample(library, arm_energy(motion), seed)
    lower, spans = plant_feet(lower, trans, motion.fps)
    return replace(motion, joint_names=list(motion.joint_names) + list(JOINTS),
                   rotations=np.concatenate([motion.rotations, lower.astype(motion.rotations.dtype)], axis=1),
                   root_translation=trans.astype(np.float32),
                   meta={**motion.meta, "hips_height": _hips_height(),
                         "contacts": {side: [list(s) for s in v] for side, v in spans.items()}})


@lru_cache(maxsize=1)
def _bundled_library() -> LowerBodyLibrary:
    """The library shipped with the package, read once per process (batches generate many takes)."""
    return LowerBodyLibrary.load()


def upper_body(motion: Motion) -> Motion:
    """`motion` without the lower body (its model layout's joints only)."""
    keep = [i for i, n in enumerate(motion.joint_names) if n not in JOINTS]
    return replace(motion, joint_names=[motion.joint_names[i] for i in keep], rotations=motion.rotations[:, keep],
                   root_translation=None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core.lower_body",
                                     description="Build the lower-body library from a BEAT2 SMPL-X take.")
    parser.add_argument("--capture", required=True, type=Path, help="a BEAT2 smplxflame_30 .npz with trans")
    parser.add_argument("--out", type=Path, default=ASSET)
    args = parser.parse_args(argv)
    print(build(args.capture).save(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
