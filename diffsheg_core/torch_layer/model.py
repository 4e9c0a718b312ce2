"""The UniEG denoiser of DiffSHEG: an expression branch, then a gesture branch that
sees the expression branch's predicted x0.

Parameter names and shapes follow the official implementation, so the published
checkpoints load strictly into this module (the second speech input's encoder keeps the
official name `hubert_encoder`, whatever feeds it). Read top to bottom: building blocks,
one branch, the whole network. The configuration is `config.ModelConfig`.

`PhoneticEncoder` is the project's phone recogniser, the bundled model's second speech
input (see `phonetic`).

Sampling runs the network as two calls per step, `UniEG.expression` then `UniEG.gesture`,
each over a batch of passes (conditioned, null-conditioned, without self-attention) that
the caller mixes (see `guidance`); the same two calls are what is exported to ONNX.
`forward` is the training path: one unguided prediction per row.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig
from ..errors import CheckpointError
from ..phonetic import PHONES, PhoneticConfig

def timestep_embedding(timesteps: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of diffusion steps: cosines first, then sines."""
    half = dim // 2
    freqs = torch.exp(
        -math.log(max_period) * torch.arange(half, dtype=torch.float32, device=timesteps.device) / half)
    args = timesteps[:, None].float() * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


def _mlp(d_in: int, d_hidden: int, d_out: int | None = None) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.SiLU(), nn.Linear(d_hidden, d_out or d_hidden))


class PositionalEncoding(nn.Module):
    """Sinusoidal encoding (sin on even, cos on odd dims) of period `period`, tiled to `length`."""

    def __init__(self, dim: int, period: int, length: int):
        super().__init__()
        position = torch.arange(period, dtype=torch.float32).unsqueeze(1)
        div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
        pe = torch.zeros(period, dim)
        pe[:, 0::2] = torch.sin(position * div)
        pe[:, 1::2] = torch.cos(position * div)
        reps = -(-length // period)
        self.register_buffer("pe", pe.repeat(reps, 1)[:length].unsqueeze(0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.pe[:, : x.shape[1]]


class Stylization(nn.Module):
    """AdaIN-like block: LayerNorm, scale/shift from the time+style embedding, SiLU, Linear."""

    def __init__(self, dim: int, emb_dim: int, dropout: float):
        super().__init__()
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(emb_dim, 2 * dim))
        self.norm = nn.LayerNorm(dim)
        self.out_layers = nn.Sequential(nn.SiLU(), nn.Dropout(dropout), nn.Linear(dim, dim))
        nn.init.zeros_(self.out_layers[2].weight)
        nn.init.zeros_(self.out_layers[2].bias)

    def forward(self, h: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        scale, shift = self.emb_layers(emb).unsqueeze(1).chunk(2, dim=2)
        return self.out_layers(self.norm(h) * (1 + scale) + shift)


class LinearSelfAttention(nn.Module):
    """Efficient (linear) temporal self-attention: softmax over features for queries,
    over time for keys, so the cost grows linearly with the window length."""

    def __init__(self, dim: int, heads: int, emb_dim: int, dropout: float):
        super().__init__()
        self.heads = heads
        self.norm = nn.LayerNorm(dim)
        self.query = nn.Linear(dim, dim)
        self.key = nn.Linear(dim, dim)
        self.value = nn.Linear(dim, dim)
        self.proj_out = Stylization(dim, emb_dim, dropout)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        b, t, d = x.shape
        xn = self.norm(x)
        q = F.softmax(self.query(xn).view(b, t, self.heads, -1), dim=-1)
        k = F.softmax(self.key(xn).view(b, t, self.heads, -1), dim=1)
        v = self.value(xn).view(b, t, self.heads, -1)
        context = torch.einsum("bnhd,bnhl->bhdl", k, v)
        y = torch.einsum("bnhd,bhdl->bnhl", q, context).reshape(b, t, d)
        return x + self.proj_out(y, emb)


class TemporalConv(nn.Module):
    """Local temporal mixing: a depthwise convolution over `kernel` frames of the normalised
    features, GELU, and a linear layer (zero-initialised: a new block starts as the identity)."""

    def __init__(self, dim: int, kernel: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.conv = nn.Conv1d(dim, dim, kernel, padding=kernel // 2, groups=dim)
        self.proj_out = nn.Linear(dim, dim)
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv(self.norm(x).transpose(1, 2)).transpose(1, 2)
        return x + self.proj_out(F.gelu(y))


class FeedForward(nn.Module):
    def __init__(self, dim: int, ff: int, emb_dim: int, dropout: float):
        super().__init__()
        self.linear1 = nn.Linear(dim, ff)
        self.linear2 = nn.Linear(ff, dim)
        self.dropout = nn.Dropout(dropout)
        self.proj_out = Stylization(dim, emb_dim, dropout)
        nn.init.zeros_(self.linear2.weight)
        nn.init.zeros_(self.linear2.bias)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        y = self.linear2(self.dropout(F.gelu(self.linear1(x))))
        return x + self.proj_out(y, emb)


class Layer(nn.Module):
    """Motion-speech fusion residual block (optional), attention, temporal convolution
    (optional), feed-forward."""

    def __init__(self, dim: int, cond_dim: int, cfg: ModelConfig, temporal_kernel: int = 0):
        super().__init__()
        emb_dim = cfg.time_embed_dim
        if cond_dim:
            fused = dim + cond_dim
            self.feat_proj = nn.Sequential(
                nn.LayerNorm(fused), nn.Linear(fused, 2 * dim), nn.SiLU(), nn.Linear(2 * dim, dim))
        self.sa_block = LinearSelfAttention(dim, cfg.heads, emb_dim, cfg.dropout)
        if temporal_kernel:
            self.conv_block = TemporalConv(dim, temporal_kernel)
        self.ffn = FeedForward(dim, cfg.ff, emb_dim, cfg.dropout)

    def fuse(self, h: torch.Tensor, cond: torch.Tensor, null: torch.Tensor | None = None,
             null_cond: torch.Tensor | None = None) -> torch.Tensor:
        """h + MLP([h | cond]); rows where `null` (B,) is true see `null_cond` instead of the
        whole [h | cond] (the official classifier-free null condition)."""
        fused = torch.cat([h, cond], dim=-1)
        if null is not None:
            fused = torch.where(null.view(-1, 1, 1), null_cond.to(fused.dtype), fused)
        return h + self.feat_proj(fused)

    def forward(self, h: torch.Tensor, emb: torch.Tensor, attend: torch.Tensor | None = None) -> torch.Tensor:
        """attend: (B,) bool, false for rows that bypass self-attention (skip guidance; the
        temporal convolution, being local, runs for every row)."""
        attended = self.sa_block(h, emb)
        h = attended if attend is None else torch.where(attend.view(-1, 1, 1), attended, h)
        if hasattr(self, "conv_block"):
            h = self.conv_block(h)
        return self.ffn(h, emb)


class Branch(nn.Module):
    """One motion branch (expression or gesture): embeds its noisy motion, fuses it
    with speech (and, for gesture, expression) in every layer, predicts its noise."""

    def __init__(self, motion_dim: int, extra_dim: int, cfg: ModelConfig, temporal_kernel: int = 0,
                 layers: int | None = None, embeds: bool = True):
        """`embeds`: the branch embeds the time step and style itself (else it is given the
        embedding of the branch it follows: the lower-body branch)."""
        super().__init__()
        speech = cfg.speech_latent if cfg.has_speech_input else 0
        cond_dim = cfg.audio_latent + speech + extra_dim
        if cfg.classifier_free:
            self.null_cond_emb = nn.Parameter(torch.randn(1, cfg.latent + cond_dim))
        self.PE = PositionalEncoding(cfg.latent, cfg.pe_period, cfg.pe_length)
        self.joint_embed = nn.Linear(motion_dim, cfg.latent)
        self.audio_proj = nn.Linear(2 * cfg.mel_dim, cfg.audio_latent)
        if cfg.has_speech_input:
            self.hubert_encoder = nn.Sequential(
                nn.Conv1d(cfg.speech_dim, cfg.speech_latent, 3, 1, 1, bias=False),
                nn.BatchNorm1d(cfg.speech_latent),
                nn.GELU(),
                nn.Conv1d(cfg.speech_latent, cfg.speech_latent, 3, 1, 1, bias=False),
            )
        if embeds:
            self.time_embed = _mlp(cfg.latent, cfg.time_embed_dim)
            self.pid_embed = _mlp(cfg.style_dim, cfg.time_embed_dim)
        self.temporal_decoder_blocks = nn.ModuleList(Layer(cfg.latent, cond_dim, cfg, temporal_kernel)
                                                     for _ in range(cfg.layers if layers is None else layers))
        self.out = nn.Linear(cfg.latent, motion_dim)
        self.latent = cfg.latent

    def embed(self, timesteps: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """The time step's and style's embedding the layers are modulated by."""
        return self.time_embed(timestep_embedding(timesteps, self.latent)) + self.pid_embed(style)

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, audio: torch.Tensor,
                speech: torch.Tensor | None, extra: torch.Tensor | None, style: torch.Tensor,
                null: torch.Tensor | None = None, attend: torch.Tensor | None = None,
                emb: torch.Tensor | None = None) -> torch.Tensor:
        """The branch's noise prediction for every batch row (see Layer for null / attend;
        `emb`, the embedding of the time step and style, when the branch has none)."""
        parts = [self.audio_proj(audio)]
        if speech is not None:
            parts.append(self.hubert_encoder(speech.transpose(1, 2)).transpose(1, 2))
        if extra is not None:
            parts.append(extra)
        cond = torch.cat(parts, dim=-1)
        emb = self.embed(timesteps, style) if emb is None else emb
        h = self.PE(self.joint_embed(x))
        null_cond = getattr(self, "null_cond_emb", None)
        if null is not None and null_cond is None:
            raise ValueError("a null condition needs a model trained with one (classifier_free)")
        for layer in self.temporal_decoder_blocks:
            h = layer(layer.fuse(h, cond, null, null_cond), emb, attend)
        return self.out(h)


class UniEG(nn.Module):
    """The DiffSHEG denoiser: eps_theta(x_t, t, speech, style).

    x_t is (B, T, gesture_dim + expression_dim), gesture first, normalised.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.time_embed = _mlp(cfg.latent, cfg.time_embed_dim)
        self.encoder_aud = Layer(cfg.mel_dim, 0, cfg)
        self.encoder_exp = Branch(cfg.expression_dim, 0, cfg)
        self.encoder_ges = Branch(cfg.upper_dim, cfg.expression_dim, cfg, cfg.temporal_kernel)
        if cfg.lower_dim:  # the hips and legs, fed the upper body as the gestures are fed the face
            self.encoder_low = Branch(cfg.lower_dim, 2 * cfg.upper_dim, cfg, cfg.temporal_kernel, cfg.lower_layers,
                                      embeds=False)

    def _check_speech(self, speech: torch.Tensor | None) -> None:
        if (speech is not None) != self.cfg.has_speech_input:
            raise ValueError("this model was built %s a second speech input"
                             % ("with" if self.cfg.has_speech_input else "without"))

    def expression(self, expression: torch.Tensor, timesteps: torch.Tensor, mel: torch.Tensor,
                   speech: torch.Tensor | None, style: torch.Tensor, null: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """The expression branch: (its noise prediction per row, the speech features both
        branches fuse). timesteps: (B,) in the 1000-step indexing; null: (B,) bool, rows
        that see the learned null condition (classifier-free guidance and dropout)."""
        self._check_speech(speech)
        if self.cfg.log_mel:
            mel = torch.log10(mel + 1e-5)
        emb = self.time_embed(timestep_embedding(timesteps, self.cfg.latent))
        # The official fusion residual also runs on the audio layer, which has no
        # fusion MLP: its input is added to itself before attention.
        audio = torch.cat([mel, self.encoder_aud(mel + mel, emb)], dim=-1)
        return self.encoder_exp(expression, timesteps, audio, speech, None, style, null), audio

    def gesture(self, gesture: torch.Tensor, timesteps: torch.Tensor, audio: torch.Tensor,
                speech: torch.Tensor | None, expression_x0: torch.Tensor, style: torch.Tensor,
                null: torch.Tensor | None = None, attend: torch.Tensor | None = None) -> torch.Tensor:
        """The gesture branch, which sees the expression branch's predicted x0 (the
        uni-directional expression-to-gesture flow), and with `lower_dim` the lower-body
        branch after it, which sees the upper body's noisy motion and noise prediction (the
        flow goes on: face, then gestures, then legs). attend: (B,) bool, false for rows
        without self-attention (skip guidance: see `guidance`)."""
        self._check_speech(speech)
        if not self.cfg.lower_dim:
            return self.encoder_ges(gesture, timesteps, audio, speech, expression_x0, style, null, attend)
        upper, lower = gesture.split([self.cfg.upper_dim, self.cfg.lower_dim], dim=-1)
        emb = self.encoder_ges.embed(timesteps, style)
        eps_upper = self.encoder_ges(upper, timesteps, audio, speech, expression_x0, style, null, attend, emb)
        seen = torch.cat([upper, eps_upper.detach()], dim=-1)  # x_t and eps: the upper body's x0 at any t
        eps_lower = self.encoder_low(lower, timesteps, audio, speech, seen, style, null, attend, emb.detach())
        return torch.cat([eps_upper, eps_lower], dim=-1)

    def forward(self, x_t: torch.Tensor, timesteps: torch.Tensor, mel: torch.Tensor,
                speech: torch.Tensor | None, style: torch.Tensor,
                x0_coefs: tuple[torch.Tensor, torch.Tensor], null_rows: int = 0,
                expression_x0: torch.Tensor | None = None, gesture_timesteps: torch.Tensor | None = None
                ) -> torch.Tensor:
        """Predict the noise in x_t, one unguided prediction per row (training).

        x0_coefs: sqrt(1/abar_t) and sqrt(1/abar_t - 1), each (B, 1, 1), used to turn the
        expression noise into the expression x0 that conditions the gesture branch.
        null_rows: the first `null_rows` rows see the learned null condition instead of
        their speech (classifier-free dropout).
        expression_x0: the face x0 the gesture branch sees instead (distillation feeds it the
        teacher's guided one); gesture_timesteps: the gesture branch's timesteps where they are
        not `timesteps` (a distilled student's refining pass, see training.distill).
        """
        cfg = self.cfg
        if null_rows and not cfg.classifier_free:
            raise ValueError("classifier-free dropout needs a model trained with a null condition")
        null = torch.arange(x_t.shape[0], device=x_t.device) < null_rows if null_rows else None
        gesture, expression = x_t.split([cfg.gesture_dim, cfg.expression_dim], dim=-1)
        eps_exp, audio = self.expression(expression, timesteps, mel, speech, style, null)
        sqrt_recip, sqrt_recipm1 = x0_coefs
        exp_x0 = sqrt_recip * expression - sqrt_recipm1 * eps_exp.detach() if expression_x0 is None else expression_x0
        eps_ges = self.gesture(gesture, timesteps if gesture_timesteps is None else gesture_timesteps, audio, speech,
                               exp_x0, style, null)
        return torch.cat([eps_ges, eps_exp], dim=-1)


# ---------------------------------------------------------------- the phonetic encoder

class _Activation(nn.Module):
    """GELU then dropout, one module so the convolutions keep their state-dict names."""

    def __init__(self, dropout: float):
        super().__init__()
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.dropout(nn.functional.gelu(x))


class PhoneticEncoder(nn.Module):
    """Log-mel (B, n_mels, N) -> phone logits (B, len(PHONES), N), non-causal dilated convs."""

    def __init__(self, cfg: PhoneticConfig):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("mel_mean", torch.zeros(cfg.n_mels, 1))
        self.register_buffer("mel_std", torch.ones(cfg.n_mels, 1))
        layers: list[nn.Module] = []
        width = cfg.n_mels
        for d in cfg.dilations:
            layers += [nn.Conv1d(width, cfg.channels, cfg.kernel, padding=d * (cfg.kernel // 2), dilation=d),
                       _Activation(cfg.dropout)]
            width = cfg.channels
        layers.append(nn.Conv1d(width, len(PHONES), 1))
        self.net = nn.Sequential(*layers)

    def forward(self, mel: torch.Tensor) -> torch.Tensor:
        return self.net((mel - self.mel_mean) / self.mel_std)


def state_arrays(module: nn.Module, dtype: torch.dtype = torch.float32) -> dict[str, np.ndarray]:
    """`module`'s state dict as numpy arrays (what model files hold), floating-point tensors
    in `dtype` and integer buffers as they are."""
    return {k: v.detach().cpu().to(dtype if v.is_floating_point() else v.dtype).numpy()
            for k, v in module.state_dict().items()}


def load_state_strict(model: nn.Module, state: dict, source: str, hint: str = "") -> None:
    """Load `state` (torch tensors or numpy arrays) into `model`, refusing any missing,
    unexpected or misshapen key.

    Only BatchNorm's `num_batches_tracked` counters may be absent (safetensors exports
    often drop integer buffers; they play no part in inference).
    """
    expected = model.state_dict()
    state = {**{k: v for k, v in expected.items() if k.endswith("num_batches_tracked")}, **state}
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    reshaped = sorted(
        f"{k}: file {tuple(state[k].shape)}, model {tuple(expected[k].shape)}"
        for k in set(expected) & set(state) if tuple(state[k].shape) != tuple(expected[k].shape))
    if missing or unexpected or reshaped:
        lines = [f"{source} does not match the model:"]
        for title, items in (("missing keys", missing), ("unexpected keys", unexpected),
                             ("wrong shapes", reshaped)):
            if items:
                lines.append(f"  {title} ({len(items)}): " + ", ".join(items))
        likely = hint or (
            "the file is truncated or damaged" if missing and not unexpected and not reshaped
            else "the checkpoint was made for another model configuration")
        lines.append(f"  likely cause: {likely}")
        raise CheckpointError("\n".join(lines))
    model.load_state_dict({k: torch.tensor(v) if isinstance(v, np.ndarray) else v
                           for k, v in state.items()}, strict=True)
