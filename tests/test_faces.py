"""A language's own face (issue 42): added to a model file (training/faces.py), stored beside
the shared face, and run in its place by the jobs that name the language, every other job
running the model as it was. On small random models and real speech; the bundled model's
Mandarin face is measured against the real captured face in test_languages.py."""

from dataclasses import replace

import numpy as np
import pytest

from conftest import DATA, random_bundle
from diffsheg_core.audio import Audio, load_audio
from diffsheg_core.checkpoints import (CheckpointError, graph_weights, load_model, read_safetensors,
                                       save_checkpoint, stored_face_languages, write_safetensors)
from diffsheg_core.errors import DiffshegError
from diffsheg_core.pipeline import generate
from diffsheg_core.settings import GenerateSettings
from diffsheg_core.training.faces import add_face, main as add_face_main, remove_face

SPEECH = DATA / "audio" / "lang" / "zh_aishell_1.wav"


@pytest.fixture(scope="module")
def models():
    """A small random model, the same model with another expression branch (as a face-only
    fine-tune of it is), and 2 s of real Mandarin speech."""
    base = random_bundle(seed=3)
    other = random_bundle(seed=4)
    tuned = replace(base, weights={**base.weights, **graph_weights({"expression": other.graphs["expression"]})},
                    graphs={**base.graphs, "expression": other.graphs["expression"]}, model_id="random-small-zh",
                    source="random-small-zh")
    audio = load_audio(SPEECH)
    clip = Audio(audio.samples[: 2 * audio.sample_rate], audio.sample_rate)
    return base, tuned, clip


def test_a_language_s_face_travels_in_the_file_and_runs_in_the_shared_face_s_place(models, tmp_path):
    base, tuned, clip = models
    path = save_checkpoint(add_face(base, tuned, " ZH "), tmp_path / "m.safetensors")
    model = load_model(path)
    assert sorted(model.faces) == stored_face_languages(path) == ["zh"]
    assert model.faces["zh"].graph != tuned.graphs["expression"]  # its products by weights in int8
    assert model.faces["zh"].record["model_id"] == "random-small-zh"
    assert model.graphs == base.graphs and model.live_graphs == base.live_graphs  # the shared face is as it was
    zh = model.for_language("zh")
    assert model.for_language(None) is model and model.for_language("zh") is zh  # made once
    assert zh.graphs["expression"] == model.faces["zh"].graph and zh.graphs["gesture"] == base.graphs["gesture"]
    # a job in the language runs the fine-tuned model's face (its products in int8 change it by
    # far less than a seed does); any other, the model as it was, to the bit
    as_tuned = generate(clip, model=tuned, seed=1)
    in_zh = generate(clip, model=model, seed=1, language="zh")
    shared = generate(clip, model=model, seed=1)
    seed_change = np.abs(generate(clip, model=tuned, seed=2).face - as_tuned.face).mean()
    assert np.abs(in_zh.face - as_tuned.face).mean() < 0.1 * seed_change
    assert np.array_equal(shared.face, generate(clip, model=base, seed=1).face)
    assert np.abs(shared.face - in_zh.face).mean() > 0.5 * seed_change
    assert in_zh.meta["language"] == "zh" and shared.meta["language"] is None
    # taken out again, the file holds what the model's own does, tensor for tensor
    removed = read_safetensors(save_checkpoint(remove_face(model, "zh"), tmp_path / "removed.safetensors"), "")
    own = read_safetensors(save_checkpoint(load_model(save_checkpoint(base, tmp_path / "base.safetensors")),
                                           tmp_path / "base.safetensors"), "")
    assert removed[0] == own[0] and removed[1].keys() == own[1].keys()
    assert all(np.array_equal(v, own[1][k]) for k, v in removed[1].items())


def test_the_torch_backend_and_a_re_export_keep_the_face(models):
    from diffsheg_core.torch_layer.export import with_graphs

    base, tuned, clip = models
    model = add_face(base, tuned, "zh")
    by_onnx = generate(clip, model=model, seed=2, language="zh")
    by_torch = generate(clip, model=model, seed=2, language="zh", backend="torch")  # the same weights in float
    seed_change = np.abs(generate(clip, model=model, seed=3, language="zh").face - by_onnx.face).mean()
    assert np.abs(by_torch.face - by_onnx.face).mean() < 0.1 * seed_change
    face = dict(model.faces["zh"].weights)
    with_graphs(model)  # export-onnx: the face is exported again, to the same weights
    assert model.languages == {} and face.keys() == model.faces["zh"].weights.keys()
    assert all(np.array_equal(face[k], v) for k, v in model.faces["zh"].weights.items())
    np.testing.assert_allclose(generate(clip, model=model, seed=2, language="zh").face, by_onnx.face, atol=1e-5)


def test_a_face_that_is_not_the_model_s_own_fine_tune_is_refused(models):
    base, tuned, _ = models
    gesture = next(k for k in graph_weights({"gesture": base.graphs["gesture"]}))
    moved = replace(tuned, weights={**tuned.weights, gesture: tuned.weights[gesture] + 1})
    with pytest.raises(DiffshegError, match=f"differs from random-small beyond the face \\(weights outside the "
                                            f"face: {gesture}\\).*trains = \"face\""):
        add_face(base, moved, "zh")
    with pytest.raises(DiffshegError, match="has another network than random-small"):
        add_face(base, random_bundle(seed=4, latent=32), "zh")
    with pytest.raises(DiffshegError, match="differs from random-small beyond the face \\(its normalisation"):
        add_face(base, replace(tuned, std=tuned.std * 2), "zh")
    with pytest.raises(DiffshegError, match="language must be a language code such as zh or pt-br .*, got 'Mandarin'"):
        add_face(base, tuned, "Mandarin")
    with pytest.raises(DiffshegError, match="has no face of its own for 'zh' \\(it has: none\\): nothing to remove"):
        remove_face(base, "zh")


def test_a_language_without_a_face_of_its_own_says_which_there_are(models, tmp_path, capsys):
    from diffsheg_core.cli import main

    base, tuned, clip = models
    with pytest.raises(CheckpointError, match="random-small has no face of its own for language 'ja' \\(it has: "
                                              "zh\\): leave the language unset for the model's shared face"):
        add_face(base, tuned, "zh").for_language("ja")
    with pytest.raises(DiffshegError, match="language must be a language code"):
        GenerateSettings(language="zh_CN!")
    path = save_checkpoint(base, tmp_path / "base.safetensors")
    out = tmp_path / "take.npz"
    assert main(["generate", str(SPEECH), "--model", str(path), "--language", "ZH", "--out", str(out)]) == 2
    assert "has no face of its own for language 'zh' (it has: none)" in capsys.readouterr().err and not out.exists()


def test_add_face_writes_the_model_file_and_a_damaged_face_is_refused_on_load(models, tmp_path, capsys):
    base, tuned, _ = models
    model, fine = save_checkpoint(base, tmp_path / "m.safetensors"), save_checkpoint(tuned, tmp_path / "t.safetensors")
    assert add_face_main([str(model), str(fine), "--language", "zh"]) == 0
    assert "its languages' own faces: zh" in capsys.readouterr().out and stored_face_languages(model) == ["zh"]
    meta, tensors = read_safetensors(model, "")
    # the metadata names a face whose graph is missing
    write_safetensors(tensors, {**meta, "faces": '{"zh": {}, "ja": {}}'}, tmp_path / "named.safetensors")
    with pytest.raises(CheckpointError, match="its languages' own faces are incomplete"):
        load_model(tmp_path / "named.safetensors")
    # a face of another network
    alien = random_bundle(seed=5, latent=32).graphs["expression"]
    write_safetensors({**tensors, "onnx.face.zh.expression": np.frombuffer(alien, np.uint8)}, meta,
                      tmp_path / "alien.safetensors")
    with pytest.raises(CheckpointError, match="disagree|not this model's expression branch"):
        load_model(tmp_path / "alien.safetensors")


def test_a_live_session_in_the_language_runs_its_face(models):
    from diffsheg_core.live.session import LiveSession
    from diffsheg_core.live.sources import FileSource

    base, tuned, _ = models
    model = add_face(base, tuned, "zh")
    session = LiveSession(FileSource(SPEECH), GenerateSettings(model=model, language="zh"))
    assert session.bundle is model.for_language("zh")
    assert LiveSession(FileSource(SPEECH), GenerateSettings(model=model)).bundle is model


def test_a_range_regenerated_keeps_the_take_s_language(models):
    """As a range keeps the take's emotion: without a language of its own, Regenerate Range
    runs the face the take was made with."""
    from diffsheg_core.pipeline import regenerate

    base, tuned, clip = models
    model = add_face(base, tuned, "zh")
    take = generate(clip, model=model, seed=1, language="zh")
    kept = regenerate(take, clip, start=10, end=20, model=model, seed=5)
    asked = regenerate(take, clip, start=10, end=20, model=model, seed=5, language="zh")
    assert kept.meta["language"] == "zh" and np.array_equal(kept.face, asked.face)
    shared = regenerate(generate(clip, model=model, seed=1), clip, start=10, end=20, model=model, seed=5)
    assert shared.meta["language"] is None and not np.array_equal(shared.face[10:20], kept.face[10:20])
