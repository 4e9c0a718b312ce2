"""The VMC sender (diffsheg_core.live.vmc): real UDP on 127.0.0.1 to a real python-osc
receiver, frames of the bundled model's output, the BEAT -> Unity axis change checked on
the geometry, the metacarpals folded into the finger bones, addresses parsed."""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import numpy as np
import pytest
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_server import BlockingOSCUDPServer

from diffsheg_core import generate, rigs
from diffsheg_core.bvh import beat_skeleton
from diffsheg_core.errors import DiffshegError
from diffsheg_core.live import vmc
from diffsheg_core.live.vmc import VmcSender, parse_address
from diffsheg_core.rotations import axis_angle_to_matrix, axis_angle_to_quaternion, convert

SAMPLE = Path(vmc.__file__).resolve().parents[1] / "samples" / "sample_speech.wav"
MIRROR = np.diag([-1.0, 1.0, 1.0])  # BEAT axes -> Unity axes: +X is the character's left in BEAT, its right in Unity
ADDRESSES = {vmc.OK, vmc.TIME, vmc.ROOT, vmc.BONE, vmc.BLEND, vmc.APPLY}
PASCAL = [n[0].upper() + n[1:] for n in rigs.ARKIT51]
N_JOINTS, N_FACE = len(rigs.BEAT_JOINTS), len(rigs.ARKIT51)


class Receiver:
    """A python-osc server on a free port of 127.0.0.1, in a thread, recording every message
    in arrival order. A blocking server handles datagrams one after another in one thread, so
    the order recorded is the order they came in (a threading server would race them)."""

    def __init__(self):
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(self._record)
        self.messages: list[tuple[str, tuple]] = []
        self._arrived = threading.Condition()
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), dispatcher)
        self.port = self.server.server_address[1]
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def _record(self, address: str, *args) -> None:
        with self._arrived:
            self.messages.append((address, args))
            self._arrived.notify_all()

    def frames(self, count: int) -> list[list[tuple[str, tuple]]]:
        """The first `count` frames (each starts with /VMC/Ext/OK), waiting for the last Apply."""
        with self._arrived:
            done = self._arrived.wait_for(
                lambda: sum(a == vmc.APPLY for a, _ in self.messages) >= count, timeout=5.0)
        assert done, f"{count} frames did not arrive within 5 s"
        starts = [i for i, (a, _) in enumerate(self.messages) if a == vmc.OK]
        return [self.messages[a:b] for a, b in zip(starts, starts[1:] + [len(self.messages)])][:count]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver():
    r = Receiver()
    yield r
    r.close()


@pytest.fixture(scope="module")
def motion():
    return generate(str(SAMPLE), upper_body_only=True)  # live sends the upper body


def send_frames(receiver: Receiver, rotations, faces, roots=None, **options) -> list[list[tuple[str, tuple]]]:
    """Send frames at a live pace (each one received before the next goes) and return them."""
    with VmcSender("127.0.0.1", receiver.port, rigs.BEAT, **options) as sender:
        for i, (rot, face) in enumerate(zip(rotations, faces)):
            sender.send(rot, face, i / 15.0, None if roots is None else roots[i])
            receiver.frames(i + 1)
        assert (sender.errors, sender.frames_sent) == (0, len(rotations))
    return receiver.frames(len(rotations))


def bones_of(frame) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Bone name -> (local position, Unity quaternion x, y, z, w) of a received frame."""
    return {args[0]: (np.array(args[1:4]), np.array(args[4:8])) for a, args in frame if a == vmc.BONE}


def unity_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """The rotation a Unity quaternion (x, y, z, w) applies (Unity's Quaternion * Vector3)."""
    x, y, z, w = q_xyzw
    return convert(np.array([w, x, y, z]), "quaternion", "matrix")


def test_human_body_bones_are_unity_s_55():
    assert len(vmc.HUMAN_BODY_BONES) == len(set(vmc.HUMAN_BODY_BONES)) == 55
    assert vmc.HUMAN_BODY_BONES[:3] == ("Hips", "LeftUpperLeg", "RightUpperLeg")
    assert vmc.HUMAN_BODY_BONES[24] == "LeftThumbProximal" and vmc.HUMAN_BODY_BONES[-1] == "UpperChest"


def test_model_output_arrives_as_valid_vmc_frames(receiver, motion):
    frames = send_frames(receiver, motion.rotations[:30], motion.face[:30])
    assert len(frames) == 30
    for i, frame in enumerate(frames):
        addresses = [a for a, _ in frame]
        assert set(addresses) <= ADDRESSES
        assert frame[0] == (vmc.OK, (1,))
        assert addresses.count(vmc.TIME) == 1 and addresses.count(vmc.ROOT) == 1
        time_args = frame[addresses.index(vmc.TIME)][1]
        assert len(time_args) == 1 and time_args[0] == pytest.approx(i / 15.0)
        assert frame[addresses.index(vmc.ROOT)][1] == ("root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)

        bones = bones_of(frame)
        assert len(bones) == addresses.count(vmc.BONE) == 44  # each bone once
        assert set(bones) <= set(vmc.HUMAN_BODY_BONES)
        for name, (position, q) in bones.items():
            assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-5), name
            assert np.all(np.isfinite(position)), name
        assert bones["Hips"][0][1] == pytest.approx(0.8855, abs=1e-3)  # standing on the floor

        blends = [args for a, args in frame if a == vmc.BLEND]
        assert [b[0] for b in blends] == PASCAL + list(vmc.VRM_PRESETS)
        assert all(len(b) == 2 and 0.0 <= b[1] <= 1.0 for b in blends)
        assert addresses[-1] == vmc.APPLY and addresses.count(vmc.APPLY) == 1  # after every Val


def test_arkit_names_without_presets(receiver, motion):
    frame, = send_frames(receiver, motion.rotations[:1], motion.face[:1], names="arkit", presets=False)
    blends = [args for a, args in frame if a == vmc.BLEND]
    assert [name for name, _ in blends] == list(rigs.ARKIT51)
    np.testing.assert_allclose([v for _, v in blends], np.clip(motion.face[0], 0, 1), atol=1e-6)


def test_lowering_the_left_arm_lowers_it_in_unity(receiver):
    """BEAT's left arm lies along +X; turning it -90 degrees about +Z points it down. In Unity
    the left arm lies along -X, and the quaternion sent must point it down too."""
    rotations = np.zeros((N_JOINTS, 3))
    rotations[rigs.BEAT_JOINTS.index("LeftArm")] = [0.0, 0.0, -np.pi / 2]
    upper_arm = beat_skeleton().offsets[beat_skeleton().joint_names.index("LeftForeArm")]
    np.testing.assert_allclose(axis_angle_to_matrix(rotations[rigs.BEAT_JOINTS.index("LeftArm")]) @ upper_arm,
                               [0.0, -np.linalg.norm(upper_arm), 0.0], atol=1e-4)

    frame, = send_frames(receiver, [rotations], [np.zeros(N_FACE)])
    bones = bones_of(frame)
    arm_in_unity = bones["LeftLowerArm"][0]  # the elbow, seen from the shoulder joint, at rest
    assert arm_in_unity[0] < -0.3 and abs(arm_in_unity[1]) < 1e-6  # left = -X in Unity, metres
    lowered = unity_matrix(bones["LeftUpperArm"][1]) @ arm_in_unity
    np.testing.assert_allclose(lowered, [0.0, -np.linalg.norm(arm_in_unity), 0.0], atol=1e-6)


def test_every_rotation_is_the_mirrored_beat_rotation(receiver):
    """For bones with a joint of their own (no folding): Unity's rotation applied to a
    mirrored vector is the mirrored BEAT rotation of that vector, and the quaternion is
    BEAT's (x, y, z, w) as (x, -y, -z, w)."""
    rng = np.random.default_rng(5)
    rotations = rng.normal(scale=0.6, size=(N_JOINTS, 3))
    frame, = send_frames(receiver, [rotations], [np.zeros(N_FACE)])
    bones = bones_of(frame)
    vectors = rng.normal(size=(3, 8))
    for bone, joint in [("Spine", "Spine"), ("Neck", "Neck"), ("Head", "Neck1"),
                        ("LeftShoulder", "LeftShoulder"), ("RightUpperArm", "RightArm"),
                        ("LeftLowerArm", "LeftForeArm"), ("RightHand", "RightHand"),
                        ("LeftMiddleProximal", "LeftHandMiddle1"), ("RightThumbDistal", "RightHandThumb3")]:
        beat = rotations[rigs.BEAT_JOINTS.index(joint)]
        unity = unity_matrix(bones[bone][1])
        np.testing.assert_allclose(unity @ MIRROR @ vectors, MIRROR @ axis_angle_to_matrix(beat) @ vectors,
                                   atol=1e-5, err_msg=bone)
        w, x, y, z = axis_angle_to_quaternion(beat)
        assert np.allclose(bones[bone][1], [x, -y, -z, w], atol=1e-6) or \
            np.allclose(bones[bone][1], [-x, y, z, -w], atol=1e-6), bone
    for bone in ("Hips", "Chest", "UpperChest"):  # the model does not move them: at rest
        np.testing.assert_allclose(bones[bone][1], [0.0, 0.0, 0.0, 1.0], atol=1e-7)


# BEAT joints from the hand down to each finger's first Unity bone: the metacarpals fold in
METACARPAL_CHAINS = {"Thumb": ("HandIndex", "HandThumb1"), "Index": ("HandIndex", "HandIndex1"),
                     "Middle": ("HandMiddle1",), "Ring": ("HandRing", "HandRing1"),
                     "Little": ("HandRing", "HandPinky", "HandPinky1")}
BEAT_FINGER = {"Thumb": "Thumb", "Index": "Index", "Middle": "Middle", "Ring": "Ring", "Little": "Pinky"}


def test_metacarpals_fold_into_the_finger_bones(receiver):
    """Posed at random, every finger's tip seen from its proximal joint, in the hand's frame,
    is where BEAT's chain (metacarpals included) puts it, mirrored into Unity axes."""
    rng = np.random.default_rng(11)
    rotations = rng.normal(scale=0.4, size=(N_JOINTS, 3))
    frame, = send_frames(receiver, [rotations], [np.zeros(N_FACE)])
    bones = bones_of(frame)
    skeleton = beat_skeleton()

    def offset(joint: str) -> np.ndarray:
        return skeleton.offsets[skeleton.joint_names.index(joint)] / 100.0

    def rotation(joint: str) -> np.ndarray:
        return axis_angle_to_matrix(rotations[rigs.BEAT_JOINTS.index(joint)])

    for side in ("Left", "Right"):
        for finger, chain in METACARPAL_CHAINS.items():
            b = f"{side}Hand{BEAT_FINGER[finger]}"
            beat_tip = offset(f"{b}2") + rotation(f"{b}2") @ (offset(f"{b}3") + rotation(f"{b}3") @ offset(f"{b}4"))
            for joint in reversed(chain):
                beat_tip = rotation(f"{side}{joint}") @ beat_tip
            u = f"{side}{finger}"
            unity_tip = bones[f"{u}Intermediate"][0] + unity_matrix(bones[f"{u}Intermediate"][1]) @ (
                bones[f"{u}Distal"][0] + unity_matrix(bones[f"{u}Distal"][1]) @ (MIRROR @ offset(f"{b}4")))
            unity_tip = unity_matrix(bones[f"{u}Proximal"][1]) @ unity_tip
            np.testing.assert_allclose(unity_tip, MIRROR @ beat_tip, atol=1e-6, err_msg=u)
            # the proximal bone sits where BEAT's proximal joint rests, seen from the hand
            rest = sum(offset(f"{side}{joint}") for joint in chain)
            np.testing.assert_allclose(bones[f"{u}Proximal"][0], MIRROR @ rest, atol=1e-6, err_msg=u)


def _world(bones: dict, chain: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """World rotation and position of the last bone of `chain` (root first) in Unity."""
    rotation, position = np.eye(3), np.zeros(3)
    for bone in chain:
        position = position + rotation @ bones[bone][0]
        rotation = rotation @ unity_matrix(bones[bone][1])
    return rotation, position


def test_live_legs_arrive_where_the_lower_body_puts_them(receiver):
    """A whole-body frame (the lower body after the layout's joints, and the hips'
    translation) sends the hips, legs, feet and toes: the Hips stand where the translation
    puts them, and each ankle and toe, by Unity's own forward kinematics from the bones
    received, is where the lower body puts it (mirrored into Unity axes)."""
    from diffsheg_core.lower_body import body as lb

    whole = generate(str(SAMPLE), steps=5)
    k = whole.n_frames // 2
    rotations, root = whole.rotations[k], whole.root_translation[k].astype(np.float64)
    frame, = send_frames(receiver, [rotations], [whole.face[k]], legs=True, roots=[root])
    bones = bones_of(frame)
    assert len(bones) == 44 + len(vmc.LEG_BONES)
    rest = vmc._beat_rig(True).positions[0]
    np.testing.assert_allclose(bones["Hips"][0], rest + MIRROR @ root, atol=1e-6)
    lower = rotations[None, -len(lb.JOINTS):].astype(np.float64)
    world = lb._world(lower, root[None])
    hips = world["Hips"][1][0]
    skeleton = beat_skeleton()
    for prefix in ("Left", "Right"):
        chain = ["Hips", f"{prefix}UpperLeg", f"{prefix}LowerLeg", f"{prefix}Foot"]
        _, ankle = _world(bones, chain)
        np.testing.assert_allclose(ankle - bones["Hips"][0], MIRROR @ (world[f"{prefix}Foot"][1][0] - hips),
                                   atol=1e-5, err_msg=prefix)
        toe_rotation, toe = _world(bones, chain + [f"{prefix}Toes"])
        tip = skeleton.offsets[skeleton.joint_names.index(f"{prefix}ToeBaseEnd")] / 100.0
        np.testing.assert_allclose(toe + toe_rotation @ MIRROR @ tip - bones["Hips"][0],
                                   MIRROR @ (world[f"{prefix}ToeEnd"][1][0] - hips), atol=1e-5, err_msg=prefix)


def test_each_datagram_is_a_bundle_small_enough_for_one_ethernet_frame(motion):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(5.0)
        with VmcSender("127.0.0.1", sock.getsockname()[1], rigs.BEAT) as sender:
            sender.send(motion.rotations[0], motion.face[0], 0.0)
        addresses = []
        while vmc.APPLY not in addresses:
            dgram = sock.recv(65536)
            assert len(dgram) <= vmc.MAX_DATAGRAM and OscBundle.dgram_is_bundle(dgram)
            addresses += [m.address for m in OscBundle(dgram)]
    assert len(addresses) == 3 + 44 + N_FACE + len(vmc.VRM_PRESETS) + 1


def test_presets_formula():
    face = np.zeros(N_FACE)
    channel = {name: i for i, name in enumerate(rigs.ARKIT51)}
    face[channel["jawOpen"]] = 0.5
    np.testing.assert_allclose(vmc.preset_weights(face), [0, 0, 1, 0, 0, 0, 0])  # wide open: A
    face[channel["mouthPucker"]] = 1.0
    np.testing.assert_allclose(vmc.preset_weights(face), [0, 0, 0, 0, 0, 0, 1])  # open and round: O
    face[channel["jawOpen"]] = 0.0
    face[channel["eyeBlinkRight"]] = 0.7
    np.testing.assert_allclose(vmc.preset_weights(face), [0, 0.7, 0, 0, 1, 0, 0])  # closed and round: U


def test_presets_never_open_the_mouth_past_one_vowel(motion):
    vowels = np.array([vmc.preset_weights(f)[2:] for f in motion.face])
    assert vowels.min() >= 0.0 and vowels.sum(axis=1).max() <= 1.0 + 1e-9
    assert vowels[:, 0].max() > 0.5  # but the sample speech does open it: A reaches past half


def test_a_failed_send_is_counted_not_raised():
    # a broadcast address without SO_BROADCAST: the system refuses every datagram
    with VmcSender("255.255.255.255", 39539, rigs.BEAT) as sender:
        sender.send(np.zeros((N_JOINTS, 3)), np.zeros(N_FACE), 0.0)
        assert sender.errors >= 1 and sender.frames_sent == 1
        assert "255.255.255.255:39539" in sender.last_error and "check the address" in sender.last_error


def test_bad_settings_and_frames_are_refused_with_the_fix():
    with pytest.raises(DiffshegError, match="needs the 'beat' layout"):
        VmcSender("127.0.0.1", 39539, rigs.SMPLX)
    with pytest.raises(DiffshegError, match="'pascal'"):
        VmcSender("127.0.0.1", 39539, rigs.BEAT, names="camel")
    with pytest.raises(DiffshegError, match="from 1 to 65535"):
        VmcSender("127.0.0.1", 0, rigs.BEAT)
    with pytest.raises(DiffshegError, match="cannot find the VMC receiver's host"):
        VmcSender("no such host", 39539, rigs.BEAT)
    sender = VmcSender("127.0.0.1", 39539, rigs.BEAT)
    with pytest.raises(DiffshegError, match=r"\(47, 3\) rotations"):
        sender.send(np.zeros((46, 3)), np.zeros(N_FACE), 0.0)
    with pytest.raises(DiffshegError, match="51 face weights"):
        sender.send(np.zeros((N_JOINTS, 3)), np.zeros(52), 0.0)
    sender.close()
    with VmcSender("127.0.0.1", 39539, rigs.BEAT, legs=True) as legs:
        with pytest.raises(DiffshegError, match=r"\(56, 3\) rotations for the 'beat' layout with legs"):
            legs.send(np.zeros((N_JOINTS, 3)), np.zeros(N_FACE), 0.0, np.zeros(3))
        with pytest.raises(DiffshegError, match="needs the hips' translation"):
            legs.send(np.zeros((N_JOINTS + 9, 3)), np.zeros(N_FACE), 0.0)
    with pytest.raises(DiffshegError, match="closed"):
        sender.send(np.zeros((N_JOINTS, 3)), np.zeros(N_FACE), 0.0)


@pytest.mark.parametrize("text, expected", [
    ("192.168.1.20:39539", ("192.168.1.20", 39539)), (":39540", ("127.0.0.1", 39540)),
    ("39539", ("127.0.0.1", 39539)), (" localhost:9000 ", ("localhost", 9000)),
    ("[::1]:39539", ("::1", 39539)),
])
def test_parse_address(text, expected):
    assert parse_address(text) == expected


@pytest.mark.parametrize("text, problem", [
    ("", "port"), ("vseeface", "port"), ("127.0.0.1:", "port"), ("127.0.0.1:0", "port"),
    ("127.0.0.1:70000", "port"), ("127.0.0.1:-5", "port"), ("::1:39539", "host"), ("my pc:39539", "host"),
])
def test_parse_address_errors_name_the_fix(text, problem):
    with pytest.raises(DiffshegError, match=f"the {problem} .*HOST:PORT, e.g. 127.0.0.1:39539"):
        parse_address(text)
