"""Our checkpoint format and the official DiffSHEG checkpoints: strict, safe loading."""

import argparse
import json
import sys
from dataclasses import replace

import numpy as np
import pytest
import soundfile as sf
import torch
from safetensors.torch import load_file

from conftest import random_bundle
from diffsheg_core import CheckpointError, DiffshegError, generate
from diffsheg_core.bvh import read_bvh
from diffsheg_core.checkpoints import (load_model, read_safetensors, save_checkpoint, stored_style_count,
                                       stored_style_names)
from diffsheg_core.motion import read_arkit_json
from diffsheg_core.official_checkpoints import official_stats
from diffsheg_core.runtime.backends import choose_backend
from diffsheg_core.torch_layer.model import ModelConfig, UniEG


def golden_official_file(golden_dir, tmp_path, prefix="module."):
    """The golden small BEAT weights saved the way the official trainer saves checkpoints."""
    state = load_file(str(golden_dir / "beat_small.safetensors"))
    state = {prefix + k: v for k, v in state.items()}
    path = tmp_path / "beat_small.pth"
    torch.save({"encoder": state, "epoch": 999}, path)
    return path


def test_our_format_round_trips(tmp_path):
    bundle = random_bundle(seed=3)
    bundle.info = {"trained_on": "nothing"}
    path = save_checkpoint(bundle, tmp_path / "m.safetensors")
    loaded = load_model(path)
    assert loaded.config == bundle.config and loaded.model_id == bundle.model_id
    assert loaded.trained is False and loaded.info == {"trained_on": "nothing"}
    assert loaded.sampling == bundle.sampling
    assert sorted(loaded.weights) == sorted(bundle.weights)
    for k, a in bundle.weights.items():
        b = loaded.weights[k]
        assert isinstance(b, np.ndarray) and b.dtype == a.dtype and np.array_equal(a, b), k
    assert np.array_equal(loaded.std, bundle.std)
    # the ONNX graphs travel byte for byte, so the file runs without torch, live's int8 ones too
    assert loaded.has_graphs and loaded.graphs == bundle.graphs and loaded.live_graphs == bundle.live_graphs
    meta, tensors = read_safetensors(path, "")
    assert all(isinstance(v, np.ndarray) for v in tensors.values())
    assert {k for k in tensors if k.startswith("onnx.")} == {
        "onnx.expression", "onnx.gesture", "onnx.live.expression", "onnx.live.gesture"}


def test_truncated_checkpoint_is_reported(tmp_path):
    path = save_checkpoint(random_bundle(graphs=False), tmp_path / "m.safetensors")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_model(path)


def test_missing_checkpoint_is_reported(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_model(tmp_path / "absent.pth")


def test_style_names_that_do_not_name_each_style_are_refused_on_load(tmp_path):
    """Names must be style_dim different texts, as the trainer writes them; reading the
    metadata alone (the add-on's menu) gives none for such a file, and its style count."""
    bundle = random_bundle(graphs=False, style_dim=3)
    for names in ([1, 2, 3], ["calm", "lively"], ["calm", "calm", "wild"], "calm"):
        path = save_checkpoint(replace(bundle, info={"style_names": names}), tmp_path / "styled.safetensors")
        with pytest.raises(CheckpointError, match=r"styled.safetensors: its style names .* are not 3 different "
                                                  r"names \(text\), one per style of the model"):
            load_model(path)
        assert stored_style_names(path) == [] and stored_style_count(path) == 3
    path = save_checkpoint(replace(bundle, info={"style_names": ["a", "b", "c"]}), tmp_path / "styled.safetensors")
    assert load_model(path).style_names == stored_style_names(path) == ["a", "b", "c"]


def test_style_counts_of_official_checkpoints_are_read_without_torch(golden_dir, tmp_path, monkeypatch):
    """From the tensor shapes in the checkpoint's pickle: 30 speakers for BEAT, 4 for SHOW,
    with torch unimportable; files that are no torch zip cannot tell."""
    beat = golden_official_file(golden_dir, tmp_path)
    show = tmp_path / "show_small.pth"
    torch.save({"encoder": load_file(str(golden_dir / "show_small.safetensors")), "epoch": 1}, show)
    other = tmp_path / "other.pth"
    other.write_bytes(b"\x80\x02 not a torch zip")
    monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` fails, as where it is not installed
    assert (stored_style_count(beat), stored_style_count(show), stored_style_count(other)) == (30, 4, None)
    assert stored_style_count(tmp_path / "absent.pth") is None
    assert stored_style_names(beat) == []


def test_official_checkpoint_loads_strictly_with_inferred_config(golden_dir, data_dir, tmp_path):
    bundle = load_model(golden_official_file(golden_dir, tmp_path), stats_dir=data_dir / "beat")
    cfg = bundle.config
    assert (cfg.gesture_dim, cfg.expression_dim, cfg.style_dim, cfg.latent, cfg.layers, cfg.ff) == \
        (141, 51, 30, 64, 2, 128)
    assert cfg.speech_encoder == "hubert" and cfg.has_speech_input and not cfg.phonetic_input
    assert not cfg.classifier_free and cfg.clip_len == 34 and cfg.layout == "beat"
    assert bundle.sampling.overlap == 4 and bundle.guidance is None
    assert bundle.mean.shape == (192,) and np.allclose(bundle.mean[:141], np.load(data_dir / "beat/axis_angle_mean.npy"))
    # the weights, as numpy, under their official names (the `module.` prefix dropped)
    golden = load_file(str(golden_dir / "beat_small.safetensors"))
    assert set(bundle.weights) == set(golden)
    assert all(isinstance(v, np.ndarray) and np.array_equal(v, golden[k].numpy()) for k, v in bundle.weights.items())
    # official checkpoints carry no ONNX graphs: they run on the torch backend
    assert not bundle.has_graphs and choose_backend(bundle, "auto", "cpu") == "torch"
    with pytest.raises(DiffshegError, match="no ONNX graphs"):
        choose_backend(bundle, "onnx", "cpu")


def test_official_checkpoint_without_stats_explains(golden_dir, tmp_path, monkeypatch):
    monkeypatch.delenv("DIFFSHEG_OFFICIAL_STATS", raising=False)
    with pytest.raises(CheckpointError, match="axis_angle_mean.npy.*--stats"):
        load_model(golden_official_file(golden_dir, tmp_path))


def test_official_stats_are_found_beside_the_checkpoint(golden_dir, data_dir, tmp_path, monkeypatch):
    import shutil

    monkeypatch.delenv("DIFFSHEG_OFFICIAL_STATS", raising=False)
    path = golden_official_file(golden_dir, tmp_path)
    for name in ("axis_angle_mean.npy", "axis_angle_std.npy", "facial51_mean.npy", "facial51_std.npy"):
        shutil.copy(data_dir / "beat" / name, tmp_path / name)
    assert load_model(path).std.shape == (192,)


def test_corrupted_official_checkpoint_names_each_key(golden_dir, data_dir, tmp_path):
    state = {k: v for k, v in load_file(str(golden_dir / "beat_small.safetensors")).items()}
    state.pop("encoder_ges.temporal_decoder_blocks.1.ffn.linear2.bias")
    state["encoder_exp.joint_embed.weights"] = state.pop("encoder_exp.joint_embed.weight")
    state["encoder_exp.audio_proj.bias"] = torch.zeros(7)
    path = tmp_path / "corrupt.pth"
    torch.save({"encoder": state}, path)
    with pytest.raises(CheckpointError) as err:
        load_model(path, stats_dir=data_dir / "beat")
    msg = str(err.value)
    for key in ("encoder_ges.temporal_decoder_blocks.1.ffn.linear2.bias", "encoder_exp.joint_embed.weight",
                "encoder_exp.joint_embed.weights", "encoder_exp.audio_proj.bias"):
        assert key in msg
    assert "likely cause" in msg


def test_pickle_needing_code_is_refused(golden_dir, tmp_path):
    path = tmp_path / "with_options.pth"
    torch.save({"encoder": {}, "opt": argparse.Namespace(lr=1)}, path)
    with pytest.raises(CheckpointError, match="arbitrary code"):
        load_model(path)


def test_show_stats_follow_the_official_layout(data_dir):
    mean, std = official_stats("show", data_dir / "show")
    stats = np.load(data_dir / "show" / "talkshow_mean_std.npy", allow_pickle=True).item()
    assert mean.shape == std.shape == (232,)
    # gesture: SMPL-X joints 3, 6, 9 (body slots 2, 5, 8), 12..21, then both hands
    assert np.allclose(mean[:3], stats["pose_mean"][12 + 6: 12 + 9], rtol=1e-6)
    assert np.allclose(mean[9:39], stats["pose_mean"][12 + 33: 12 + 63], rtol=1e-6)
    assert np.allclose(mean[39:129], stats["pose_mean"][75:165], rtol=1e-6)
    # expression: jaw, then 100 FLAME coefficients; the jaw's "std" is its mean (official quirk)
    assert np.allclose(mean[129:132], stats["pose_mean"][:3], rtol=1e-6)
    assert np.allclose(std[129:132], stats["pose_mean"][:3], rtol=1e-6)
    assert np.allclose(std[132:], stats["expression_std"], rtol=1e-6)


def test_official_size_beat_end_to_end_with_random_weights(data_dir, tmp_path):
    """Full-size official BEAT network (random weights) and a HuBERT-layout model (random),
    official FOPPAS preset, 10 s of real speech: BVH and ARKit JSON come out and re-parse."""
    transformers = pytest.importorskip("transformers")
    torch.manual_seed(0)
    hubert = tmp_path / "hubert"
    transformers.HubertModel(transformers.HubertConfig(
        hidden_size=1024, num_hidden_layers=1, num_attention_heads=4, intermediate_size=256,
        conv_dim=(32,) * 7, num_conv_pos_embeddings=16, num_conv_pos_embedding_groups=4,
    )).save_pretrained(hubert)
    model = UniEG(ModelConfig())
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.02)
    ckpt = tmp_path / "beat_official.pth"
    torch.save({"encoder": model.state_dict()}, ckpt)
    del model
    bundle = load_model(ckpt, stats_dir=data_dir / "beat")
    samples, sr = sf.read(data_dir / "audio" / "2_scott_0_3_3.wav", dtype="float32")
    motion = generate(samples[: 10 * sr], sr, model=bundle, device="cpu", hubert_path=str(hubert))
    assert motion.n_frames == 150 and np.isfinite(motion.rotations).all()
    assert motion.meta["backend"] == "torch"  # no graphs in an official checkpoint
    from diffsheg_core.bvh import write_bvh
    from diffsheg_core.motion import write_arkit_json
    bvh = read_bvh(write_bvh(motion, tmp_path / "out.bvh"))
    assert len(bvh.frames) == 150 and len(bvh.joint_names) == 75
    face = read_arkit_json(write_arkit_json(motion, tmp_path / "out.json"))
    assert face.weights.shape == (150, 51)
    assert json.loads((tmp_path / "out.json").read_text())["names"][0] == "browDownLeft"


class _RunsCommand:
    """What a crafted pickle holds: unpickling it calls os.system."""

    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        import os

        return os.system, (self.command,)


def crafted_npy(path, payload) -> None:
    """A .npy file as np.save writes a pickled object array, holding `payload`."""
    import pickle

    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "|O", "fortran_order": False, "shape": ()})
        pickle.dump(payload, fh, protocol=3)


def test_show_stats_are_read_as_np_load_reads_them(data_dir):
    from diffsheg_core.official_checkpoints import _show_stats

    path = data_dir / "show" / "talkshow_mean_std.npy"
    expected = np.load(path, allow_pickle=True).item()
    stats = _show_stats(path)
    assert set(stats) == set(expected)
    for key, values in expected.items():
        assert stats[key].dtype == values.dtype and np.array_equal(stats[key], values), key


@pytest.mark.parametrize("nested", [False, True])
def test_a_stats_file_that_would_run_code_is_refused_and_runs_nothing(data_dir, tmp_path, nested):
    marker = tmp_path / "ran"
    evil = _RunsCommand(f"touch {marker}")
    stats = np.load(data_dir / "show" / "talkshow_mean_std.npy", allow_pickle=True).item()
    crafted_npy(tmp_path / "talkshow_mean_std.npy", {**stats, "pose_std": evil} if nested else evil)
    # the file is what it claims: numpy's own loader runs its command
    np.load(tmp_path / "talkshow_mean_std.npy", allow_pickle=True)
    assert marker.exists()
    marker.unlink()
    with pytest.raises(CheckpointError, match="talkshow_mean_std.npy: refused to load: it names the global "
                                              "(posix|nt).system") as err:
        official_stats("show", tmp_path)
    assert "\n" not in str(err.value) and "data.tar.gz" in str(err.value)
    assert not marker.exists()


@pytest.mark.parametrize("change,match", [
    (lambda s: {k: v for k, v in s.items() if k != "expression_std"}, "expected a dict of pose_mean"),
    (lambda s: {**s, "pose_std": s["pose_std"][:-1]}, r"\('pose_std'\): expected 165 floating-point "
                                                      r"statistics, found an array of dtype float64 and shape \(164,\)"),
    (lambda s: {**s, "expression_mean": s["expression_mean"].astype(object)}, "dtype object"),
    (lambda s: {**s, "pose_mean": np.full(165, np.nan)}, "NaN or infinite"),
    (lambda s: [s["pose_mean"]], "found list"),
    (lambda s: s["pose_mean"], "found ndarray"),
])
def test_show_stats_of_the_wrong_form_are_refused(data_dir, tmp_path, change, match):
    stats = np.load(data_dir / "show" / "talkshow_mean_std.npy", allow_pickle=True).item()
    crafted_npy(tmp_path / "talkshow_mean_std.npy", change(stats))
    with pytest.raises(CheckpointError, match=match) as err:
        official_stats("show", tmp_path)
    assert str(tmp_path / "talkshow_mean_std.npy") in str(err.value)


@pytest.mark.parametrize("name,values,match", [
    ("axis_angle_std.npy", np.array([{"a": 1}], dtype=object), "not a plain array of statistics"),
    ("facial51_mean.npy", np.zeros(52), r"expected 51 floating-point statistics, found an array of dtype "
                                        r"float64 and shape \(52,\)"),
    ("axis_angle_mean.npy", np.zeros((141, 1)), "expected 141"),
])
def test_beat_stats_of_the_wrong_form_are_refused(data_dir, tmp_path, name, values, match):
    import shutil

    for stats in ("axis_angle_mean.npy", "axis_angle_std.npy", "facial51_mean.npy", "facial51_std.npy"):
        shutil.copy(data_dir / "beat" / stats, tmp_path / stats)
    (tmp_path / name).unlink()
    np.save(tmp_path / name, values, allow_pickle=True)
    with pytest.raises(CheckpointError, match=match) as err:
        official_stats("beat", tmp_path)
    assert str(tmp_path / name) in str(err.value) and "\n" not in str(err.value)
