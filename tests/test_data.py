"""Dataset readers on small fixtures written in the public BEAT, BEAT2 and Live Link Face
formats from the real take 2_scott_0_1_1 (motion capture, SMPL-X and audio), broken
takes included."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from diffsheg_core.bvh import bvh_to_motion, read_bvh, write_bvh_data
from diffsheg_core.training.corpus.build import MANIFEST, BuildConfig, build, read_manifest
from diffsheg_core.training.corpus.teacher import load_utterance
from diffsheg_core.training.data import (
    ClipDataset, DataConfig, load_takes, normalisation, official_stats, window_starts,
)
from diffsheg_core.training.data.beat2 import read_motion
from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import Motion, write_arkit_json, write_livelink_csv
from diffsheg_core.rigs import ARKIT51, BEAT, BEAT_BODY, SMPLX

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
REAL_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
REAL_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
REAL_NPZ = DATA / "beat2" / "2_scott_0_1_1.npz"
SECONDS = 5.0


def _audio(start: float, seconds: float = SECONDS) -> tuple[np.ndarray, int]:
    y, sr = sf.read(REAL_WAV, dtype="float32")
    return y[int(start * sr): int((start + seconds) * sr)], sr


def _write_wav(path: Path, start: float, seconds: float = SECONDS) -> None:
    y, sr = _audio(start, seconds)
    path.parent.mkdir(parents=True, exist_ok=True)
    sf.write(path, y, sr)


def _write_bvh(path: Path, start: float, fps: float = 120.0, seconds: float = SECONDS) -> None:
    """A BEAT-format BVH of the real capture from `start`, at `fps` (15 fps rows repeated to
    reach a multiple of 15 fps; other rates keep the 15 fps rows and just claim `fps`)."""
    data = read_bvh(REAL_BVH, fps=15.0)
    rows = data.frames[1 + int(start * 15): 1 + int((start + seconds) * 15)]  # row 0: template pose
    out = data.copy()
    out.frames = np.repeat(rows, int(fps // 15), axis=0) if fps % 15 == 0 else rows
    out.frame_time = 1.0 / fps
    write_bvh_data(out, path)


def _face(seconds: float, fps: float, seed: int) -> Motion:
    n = int(seconds * fps)
    t = np.arange(n) / fps
    face = np.random.default_rng(seed).uniform(0, 0.2, size=(n, len(ARKIT51)))
    face[:, ARKIT51.index("jawOpen")] = 0.3 + 0.3 * np.sin(2 * np.pi * 3 * t)
    return Motion(fps=fps, rig="beat", joint_names=[], rotations=np.zeros((n, 0, 3)),
                  face_names=list(ARKIT51), face=face)


@pytest.fixture(scope="module")
def beat_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("beat")
    d = root / "2"
    for i, start in ((1, 0.0), (2, 10.0), (3, 20.0)):
        name = f"2_scott_0_{i}_{i}"
        _write_wav(d / f"{name}.wav", start)
        _write_bvh(d / f"{name}.bvh", start)
        write_arkit_json(_face(SECONDS, 60.0, i), d / f"{name}.json")
    (d / "2_scott_0_3_3.json").unlink()  # a take without face capture keeps its body
    # broken takes
    _write_wav(d / "2_scott_0_4_4.wav", 30.0, seconds=2.0)  # audio shorter than motion
    _write_bvh(d / "2_scott_0_4_4.bvh", 30.0)
    _write_wav(d / "2_scott_0_5_5.wav", 40.0)  # NaN in the motion
    _write_bvh(d / "2_scott_0_5_5.bvh", 40.0)
    lines = (d / "2_scott_0_5_5.bvh").read_text().splitlines()
    lines[-3] = " ".join(["nan"] + lines[-3].split()[1:])
    (d / "2_scott_0_5_5.bvh").write_text("\n".join(lines) + "\n")
    _write_wav(d / "2_scott_0_6_6.wav", 45.0)  # a joint of the layout is missing
    _write_bvh(d / "2_scott_0_6_6.bvh", 45.0)
    text = (d / "2_scott_0_6_6.bvh").read_text().replace("JOINT RightHandIndex2", "JOINT RightHandIdx2")
    (d / "2_scott_0_6_6.bvh").write_text(text)
    _write_wav(d / "2_scott_0_7_7.wav", 50.0)  # wrong frame rate: 50 fps is no multiple of 15
    _write_bvh(d / "2_scott_0_7_7.bvh", 50.0, fps=50.0)
    _write_wav(d / "2_scott_0_8_8.wav", 55.0)  # audio without motion
    (root / "train_test_split.csv").write_text(
        "id,type\n" + "".join(f"2_scott_0_{i}_{i},{'val' if i == 2 else 'train'}\n" for i in range(1, 9)))
    return root


def test_beat_reader_reads_good_takes_and_skips_broken_ones(beat_root, tmp_path):
    config = DataConfig(kind="beat", root=str(beat_root), clip_len=34, stride=10,
                        cache_dir=str(tmp_path / "cache"))
    train = load_takes(config, "train")
    assert [t.name for t in train.takes] == ["2_scott_0_1_1", "2_scott_0_3_3"]
    reasons = dict(train.skipped)
    assert set(reasons) == {f"2_scott_0_{i}_{i}" for i in (4, 5, 6, 7, 8)}
    assert "audio" in reasons["2_scott_0_4_4"] and "shorter than the motion" in reasons["2_scott_0_4_4"]
    assert "NaN" in reasons["2_scott_0_5_5"]
    assert "RightHandIndex2" in reasons["2_scott_0_6_6"]
    assert "50 fps" in reasons["2_scott_0_7_7"]
    assert "2_scott_0_8_8.bvh" in reasons["2_scott_0_8_8"]

    take = train.takes[0]
    assert take.motion.shape == (int(SECONDS * 15), BEAT.dim) and take.mel.shape == (len(take.motion), 128)
    assert take.style == 1  # speaker 2
    # gestures equal the real capture's 15 fps frames (axis-angle of its Euler angles)
    real = bvh_to_motion(read_bvh(REAL_BVH, fps=15.0), BEAT).rotations.reshape(-1, BEAT.gesture_dim)
    np.testing.assert_allclose(take.motion[:, : BEAT.gesture_dim], real[: len(take.motion)], atol=1e-4)
    jaw = take.motion[:, BEAT.gesture_dim + ARKIT51.index("jawOpen")]
    t = np.arange(len(jaw)) / 15.0
    np.testing.assert_allclose(jaw, 0.3 + 0.3 * np.sin(2 * np.pi * 3 * t), atol=2e-3)
    assert take.mask.all() and not train.takes[1].mask[BEAT.gesture_dim:].any()

    val = load_takes(config, "val")
    assert [t.name for t in val.takes] == ["2_scott_0_2_2"]


def test_cache_reuses_entries_until_a_file_changes(beat_root, tmp_path):
    config = DataConfig(kind="beat", root=str(beat_root), cache_dir=str(tmp_path / "cache"))
    first = load_takes(config, "val").takes[0]
    entries = list((tmp_path / "cache").glob("*.npz"))
    assert len(entries) == 1
    again = load_takes(config, "val").takes[0]
    np.testing.assert_array_equal(first.motion, again.motion)
    np.testing.assert_array_equal(first.mel, again.mel)
    assert list((tmp_path / "cache").glob("*.npz")) == entries
    assert (load_takes(DataConfig(kind="beat", root=str(beat_root), fps=30.0,
                                  cache_dir=str(tmp_path / "cache")), "val").takes[0].n_frames
            == 2 * first.n_frames)
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2


def test_clips_and_normalisation(beat_root):
    config = DataConfig(kind="beat", root=str(beat_root), clip_len=34, stride=10)
    train = load_takes(config, "train")
    stats = normalisation(config, train)
    assert stats.mean.shape == (BEAT.dim,)
    # the face channels come only from the take that has them
    face = train.takes[0].motion[:, BEAT.gesture_dim:]
    np.testing.assert_allclose(stats.mean[BEAT.gesture_dim:], face.mean(axis=0), atol=1e-5)
    clips = ClipDataset(train.takes, 34, 10, stats)
    per_take = len(window_starts(int(SECONDS * 15), 34, 10))
    assert per_take == 5 and len(clips) == 2 * per_take
    item = clips[per_take + 1]  # second window of the take without face
    assert item["motion"].shape == (34, BEAT.dim) and item["mel"].shape == (34, 128)
    assert item["mask"][: BEAT.gesture_dim].all() and not item["mask"][BEAT.gesture_dim:].any()
    assert float(item["motion"][:, BEAT.gesture_dim:].abs().max()) == 0.0
    stacked = np.concatenate([clips._normalised[0]])
    assert abs(float(stacked[:, BEAT.gesture_dim:].mean())) < 0.2

    official = normalisation(DataConfig(kind="beat", root=str(beat_root), stats=str(DATA / "beat")), train)
    np.testing.assert_allclose(official.mean[:141], np.load(DATA / "beat" / "axis_angle_mean.npy"), rtol=1e-6)
    with pytest.raises(DiffshegError, match="no training clips"):
        ClipDataset(train.takes, 1000, 10, stats)


def _write_beat2_npz(path: Path, start: float, seconds: float = SECONDS, **change) -> None:
    with np.load(REAL_NPZ, allow_pickle=True) as z:
        arrays = {k: z[k] for k in z.files}
    a, b = int(start * 30), int((start + seconds) * 30)
    for k in ("poses", "expressions", "trans"):
        arrays[k] = arrays[k][a:b]
    arrays.update(change)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)


@pytest.fixture(scope="module")
def beat2_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("beat2")
    good = {"2_scott_0_1_1": 0.0, "2_scott_0_2_2": 10.0, "4_lawrence_0_3_3": 20.0}
    for name, start in good.items():
        _write_wav(root / "wave16k" / f"{name}.wav", start)
        _write_beat2_npz(root / "smplxflame_30" / f"{name}.npz", start)
    _write_wav(root / "wave16k" / "2_scott_0_4_4.wav", 30.0)
    with np.load(REAL_NPZ) as z:
        poses = z["poses"][900:1050].copy()
    _write_beat2_npz(root / "smplxflame_30" / "2_scott_0_4_4.npz", 30.0, poses=poses[:, :150])
    _write_wav(root / "wave16k" / "2_scott_0_5_5.wav", 40.0)
    _write_beat2_npz(root / "smplxflame_30" / "2_scott_0_5_5.npz", 40.0, mocap_frame_rate=np.int32(25))
    poses = poses.copy()
    poses[7, 5] = np.nan
    _write_wav(root / "wave16k" / "2_scott_0_6_6.wav", 30.0)
    _write_beat2_npz(root / "smplxflame_30" / "2_scott_0_6_6.npz", 30.0, poses=poses)
    _write_wav(root / "wave16k" / "2_scott_0_7_7.wav", 45.0)  # its motion file is missing
    rows = [("2_scott_0_1_1", "train"), ("2_scott_0_2_2", "test"), ("4_lawrence_0_3_3", "train"),
            ("2_scott_0_4_4", "train"), ("2_scott_0_5_5", "train"), ("2_scott_0_6_6", "train"),
            ("2_scott_0_7_7", "train")]
    (root / "train_test_split.csv").write_text("id,type\n" + "".join(f"{a},{b}\n" for a, b in rows))
    return root


def test_beat2_reader(beat2_root):
    config = DataConfig(kind="beat2", root=str(beat2_root), clip_len=34)
    assert config.layout is SMPLX
    train = load_takes(config, "train")
    assert [t.name for t in train.takes] == ["2_scott_0_1_1", "4_lawrence_0_3_3"]
    assert [t.style for t in train.takes] == [1, 3]
    reasons = dict(train.skipped)
    assert "joints are missing" in reasons["2_scott_0_4_4"]
    assert "25 fps" in reasons["2_scott_0_5_5"]
    assert "NaN" in reasons["2_scott_0_6_6"]
    assert "2_scott_0_7_7.npz" in reasons["2_scott_0_7_7"]

    take = train.takes[0]
    assert take.motion.shape == (int(SECONDS * 15), SMPLX.dim)
    with np.load(REAL_NPZ) as z:
        poses, expressions = z["poses"][::2], z["expressions"][::2]
    rotations, face = SMPLX.split(take.motion)
    np.testing.assert_allclose(rotations[:, SMPLX.joint_names.index("jaw")], poses[: len(face), 66:69], atol=1e-6)
    np.testing.assert_allclose(rotations[:, SMPLX.joint_names.index("right_wrist")],
                               poses[: len(face), 63:66], atol=1e-6)
    np.testing.assert_allclose(face, expressions[: len(face)], atol=1e-6)
    assert [t.name for t in load_takes(config, "test").takes] == ["2_scott_0_2_2"]
    stats = official_stats(SMPLX, DATA / "show")
    assert stats.mean.shape == (SMPLX.dim,)


def test_beat2_full_real_take_reads_at_15_fps():
    motion = read_motion(REAL_NPZ, 15.0)
    assert motion.shape == (953, SMPLX.dim)


@pytest.fixture(scope="module")
def folder_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("recordings")
    _write_wav(root / "talk_a.wav", 0.0)
    _write_bvh(root / "talk_a.bvh", 0.0, fps=30.0)
    write_livelink_csv(_face(SECONDS, 60.0, 1), root / "talk_a.csv")
    _write_wav(root / "talk_b.wav", 10.0)  # face only, as an ARKit JSON
    write_arkit_json(_face(SECONDS, 60.0, 2), root / "talk_b.json")
    _write_wav(root / "talk_c.wav", 20.0)  # body only
    _write_bvh(root / "talk_c.bvh", 20.0, fps=120.0)
    _write_wav(root / "talk_d.wav", 30.0)  # nothing to learn from
    (root / "talk_e.wav").write_bytes(b"RIFF not really audio")
    _write_bvh(root / "talk_e.bvh", 30.0)
    return root


def test_folder_reader(folder_root):
    config = DataConfig(kind="folder", root=str(folder_root), val_fraction=0.0, style=3)
    train = load_takes(config, "train")
    assert [t.name for t in train.takes] == ["talk_a", "talk_b", "talk_c"]
    assert {t.style for t in train.takes} == {3}
    a, b, c = train.takes
    assert a.mask.all()
    assert not b.mask[: BEAT.gesture_dim].any() and b.mask[BEAT.gesture_dim:].all()
    assert c.mask[: BEAT.gesture_dim].all() and not c.mask[BEAT.gesture_dim:].any()
    real = bvh_to_motion(read_bvh(REAL_BVH, fps=15.0), BEAT).rotations.reshape(-1, BEAT.gesture_dim)
    np.testing.assert_allclose(a.motion[:, : BEAT.gesture_dim], real[: len(a.motion)], atol=1e-4)
    jaw = a.motion[:, BEAT.gesture_dim + ARKIT51.index("jawOpen")]
    np.testing.assert_allclose(jaw, 0.3 + 0.3 * np.sin(2 * np.pi * 3 * np.arange(len(jaw)) / 15), atol=2e-3)
    reasons = dict(train.skipped)
    assert set(reasons) == {"talk_d", "talk_e"}
    assert "no motion for this audio" in reasons["talk_d"]
    assert "talk_e.wav" in reasons["talk_e"]


@pytest.fixture(scope="module")
def corpus_root(tmp_path_factory):
    """A two-sentence corpus made by the real builder, plus a failed utterance in its
    manifest and one whose motion file is damaged."""
    out = tmp_path_factory.mktemp("corpus")
    text = out / "two.txt"
    text.write_text("Peter and Bob bought a map of the big park.\n\n"
                    "My father always opens the window before breakfast.")
    root = out / "c"
    build(BuildConfig(out=root, hours=12 / 3600, jobs=1, seed=3, engines=("espeak",), text_files=(text,)),
          progress=False)
    good = sorted(read_manifest(root).values(), key=lambda r: r["index"])
    damaged = dict(good[0], index=len(good), wav="utt/damaged.wav", npz="utt/damaged.npz")
    (root / damaged["wav"]).write_bytes((root / good[0]["wav"]).read_bytes())
    (root / damaged["npz"]).write_bytes(b"PK not an npz")
    with open(root / MANIFEST, "a") as fh:
        fh.write(json.dumps({"index": len(good) + 1, "error": "espeak-ng rejected the text"}) + "\n")
        fh.write(json.dumps(damaged) + "\n")
    return root, good


def test_corpus_reader(corpus_root, tmp_path):
    from diffsheg_core.training.corpus.teacher import STYLE_NAMES

    root, good = corpus_root
    config = DataConfig(kind="corpus", root=str(root), val_fraction=0.0, style=2, clip_len=16,
                        cache_dir=str(tmp_path / "cache"))
    assert config.layout is BEAT
    train = load_takes(config, "train")
    assert [t.name for t in train.takes] == [Path(r["wav"]).stem for r in good]
    reasons = dict(train.skipped)
    assert len(reasons) == 2
    assert any("espeak-ng rejected the text" in r for r in reasons.values())
    assert any("damaged.npz" in r and "rebuild the corpus" in r for r in reasons.values())

    for take, record in zip(train.takes, good):
        motion, _, info = load_utterance(root / record["npz"])
        # the teacher's named gesture style is the class; the data's own style only stands in
        # for utterances of a corpus made before named styles
        assert take.style == STYLE_NAMES.index(info["style"]) and take.mask.all()
        assert abs(take.n_frames - record["frames"]) <= 1 and take.mel.shape == (take.n_frames, 128)
        upper = motion.rotations[:, :len(BEAT.gesture_joints)]
        np.testing.assert_allclose(take.motion, BEAT.join(upper, motion.face)[: take.n_frames])
    # the teacher's jaw moves with the speech, and the clips are cut and normalised
    jaw = np.concatenate([t.motion[:, BEAT.gesture_dim + ARKIT51.index("jawOpen")] for t in train.takes])
    assert jaw.max() > 0.2 and jaw.min() < 0.05
    clips = ClipDataset(train.takes, 16, 8, normalisation(config, train))
    assert len(clips) > 0 and clips[0]["motion"].shape == (16, BEAT.dim)
    again = load_takes(config, "train")
    np.testing.assert_array_equal(again.takes[0].mel, train.takes[0].mel)
    assert len(list((tmp_path / "cache").glob("*.npz"))) == len(good)

    # whole_body: the teacher's hips, legs and hips' translation too (layout beat_body)
    whole = load_takes(replace(config, whole_body=True), "train")
    assert whole.layout is BEAT_BODY and [t.name for t in whole.takes] == [t.name for t in train.takes]
    for take, record in zip(whole.takes, good):
        motion, _, _ = load_utterance(root / record["npz"])
        assert take.motion.shape[1] == BEAT_BODY.dim == 222
        np.testing.assert_allclose(take.motion, BEAT_BODY.join(motion.rotations, motion.face,
                                                               motion.root_translation)[: take.n_frames])
    with pytest.raises(DiffshegError, match="whole_body needs the project's corpus"):
        _ = DataConfig(kind="beat", whole_body=True).layout
    # an utterance of an older teacher has no legs: named, with the fix
    from diffsheg_core.lower_body import upper_body
    from diffsheg_core.training.corpus.teacher import save_utterance
    from diffsheg_core.training.data import corpus as corpus_reader
    from diffsheg_core.training.data.sources import TakeSource

    motion, phones, info = load_utterance(root / good[0]["npz"])
    old = save_utterance(tmp_path / "old.npz", upper_body(motion), phones, {**info, "teacher_version": 3})
    source = TakeSource("old", {"audio": root / good[0]["wav"], "motion": old}, 0, None)
    assert corpus_reader.read_take(source, config).motion.shape[1] == BEAT.dim
    with pytest.raises(DiffshegError, match=r"holds no lower body \(teacher v3\): whole_body needs a corpus built "
                                            "with teacher v4 or later"):
        corpus_reader.read_take(source, replace(config, whole_body=True))


def test_bad_configuration_is_reported(tmp_path):
    with pytest.raises(DiffshegError, match="does not exist"):
        load_takes(DataConfig(kind="beat", root=str(tmp_path / "nowhere")))
    with pytest.raises(DiffshegError, match="unknown dataset kind"):
        load_takes(DataConfig(kind="mocap", root=str(tmp_path)))
    (tmp_path / "train_test_split.csv").write_text("name,split\nx,train\n")
    with pytest.raises(DiffshegError, match="columns 'id' and 'type'"):
        load_takes(DataConfig(kind="beat2", root=str(tmp_path)))
    with pytest.raises(DiffshegError, match="no manifest.jsonl: build the corpus"):
        load_takes(DataConfig(kind="corpus", root=str(tmp_path)))
