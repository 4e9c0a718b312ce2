"""BEAT semantic relevance annotations: reading, per-frame weights, SRGR, and `evaluate`
reporting SRGR on the real BEAT take."""

import json
from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.errors import DiffshegError
from diffsheg_core.training.metrics import (
    SemanticSpan, find_semantic, pcm, read_semantic, semantic_weights, srgr,
)

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
TAKE_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
FPS = 15.0

# BEAT's layout: tab separated, no header; name, start, end, duration (s), score, keywords
ANNOTATION = (
    "deictic\t1.0\t2.0\t1.0\t0.5\tthis one\n"
    "metaphoric\t1.8\t3.0\t1.2\t1.0\tidea\n"
    "\n"
    "iconic\t10.25\t12.5\t2.25\t0.8\t\n"
    "beat\t20.0\t21.0\t1.0\t0.2\n"
)


def _write(tmp_path: Path, text: str, name: str = "2_scott_0_1_1.txt") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_read_semantic_parses_beat_annotation(tmp_path):
    spans = read_semantic(_write(tmp_path, ANNOTATION))
    assert spans == [
        SemanticSpan("deictic", 1.0, 2.0, 0.5, "this one"),
        SemanticSpan("metaphoric", 1.8, 3.0, 1.0, "idea"),
        SemanticSpan("iconic", 10.25, 12.5, 0.8, ""),
        SemanticSpan("beat", 20.0, 21.0, 0.2, ""),  # keywords column left out
    ]


def test_semantic_weights_take_the_first_covering_span_and_zero_elsewhere(tmp_path):
    w = semantic_weights(read_semantic(_write(tmp_path, ANNOTATION)), 400, FPS)
    assert w.shape == (400,)
    assert w[14] == 0.0 and w[15] == 0.5  # t = 1.0: start included
    assert w[30] == 0.5  # t = 2.0: end included, the first span wins the overlap
    assert w[31] == 1.0 and w[45] == 1.0 and w[46] == 0.0  # 2.07 s .. 3.0 s
    assert w[154] == 0.8 and w[153] == 0.0  # 10.27 s
    assert w[300] == 0.2 and w[316] == 0.0
    assert np.count_nonzero(w) == 16 + 15 + 34 + 16
    assert semantic_weights([], 10, FPS).tolist() == [0.0] * 10


def test_srgr_weights_frames_by_semantic_relevance():
    n = 60
    gt = np.random.default_rng(0).normal(size=(n, 12))
    spans = [SemanticSpan("deictic", 1.0, 2.0, 1.0), SemanticSpan("iconic", 3.0, 3.5, 0.5)]
    w = semantic_weights(spans, n, FPS)
    inside_a, inside_b = w == 1.0, w == 0.5
    assert inside_a.sum() == 16 and inside_b.sum() == 8
    assert srgr(gt, gt, w) == 1.0
    assert srgr(gt + 5.0, gt, w) == 0.0
    right_in_spans = gt + np.where(w[:, None] > 0, 0.0, 5.0)
    assert srgr(right_in_spans, gt, w) == 1.0  # frames outside spans weigh 0
    assert pcm(right_in_spans, gt) == pytest.approx(24 / 60)
    right_in_a = gt + np.where(inside_a[:, None], 0.0, 5.0)
    assert srgr(right_in_a, gt, w) == pytest.approx(16 * 1.0 / (16 * 1.0 + 8 * 0.5))
    one_joint_off = right_in_a.copy()
    one_joint_off[:, :3] += 5.0  # one joint of four wrong everywhere
    assert srgr(one_joint_off, gt, w) == pytest.approx(0.75 * 0.8)


@pytest.mark.parametrize("text, line, what", [
    ("deictic\t1.0\t2.0\t1.0\t0.5\tyou\niconic\t1.0\t2.0\n", 2, "6 tab-separated columns"),
    ("\ndeictic 1.0 2.0 1.0 0.5 you\n", 2, "6 tab-separated columns"),
    ("deictic\t1.0\t2.0\t1.0\t0.5\t\niconic\t00:01.0\t2.0\t1.0\t0.5\tyou\n", 2, "must be numbers"),
    ("a\t1\t2\t1\t1\tx\nb\t2\t3\t1\t1\tx\nc\t5.0\t4.0\t1.0\t0.5\tyou\n", 3, "end >= start"),
    ("deictic\t1.0\t2.0\t1.0\t-1\tyou\n", 1, "score >= 0"),
])
def test_broken_annotation_names_file_and_line(tmp_path, text, line, what):
    path = _write(tmp_path, text, "broken.txt")
    with pytest.raises(DiffshegError, match=f"broken.txt, line {line}: .*{what}.*fix the line"):
        read_semantic(path)


def test_missing_annotation_file(tmp_path):
    with pytest.raises(DiffshegError, match="absent.txt: semantic annotation file not found"):
        read_semantic(tmp_path / "absent.txt")


def test_find_semantic_in_beat_layouts(tmp_path):
    release = tmp_path / "release" / "2"
    release.mkdir(parents=True)
    beside = _write(release, ANNOTATION)
    assert find_semantic(release / "2_scott_0_1_1.bvh") == beside
    assert find_semantic(release / "2_scott_0_1_1.npz") is None  # a .txt beside counts for BEAT .bvh only
    cache = tmp_path / "cache"
    (cache / "sem").mkdir(parents=True)
    sem = _write(cache / "sem", ANNOTATION)
    assert find_semantic(cache / "bvh_rot" / "2_scott_0_1_1.bvh") == sem
    assert find_semantic(cache / "smplxflame_30" / "2_scott_0_1_1.npz") == sem
    assert find_semantic(cache / "bvh_rot" / "other_take.bvh") is None


# ---------------------------------------------------------------- the evaluate command

@pytest.fixture(scope="module")
def take():
    from diffsheg_core.bvh import bvh_to_motion, read_bvh

    return bvh_to_motion(read_bvh(TAKE_BVH, fps=FPS))


def _as_sample(take, rotations: np.ndarray):
    """A generated-looking motion (neutral face) with the take's joints and `rotations`."""
    from diffsheg_core.motion import Motion
    from diffsheg_core.rigs import ARKIT51

    return Motion(fps=FPS, rig="beat", joint_names=take.joint_names, rotations=rotations,
                  face_names=list(ARKIT51), face=np.zeros((take.n_frames, 51), np.float32))


def test_evaluate_reports_srgr_from_the_annotation_beside_a_beat_take(take, tmp_path):
    """The real BEAT take as reference in the training layout (bvh_rot/ + sem/); the sample
    is the capture itself, wrong on every joint outside the annotated gestures."""
    from diffsheg_core.training.evaluate import main

    (tmp_path / "bvh_rot").mkdir()
    (tmp_path / "sem").mkdir()
    reference = tmp_path / "bvh_rot" / TAKE_BVH.name
    reference.symlink_to(TAKE_BVH)
    _write(tmp_path / "sem", ANNOTATION)
    annotated = semantic_weights(read_semantic(tmp_path / "sem" / "2_scott_0_1_1.txt"), take.n_frames, FPS) > 0
    wrong_outside = take.rotations + np.where(annotated[:, None, None], 0.0, 2.0)
    sample = tmp_path / "gen.npz"
    _as_sample(take, wrong_outside).save_npz(sample)
    out = tmp_path / "report"
    assert main(["--audio", str(TAKE_WAV), "--motion", str(sample), "--reference", str(reference),
                 "--reference-fps", "15", "--out", str(out), "--no-plots"]) == 0
    cmp = json.loads((out / "metrics.json").read_text())["comparison"]
    assert cmp["SRGR gesture (delta 1.0)"] == pytest.approx(1.0)
    assert cmp["PCM gesture (delta 1.0)"] == pytest.approx(annotated.mean())
    report = (out / "report.md").read_text()
    assert "SRGR gesture (delta 1.0)" in report and "sem/2_scott_0_1_1.txt" in report

    # an explicit --semantic wins over the one found beside the reference
    elsewhere = _write(tmp_path, "iconic\t30.0\t40.0\t10.0\t1.0\tthat\n", "late.txt")
    late = (np.arange(take.n_frames) / FPS >= 30.0) & (np.arange(take.n_frames) / FPS <= 40.0)
    assert not annotated[late].any()
    assert main(["--audio", str(TAKE_WAV), "--motion", str(sample), "--reference", str(reference),
                 "--reference-fps", "15", "--semantic", str(elsewhere), "--out", str(out), "--no-plots"]) == 0
    assert json.loads((out / "metrics.json").read_text())["comparison"]["SRGR gesture (delta 1.0)"] == 0.0


def test_evaluate_without_srgr_cases(take, tmp_path):
    from diffsheg_core.training.evaluate import EvalInputs, comparison_metrics, main
    from diffsheg_core.rigs import get_layout

    layout = get_layout("beat")
    sample = _as_sample(take, take.rotations)
    inputs = EvalInputs(samples=[sample], audio=None, reference=take,
                        semantic=[SemanticSpan("iconic", 500.0, 510.0, 1.0)])
    cmp = comparison_metrics(inputs, layout)  # the annotation lies past the end of the take
    assert "SRGR gesture (delta 1.0)" not in cmp and cmp["PCM gesture (delta 1.0)"] == 1.0
    assert inputs.notes == ["no semantic gesture annotated in the compared frames: no SRGR"]
    assert "SRGR gesture (delta 1.0)" not in comparison_metrics(EvalInputs([sample], None, take), layout)
    annotation = _write(tmp_path, ANNOTATION)
    with pytest.raises(DiffshegError, match="give --reference too"):
        main(["--audio", str(TAKE_WAV), "--motion", str(tmp_path / "gen.npz"), "--semantic", str(annotation)])
