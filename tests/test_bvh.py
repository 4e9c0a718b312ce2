"""BVH reading, writing and conversion (diffsheg_core.bvh) on the real BEAT take."""

from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.bvh import (
    beat_skeleton, bvh_to_motion, joint_positions, motion_to_bvh, read_bvh, write_bvh,
)
from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import Motion, resample_motion
from diffsheg_core.rigs import BEAT_JOINTS, SMPLX_GESTURE_JOINTS
from diffsheg_core.rotations import axis_angle_to_matrix, euler_to_axis_angle, matrix_to_axis_angle

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BVH = DATA / "beat" / "2_scott_0_1_1.bvh"


@pytest.fixture(scope="module")
def shared() -> "object":
    return read_bvh(BVH, fps=15)


@pytest.fixture(scope="module")
def motion(shared) -> Motion:
    return bvh_to_motion(shared)


@pytest.fixture(scope="module")
def written(motion, tmp_path_factory) -> Path:
    return write_bvh(motion, tmp_path_factory.mktemp("bvh") / "take.bvh")


def _layout_columns(data) -> np.ndarray:
    return np.concatenate([data.rotation_columns(n)[0] for n in BEAT_JOINTS])


def _geodesic_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    rel = np.swapaxes(axis_angle_to_matrix(a), -1, -2) @ axis_angle_to_matrix(b)
    return np.degrees(np.linalg.norm(matrix_to_axis_angle(rel), axis=-1))


def test_stale_header_is_reported_not_trusted():
    with pytest.raises(DiffshegError, match=r"7669 frames.*957 rows.*stale.*fps="):
        read_bvh(BVH)


def test_read_shared_file_counts_real_rows(shared):
    assert shared.n_frames == 957
    assert shared.header_frames == 7669 and shared.header_mismatch
    assert shared.fps == 15.0
    assert len(shared.joint_names) == 75 and shared.joint_names[0] == "Hips"
    assert shared.frames.shape == (957, 228)
    assert shared.parents[0] == -1
    assert shared.joint_names[shared.parents[shared.joint_index("RightHand")]] == "RightForeArm"
    assert shared.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    cols, order = shared.rotation_columns("Spine")
    assert order == "XYZ" and cols.tolist() == [6, 7, 8]
    assert len(shared.end_sites) == 13  # head, ten fingers, two toes


def test_embedded_skeleton_is_the_shared_files_header_and_template(shared):
    skeleton = beat_skeleton()
    assert skeleton.joint_names == shared.joint_names
    assert skeleton.parents == shared.parents
    assert skeleton.channels == shared.channels
    np.testing.assert_array_equal(skeleton.offsets, shared.offsets)
    assert skeleton.end_sites.keys() == shared.end_sites.keys()
    for j, offset in shared.end_sites.items():
        np.testing.assert_array_equal(skeleton.end_sites[j], offset)
    np.testing.assert_array_equal(skeleton.frames, shared.frames[:1])


def test_bvh_to_motion_skips_template_row(shared, motion):
    assert motion.rig == "beat" and motion.fps == 15.0
    assert motion.joint_names == list(BEAT_JOINTS)
    assert motion.rotations.shape == (956, 47, 3) and motion.face.shape == (956, 0)
    assert motion.meta["skipped_template_row"] is True
    assert bvh_to_motion(shared, skip_template_row=False).n_frames == 957
    assert np.linalg.norm(motion.rotations, axis=-1).max() <= np.pi + 1e-6


def test_axis_angle_is_intrinsic_xyz_like_the_official_statistics(shared, motion):
    """The take's per-channel means sit within 2 std of the official axis-angle
    normalisation (an extrinsic reading misses some channels by 10^5 std)."""
    mean = np.load(DATA / "beat" / "axis_angle_mean.npy")
    std = np.load(DATA / "beat" / "axis_angle_std.npy")
    z = np.abs(motion.rotations.reshape(len(motion.rotations), -1).mean(0) - mean) / std
    assert z.max() < 2.0
    a, b, c = np.radians(shared.frames[10, shared.rotation_columns("RightArm")[0]])
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    j = BEAT_JOINTS.index("RightArm")
    np.testing.assert_allclose(axis_angle_to_matrix(motion.rotations[9, j]), rx @ ry @ rz, atol=1e-6)


def test_written_file_reparses_exactly(motion, written):
    expected = motion_to_bvh(motion)
    back = read_bvh(written)
    assert not back.header_mismatch
    assert back.n_frames == motion.n_frames and back.fps == 15.0
    assert back.joint_names == beat_skeleton().joint_names
    np.testing.assert_allclose(back.frames, expected.frames, atol=1e-4)
    cols = _layout_columns(back)
    others = np.setdiff1d(np.arange(228), cols)
    np.testing.assert_allclose(back.frames[:, others],
                               np.broadcast_to(beat_skeleton().frames[0, others], (len(back.frames), len(others))),
                               atol=1e-6)
    again = bvh_to_motion(back)
    assert again.meta["skipped_template_row"] is False
    assert _geodesic_deg(again.rotations, motion.rotations).max() < 1e-3


def test_shared_file_round_trips_through_motion(shared, written):
    """read -> Motion -> write -> read: the 47 joints' channel values come back.

    45 joints come back digit for digit. The two forearms pass through gimbal lock
    (Y near 90 degrees), where the capture's exporter chose other, equivalent Euler
    triples than the nearest-branch ones; there the rotations are equal instead.
    """
    back = read_bvh(written)
    cols = _layout_columns(shared)
    source = shared.frames[1:, cols].reshape(-1, 47, 3)
    result = back.frames[:, cols].reshape(-1, 47, 3)
    exact = np.abs(result - source).max(axis=(0, 2)) < 1e-4
    assert [BEAT_JOINTS[j] for j in np.flatnonzero(~exact)] == ["RightForeArm", "LeftForeArm"]
    angle = _geodesic_deg(euler_to_axis_angle(source, "XYZ"), euler_to_axis_angle(result, "XYZ"))
    assert angle.max() < 1e-4


def test_written_file_follows_motion_fps(motion, tmp_path):
    fast = resample_motion(motion, 30.0)
    back = read_bvh(write_bvh(fast, tmp_path / "fast.bvh"))
    assert back.fps == 30.0 and back.n_frames == fast.n_frames


def test_root_translation_goes_to_root_position(motion, tmp_path):
    moved = Motion(fps=motion.fps, rig="beat", joint_names=motion.joint_names,
                   rotations=motion.rotations[:5], face_names=[], face=np.zeros((5, 0)),
                   root_translation=np.arange(15, dtype=np.float32).reshape(5, 3))
    back = read_bvh(write_bvh(moved, tmp_path / "moved.bvh"))
    template = beat_skeleton().frames[0, :3]  # the BEAT skeleton is in centimetres, the Motion in metres
    np.testing.assert_allclose(back.frames[:, :3], template + 100 * moved.root_translation, atol=1e-4)


def test_smplx_motion_is_refused_with_advice():
    smplx = Motion(fps=15.0, rig="smplx", joint_names=list(SMPLX_GESTURE_JOINTS),
                   rotations=np.zeros((2, len(SMPLX_GESTURE_JOINTS), 3)), face_names=[],
                   face=np.zeros((2, 0)))
    with pytest.raises(DiffshegError, match=r"smplx.*npz"):
        motion_to_bvh(smplx)


def _broken(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_bad_files_raise_clear_errors(tmp_path, written):
    text = written.read_text()
    header, _, _ = text.partition("MOTION")
    rows = text.splitlines()
    cases = {
        "missing.bvh": (None, "no such BVH file"),
        "nomotion.bvh": (header, "no MOTION section"),
        "braces.bvh": (text.replace("}", "", 1), r"hierarchy"),
        "short_row.bvh": ("\n".join(rows[:-1] + [" ".join(rows[-1].split()[:-5])]) + "\n", r"row 955 has 223 values"),
        "nan.bvh": ("\n".join(rows[:-1] + [rows[-1].replace(rows[-1].split()[7], "nan", 1)]) + "\n", "row 955 holds NaN"),
        "text.bvh": ("\n".join(rows[:-1] + [rows[-1].replace(rows[-1].split()[7], "abc", 1)]) + "\n", "not numeric"),
        "channels.bvh": (text.replace("CHANNELS 3 Xrotation", "CHANNELS 3 Wrotation", 1), "CHANNELS of 'Spine'"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name if content is None else _broken(tmp_path, name, content)
        with pytest.raises(DiffshegError, match=message):
            read_bvh(path)


def test_truncated_file_needs_fps(tmp_path, written):
    rows = written.read_text().splitlines()
    path = _broken(tmp_path, "truncated.bvh", "\n".join(rows[:-10]) + "\n")
    with pytest.raises(DiffshegError, match="956 frames.*946 rows"):
        read_bvh(path)
    assert read_bvh(path, fps=15).n_frames == 946


@pytest.mark.blender
def test_blender_imports_written_file_with_same_pose(written):
    """Blender's BVH importer builds the 75 bones, keys every frame, and poses each
    joint where our forward kinematics (intrinsic XYZ Euler) puts it."""
    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.import_anim.bvh(filepath=str(written)) == {"FINISHED"}
    armature = next(o for o in bpy.data.objects if o.type == "ARMATURE")
    data = read_bvh(written)
    assert len(armature.data.bones) == 75
    assert {b.name for b in armature.data.bones} == set(data.joint_names)
    assert tuple(armature.animation_data.action.frame_range) == (1.0, float(data.n_frames))
    positions = joint_positions(data)
    scene = bpy.context.scene
    for frame in (0, 333, data.n_frames - 1):
        scene.frame_set(frame + 1)
        blender = np.array([armature.matrix_world @ armature.pose.bones[n].head for n in data.joint_names])
        ours_z_up = positions[frame][:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
        np.testing.assert_allclose(blender, ours_z_up, atol=1e-3)
