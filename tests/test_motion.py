"""Motion: npz round trip, frame-rate resampling, ARKit JSON and Live Link Face CSV."""

import json
from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.bvh import bvh_to_motion, read_bvh
from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import (
    LIVELINK_BLENDSHAPES, LIVELINK_HEAD, Motion, arkit_name, nominal_fps, read_arkit_json,
    read_livelink_csv, resample_motion, write_arkit_json, write_livelink_csv,
)
from diffsheg_core.rigs import ARKIT51, ARKIT52, SMPLX, SMPLX_JOINTS
from diffsheg_core.rotations import axis_angle_to_matrix, matrix_to_axis_angle

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SCENE_RATES = [24.0, 25.0, 30000 / 1001, 30.0, 60.0]


@pytest.fixture(scope="module")
def beat_motion() -> Motion:
    """The real BEAT take's 47 joints, with face weights drawn around the official
    BEAT ARKit statistics (the project has no real ARKit recording)."""
    body = bvh_to_motion(read_bvh(DATA / "beat" / "2_scott_0_1_1.bvh", fps=15))
    mean = np.load(DATA / "beat" / "facial51_mean.npy")
    std = np.load(DATA / "beat" / "facial51_std.npy")
    noise = np.random.default_rng(0).normal(size=(body.n_frames + 4, 51))
    smooth = np.stack([np.convolve(noise[:, k], np.ones(5) / 5, mode="valid") for k in range(51)], axis=1)
    face = np.clip(mean + 2.0 * std * smooth, 0.0, 1.0)
    return Motion(fps=15.0, rig="beat", joint_names=body.joint_names, rotations=body.rotations,
                  face_names=list(ARKIT51), face=face, meta={"seed": 0, "audio": "2_scott_0_1_1.wav"})


@pytest.fixture(scope="module")
def smplx_motion() -> Motion:
    """The same take in BEAT2's SMPL-X form (30 fps), in the 'smplx' layout plus translation."""
    with np.load(DATA / "beat2" / "2_scott_0_1_1.npz") as z:
        poses = z["poses"].reshape(-1, 55, 3)
        expressions, trans, rate = z["expressions"], z["trans"], float(z["mocap_frame_rate"])
    joints = [SMPLX_JOINTS.index(n) for n in SMPLX.joint_names]
    return Motion(fps=rate, rig="smplx", joint_names=list(SMPLX.joint_names), rotations=poses[:, joints],
                  face_names=list(SMPLX.face_names), face=expressions, root_translation=trans)


def _geodesic(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    rel = np.swapaxes(axis_angle_to_matrix(a), -1, -2) @ axis_angle_to_matrix(b)
    return np.linalg.norm(matrix_to_axis_angle(rel), axis=-1)


def test_npz_round_trip(beat_motion, smplx_motion, tmp_path):
    for motion in (beat_motion, smplx_motion):
        back = Motion.load_npz(motion.save_npz(tmp_path / f"{motion.rig}.npz"))
        assert (back.fps, back.rig, back.joint_names, back.face_names, back.meta) == \
            (motion.fps, motion.rig, motion.joint_names, motion.face_names, motion.meta)
        np.testing.assert_array_equal(back.rotations, motion.rotations)
        np.testing.assert_array_equal(back.face, motion.face)
        if motion.root_translation is None:
            assert back.root_translation is None
        else:
            np.testing.assert_array_equal(back.root_translation, motion.root_translation)


def test_npz_bad_file(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, poses=np.zeros(3))
    with pytest.raises(DiffshegError, match="not a motion file"):
        Motion.load_npz(path)


@pytest.mark.parametrize("fps", SCENE_RATES)
def test_resample_motion_to_scene_rates(beat_motion, smplx_motion, fps):
    for motion in (beat_motion, smplx_motion):
        out = resample_motion(motion, fps)
        assert out.fps == fps and out.meta["source_fps"] == motion.fps
        assert abs(out.duration - motion.duration) <= 1.0 / fps
        assert out.joint_names == motion.joint_names and out.face_names == motion.face_names
        assert np.all(np.isfinite(out.rotations))
        assert np.linalg.norm(out.rotations, axis=-1).max() <= np.pi + 1e-5
        # every output frame lies between its two source frames on the rotation's geodesic
        pos = np.minimum(np.arange(out.n_frames) * motion.fps / fps, motion.n_frames - 1)
        lo = np.minimum(np.floor(pos).astype(int), motion.n_frames - 2)
        whole = _geodesic(motion.rotations[lo], motion.rotations[lo + 1])
        parts = _geodesic(motion.rotations[lo], out.rotations) + _geodesic(out.rotations, motion.rotations[lo + 1])
        np.testing.assert_allclose(parts, whole, atol=1e-4)
        lo_face = np.minimum(motion.face[lo], motion.face[lo + 1]) - 1e-5
        hi_face = np.maximum(motion.face[lo], motion.face[lo + 1]) + 1e-5
        assert np.all((out.face >= lo_face) & (out.face <= hi_face))
    assert out.root_translation.shape == (out.n_frames, 3)


def test_resample_motion_keeps_source_frames_at_shared_times(beat_motion):
    out = resample_motion(beat_motion, 60.0)
    assert out.n_frames == 4 * beat_motion.n_frames
    np.testing.assert_allclose(out.face[::4], beat_motion.face, atol=1e-6)
    assert _geodesic(out.rotations[::4], beat_motion.rotations).max() < 1e-5
    again = resample_motion(out, 24.0)
    assert again.meta["source_fps"] == 15.0


def test_resample_motion_rejects_bad_rate(beat_motion):
    with pytest.raises(DiffshegError, match="positive"):
        resample_motion(beat_motion, 0.0)


def test_nominal_fps():
    assert nominal_fps(1 / 0.066667) == 15.0
    assert nominal_fps(1 / 0.008333) == 120.0
    assert nominal_fps(1 / 0.033367) == 30000 / 1001
    assert nominal_fps(17.3) == 17.3


def test_arkit_json_round_trip_in_official_form(beat_motion, tmp_path):
    path = write_arkit_json(beat_motion, tmp_path / "face.json")
    payload = json.loads(path.read_text())
    assert payload["names"] == list(ARKIT51)
    assert len(payload["frames"]) == beat_motion.n_frames
    assert set(payload["frames"][3]) == {"weights", "time"}
    assert payload["frames"][3]["time"] == pytest.approx(0.2)
    curves = read_arkit_json(path)
    assert curves.fps == 15.0 and curves.names == list(ARKIT51)
    np.testing.assert_allclose(curves.weights, beat_motion.face, atol=1e-6)


def test_livelink_csv_layout_and_round_trip(beat_motion, tmp_path):
    path = write_livelink_csv(beat_motion, tmp_path / "take.csv")
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    assert header[:2] == ["Timecode", "BlendShapeCount"]
    assert header[2:54] == list(LIVELINK_BLENDSHAPES) and header[54:] == list(LIVELINK_HEAD)
    assert sorted(arkit_name(n) for n in LIVELINK_BLENDSHAPES) == sorted(ARKIT52)
    assert lines[1].startswith("00:00:00:00.000,61,") and lines[17].startswith("00:00:01:01.000,61,")
    assert all(float(v) == 0.0 for v in lines[5].split(",")[53:])
    curves = read_livelink_csv(path)
    assert curves.fps == 15.0 and curves.names == list(ARKIT52)
    np.testing.assert_allclose(curves.weights[:, :51], beat_motion.face, atol=1e-6)
    np.testing.assert_array_equal(curves.weights[:, 51], 0.0)


def test_livelink_csv_at_ntsc_rate(beat_motion, tmp_path):
    motion = resample_motion(beat_motion, 30000 / 1001)
    curves = read_livelink_csv(write_livelink_csv(motion, tmp_path / "ntsc.csv"))
    assert curves.fps == pytest.approx(30000 / 1001)
    assert len(curves.weights) == motion.n_frames
    np.testing.assert_allclose(curves.weights[:, :51], motion.face, atol=1e-6)


def test_livelink_reader_accepts_camel_case_and_other_column_order(beat_motion, tmp_path):
    path = write_livelink_csv(beat_motion, tmp_path / "take.csv")
    rows = [line.split(",") for line in path.read_text().splitlines()]
    rows[0] = [n[0].lower() + n[1:] if arkit_name(n) else n for n in rows[0]]
    order = [0, 1] + list(range(62, 1, -1))
    camel = tmp_path / "camel.csv"
    camel.write_text("\n".join(",".join(r[k] for k in order) for r in rows) + "\n")
    curves = read_livelink_csv(camel)
    np.testing.assert_allclose(curves.weights[:, :51], beat_motion.face, atol=1e-6)
    assert arkit_name("eyeBlink_L") == "eyeBlinkLeft" and arkit_name("Head") is None


def test_livelink_dropped_frames_are_interpolated(beat_motion, tmp_path):
    path = write_livelink_csv(beat_motion, tmp_path / "take.csv")
    lines = path.read_text().splitlines()
    dropped = tmp_path / "dropped.csv"
    dropped.write_text("\n".join(lines[:11] + lines[12:]) + "\n")  # line 11 is frame 10
    curves = read_livelink_csv(dropped)
    assert curves.fps == 15.0 and len(curves.weights) == beat_motion.n_frames
    np.testing.assert_allclose(curves.weights[10, :51], (beat_motion.face[9] + beat_motion.face[11]) / 2, atol=1e-6)
    np.testing.assert_allclose(curves.weights[20, :51], beat_motion.face[20], atol=1e-6)


def _csv_variant(tmp_path: Path, source: Path, name: str, edit) -> Path:
    rows = [line.split(",") for line in source.read_text().splitlines()]
    edit(rows)
    path = tmp_path / name
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return path


def test_livelink_bad_files(beat_motion, tmp_path):
    good = write_livelink_csv(beat_motion, tmp_path / "take.csv")
    jaw = 2 + LIVELINK_BLENDSHAPES.index("JawOpen")

    def drop_jaw(rows):
        for r in rows:
            del r[jaw]

    def put_nan(rows):
        rows[7][jaw] = "nan"

    def swap(rows):
        rows[5], rows[6] = rows[6], rows[5]

    def no_timecode(rows):
        rows[0][0] = "Time"

    def bad_timecode(rows):
        rows[3][0] = "1.5"

    cases = [
        (drop_jaw, r"missing ARKit blendshape columns: jawOpen"),
        (put_nan, "frame 6 holds NaN"),
        (swap, "time does not increase at frame 5"),
        (no_timecode, "no Timecode column"),
        (bad_timecode, "row 3: Timecode '1.5'"),
    ]
    for k, (edit, message) in enumerate(cases):
        path = _csv_variant(tmp_path, good, f"bad{k}.csv", edit)
        with pytest.raises(DiffshegError, match=message) as info:
            read_livelink_csv(path)
        assert str(path) in str(info.value)
    short = _csv_variant(tmp_path, good, "short.csv", lambda rows: rows.__delitem__(slice(10, None)))
    with pytest.raises(DiffshegError, match="shorter than a second.*timecode_rate"):
        read_livelink_csv(short)
    assert read_livelink_csv(short, timecode_rate=15).fps == 15.0
    with pytest.raises(DiffshegError, match="no such CSV"):
        read_livelink_csv(tmp_path / "absent.csv")


def test_arkit_json_bad_files(beat_motion, tmp_path):
    good = json.loads(write_arkit_json(beat_motion, tmp_path / "face.json").read_text())
    no_time = json.loads(json.dumps(good))
    del no_time["frames"][2]["time"]
    short_frame = json.loads(json.dumps(good))
    short_frame["frames"][2]["weights"] = short_frame["frames"][2]["weights"][:-1]
    backwards = json.loads(json.dumps(good))
    backwards["frames"][4]["time"] = 0.0
    cases = [(no_time, "not an ARKit JSON"), (short_frame, "not an ARKit JSON|one weight per name"),
             (backwards, "time does not increase at frame 4")]
    for k, (payload, message) in enumerate(cases):
        path = tmp_path / f"bad{k}.json"
        path.write_text(json.dumps(payload))
        with pytest.raises(DiffshegError, match=message):
            read_arkit_json(path)
    garbage = tmp_path / "garbage.json"
    garbage.write_text("{not json")
    with pytest.raises(DiffshegError, match="not an ARKit JSON"):
        read_arkit_json(garbage)


def test_face_writers_refuse_non_arkit_motion(smplx_motion, tmp_path):
    with pytest.raises(DiffshegError, match="ARKit.*npz"):
        write_arkit_json(smplx_motion, tmp_path / "x.json")
    with pytest.raises(DiffshegError, match="ARKit.*npz"):
        write_livelink_csv(smplx_motion, tmp_path / "x.csv")


def test_the_whole_body_layout_holds_the_legs_and_the_hips_translation():
    """beat_body: beat's 47 joints, the 9 of the hips and legs, then the hips' translation
    (171 gesture channels), the same face; a Motion of it is on the BEAT skeleton. It widens
    beat (a beat model can be fine-tuned into it), and joining needs the translation."""
    from diffsheg_core.errors import DiffshegError
    from diffsheg_core.rigs import BEAT, BEAT_BODY, BEAT_LOWER_JOINTS, SMPLX, get_layout

    assert get_layout("beat_body") is BEAT_BODY and BEAT_BODY.rig == BEAT.rig == "beat"
    assert BEAT_BODY.gesture_dim == 171 and BEAT_BODY.dim == 222
    assert BEAT_BODY.joint_names == BEAT.joint_names + BEAT_LOWER_JOINTS
    rng = np.random.default_rng(0)
    rotations, face, root = rng.normal(size=(5, 56, 3)), rng.random((5, 51)), rng.normal(size=(5, 3))
    flat = BEAT_BODY.join(rotations, face, root)
    assert flat.shape == (5, 222)
    got_rotations, got_face = BEAT_BODY.split(flat)
    np.testing.assert_array_equal(got_rotations, rotations)
    np.testing.assert_array_equal(got_face, face)
    np.testing.assert_array_equal(BEAT_BODY.root(flat), root)
    assert BEAT.root(flat[:, :192]) is None
    channels = BEAT_BODY.widened_channels(BEAT)
    np.testing.assert_array_equal(flat[:, channels], BEAT.join(rotations[:, :47], face))
    assert BEAT.widened_channels(BEAT_BODY) is None and BEAT_BODY.widened_channels(SMPLX) is None
    with pytest.raises(DiffshegError, match="layout 'beat_body' holds the hips' translation: the motion has none"):
        BEAT_BODY.join(rotations, face)
