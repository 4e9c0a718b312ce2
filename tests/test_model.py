"""The UniEG network reproduces the official DiffSHEG network (golden vectors)."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from diffsheg_core.checkpoints import load_state_strict
from diffsheg_core.errors import CheckpointError
from diffsheg_core.model import ModelConfig, UniEG

SMALL = dict(latent=64, layers=2, ff=128, heads=4)
SHOW = dict(gesture_dim=129, expression_dim=103, style_dim=4, classifier_free=True, clip_len=88,
            layout="smplx")
CASES = [
    ("beat_small", "beat_small_io.npz", {}, None),
    ("beat_small", "beat_small_T20_io.npz", {}, None),
    ("show_small", "show_small_io.npz", SHOW, 1.25),
]


def run_golden(model: UniEG, io: dict, guidance):
    with torch.no_grad():
        return model(
            torch.from_numpy(io["x_t"]), torch.from_numpy(io["timesteps"]), torch.from_numpy(io["mel"]),
            torch.from_numpy(io["hubert"]), torch.from_numpy(io["person_id"]),
            (torch.from_numpy(io["sqrt_recip_alphas_cumprod"]),
             torch.from_numpy(io["sqrt_recipm1_alphas_cumprod"])),
            guidance).numpy()


@pytest.mark.parametrize("weights,io_file,extra,guidance", CASES)
def test_golden_outputs(golden_dir, weights, io_file, extra, guidance):
    model = UniEG(ModelConfig(**SMALL, **extra)).eval()
    load_state_strict(model, load_file(str(golden_dir / f"{weights}.safetensors")), weights)
    io = dict(np.load(golden_dir / io_file))
    out = run_golden(model, io, guidance)
    assert out.shape == io["eps_out"].shape
    assert np.abs(out - io["eps_out"]).max() < 1e-5


@pytest.mark.parametrize("name,extra", [("beat", {}), ("show", SHOW)])
def test_full_size_state_dict_matches_official_keys(golden_dir, name, extra):
    official = json.loads((golden_dir / f"{name}_full_keys.json").read_text())
    ours = {k: list(v.shape) for k, v in UniEG(ModelConfig(**extra)).state_dict().items()}
    assert ours == official


def test_official_beat_parameter_count():
    model = UniEG(ModelConfig())
    assert sum(p.numel() for p in model.parameters()) == 155_416_560


def test_corrupted_state_dict_names_every_problem(golden_dir):
    state = load_file(str(golden_dir / "beat_small.safetensors"))
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
    model = UniEG(ModelConfig(**SMALL, use_hubert=False))
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
    model = UniEG(ModelConfig(**SMALL, use_hubert=False, classifier_free=True)).eval()
    for p in model.parameters():  # wake the zero-initialised layers up
        torch.nn.init.normal_(p, std=0.05)
    x = torch.randn(2, 8, model.cfg.dim)
    args = (torch.tensor([400, 700]), torch.rand(2, 8, 128), None, torch.eye(30)[:2],
            (torch.full((2, 1, 1), 2.0), torch.full((2, 1, 1), 1.5)))
    seen = []
    model.encoder_ges.register_forward_pre_hook(lambda mod, inputs: seen.append(inputs))
    g = model.cfg.gesture_dim
    with torch.no_grad():
        guided = model(x, *args, guidance=2.0)
        skipped = model(x, *args, guidance=2.0, skip_guidance=0.5)
        branch_inputs = seen[-1][:6]  # gesture, timesteps, speech, hubert, expression x0, style
        cond = model.encoder_ges(*branch_inputs, None)
        blocks = model.encoder_ges.temporal_decoder_blocks
        attention = [layer.sa_block for layer in blocks]
        for layer in blocks:
            layer.sa_block = _NoAttention()
        without = model.encoder_ges(*branch_inputs, None)
        for layer, sa in zip(blocks, attention):
            layer.sa_block = sa
    torch.testing.assert_close(skipped[..., g:], guided[..., g:])
    torch.testing.assert_close(skipped[..., :g], cond + 0.5 * (cond - without))
    assert seen[-1][6] is None  # no classifier-free pass in the gesture branch
    assert not torch.allclose(cond, without)
