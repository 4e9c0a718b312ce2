"""The VMC protocol over OSC/UDP: each generated frame goes to VSeeFace, Warudo, VNyan or
any other VMC receiver ("marionette") as a performer's bone and blendshape messages.

Per frame: /VMC/Ext/OK (1: a model is loaded), /VMC/Ext/T (the frame's time in seconds),
/VMC/Ext/Root/Pos, one /VMC/Ext/Bone/Pos per humanoid bone (Unity HumanBodyBones name,
local position in metres, local rotation as a quaternion x, y, z, w, Unity axes), one
/VMC/Ext/Blend/Val per blendshape and a final /VMC/Ext/Blend/Apply. docs/live-vmc.md has the
mapping from our joints and channels to bones and blendshapes, for animators.

Only the 'beat' layout is sent (the bundled model's). SMPL-X models are refused: their face
is 100 expression coefficients with no ARKit or VRM blendshape to drive, and the package
has no SMPL-X rest skeleton for the bone positions VMC carries.
"""

from __future__ import annotations

import math
import socket
from dataclasses import dataclass
from functools import lru_cache, reduce

import numpy as np
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.udp_client import UDPClient

from .. import rigs
from ..bvh import beat_skeleton
from ..errors import DiffshegError
from ..lower_body import JOINTS as LEG_JOINTS
from ..rotations import axis_angle_to_matrix, convert
from ..vowels import VOWELS, vowel_weights

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 39539  # where VMC receivers listen unless told otherwise

# Each frame is about 7 kB of OSC (44 bones, 58 blendshapes), sent as several bundles of at
# most this many bytes. 1400 fits one Ethernet frame (MTU 1500 less the IP and UDP headers,
# with room left for VPN or PPPoE overhead), so a datagram is never split into IP fragments
# on a LAN: a lost packet on Wi-Fi then costs a few bones for one frame, where a lost
# fragment of one 7 kB datagram would cost the whole frame. It also stays under the fixed
# receive buffers (4-8 kB) some OSC receivers read into. Messages are independent in VMC,
# so a frame may span bundles; Blend/Apply goes last so that it follows every Blend/Val.
MAX_DATAGRAM = 1400

OK, TIME, ROOT, BONE = "/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos", "/VMC/Ext/Bone/Pos"
BLEND, APPLY = "/VMC/Ext/Blend/Val", "/VMC/Ext/Blend/Apply"

_FINGER_PARTS = ("Proximal", "Intermediate", "Distal")
_FINGERS = ("Thumb", "Index", "Middle", "Ring", "Little")

HUMAN_BODY_BONES: tuple[str, ...] = (
    "Hips", "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg",
    "LeftFoot", "RightFoot", "Spine", "Chest", "Neck", "Head",
    "LeftShoulder", "RightShoulder", "LeftUpperArm", "RightUpperArm",
    "LeftLowerArm", "RightLowerArm", "LeftHand", "RightHand",
    "LeftToes", "RightToes", "LeftEye", "RightEye", "Jaw",
) + tuple(f"{side}{finger}{part}" for side in ("Left", "Right")
          for finger in _FINGERS for part in _FINGER_PARTS) + ("UpperChest",)
"""The 55 bone names of Unity's HumanBodyBones, in enum order: the names VMC bones go by."""

VRM_PRESETS: tuple[str, ...] = ("Blink_L", "Blink_R") + VOWELS
"""VRM 0.x blendshape presets derived from the ARKit channels (`preset_weights`)."""

NAME_STYLES = ("pascal", "arkit")


def _beat_side(side: str) -> list[tuple[str, str, str]]:
    """(Unity bone, its Unity parent, the BEAT joint at that bone) for one arm and hand."""
    rows = [(f"{side}Shoulder", "UpperChest", f"{side}Shoulder"),
            (f"{side}UpperArm", f"{side}Shoulder", f"{side}Arm"),
            (f"{side}LowerArm", f"{side}UpperArm", f"{side}ForeArm"),
            (f"{side}Hand", f"{side}LowerArm", f"{side}Hand")]
    for finger, beat_finger in zip(_FINGERS, ("Thumb", "Index", "Middle", "Ring", "Pinky")):
        parent = f"{side}Hand"
        for k, part in enumerate(_FINGER_PARTS, start=1):
            bone = f"{side}{finger}{part}"
            rows.append((bone, parent, f"{side}Hand{beat_finger}{k}"))
            parent = bone
    return rows


BEAT_BONES: tuple[tuple[str, str | None, str], ...] = (
    ("Hips", None, "Hips"),
    ("Spine", "Hips", "Spine"),
    ("Chest", "Spine", "Spine1"),
    ("UpperChest", "Chest", "Spine3"),
    ("Neck", "UpperChest", "Neck"),
    ("Head", "Neck", "Head"),
    *_beat_side("Left"), *_beat_side("Right"),
)
"""(Unity bone, Unity parent, BEAT joint) for every bone of the upper body sent, parents first.

A Unity bone's rotation is the product of the BEAT rotations on the path from its Unity
parent's joint (excluded) down to its own joint (included), so joints Unity lacks fold
into the bone below them: Spine2 into UpperChest, Neck1 into Head, the metacarpals
HandIndex into the index and thumb proximals (BEAT hangs the thumb on HandIndex),
HandRing into the ring proximal, HandRing and HandPinky into the little proximal. The
folded bone then points where BEAT's chain points. Joints the model does not move (Hips,
Spine1-3, Head) count as identity: the model's rotations are relative to the T-pose with
them at rest. Eyes and jaw are not sent; the receiver keeps its own, and its own legs
where the frames have none (upper body only)."""

LEG_BONES: tuple[tuple[str, str, str], ...] = tuple(
    row for side in ("Left", "Right") for row in (
        (f"{side}UpperLeg", "Hips", f"{side}UpLeg"), (f"{side}LowerLeg", f"{side}UpperLeg", f"{side}Leg"),
        (f"{side}Foot", f"{side}LowerLeg", f"{side}Foot"), (f"{side}Toes", f"{side}Foot", f"{side}ToeBase")))
"""(Unity bone, Unity parent, BEAT joint) of the legs, sent when the frames have the lower
body (lower_body.JOINTS after the layout's joints): then the Hips turn as its Hips joint
does, and stand where its root translation puts them (BEAT's RightForeFoot folds into
the toes)."""


@dataclass(frozen=True)
class _BeatRig:
    """Per sent bone: the layout joints whose rotations multiply into it (index J, one past
    the layout's joints, stands for identity and pads shorter paths) and its local rest
    position in metres, Unity axes."""

    bones: tuple[str, ...]
    paths: np.ndarray  # (B, L) int
    positions: np.ndarray  # (B, 3)


def _path(parents: list[int], names: list[str], top: str | None, joint: str) -> list[str]:
    """BEAT joints from just below `top` down to `joint` (root first)."""
    chain, k = [], names.index(joint)
    while k >= 0 and names[k] != top:
        chain.append(names[k])
        k = parents[k]
    if top is not None and k < 0:
        raise DiffshegError(f"BEAT joint '{top}' is not above '{joint}' in the skeleton")
    return chain[::-1]


def _mirror_x_position(p: np.ndarray) -> np.ndarray:
    """A BEAT vector in Unity axes: BEAT's +X is the character's left, Unity's its right."""
    return p * np.array([-1.0, 1.0, 1.0])


@lru_cache(maxsize=2)
def _beat_rig(legs: bool = False) -> _BeatRig:
    skeleton = beat_skeleton()
    names, parents = skeleton.joint_names, skeleton.parents
    rest = np.zeros((len(names), 3))
    for k, parent in enumerate(parents):  # parents come before children in a BVH
        rest[k] = skeleton.offsets[k] + (rest[parent] if parent >= 0 else 0.0)
    rows = BEAT_BONES + (LEG_BONES if legs else ())
    by_unity = {bone: joint for bone, _, joint in rows}
    joints = rigs.BEAT_JOINTS + (LEG_JOINTS if legs else ())
    paths, positions = [], []
    for bone, parent, joint in rows:
        top = by_unity[parent] if parent else None
        paths.append([joints.index(j) for j in _path(parents, names, top, joint) if j in joints])
        # the Hips stand on the floor: as high above the root as the lowest joint is below them
        origin = rest[names.index(top)] if top else np.array([0.0, rest[:, 1].min(), 0.0])
        positions.append(_mirror_x_position(rest[names.index(joint)] - origin) / 100.0)
    width = max(len(p) for p in paths)
    padded = np.array([p + [len(joints)] * (width - len(p)) for p in paths], dtype=int)
    return _BeatRig(tuple(b for b, _, _ in rows), padded, np.array(positions))


def unity_rotations(rotations: np.ndarray) -> np.ndarray:
    """(47, 3) BEAT axis-angle rotations -> (B, 4) local quaternions (x, y, z, w) in Unity
    axes of the bones in BEAT_BONES, folded joints multiplied in; (56, 3) with the lower
    body after them (lower_body.JOINTS) -> those of BEAT_BONES and LEG_BONES.

    Unity's axes are BEAT's mirrored in X (M = diag(-1, 1, 1)). A rotation R seen through
    a mirror is M R M: the rotation by -angle about M axis = (-ax, ay, az), which is the
    rotation by +angle about (ax, -ay, -az). So the quaternion (x, y, z, w) becomes
    (x, -y, -z, w). Unity's quaternion algebra is the usual Hamilton one (being
    left-handed changes how its axes are drawn, not the formulas), so this is the value a
    Transform's localRotation takes.
    """
    rig = _beat_rig(len(rotations) > len(rigs.BEAT_JOINTS))
    matrices = np.concatenate([axis_angle_to_matrix(rotations), np.eye(3)[None]])
    composed = reduce(np.matmul, (matrices[rig.paths[:, k]] for k in range(rig.paths.shape[1])))
    w, x, y, z = np.moveaxis(convert(composed, "matrix", "quaternion"), -1, 0)
    return np.stack([x, -y, -z, w], axis=-1)


def blendshape_names(style: str) -> tuple[str, ...]:
    """The ARKit channel names as sent: 'pascal' (JawOpen, EyeBlinkLeft), as Perfect Sync
    avatars made with HANA_Tool or from the VRoid Perfect Sync models name their blendshape
    clips, or 'arkit' (jawOpen, eyeBlinkLeft) for avatars whose clips keep Apple's
    spelling. The VMC specification warns that blendshape names are case-sensitive since
    UniVRM made them so; only lenient receivers (those built on EVMC4U) ignore case."""
    if style not in NAME_STYLES:
        raise DiffshegError(f"unknown blendshape name style {style!r}: choose 'pascal' "
                            "(JawOpen, for Perfect Sync avatars) or 'arkit' (jawOpen)")
    if style == "arkit":
        return rigs.ARKIT51
    return tuple(n[0].upper() + n[1:] for n in rigs.ARKIT51)


def preset_weights(face: np.ndarray) -> np.ndarray:
    """The VRM 0.x presets Blink_L, Blink_R, A, I, U, E, O from 51 ARKit weights (0..1).
    Blinks are eyeBlinkLeft / eyeBlinkRight (ARKit's Left is the face's own left, as VRM's
    _L); the vowels are `vowels.vowel_weights`, as the add-on drives VRoid's and Ready
    Player Me's vowel keys, so they add up to at most one full vowel."""
    face = np.clip(np.asarray(face, dtype=np.float64), 0.0, 1.0)
    blinks = face[[rigs.ARKIT51.index("eyeBlinkLeft"), rigs.ARKIT51.index("eyeBlinkRight")]]
    return np.concatenate([blinks, vowel_weights(face[None], rigs.ARKIT51)[0]])


def parse_address(text: str) -> tuple[str, int]:
    """'HOST:PORT', ':PORT' or 'PORT' -> (host, port); the host defaults to 127.0.0.1 and
    an IPv6 host goes in brackets ('[::1]:39539')."""
    raw_host, _, port_text = text.strip().rpartition(":")
    bracketed = raw_host.startswith("[") and raw_host.endswith("]")
    host = raw_host[1:-1] if bracketed else raw_host
    fix = f"give the VMC receiver as HOST:PORT, e.g. {DEFAULT_HOST}:{DEFAULT_PORT}, or just the port"
    if not (port_text.isascii() and port_text.isdigit()) or not 1 <= int(port_text) <= 65535:
        raise DiffshegError(f"VMC address {text!r}: the port must be a whole number from 1 to 65535; {fix}")
    if any(c.isspace() or c in "[]" for c in host) or (":" in host and not bracketed):
        raise DiffshegError(f"VMC address {text!r}: the host is not valid (an IPv6 host goes in "
                            f"brackets, [::1]:{DEFAULT_PORT}); {fix}")
    return host or DEFAULT_HOST, int(port_text)


def _message(address: str, *args: str | float | int) -> OscMessage:
    builder = OscMessageBuilder(address=address)
    for arg in args:
        builder.add_arg(arg)
    return builder.build()


def _bundles(messages: list[OscMessage], limit: int = MAX_DATAGRAM) -> list[OscBundle]:
    """Messages in order, packed greedily into bundles of at most `limit` bytes (a bundle
    is a 16-byte header, then each message with a 4-byte length in front)."""
    bundles, builder, size = [], None, 0
    for msg in messages:
        if builder is not None and size + 4 + msg.size > limit:
            bundles.append(builder.build())
            builder = None
        if builder is None:
            builder, size = OscBundleBuilder(IMMEDIATELY), 16
        builder.add_content(msg)
        size += 4 + msg.size
    if builder is not None:
        bundles.append(builder.build())
    return bundles


def _resolve(host: str, port: int) -> tuple[str, socket.AddressFamily]:
    """The host's numeric address, looked up once rather than at every datagram."""
    try:
        family, _, _, _, sockaddr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
    except OSError as exc:
        raise DiffshegError(f"cannot find the VMC receiver's host '{host}' ({exc}): give its IP "
                            f"address, e.g. {DEFAULT_HOST} for this computer") from None
    return sockaddr[0], family


class VmcSender:
    """Sends frames of a 'beat' layout motion to one VMC receiver.

    A failed send (no route to the receiver's network, a full socket buffer) never raises:
    a live session must not stop because the avatar app is away. It is counted in
    `errors`, and `last_error` says what went wrong and what to check; the session reports
    them. A receiver that is not running is not an error: UDP cannot tell.
    """

    def __init__(self, host: str, port: int, layout: rigs.Layout, *,
                 names: str = "pascal", presets: bool = True, legs: bool = False):
        if layout.name != rigs.BEAT.name:
            raise DiffshegError(
                f"VMC output needs the 'beat' layout (the bundled model's), not '{layout.name}': "
                "its face channels are not ARKit blendshapes an avatar app could show; "
                "save that motion to a file instead")
        if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
            raise DiffshegError(f"VMC port {port!r} is not valid: give a whole number from 1 to 65535 "
                                f"(receivers listen on {DEFAULT_PORT} by default)")
        self.layout = layout
        self.legs = legs  # frames carry the lower body (lower_body.JOINTS) and the hips' translation
        self.host, self.port = host, port
        self.presets = presets
        self.blend_names = blendshape_names(names) + (VRM_PRESETS if presets else ())
        address, family = _resolve(host, port)
        self._client: UDPClient | None = UDPClient(address, port, family=family)
        self._ok = _message(OK, 1)
        self._root = _message(ROOT, "root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        self.frames_sent = 0
        self.errors = 0  # datagrams that could not be sent
        self.last_error: str | None = None

    def __enter__(self) -> VmcSender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def send(self, rotations: np.ndarray, face: np.ndarray, t: float,
             root_translation: np.ndarray | None = None) -> None:
        """Send one frame: (J, 3) axis-angle rotations and (C,) face weights of the layout,
        `t` the frame's time in seconds; with `legs`, the rotations go on with the lower
        body's and `root_translation` (3,) is the hips' (metres, lower_body's axes)."""
        if self._client is None:
            raise DiffshegError("this VMC sender is closed: make a new VmcSender to send again")
        for bundle in _bundles(self._messages(rotations, face, t, root_translation)):
            try:
                self._client.send(bundle)
            except OSError as exc:
                self.errors += 1
                self.last_error = (f"could not send to the VMC receiver at {self.host}:{self.port} "
                                   f"({exc.strerror or exc}): check the address and that this "
                                   "computer can reach the one running the avatar app")
        self.frames_sent += 1

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def _messages(self, rotations: np.ndarray, face: np.ndarray, t: float,
                  root_translation: np.ndarray | None = None) -> list[OscMessage]:
        rotations, face, root = self._checked(rotations, face, t, root_translation)
        rig = _beat_rig(self.legs)
        quats = unity_rotations(rotations)
        positions = rig.positions.copy()
        if root is not None:
            positions[rig.bones.index("Hips")] += _mirror_x_position(root)
        weights = np.clip(face, 0.0, 1.0)
        if self.presets:
            weights = np.concatenate([weights, preset_weights(face)])
        return ([self._ok, _message(TIME, float(t)), self._root]
                + [_message(BONE, bone, *map(float, p), *map(float, q))
                   for bone, p, q in zip(rig.bones, positions, quats)]
                + [_message(BLEND, name, float(v)) for name, v in zip(self.blend_names, weights)]
                + [_message(APPLY)])

    def _checked(self, rotations: np.ndarray, face: np.ndarray, t: float, root_translation: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        rotations = np.asarray(rotations, dtype=np.float64)
        face = np.asarray(face, dtype=np.float64)
        joints, channels = len(self.layout.joint_names) + (len(LEG_JOINTS) if self.legs else 0), len(self.layout.face_names)
        what = f"the '{self.layout.name}' layout" + (" with legs" if self.legs else "")
        if rotations.shape != (joints, 3):
            raise DiffshegError(f"a VMC frame needs ({joints}, 3) rotations for {what}, got shape {rotations.shape}")
        root = None
        if self.legs:
            if root_translation is None or np.shape(root_translation) != (3,):
                raise DiffshegError("a VMC frame with legs needs the hips' translation (3 numbers, metres), got "
                                    f"{'none' if root_translation is None else f'shape {np.shape(root_translation)}'}")
            root = np.asarray(root_translation, dtype=np.float64)
            if not np.all(np.isfinite(root)):
                raise DiffshegError("a VMC frame holds a NaN or infinite hips translation")
        if face.shape != (channels,):
            raise DiffshegError(f"a VMC frame needs {channels} face weights for the "
                                f"'{self.layout.name}' layout, got shape {face.shape}")
        if not (np.all(np.isfinite(face)) and math.isfinite(t)):
            raise DiffshegError("a VMC frame holds NaN or infinite face weights or time")
        return rotations, face, root
