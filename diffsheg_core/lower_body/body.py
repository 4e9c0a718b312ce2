"""The canonical body's legs: the BEAT skeleton's hips and legs (x left, y up, z forward;
legs straight down at rest) standing on the floor y = 0, where its joints, ankles and soles
are (`foot_positions`), when a foot is on the floor (`contacts`: low and slow) and what legs
are measured by (`figures`, `feet_figures`, `ankle_figures`); and a Motion's lower body
taken out or put in (`lower_rotations`, `with_lower_body`, `upper_body`).
numpy only: it runs inside Blender.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from ..errors import DiffshegError
from ..kinematics import rest_offsets
from ..motion import Motion
from ..rigs import BEAT_LOWER_JOINTS
from ..rotations import axis_angle_to_quaternion, quaternion_conjugate, quaternion_product

JOINTS = BEAT_LOWER_JOINTS
"""The joints added to a `beat` Motion, in its BEAT skeleton names."""
LEGS = {"right": ("RightUpLeg", "RightLeg", "RightFoot"), "left": ("LeftUpLeg", "LeftLeg", "LeftFoot")}

CONTACT_HEIGHT = 0.03   # m above the floor a contact foot's sole may be
CONTACT_SPEED = 0.15    # m/s a contact foot's ankle may move before pinning
MIN_CONTACT = 4         # frames: a shorter low, slow stretch is a step, not a contact


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


def _apply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors `v` (..., 3) by quaternions `q` (..., 4), broadcast."""
    v4 = np.concatenate([np.zeros(np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (1,)),
                         np.broadcast_to(v, np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (3,))], axis=-1)
    return quaternion_product(quaternion_product(q, v4), quaternion_conjugate(q))[..., 1:]


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
    return {side: [(a, b) for a, b in _runs(_down(ankle, sole, fps)) if b - a + 1 >= MIN_CONTACT]
            for side, (ankle, sole) in _feet(world).items()}


def _down(ankle: np.ndarray, sole: np.ndarray, fps: float, before: np.ndarray | None = None) -> np.ndarray:
    """(T,) whether the foot is on the floor: its sole within CONTACT_HEIGHT of it and its
    ankle slower than CONTACT_SPEED since the frame before (`before`: the ankle then, (1, 3);
    None, the first frame counts as still)."""
    speed = np.linalg.norm(np.diff(ankle, axis=0, prepend=ankle[:1] if before is None else before), axis=-1) * fps
    return (sole[:, 1] < CONTACT_HEIGHT) & (speed < CONTACT_SPEED)


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


def figures(lower: np.ndarray, trans: np.ndarray, fps: float) -> dict[str, float]:
    """What legs are measured by against the capture: the hips' sway speed (m/s, over the
    floor) and range (m, the wider of x and z), the knees' bend range (degrees, both knees'
    mean) and the foot-skating ratio."""
    knees = np.degrees(np.linalg.norm(lower[:, [JOINTS.index("RightLeg"), JOINTS.index("LeftLeg")]], axis=-1))
    return {"sway speed": float(np.linalg.norm(np.diff(trans[:, [0, 2]], axis=0), axis=-1).mean() * fps),
            "sway range": float(np.ptp(trans[:, [0, 2]], axis=0).max()),
            "knee range": float(np.ptp(knees, axis=0).mean()),
            "skating": foot_skating(lower, trans, fps)}


FEET_LOW = 0.02        # m above its lowest height an ankle counts as low (SpeechAct's skating measure)
FEET_STILL = 0.05      # m/s under which a low ankle counts as in contact
FEET_MOVE = 0.15       # m/s over which an ankle counts as moving (a step or a glide)


def feet_figures(lower: np.ndarray, trans: np.ndarray, fps: float) -> dict[str, float]:
    """`ankle_figures` of the canonical body's ankles."""
    return ankle_figures([ankle for ankle, _ in foot_positions(lower, trans).values()], fps)


def ankle_figures(ankles: list[np.ndarray], fps: float, up: int = 1) -> dict[str, float]:
    """What a viewer sees of the feet, from each ankle's (T, 3) world positions in metres
    (`up`: the vertical axis, 1 here, 2 in Blender), averaged over the feet: `skating` the
    mean horizontal speed (m/s) of an ankle over the frames it is within FEET_LOW of its
    lowest height (SpeechAct's measure), `contact` the share of frames it is that low and
    slower than FEET_STILL, `moves per minute` the stretches it moves faster than
    FEET_MOVE, and `lift` the median of those moves' highest ankle point above its lowest (m)."""
    skating, contact, moves, lifts = [], [], 0, []
    floor = [axis for axis in range(3) if axis != up]
    for ankle in ankles:
        height = ankle[:, up] - ankle[:, up].min()
        step = np.diff(ankle, axis=0, prepend=ankle[:1]) * fps
        across, speed = np.linalg.norm(step[:, floor], axis=-1), np.linalg.norm(step, axis=-1)
        low = height < FEET_LOW
        skating.append(float(across[low].mean()) if low.any() else 0.0)
        contact.append(float(np.mean(low & (speed < FEET_STILL))))
        runs = _runs(across > FEET_MOVE)
        moves += len(runs)
        lifts += [float(height[max(a - 1, 0):b + 2].max()) for a, b in runs]
    return {"skating": float(np.mean(skating)), "contact": float(np.mean(contact)),
            "moves per minute": moves / (len(ankles[0]) / fps / 60.0),
            "lift": float(np.median(lifts)) if lifts else 0.0}


def foot_yaw(lower: np.ndarray, trans: np.ndarray) -> dict[str, np.ndarray]:
    """Per foot (T,) how far its toes turn out from the hips' facing, in degrees about the
    vertical (positive: out, away from the other foot; negative: in, pigeon-toed): the angle
    on the floor between the foot's forward (ankle-side sole to toe base, the foot bone's +z)
    and the pelvis's forward (its +z), on the canonical body."""
    world = _world(lower, trans)
    ahead = np.array([0.0, 0.0, 1.0])
    hips = _apply(world["Hips"][0], ahead)
    out = {}
    for side, prefix, outward in (("right", "Right", -1.0), ("left", "Left", 1.0)):
        foot = _apply(world[f"{prefix}Foot"][0], ahead)
        # signed turn about +y (towards +x, the body's left) from the hips' forward to the foot's
        turn = np.arctan2(hips[:, 2] * foot[:, 0] - hips[:, 0] * foot[:, 2],
                          hips[:, 0] * foot[:, 0] + hips[:, 2] * foot[:, 2])
        out[side] = np.degrees(outward * turn)
    return out


def _lowest(world: dict) -> np.ndarray:
    """(T,) the height of the lowest foot point (either sole or toe end)."""
    return np.min([world[f"{p}{point}"][1][:, 1] for p in ("Right", "Left") for point in ("Sole", "ToeEnd")], axis=0)


# ---------------------------------------------------------------- a Motion's lower body

def lower_rotations(motion: Motion) -> np.ndarray:
    """(T, 9, 3) the rotations of `motion`'s hips and legs (JOINTS, in that order), float64."""
    return motion.rotations[:, [motion.joint_names.index(j) for j in JOINTS]].astype(np.float64)


def with_lower_body(motion: Motion, lower: np.ndarray, trans: np.ndarray, spans: dict) -> Motion:
    """`motion` with (T, 9, 3) `lower` after its joints, `trans` as its root translation and
    the contact `spans` and the hips' rest height in its meta."""
    return replace(motion, joint_names=list(motion.joint_names) + list(JOINTS),
                   rotations=np.concatenate([motion.rotations, lower.astype(motion.rotations.dtype)], axis=1),
                   root_translation=trans.astype(np.float32),
                   meta={**motion.meta, "hips_height": _hips_height(),
                         "contacts": {side: [list(s) for s in v] for side, v in spans.items()}})


def upper_body(motion: Motion) -> Motion:
    """`motion` without the lower body (its model layout's joints only)."""
    keep = [i for i, n in enumerate(motion.joint_names) if n not in JOINTS]
    return replace(motion, joint_names=[motion.joint_names[i] for i in keep], rotations=motion.rotations[:, keep],
                   root_translation=None)


def _check_whole_body(motion: Motion) -> None:
    """Planting needs what a whole-body model makes: the hips, legs and root translation."""
    if motion.root_translation is None or not set(JOINTS) <= set(motion.joint_names):
        raise DiffshegError("planting the feet needs a motion with the hips, legs and root translation "
                            "of a whole-body model")
