"""Keys an animator can edit (issue 25, item 1), in headless Blender on real rigs with
20 s of real speech: sparse Bezier poses, a bone's rotation channels on shared frames,
within the error bound on every frame, typed GENERATED; every frame stays available."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from addon_fixtures import append_face, bpy, cut_speech, import_beat_armature, import_readyplayerme, reset_scene
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

import diffsheg_core
from blender_addon.scene.bake import BakeOptions, bake_motion
from blender_addon.scene.keying import fcurves_of
from blender_addon.scene.preset import load_preset
from diffsheg_core.errors import DiffshegError
from diffsheg_core.keyframes import rotation_angle, to_quaternions

SECONDS = 20.0


@pytest.fixture(scope="module")
def motion(tmp_path_factory):
    speech = cut_speech(tmp_path_factory.mktemp("speech"), seconds=SECONDS)
    return diffsheg_core.generate(str(speech), device="cpu")


def _targets(rig: str):
    if rig == "beat":
        return import_beat_armature(), [append_face()], load_preset("beat")
    armature, faces = import_readyplayerme()
    return armature, faces, None  # Auto


def _curves(id_data) -> dict:
    """{(data_path, index): (frames, values, types)} of the Action on `id_data`."""
    out = {}
    for fc in fcurves_of(id_data):
        points = fc.keyframe_points
        co = np.empty(2 * len(points), dtype=np.float32)
        points.foreach_get("co", co)
        out[(fc.data_path, fc.array_index)] = (co[0::2], co[1::2], {p.type for p in points}, fc)
    return out


def _bone_groups(curves: dict) -> dict:
    groups = defaultdict(dict)
    for (path, index), curve in curves.items():
        if path.startswith("pose.bones") and not path.endswith(".location"):  # rotations
            groups[path][index] = curve
    return groups


MODES = {"rotation_quaternion": "QUATERNION", "rotation_axis_angle": "AXIS_ANGLE"}


@pytest.mark.parametrize("rig,fps", [("beat", 29.97), ("readyplayerme", 24.0)])
def test_default_keys_are_sparse_poses_within_the_bound(motion, rig, fps):
    """Every frame first (the generated motion, exactly), then the default poses on the same
    objects: every frame of every bone within 1 degree and every shape key within 0.02, at
    most 3 keys per second per bone and 2 per shape key on average, each bone's rotation
    channels keyed on the same frames, every key GENERATED with Bezier handles."""
    scene = reset_scene(fps=fps)
    armature, faces, preset = _targets(rig)
    every = BakeOptions(armature=armature, face_meshes=faces, preset=preset, every_frame=True, add_sound=False)
    bake_motion(scene, motion, None, every)
    dense = {id(ob): _curves(ob) for ob in [armature] + [f.data.shape_keys for f in faces]}
    result = bake_motion(scene, motion, None, BakeOptions(armature=armature, face_meshes=faces, preset=preset,
                                                          add_sound=False))
    frames = np.arange(1, 1 + result.n_frames, dtype=np.float64)
    seconds = result.n_frames / fps

    sparse = _curves(armature)
    bone_rates, worst_angle = [], 0.0
    for path, channels in _bone_groups(sparse).items():
        key_frames = [tuple(c[0]) for c in channels.values()]
        assert len(set(key_frames)) == 1, f"{path}: channels keyed on different frames"
        mode = MODES.get(path.rsplit(".", 1)[1], armature.pose.bones[path.split('"')[1]].rotation_mode)
        got = np.stack([[channels[i][3].evaluate(f) for f in frames] for i in sorted(channels)], axis=1)
        want = np.stack([dense[id(armature)][(path, i)][1] for i in sorted(channels)], axis=1)
        angle = rotation_angle(to_quaternions(got, mode), to_quaternions(want.astype(np.float64), mode))
        worst_angle = max(worst_angle, float(angle.max()))
        bone_rates.append(len(key_frames[0]) / seconds)
    assert worst_angle <= 1.0 + 1e-3, worst_angle
    assert len(bone_rates) >= 20 and np.mean(bone_rates) <= 3.0, np.mean(bone_rates)

    face_rates, worst_face = [], 0.0
    for face in faces:
        key = face.data.shape_keys
        for name, (co_f, co_v, types, fc) in _curves(key).items():
            want = dense[id(key)][name][1]
            got = np.array([fc.evaluate(f) for f in frames])
            worst_face = max(worst_face, float(np.abs(got - want).max()))
            face_rates.append(len(co_f) / seconds)
    assert worst_face <= 0.02 + 1e-4, worst_face
    assert len(face_rates) >= 40 and np.mean(face_rates) <= 2.0, np.mean(face_rates)

    for ob in [armature] + [f.data.shape_keys for f in faces]:
        for fc in fcurves_of(ob):
            assert {p.type for p in fc.keyframe_points} == {"GENERATED"}
            assert {p.interpolation for p in fc.keyframe_points} == {"BEZIER"}
            assert {p.handle_left_type for p in fc.keyframe_points} == {"ALIGNED"}


def test_keys_fall_on_the_motions_turning_points(motion):
    """A bone's keys between its first and last are poses: most sit within a frame of a
    local minimum of the bone's speed (where its motion turns or holds). The upper body's:
    the hips and legs are keyed within a tighter bound that keeps the feet planted."""
    from blender_addon.scene.retarget import LOWER_BODY as LOWER
    from diffsheg_core.keyframes import turning_points

    scene = reset_scene(fps=24)
    armature, faces, preset = _targets("beat")
    bake_motion(scene, motion, None, BakeOptions(armature=armature, preset=preset, every_frame=True,
                                                 add_sound=False))
    dense = _bone_groups(_curves(armature))
    bake_motion(scene, motion, None, BakeOptions(armature=armature, preset=preset, add_sound=False))
    on, total = 0, 0
    for path, channels in _bone_groups(_curves(armature)).items():
        if path.split('"')[1] in LOWER:
            continue
        values = np.stack([dense[path][i][1] for i in sorted(dense[path])], axis=1).astype(np.float64)
        turns = turning_points(values) + 1
        keys = channels[0][0][1:-1]
        on += int(sum(np.abs(turns - k).min() <= 1 for k in keys)) if len(turns) else 0
        total += len(keys)
    assert total > 0 and on >= 0.7 * total, (on, total)  # about 47 % of all frames are that close


def test_every_frame_keys_each_frame_and_bad_bounds_are_refused(motion):
    scene = reset_scene(fps=24)
    armature, faces, preset = _targets("beat")
    result = bake_motion(scene, motion, None, BakeOptions(armature=armature, face_meshes=faces, preset=preset,
                                                          every_frame=True, add_sound=False))
    for fc in fcurves_of(armature) + fcurves_of(faces[0].data.shape_keys):
        assert len(fc.keyframe_points) == result.n_frames
        assert {p.type for p in fc.keyframe_points} == {"GENERATED"}
    for bad in ({"max_error": 0.0}, {"max_error": float("nan")}, {"max_face_error": -1.0},
                {"smoothing": float("nan")}):
        with pytest.raises(DiffshegError, match="must be a number"):
            BakeOptions(armature=armature, **bad)
