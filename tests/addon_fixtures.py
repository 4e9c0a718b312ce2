"""Shared helpers and fixtures for the headless bpy tests of the Blender add-on
(tests/test_addon_*.py; each imports the autouse fixture exit_before_blender_teardown).

Real material only, by path: the BEAT mocap take and its audio, the ARKit face mesh,
real speech. Rigs are made the way users get them: BVH import, Rigify generation, and
an SMPL-X-named armature built bone by bone. The tests run on every Blender the add-on
supports (4.2 LTS and later; tools/test_blender_versions.sh runs them on a given bpy).
"""

from __future__ import annotations

import atexit
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import soundfile as sf  # noqa: E402

from diffsheg_core.bvh import bvh_to_motion, read_bvh  # noqa: E402
from diffsheg_core.motion import Motion  # noqa: E402
from diffsheg_core.rigs import ARKIT51, SMPLX_JOINTS  # noqa: E402

DATA = REPO.parent / "shared" / "data"
BEAT_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
BEAT_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
BEAT2_NPZ = DATA / "beat2" / "2_scott_0_1_1.npz"
FACE_BLEND = DATA / "rigs" / "beat_face_arkit51.blend"
SPEECH = DATA / "audio" / "2_scott_0_3_3.wav"
READYPLAYERME = DATA / "rigs" / "readyplayerme_brunette.glb"
SPEECH_2 = DATA / "audio" / "12_zhao_2_3_3.wav"
MISNAMED_MP3 = DATA / "audio" / "2_scott_0_103_103_28s.wav"

# Blender builds without Audaspace (the bpy 4.x modules on PyPI) can hold no sound strip
# and write no audio track.
HAS_AUDIO = bool(bpy.app.build_options.audaspace)


@pytest.fixture(scope="session", autouse=True)
def exit_before_blender_teardown(request):
    """The bpy modules before 5.0 crash (4.2, 4.3) or hang (4.5) in Blender's exit-time
    teardown once classes with Python callbacks were registered, after all tests ran.
    There the process ends with pytest's exit status before that teardown."""
    yield
    if bpy.app.version < (5, 0):
        atexit.register(_exit_now, request.session)


def _exit_now(session) -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(int(session.exitstatus))


def report_text() -> str:
    """The details of the last Generate: the "DiffSHEG report" Text datablock."""
    return bpy.data.texts["DiffSHEG report"].as_string()


def reset_scene(fps: float = 24.0) -> "bpy.types.Scene":
    """Factory settings, empty scene, the add-on registered, the given frame rate."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ensure_registered()
    scene = bpy.context.scene
    set_fps(scene, fps)
    return scene


def set_fps(scene, fps: float) -> None:
    """29.97 is set as Blender's presets do: fps 30, fps_base 1.001."""
    if abs(fps - round(fps)) < 1e-6:
        scene.render.fps, scene.render.fps_base = int(round(fps)), 1.0
    else:
        scene.render.fps, scene.render.fps_base = int(np.ceil(fps)), np.ceil(fps) / fps


def ensure_registered() -> None:
    import blender_addon

    if not hasattr(bpy.types.Scene, "diffsheg"):
        blender_addon.register()


def cut_speech(tmp_path: Path, seconds: float = 3.0, source: Path = SPEECH, offset: float = 5.0,
               name: str | None = None) -> Path:
    """A few seconds of real speech written to tmp_path as 16-bit WAV."""
    info = sf.info(str(source))
    start = int(offset * info.samplerate)
    samples, rate = sf.read(str(source), start=start, frames=int(seconds * info.samplerate))
    out = tmp_path / (name or f"{source.stem}_{seconds:g}s.wav")
    sf.write(str(out), samples, rate, subtype="PCM_16")
    return out


def mocap_motion(frames: int | None = None) -> Motion:
    """The real BEAT take as a beat-layout Motion (15 fps), with ARKit face weights built
    from the same take's audio: jawOpen follows the speech envelope, blinks every 3 s."""
    body = bvh_to_motion(read_bvh(BEAT_BVH, fps=15.0))
    n = body.n_frames if frames is None else frames
    audio, rate = sf.read(str(BEAT_WAV), dtype="float32")
    hop = rate // 15
    rms = np.sqrt(np.mean(audio[: n * hop].reshape(n, hop) ** 2, axis=1))
    face = np.zeros((n, len(ARKIT51)), dtype=np.float32)
    face[:, ARKIT51.index("jawOpen")] = rms / rms.max()
    blink = (np.arange(n) % 45 < 3).astype(np.float32)
    face[:, ARKIT51.index("eyeBlinkLeft")] = blink
    face[:, ARKIT51.index("eyeBlinkRight")] = blink
    return Motion(fps=15.0, rig="beat", joint_names=body.joint_names, rotations=body.rotations[:n],
                  face_names=list(ARKIT51), face=face, meta={"audio_file": str(BEAT_WAV)})


def import_beat_armature(animated: bool = False):
    """The BEAT skeleton as Blender's BVH importer makes it from the shared take."""
    bpy.ops.import_anim.bvh(filepath=str(BEAT_BVH), update_scene_fps=False, update_scene_duration=False)
    ob = bpy.context.object
    if not animated:
        ob.animation_data_clear()
        for pb in ob.pose.bones:
            pb.rotation_quaternion, pb.rotation_euler, pb.location = (1, 0, 0, 0), (0, 0, 0), (0, 0, 0)
    return ob


def append_face():
    """The real ARKit face mesh 'Neutral' (Basis + 51 ARKit shape keys). The file is in
    Blender 5.0's .blend format, which Blender 4.2-4.4 cannot read: there a stand-in with
    the same object name, shape-key names and slider ranges is built (with a warning)."""
    try:
        with bpy.data.libraries.load(str(FACE_BLEND)) as (src, dst):
            dst.objects = ["Neutral"]
    except OSError:
        if not _blender5_file_format(FACE_BLEND):
            raise
        warnings.warn(f"this Blender cannot read {FACE_BLEND.name} (Blender 5.0 file format): "
                      "a stand-in face with the same ARKit shape keys is used")
        return _stand_in_face()
    ob = dst.objects[0]
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _blend_header(path: Path) -> bytes:
    import zstandard  # a dependency of the bpy module

    with open(path, "rb") as f:
        if f.read(4) == b"\x28\xb5\x2f\xfd":  # zstd-compressed .blend
            f.seek(0)
            return zstandard.ZstdDecompressor().stream_reader(f).read(17)
        f.seek(0)
        return f.read(17)


def _blender5_file_format(path: Path) -> bool:
    """Blender 5.0 headers give the header size after 'BLENDER' ('BLENDER17-01v0500');
    older ones a pointer-size character ('BLENDER-v402')."""
    header = _blend_header(path)
    return header.startswith(b"BLENDER") and header[7:9].isdigit()


def _stand_in_face():
    """A sphere 'Neutral' with Basis + the 51 ARKit shape keys, each moving one vertex."""
    import bmesh

    mesh = bpy.data.meshes.new("Neutral")
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=16, v_segments=8, radius=0.1)
    bm.to_mesh(mesh)
    bm.free()
    ob = bpy.data.objects.new("Neutral", mesh)
    bpy.context.scene.collection.objects.link(ob)
    ob.shape_key_add(name="Basis")
    for i, name in enumerate(ARKIT51):
        point = ob.shape_key_add(name=name, from_mix=False).data[i]
        point.co = point.co * 1.2
    return ob


# SMPL-X joints (T-pose, metres, Y up / Z forward as in SMPL-X) for an SMPL-X-named rig.
_SMPLX_PARENTS = {
    "pelvis": None, "spine1": "pelvis", "spine2": "spine1", "spine3": "spine2", "neck": "spine3",
    "head": "neck", "jaw": "head", "left_collar": "spine3", "right_collar": "spine3",
    "left_shoulder": "left_collar", "right_shoulder": "right_collar",
    "left_elbow": "left_shoulder", "right_elbow": "right_shoulder",
    "left_wrist": "left_elbow", "right_wrist": "right_elbow",
}
_SMPLX_POSITIONS = {
    "pelvis": (0, 0.0, 0), "spine1": (0, 0.1, -0.01), "spine2": (0, 0.24, 0), "spine3": (0, 0.3, 0.01),
    "neck": (0, 0.52, -0.02), "head": (0, 0.6, 0.02), "jaw": (0, 0.62, 0.05),
    "left_collar": (0.07, 0.43, 0), "right_collar": (-0.07, 0.43, 0),
    "left_shoulder": (0.18, 0.45, -0.01), "right_shoulder": (-0.18, 0.45, -0.01),
    "left_elbow": (0.44, 0.45, -0.02), "right_elbow": (-0.44, 0.45, -0.02),
    "left_wrist": (0.69, 0.45, -0.02), "right_wrist": (-0.69, 0.45, -0.02),
}


def _smplx_layout() -> dict[str, tuple[str | None, tuple[float, float, float]]]:
    joints = {n: (_SMPLX_PARENTS[n], _SMPLX_POSITIONS[n]) for n in _SMPLX_PARENTS}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        for k, finger in enumerate(("index", "middle", "ring", "pinky", "thumb")):
            base_x, z = 0.78 + (0.0 if finger != "thumb" else -0.05), 0.03 - 0.015 * k
            y = 0.45 - (0.02 if finger == "thumb" else 0.0)
            parent = f"{side}_wrist"
            for i in (1, 2, 3):
                name = f"{side}_{finger}{i}"
                joints[name] = (parent, (sign * (base_x + 0.03 * (i - 1)), y, z + (0.03 if finger == "thumb" else 0)))
                parent = name
    return joints


def build_smplx_armature(roll_seed: int = 0, name: str = "SMPLX-neutral"):
    """An armature named like the SMPL-X Blender add-on's (the bones this project keys),
    Z up and facing -Y, with pseudo-random bone rolls (a seed) to show roll independence."""
    assert set(_SMPLX_PARENTS) <= set(SMPLX_JOINTS)
    rng = np.random.default_rng(roll_seed)
    joints = _smplx_layout()
    arm = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    children = {n: [c for c, (p, _) in joints.items() if p == n] for n in joints}

    def to_blender(p):  # Y-up, facing +Z  ->  Z-up, facing -Y
        return (p[0], -p[2], p[1])

    for n, (parent, pos) in joints.items():
        eb = arm.edit_bones.new(n)
        eb.head = to_blender(pos)
        kids = children[n]
        if kids:
            tail = np.mean([joints[c][1] for c in kids], axis=0)
        else:
            tail = np.array(pos) + (np.array(pos) - np.array(joints[parent][1])) * 0.5 if parent else np.array(pos) + (0, 0.1, 0)
        if np.linalg.norm(np.array(tail) - pos) < 1e-3:
            tail = np.array(pos) + (0, 0.05, 0)
        eb.tail = to_blender(tail)
        eb.roll = float(rng.uniform(-np.pi, np.pi)) if roll_seed else 0.0
    for n, (parent, _) in joints.items():
        if parent:
            arm.edit_bones[n].parent = arm.edit_bones[parent]
    bpy.ops.object.mode_set(mode="OBJECT")
    return ob


@pytest.fixture(scope="session")
def rigify_blend(tmp_path_factory) -> Path:
    """A .blend with a Rigify rig generated from the human metarig (made once per session,
    also when several test modules import this fixture)."""
    path = tmp_path_factory.getbasetemp() / "rigify_human.blend"
    return path if path.is_file() else generate_rigify_blend(path)


def generate_rigify_blend(path: Path) -> Path:
    """A Rigify rig generated from the human metarig, saved to `path`."""
    import addon_utils

    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon_utils.enable("rigify", default_set=True)
    bpy.ops.object.armature_human_metarig_add()
    bpy.ops.pose.rigify_generate()
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def armature_pose_matrices(ob, bones: list[str]) -> np.ndarray:
    """(len(bones), 3, 3) armature-space pose orientations, scale removed."""
    out = []
    for b in bones:
        m = np.array(ob.pose.bones[b].matrix.to_3x3())
        out.append(m / np.linalg.norm(m, axis=0, keepdims=True))
    return np.array(out)


def smplx_mocap_motion(frames: int = 120) -> Motion:
    """The same real take in the SMPL-X layout (BEAT2 npz, 30 fps), joints as the
    `smplx` layout orders them, jaw included; no expression weights."""
    from diffsheg_core.rigs import SMPLX

    with np.load(BEAT2_NPZ) as z:
        poses = z["poses"][:frames].reshape(frames, 55, 3)
        fps = float(z["mocap_frame_rate"])
    index = [SMPLX_JOINTS.index(n) for n in SMPLX.joint_names]
    return Motion(fps=fps, rig="smplx", joint_names=list(SMPLX.joint_names), rotations=poses[:, index],
                  face_names=[], face=np.zeros((frames, 0)))


def world_direction(ob, bone: str) -> np.ndarray:
    """World-space unit direction (head to tail) of a posed bone."""
    pb = ob.pose.bones[bone]
    v = np.array(ob.matrix_world @ pb.tail) - np.array(ob.matrix_world @ pb.head)
    return v / np.linalg.norm(v)


def scene_state(scene) -> dict:
    """What generation may change: Actions, assignments, NLA tracks, strips, frame range."""
    from blender_addon.scene.sound import sound_strips

    def anim(id_data):
        ad = id_data.animation_data if id_data is not None else None
        if ad is None:
            return None
        return (ad.action.name if ad.action else None, [t.name for t in ad.nla_tracks])

    return {
        "actions": sorted(bpy.data.actions.keys()),
        "objects": {ob.name: (anim(ob), anim(getattr(ob.data, "shape_keys", None)))
                    for ob in scene.objects},
        "strips": [s.name for s in sound_strips(scene)],
        "range": (scene.frame_start, scene.frame_end),
    }


def _unreal_name(beat: str) -> str | None:
    """The UE mannequin's name for a BEAT joint (None: no such bone on a UE rig)."""
    import re

    fixed = {"Hips": "pelvis", "Neck": "neck_01", "Neck1": "neck_02", "Head": "head"}
    if beat in fixed:
        return fixed[beat]
    m = re.fullmatch(r"(Left|Right)(Shoulder|Arm|ForeArm|Hand)", beat)
    if m:
        part = {"Shoulder": "clavicle", "Arm": "upperarm", "ForeArm": "lowerarm", "Hand": "hand"}[m[2]]
        return f"{part}_{m[1][0].lower()}"
    m = re.fullmatch(r"(Left|Right)Hand(Index|Middle|Ring|Pinky|Thumb)(\d?)", beat)
    if m:
        return f"{m[2].lower()}_{('0' + m[3]) if m[3] else 'metacarpal'}_{m[1][0].lower()}"
    return None


def build_unreal_armature(beat_rig, spine_bones: int = 5, neck_02: bool = True, arms_down: float = 0.0,
                          axis_seed: int = 1, name: str = "UE_Mannequin"):
    """An Unreal-style armature (UE5: spine_01-05, neck_01/02; UE4-like without neck_02)
    with the joints of the BEAT rig `beat_rig` (at rest). As an FBX import without
    automatic bone orientation makes them, each bone's own axis points anywhere (a
    pseudo-random direction and roll from `axis_seed`), not at its child. `arms_down`
    degrees lowers the arms about the shoulders (an A-pose rest)."""
    src = {b.name: np.array(b.head_local) for b in beat_rig.data.bones}
    parent_of = {b.name: (b.parent.name if b.parent else None) for b in beat_rig.data.bones}
    joints: dict[str, tuple[str | None, np.ndarray]] = {"pelvis": (None, src["Hips"])}
    spine = [src["Spine"] + (src["Neck"] - src["Spine"]) * k / spine_bones for k in range(spine_bones)]
    for k, pos in enumerate(spine):
        joints[f"spine_{k + 1:02d}"] = ("pelvis" if k == 0 else f"spine_{k:02d}", pos)
    top = f"spine_{spine_bones:02d}"
    up = (src["Neck"] - src["Spine"]) / np.linalg.norm(src["Neck"] - src["Spine"])
    for beat, pos in src.items():
        ue = _unreal_name(beat)
        if ue is None or ue == "pelvis" or (ue == "neck_02" and not neck_02):
            continue
        parent = parent_of[beat]
        while parent not in ("Spine3", None) and (_unreal_name(parent) is None
                                                 or (_unreal_name(parent) == "neck_02" and not neck_02)):
            parent = parent_of[parent]
        joints[ue] = (top if parent == "Spine3" else _unreal_name(parent), pos)
    if arms_down:
        for side in ("l", "r"):
            pivot = joints[f"upperarm_{side}"][1]
            arm = joints[f"hand_{side}"][1] - pivot
            axis = np.cross(arm, -up)
            rot = axis_angle_matrix(np.radians(arms_down) * axis / np.linalg.norm(axis))
            below = {n for n in joints if _descends(joints, n, f"upperarm_{side}")}
            for n in below:
                joints[n] = (joints[n][0], pivot + rot @ (joints[n][1] - pivot))
    rng = np.random.default_rng(axis_seed)
    arm_data = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, arm_data)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    for n, (_, pos) in joints.items():
        eb = arm_data.edit_bones.new(n)
        direction = rng.normal(size=3)
        eb.head, eb.tail = pos, pos + 3.0 * direction / np.linalg.norm(direction)
        eb.roll = float(rng.uniform(-np.pi, np.pi))
    for n, (parent, _) in joints.items():
        if parent:
            arm_data.edit_bones[n].parent = arm_data.edit_bones[parent]
    bpy.ops.object.mode_set(mode="OBJECT")
    return ob


def _descends(joints: dict, name: str, ancestor: str) -> bool:
    while name is not None:
        if name == ancestor:
            return True
        name = joints[name][0]
    return False


def axis_angle_matrix(v) -> np.ndarray:
    from diffsheg_core.rotations import axis_angle_to_matrix

    return axis_angle_to_matrix(np.asarray(v, dtype=np.float64))


def head_direction(ob, bone: str, child: str) -> np.ndarray:
    """World-space unit direction from a posed bone's head to its child's head (what a
    bone points at, whichever way its own axis points)."""
    a, b = ob.pose.bones[bone].head, ob.pose.bones[child].head
    v = np.array(ob.matrix_world @ b) - np.array(ob.matrix_world @ a)
    return v / np.linalg.norm(v)


def world_delta(ob, bone: str) -> np.ndarray:
    """World rotation of a posed bone relative to its rest (independent of bone roll)."""
    m = np.array(ob.matrix_world.to_3x3()) @ np.array(ob.pose.bones[bone].matrix.to_3x3())
    r = np.array(ob.matrix_world.to_3x3()) @ np.array(ob.data.bones[bone].matrix_local.to_3x3())
    m, r = m / np.linalg.norm(m, axis=0), r / np.linalg.norm(r, axis=0)
    return m @ r.T


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Degrees between two directions, or of the rotation between two rotation matrices."""
    if a.shape == (3, 3):
        return float(np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1) / 2, -1, 1))))
    return float(np.degrees(np.arccos(np.clip(a @ b, -1, 1))))


def import_readyplayerme():
    """The real Ready Player Me avatar (glTF): (armature, [Wolf3D_Head, Wolf3D_Teeth])."""
    bpy.ops.import_scene.gltf(filepath=str(READYPLAYERME))
    objects = bpy.context.scene.objects
    return objects["Armature"], [objects["Wolf3D_Head"], objects["Wolf3D_Teeth"]]


# Whole-body rigs (test_addon_whole_body.py): the bones of a preset placed on the BEAT rest
# skeleton (legs straight down), in the units and axes the rig's usual import gives.

def build_armature(name: str, joints: dict, *, unit: float = 1.0, y_up: bool = False, object_scale: float = 1.0,
                   facing_y: bool = False, axis_seed: int | None = None):
    """An armature of `joints` ({bone: (parent or None, head in metres, Y up, facing +Z)}),
    its data in units of `unit` metres: Z up facing -Y (facing +Y with `facing_y`), or Y up
    under an object turned 90 degrees about X as FBX imports are (`y_up`), scaled by
    `object_scale`. Each bone points at its children, or (`axis_seed`) anywhere with any
    roll, as an FBX import without automatic bone orientation makes them."""
    rng = np.random.default_rng(axis_seed or 0)

    def data(p) -> np.ndarray:
        x, y, z = np.asarray(p, dtype=np.float64) / unit
        x, z = (-x, -z) if facing_y else (x, z)
        return np.array([x, y, z] if y_up else [x, -z, y])

    arm = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(ob)
    ob.rotation_euler = (np.pi / 2, 0.0, 0.0) if y_up else (0.0, 0.0, 0.0)
    ob.scale = (object_scale,) * 3
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    for n, (parent, pos) in joints.items():
        eb = arm.edit_bones.new(n)
        head = data(pos)
        kids = [data(p) for c, (up, p) in joints.items() if up == n]
        if axis_seed is not None:
            direction = rng.normal(size=3)
            tail = head + 0.05 / unit * direction / np.linalg.norm(direction)
        elif kids:
            tail = np.mean(kids, axis=0)
        else:
            tail = head + 0.5 * (head - data(joints[parent][1])) if parent else head + data((0, 0.1, 0))
        if np.linalg.norm(tail - head) < 1e-3 / unit:
            tail = head + data((0, 0.05, 0))
        eb.head, eb.tail = head, tail
        eb.roll = float(rng.uniform(-np.pi, np.pi)) if axis_seed is not None else 0.0
    for n, (parent, _) in joints.items():
        if parent:
            arm.edit_bones[n].parent = arm.edit_bones[parent]
    bpy.ops.object.mode_set(mode="OBJECT")
    return ob


def preset_joints(preset_name: str) -> dict:
    """{bone: (parent, head in metres, Y up, facing +Z, feet on y = 0)} for the beat-layout
    bones of a preset, on the BEAT rest skeleton; a chain (spine_01-05) spread evenly
    from its joint to the next joint the preset maps."""
    from blender_addon.scene.preset import load_preset
    from diffsheg_core.bvh import beat_skeleton

    skel = beat_skeleton()
    names, parents = list(skel.joint_names), list(skel.parents)
    pos = np.zeros((len(names), 3))
    for j, p in enumerate(parents):
        pos[j] = (pos[p] if p >= 0 else 0.0) + 0.01 * np.asarray(skel.offsets[j])
    pos[:, 1] -= pos[:, 1].min()
    bones = load_preset(preset_name).joint_map("beat")

    def mapped_above(j: int) -> int:
        p = parents[j]
        while p >= 0 and names[p] not in bones:
            p = parents[p]
        return p

    out = {}
    for j, joint in enumerate(names):
        if joint not in bones:
            continue
        chain, above = bones[joint], mapped_above(j)
        end = next((pos[c] for c, n in enumerate(names) if n in bones and mapped_above(c) == j), pos[j])
        parent = bones[names[above]][-1] if above >= 0 else None
        for k, bone in enumerate(chain):
            out[bone] = (parent, pos[j] + (end - pos[j]) * k / len(chain))
            parent = bone
    return out


def build_mixamo_armature():
    """A Mixamo character as Blender's FBX importer makes it: centimetres, Y up under an
    object turned 90 degrees and scaled 0.01, bone axes not at their children."""
    return build_armature("Armature", preset_joints("mixamo"), unit=0.01, y_up=True, object_scale=0.01,
                          axis_seed=3)


def build_unreal_body_armature():
    """A UE5 mannequin with legs under its floor-level root bone: centimetres in a scene of
    unit scale 0.01, facing +Y, bone axes not at their children."""
    bpy.context.scene.unit_settings.scale_length = 0.01
    joints = {"root": (None, (0.0, 0.0, 0.0))}
    for bone, (parent, pos) in preset_joints("unreal").items():
        joints[bone] = (parent or "root", pos)
    return build_armature("UE_Mannequin", joints, unit=0.01, facing_y=True, axis_seed=5)


def build_vroid_armature():
    """A VRoid avatar as the VRM add-on imports it: J_Bip_* bones under Root, metres, Z up."""
    joints = {"Root": (None, (0.0, 0.0, 0.0))}
    for bone, (parent, pos) in preset_joints("vrm").items():
        joints[bone] = (parent or "Root", pos)
    return build_armature("Armature", joints)


# SMPL-X legs (neutral template, metres from the pelvis, Y up): splayed a little, not straight down.
_SMPLX_LEFT_LEG = {"left_hip": ("pelvis", (0.071, -0.091, -0.005)), "left_knee": ("left_hip", (0.106, -0.451, -0.013)),
                   "left_ankle": ("left_knee", (0.093, -0.886, -0.050)),
                   "left_foot": ("left_ankle", (0.119, -0.940, 0.076))}


def build_smplx_body_armature(name: str = "SMPLX-neutral"):
    """An SMPL-X-named armature with legs (build_smplx_armature's upper body), Z up facing -Y."""
    joints = dict(_smplx_layout())
    for bone, (parent, (x, y, z)) in _SMPLX_LEFT_LEG.items():
        joints[bone] = (parent, (x, y, z))
        joints[bone.replace("left", "right")] = (parent.replace("left", "right"), (-x, y, z))
    return build_armature(name, joints)
