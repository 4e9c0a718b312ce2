"""The UniEG network reproduces the official DiffSHEG network (golden vectors), on the
training path (`UniEG.forward`) and on the sampling path (the two calls of a step on
either backend, mixed by `guidance.step_eps`)."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file as load_numpy
from safetensors.torch import load_file

from conftest import random_bundle
from diffsheg_core.checkpoints import ModelBundle
from diffsheg_core.diffusion import Schedule
from diffsheg_core.errors import CheckpointError
from diffsheg_core.foppas import PRESETS
from diffsheg_core.guidance import Guidance, step_eps
from diffsheg_core.runtime.backends import OnnxNetwork, open_network
from diffsheg_core.torch_layer.backend import TorchNetwork
from diffsheg_core.torch_layer.export import network_graphs
from diffsheg_core.torch_layer.model import ModelConfig, UniEG, load_state_strict, state_arrays

SMALL = dict(latent=64, layers=2, ff=128, heads=4)
SHOW = dict(gesture_dim=129, expression_dim=103, style_dim=4, classifier_free=True, clip_len=88,
            layout="smplx")
CASES = [
    ("beat_small", "beat_small_io.npz", {}, None),
    ("beat_small", "beat_small_T20_io.npz", {}, None),
    ("show_small", "show_small_io.npz", SHOW, 1.25),
]


def run_golden(model: UniEG, io: dict):
    """The unguided training path."""
    with torch.no_grad():
        return model(
            torch.from_numpy(io["x_t"]), torch.from_numpy(io["timesteps"]), torch.from_numpy(io["mel"]),
            torch.from_numpy(io["hubert"]), torch.from_numpy(io["person_id"]),
            (torch.from_numpy(io["sqrt_recip_alphas_cumprod"]),
             torch.from_numpy(io["sqrt_recipm1_alphas_cumprod"]))).numpy()


def golden_args(io: dict, rows: slice) -> tuple:
    """step_eps's inputs after the network (x, timesteps, mel, speech, style, x0_coefs)."""
    return (io["x_t"][rows], io["timesteps"][rows], io["mel"][rows], io["hubert"][rows],
            io["person_id"][rows],
            (io["sqrt_recip_alphas_cumprod"][rows], io["sqrt_recipm1_alphas_cumprod"][rows]))


def sample_golden(network, cfg: ModelConfig, io: dict, guidance) -> np.ndarray:
    """The sampling path, one window (batch row) per call as the sampler runs it."""
    return np.concatenate([
        step_eps(network, cfg.gesture_dim, *golden_args(io, slice(row, row + 1)), Guidance(guidance))[0]
        for row in range(len(io["x_t"]))])


def golden_bundle(golden_dir, weights: str, extra: dict, graphs: bool = False) -> ModelBundle:
    cfg = ModelConfig(**SMALL, **extra)
    state = load_numpy(str(golden_dir / f"{weights}.safetensors"))
    bundle = ModelBundle(config=cfg, weights=state, mean=np.zeros(cfg.dim, np.float32),
                         std=np.ones(cfg.dim, np.float32), sampling=PRESETS["official-beat"],
                         model_id=weights, trained=False, source=weights)
    if graphs:
        bundle.graphs = network_graphs(cfg, state, weights)
        assert bundle.has_graphs
    return bundle


@pytest.mark.parametrize("weights,io_file,extra,guidance", [c for c in CASES if c[3] is None])
def test_golden_outputs_on_the_training_path(golden_dir, weights, io_file, extra, guidance):
    model = UniEG(ModelConfig(**SMALL, **extra)).eval()
    load_state_strict(model, load_file(str(golden_dir / f"{weights}.safetensors")), weights)
    io = dict(np.load(golden_dir / io_file))
    out = run_golden(model, io)
    assert out.shape == io["eps_out"].shape
    assert np.abs(out - io["eps_out"]).max() < 1e-5


@pytest.mark.parametrize("backend", ["torch", "onnx"])
@pytest.mark.parametrize("weights,io_file,extra,guidance", CASES)
def test_golden_outputs_on_the_sampling_path(golden_dir, weights, io_file, extra, guidance, backend):
    """Both backends, the guidance (SHOW: classifier-free 1.25) mixed in numpy."""
    bundle = golden_bundle(golden_dir, weights, extra, graphs=backend == "onnx")
    network = OnnxNetwork(bundle, threads=2) if backend == "onnx" else TorchNetwork(bundle, "cpu", "fp32")
    io = dict(np.load(golden_dir / io_file))
    out = sample_golden(network, bundle.config, io, guidance)
    assert out.shape == io["eps_out"].shape and out.dtype == np.float32
    assert np.abs(out - io["eps_out"]).max() < 1e-5  # measured: 1e-7 (BEAT), 2e-7 (SHOW) on both


def test_guided_step_eps_keeps_the_rows_of_a_batch_apart(golden_dir):
    bundle = golden_bundle(golden_dir, "show_small", SHOW)
    io = dict(np.load(golden_dir / "show_small_io.npz"))
    out = step_eps(TorchNetwork(bundle, "cpu", "fp32"), bundle.config.gesture_dim,
                   *golden_args(io, slice(None)), Guidance(1.25))[0]
    assert np.abs(out - io["eps_out"]).max() < 1e-5


@pytest.mark.parametrize("name,extra", [("beat", {}), ("show", SHOW)])
def test_full_size_state_dict_matches_official_keys(golden_dir, name, extra):
    official = json.loads((golden_dir / f"{name}_full_keys.json").read_text())
    ours = {k: list(v.shape) for k, v in UniEG(ModelConfig(**extra)).state_dict().items()}
    assert ours == official


def test_official_beat_parameter_count():
    model = UniEG(ModelConfig())
    assert sum(p.numel() for p in model.parameters()) == 155_416_560


@pytest.mark.parametrize("kind", ["torch", "numpy"])
def test_corrupted_state_dict_names_every_problem(golden_dir, kind):
    state = (load_file if kind == "torch" else load_numpy)(str(golden_dir / "beat_small.safetensors"))
    state.pop("encoder_exp.out.bias")
    state["encoder_ges.renamed_weight"] = state.pop("encoder_ges.out.weight")
    state["encoder_aud.ffn.linear1.weight"] = state["encoder_aud.ffn.linear1.weight"][:, :7]
    with pytest.raises(CheckpointError) as err:
        load_state_strict(UniEG(ModelConfig(**SMALL)), state, "corrupt.safetensors")
    msg = str(err.value)
    for key in ("encoder_exp.out.bias", "encoder_ges.out.weight", "encoder_ges.renamed_weight",
                "encoder_aud.ffn.linear1.weight"):
        assert key in msg
    assert "likely cause" in msg


def test_gesture_branch_sees_detached_expression_x0():
    torch.manual_seed(0)
    model = UniEG(ModelConfig(**SMALL, speech_encoder=None))
    for p in model.parameters():  # wake the zero-initialised layers up
        torch.nn.init.normal_(p, std=0.05)
    x = torch.randn(1, 8, model.cfg.dim)
    coefs = (torch.full((1, 1, 1), 2.0), torch.full((1, 1, 1), 1.5))
    args = (torch.tensor([400]), torch.rand(1, 8, 128), None, torch.eye(30)[:1], coefs)
    eps = model(x, *args)
    gesture_loss = eps[..., : model.cfg.gesture_dim].sum()
    gesture_loss.backward()
    assert all(p.grad is None or p.grad.abs().max() == 0 for p in model.encoder_exp.parameters())
    # but changing the expression input changes the gesture output (uni-directional flow)
    x2 = x.clone()
    x2[..., model.cfg.gesture_dim:] += 1.0
    with torch.no_grad():
        eps_a, eps_b = model(x, *args), model(x2, *args)
    assert not torch.allclose(eps_a[..., :141], eps_b[..., :141])


class _NoAttention(torch.nn.Module):
    def forward(self, h, emb):
        return h


def test_skip_guidance_steers_gestures_away_from_the_branch_without_self_attention():
    """eps_gesture + s (eps_gesture - eps_gesture without its self-attention blocks); the
    expression branch keeps its classifier-free guidance, the gesture branch drops it."""
    torch.manual_seed(0)
    model = UniEG(ModelConfig(**SMALL, speech_encoder=None, classifier_free=True)).eval()
    for p in model.parameters():  # wake the zero-initialised layers up
        torch.nn.init.normal_(p, std=0.05)
    cfg = model.cfg
    bundle = ModelBundle(config=cfg, weights=state_arrays(model),
                         mean=np.zeros(cfg.dim, np.float32), std=np.ones(cfg.dim, np.float32),
                         sampling=PRESETS["official-beat"], source="skip-test")
    network = TorchNetwork(bundle, "cpu", "fp32")
    model = network.model
    gen = np.random.default_rng(0)
    x = gen.standard_normal((2, 8, cfg.dim), dtype=np.float32)
    mel = gen.random((2, 8, 128), dtype=np.float32)
    timesteps, style = np.array([400, 700]), np.eye(30, dtype=np.float32)[:2]
    coefs = (np.full((2, 1, 1), 2.0, np.float32), np.full((2, 1, 1), 1.5, np.float32))
    seen = []
    model.encoder_ges.register_forward_pre_hook(lambda mod, inputs: seen.append(inputs))
    g = cfg.gesture_dim
    for row in range(2):  # one window per call, as the sampler runs it
        r = slice(row, row + 1)
        args = (x[r], timesteps[r], mel[r], None, style[r], (coefs[0][r], coefs[1][r]))
        guided = step_eps(network, g, *args, Guidance(2.0))[0]
        skipped = step_eps(network, g, *args, Guidance(2.0, skip=0.5))[0]
        # the skip pass: [conditioned | without self-attention], no null-conditioned row
        branch_inputs = seen[-1]  # gesture, timesteps, audio, speech, expression x0, style, null, attend
        assert branch_inputs[6] is None  # no classifier-free pass in the gesture branch
        assert branch_inputs[7].tolist() == [True, False]
        assert all(torch.equal(v[0], v[1]) for v in branch_inputs[:6] if v is not None)
        conditioned = [v if v is None else v[:1] for v in branch_inputs[:6]]
        with torch.no_grad():
            cond = model.encoder_ges(*conditioned, None)
            blocks = model.encoder_ges.temporal_decoder_blocks
            attention = [layer.sa_block for layer in blocks]
            for layer in blocks:
                layer.sa_block = _NoAttention()
            without = model.encoder_ges(*conditioned, None)
            for layer, sa in zip(blocks, attention):
                layer.sa_block = sa
        cond, without = cond.numpy(), without.numpy()
        torch.testing.assert_close(torch.from_numpy(skipped[..., g:]), torch.from_numpy(guided[..., g:]))
        torch.testing.assert_close(torch.from_numpy(skipped[..., :g]),
                                   torch.from_numpy(cond + 0.5 * (cond - without)))
        assert not np.allclose(cond, without)
        # a lower branch's channels (the last `lower`: the legs, live) at a skip scale of their own
        legs = step_eps(network, g, *args, Guidance(2.0, skip=0.5, legs_skip=1.5, lower=5))[0]
        torch.testing.assert_close(torch.from_numpy(legs[..., :g - 5]), torch.from_numpy(skipped[..., :g - 5]))
        torch.testing.assert_close(torch.from_numpy(legs[..., g - 5:g]),
                                   torch.from_numpy(cond[..., g - 5:] + 1.5 * (cond[..., g - 5:] - without[..., g - 5:])))
        # and the expression branch of both is classifier-free guided: u + 2 (c - u)
        exp_null, _ = network.expression(x[r][..., g:], timesteps[r], mel[r], None, style[r], np.array([True]))
        exp_cond, _ = network.expression(x[r][..., g:], timesteps[r], mel[r], None, style[r], None)
        torch.testing.assert_close(torch.from_numpy(guided[..., g:]),
                                   torch.from_numpy(exp_null + 2.0 * (exp_cond - exp_null)))
        assert not np.allclose(exp_null, exp_cond)


GUIDANCE_MODES = {"none": Guidance(), "cfg": Guidance(2.0), "skip": Guidance(skip=0.5),
                  "cfg+skip": Guidance(2.0, skip=0.5)}


@pytest.fixture(scope="module", params=[0, 5], ids=["official", "temporal-conv"])
def guided_bundle(request):
    """A fresh random model with a null condition and a second speech input (HuBERT layout),
    as published and with temporal convolutions."""
    return random_bundle(classifier_free=True, speech_encoder="hubert", speech_dim=32,
                         temporal_kernel=request.param)


@pytest.mark.parametrize("length", [34, 20])
@pytest.mark.parametrize("mode", list(GUIDANCE_MODES))
def test_onnx_and_torch_backends_agree_on_every_guidance_mode(guided_bundle, mode, length):
    bundle, guidance = guided_bundle, GUIDANCE_MODES[mode]
    cfg = bundle.config
    onnx_net = open_network(bundle, backend="onnx", device="cpu", threads=2)
    torch_net = open_network(bundle, backend="torch", device="cpu", threads=2)
    assert (onnx_net.name, torch_net.name) == ("onnx", "torch")
    sched = Schedule.linear().respaced(25)
    gen = np.random.default_rng(length)
    mel = gen.random((1, length, cfg.mel_dim), dtype=np.float32)
    speech = gen.standard_normal((1, length, cfg.speech_dim), dtype=np.float32)
    style = np.eye(cfg.style_dim, dtype=np.float32)[3:4]
    for index in (24, 10, 0):
        x = gen.standard_normal((1, length, cfg.dim), dtype=np.float32)
        idx = np.array([index])
        args = (cfg.gesture_dim, x, sched.model_timesteps(idx), mel, speech, style, sched.x0_coefs(idx, x),
                guidance)
        a, b = step_eps(onnx_net, *args)[0], step_eps(torch_net, *args)[0]
        assert a.shape == b.shape == (1, length, cfg.dim) and a.dtype == b.dtype == np.float32
        assert np.isfinite(a).all()
        assert np.abs(a - b).max() <= 1e-4, (mode, length, index, float(np.abs(a - b).max()))  # measured 2e-6
        if mode != "none":  # the guided passes do change the prediction (0.1 - 0.8 here)
            assert np.abs(b - step_eps(torch_net, *args[:-1], Guidance())[0]).max() > 0.05


def test_int8_graphs_store_each_weight_once_and_predict_as_the_float_ones(golden_dir):
    """A distilled student's graphs (`network_graphs(..., int8=True)`): every Linear's product
    runs in int8 but those of `FLOAT_PRODUCTS`; the file's reader gives each int8 weight back
    under its parameter's name, dequantised within half a step of its scale, and every other
    weight exactly; onnxruntime's prediction stays close to the float graphs' on every step."""
    import onnx
    from torch import nn

    from diffsheg_core.checkpoints import graph_weights
    from diffsheg_core.torch_layer.export import FLOAT_PRODUCTS

    bundle = golden_bundle(golden_dir, "beat_small", {}, graphs=True)
    cfg, weights = bundle.config, bundle.weights
    graphs = network_graphs(cfg, weights, "beat_small", int8=True)
    held = graph_weights(graphs)
    initializers = [i for g in graphs.values() for i in onnx.load_from_string(g).graph.initializer]
    stored = {i.name for i in initializers}
    codes = [onnx.numpy_helper.to_array(i) for i in initializers if i.name.endswith(".int8")]
    assert codes and max(np.abs(c.astype(int)).max() for c in codes) == 127  # full range, a scale per column
    int8 = {n.removeprefix("model.").removesuffix(".int8").removesuffix(".T") for n in stored if n.endswith(".int8")}
    linear = {f"{name}.weight" for name, module in UniEG(cfg).named_modules() if isinstance(module, nn.Linear)}
    assert int8 == {n for n in linear if not set(n.split(".")) & set(FLOAT_PRODUCTS)} and int8 < linear
    assert set(held) == set(graph_weights(bundle.graphs))
    for name, value in held.items():
        weight = np.asarray(weights[name], np.float32)
        if name in int8:
            step = np.abs(weight).max(axis=1, keepdims=True) / 127  # a scale per output feature
            assert value.dtype == np.float32 and (np.abs(value - weight) <= step / 2 + 1e-7).all(), name
        else:
            np.testing.assert_array_equal(value, weight)
    float_net = OnnxNetwork(bundle, threads=1)
    int8_net = OnnxNetwork(replace(bundle, graphs=graphs), threads=1)
    gen, sched = np.random.default_rng(3), Schedule.linear().respaced(25)
    for index in (24, 10, 0):
        x = gen.standard_normal((1, cfg.clip_len, cfg.dim), dtype=np.float32)
        idx = np.array([index])
        mel = gen.random((1, cfg.clip_len, cfg.mel_dim), np.float32)
        speech = gen.standard_normal((1, cfg.clip_len, cfg.speech_dim), np.float32)
        args = (cfg.gesture_dim, x, sched.model_timesteps(idx), mel, speech,
                np.eye(cfg.style_dim, dtype=np.float32)[:1], sched.x0_coefs(idx, x), Guidance())
        a, b = step_eps(int8_net, *args)[0], step_eps(float_net, *args)[0]
        error = np.abs(a - b).mean() / np.abs(b).mean()
        assert 0 < error <= 0.01, (index, error)  # measured 0.0016: int8 ran, and rounded little


def test_live_graphs_hold_no_weights_and_run_the_int8_graphs_numbers(golden_dir):
    """A model's live graphs (`live_graphs`): the int8 graphs with every initializer left out,
    marked external data; opened, each is made from the model's weights (`supplied_weights`,
    whose int8 codes and scales are onnxruntime's quantiser's own: the export checks every
    one), so they predict exactly as the int8 graphs holding their weights do."""
    import onnx

    from diffsheg_core.runtime.graphs import SUPPLIED, read_graph
    from diffsheg_core.torch_layer.export import live_graphs

    bundle = golden_bundle(golden_dir, "beat_small", {}, graphs=True)
    cfg = bundle.config
    live = live_graphs(cfg, bundle.weights, "beat_small")
    int8 = network_graphs(cfg, bundle.weights, "beat_small", int8=True)
    for name, graph in live.items():
        proto = onnx.load_from_string(graph)
        assert proto.graph.initializer and all(
            i.data_location == onnx.TensorProto.EXTERNAL and not i.raw_data
            and [(e.key, e.value) for e in i.external_data] == [("location", SUPPLIED)] for i in proto.graph.initializer)
        assert sorted(read_graph(graph).external) == sorted(i.name for i in onnx.load_from_string(int8[name]).graph.initializer)
        assert len(graph) < len(int8[name]) / 5
    live_net = OnnxNetwork(bundle, threads=1, graphs={**bundle.graphs, **live})
    int8_net = OnnxNetwork(replace(bundle, graphs={**bundle.graphs, **int8}), threads=1)
    gen, sched = np.random.default_rng(4), Schedule.linear().respaced(25)
    for index in (24, 3):
        x = gen.standard_normal((2, cfg.clip_len, cfg.dim), dtype=np.float32)
        idx = np.array([index, index])
        mel = gen.random((2, cfg.clip_len, cfg.mel_dim), np.float32)
        speech = gen.standard_normal((2, cfg.clip_len, cfg.speech_dim), np.float32)
        args = (cfg.gesture_dim, x, sched.model_timesteps(idx), mel, speech,
                np.eye(cfg.style_dim, dtype=np.float32)[[0, 1]], sched.x0_coefs(idx, x), Guidance())
        np.testing.assert_array_equal(step_eps(live_net, *args)[0], step_eps(int8_net, *args)[0])


def test_an_int8_export_keeps_zero_weights_and_the_gemms_it_leaves_float(monkeypatch):
    """A fresh network's zero-initialised layers (their int8 scales all 1) and a Gemm kept
    float (the time embedding, made a float product here) come back from the graphs as the
    weights they are, each once: the int8 export never halves a scale, and a Gemm it leaves
    float stays float (onnxruntime quantises a Gemm as the MatMul it becomes)."""
    import onnx

    from diffsheg_core.checkpoints import graph_weights
    from diffsheg_core.torch_layer import export

    cfg = ModelConfig(**SMALL)
    weights = state_arrays(UniEG(cfg))
    in_float = graph_weights(network_graphs(cfg, weights, "fresh"))  # torch's export keeps one of equal tensors
    zero = [name for name, value in weights.items() if value.ndim == 2 and not value.any() and name in in_float]
    assert len(zero) >= 4
    monkeypatch.setattr(export, "FLOAT_PRODUCTS", export.FLOAT_PRODUCTS + ("time_embed",))
    graphs = network_graphs(cfg, weights, "fresh", int8=True)
    held = graph_weights(graphs)
    stored = {i.name for g in graphs.values() for i in onnx.load_from_string(g).graph.initializer}
    assert not any(name.endswith(".fp16") and ".int8" in name for name in stored)
    assert any(name.endswith(".int8") for name in stored) and not any("time_embed" in n and ".int8" in n for n in stored)
    for name in zero + ["time_embed.0.weight"]:
        np.testing.assert_array_equal(held[name], weights[name])
