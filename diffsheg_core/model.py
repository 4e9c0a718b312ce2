"""The UniEG denoiser of DiffSHEG: an expression branch, then a gesture branch that
sees the expression branch's predicted x0.

Parameter names and shapes follow the official implementation, so the published
checkpoints load strictly into this module (see `checkpoints`). Read top to bottom:
configuration, building blocks, one branch, the whole network.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn


SPEECH_ENCODERS = ("hubert", "phonetic")


@dataclass
class ModelConfig:
    """Sizes and switches of a UniEG network (defaults: the official BEAT model)."""

    gesture_dim: int = 141
    expression_dim: int = 51
    style_dim: int = 30           # one-hot speaker / style classes
    mel_dim: int = 128            # mel bands per motion frame
    audio_latent: int = 256       # width of the projected [mel | encoded mel] feature
    use_hubert: bool = True       # a second speech input, encoded per branch to hubert_latent
    speech_encoder: str = "hubert"  # its source: hubert (official, 1024-d) or phonetic (stored in the model file)
    hubert_dim: int = 1024
    hubert_latent: int = 128
    latent: int = 512
    layers: int = 8               # per branch
    ff: int = 1024
    heads: int = 8
    dropout: float = 0.0
    pe_period: int = 600          # sinusoidal PE, restarting in every window
    pe_length: int = 1200
    classifier_free: bool = False  # learned null condition for guidance
    log_mel: bool = False         # feed log10(mel + 1e-5) instead of the raw power mel (official: raw)
    clip_len: int = 34            # frames per diffusion window (n_poses)
    fps: float = 15.0
    layout: str = "beat"

    def __post_init__(self):
        if self.speech_encoder not in SPEECH_ENCODERS:
            raise ValueError(f"speech_encoder must be one of {', '.join(SPEECH_ENCODERS)}, "
                             f"got {self.speech_encoder!r}")

    @property
    def dim(self) -> int:
        return self.gesture_dim + self.expression_dim

    @property
    def phonetic_input(self) -> bool:
        """The second speech input is the phonetic encoder's (stored with the model)."""
        return self.use_hubert and self.speech_encoder == "phonetic"

    @property
    def time_embed_dim(self) -> int:
        return 4 * self.latent

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "ModelConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown model configuration fields: {sorted(unknown)}")
        return cls(**values)


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
    """Motion-speech fusion residual block (optional), attention, feed-forward."""

    def __init__(self, dim: int, cond_dim: int, cfg: ModelConfig):
        super().__init__()
        emb_dim = cfg.time_embed_dim
        if cond_dim:
            fused = dim + cond_dim
            self.feat_proj = nn.Sequential(
                nn.LayerNorm(fused), nn.Linear(fused, 2 * dim), nn.SiLU(), nn.Linear(2 * dim, dim))
        self.sa_block = LinearSelfAttention(dim, cfg.heads, emb_dim, cfg.dropout)
        self.ffn = FeedForward(dim, cfg.ff, emb_dim, cfg.dropout)

    def fuse(self, h: torch.Tensor, cond: torch.Tensor, null_rows: int = 0,
             null_cond: torch.Tensor | None = None) -> torch.Tensor:
        """h + MLP([h | cond]); the first `null_rows` batch rows see `null_cond` instead."""
        fused = torch.cat([h, cond], dim=-1)
        if null_rows:
            fused = torch.cat([null_cond.expand(null_rows, fused.shape[1], -1), fused[null_rows:]])
        return h + self.feat_proj(fused)

    def forward(self, h: torch.Tensor, emb: torch.Tensor, skip_rows: int = 0) -> torch.Tensor:
        """skip_rows: the last `skip_rows` batch rows bypass self-attention (skip guidance)."""
        if skip_rows:
            keep = h.shape[0] - skip_rows
            h = torch.cat([self.sa_block(h[:keep], emb[:keep]), h[keep:]])
        else:
            h = self.sa_block(h, emb)
        return self.ffn(h, emb)


class Branch(nn.Module):
    """One motion branch (expression or gesture): embeds its noisy motion, fuses it
    with speech (and, for gesture, expression) in every layer, predicts its noise."""

    def __init__(self, motion_dim: int, extra_dim: int, cfg: ModelConfig):
        super().__init__()
        hub = cfg.hubert_latent if cfg.use_hubert else 0
        cond_dim = cfg.audio_latent + hub + extra_dim
        if cfg.classifier_free:
            self.null_cond_emb = nn.Parameter(torch.randn(1, cfg.latent + cond_dim))
        self.PE = PositionalEncoding(cfg.latent, cfg.pe_period, cfg.pe_length)
        self.joint_embed = nn.Linear(motion_dim, cfg.latent)
        self.audio_proj = nn.Linear(2 * cfg.mel_dim, cfg.audio_latent)
        if cfg.use_hubert:
            self.hubert_encoder = nn.Sequential(
                nn.Conv1d(cfg.hubert_dim, cfg.hubert_latent, 3, 1, 1, bias=False),
                nn.BatchNorm1d(cfg.hubert_latent),
                nn.GELU(),
                nn.Conv1d(cfg.hubert_latent, cfg.hubert_latent, 3, 1, 1, bias=False),
            )
        self.time_embed = _mlp(cfg.latent, cfg.time_embed_dim)
        self.pid_embed = _mlp(cfg.style_dim, cfg.time_embed_dim)
        self.temporal_decoder_blocks = nn.ModuleList(Layer(cfg.latent, cond_dim, cfg) for _ in range(cfg.layers))
        self.out = nn.Linear(cfg.latent, motion_dim)
        self.latent = cfg.latent

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, audio: torch.Tensor,
                hubert: torch.Tensor | None, extra: torch.Tensor | None, style: torch.Tensor,
                guidance: float | None, null_rows: int = 0, skip_guidance: float | None = None
                ) -> torch.Tensor:
        parts = [self.audio_proj(audio)]
        if hubert is not None:
            parts.append(self.hubert_encoder(hubert.transpose(1, 2)).transpose(1, 2))
        if extra is not None:
            parts.append(extra)
        cond = torch.cat(parts, dim=-1)
        emb = self.time_embed(timestep_embedding(timesteps, self.latent)) + self.pid_embed(style)
        h = self.PE(self.joint_embed(x))

        rows, skip_rows = x.shape[0], 0
        if guidance is not None or skip_guidance is not None:
            # Two passes in one batch: [null | cond] for classifier-free guidance,
            # [cond | cond without self-attention] for skip guidance.
            null_rows, skip_rows = (rows, 0) if guidance is not None else (0, rows)
            h, cond, emb = (torch.cat([v, v]) for v in (h, cond, emb))
        for layer in self.temporal_decoder_blocks:
            h = layer(layer.fuse(h, cond, null_rows, getattr(self, "null_cond_emb", None)), emb, skip_rows)
        out = self.out(h)
        if guidance is not None:
            uncond, cond_out = out[:rows], out[rows:]
            return uncond + guidance * (cond_out - uncond)
        if skip_guidance is not None:
            cond_out, skipped = out[:rows], out[rows:]
            return cond_out + skip_guidance * (cond_out - skipped)
        return out


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
        self.encoder_ges = Branch(cfg.gesture_dim, cfg.expression_dim, cfg)

    def forward(self, x_t: torch.Tensor, timesteps: torch.Tensor, mel: torch.Tensor,
                hubert: torch.Tensor | None, style: torch.Tensor,
                x0_coefs: tuple[torch.Tensor, torch.Tensor],
                guidance: float | None = None, null_rows: int = 0,
                skip_guidance: float | None = None) -> torch.Tensor:
        """Predict the noise in x_t.

        timesteps: (B,) in the 1000-step indexing. x0_coefs: sqrt(1/abar_t) and
        sqrt(1/abar_t - 1), each (B, 1, 1), used to turn the expression noise into the
        expression x0 that conditions the gesture branch. guidance: classifier-free
        scale (only for models trained with a null condition; None = unguided).
        null_rows: in training, the first `null_rows` batch rows see the learned null
        condition instead of their speech (classifier-free dropout).

        skip_guidance: scale s of skip-layer guidance on the gesture branch (None = off):
        eps + s (eps - eps without the branch's self-attention blocks), which steers the
        gestures away from what the network makes of each frame without its temporal
        context (after Spatiotemporal Skip Guidance, Hyung et al. 2024). It replaces the
        gesture branch's classifier-free pass, so guided generation costs the same: speech
        guidance hardly moves the gestures, while small networks' gestures come out at
        about 0.6x the amplitude of their data and skip guidance restores it.
        """
        cfg = self.cfg
        if (hubert is not None) != cfg.use_hubert:
            raise ValueError(
                "this model was built %s HuBERT features" % ("with" if cfg.use_hubert else "without"))
        if (guidance is not None or null_rows) and not cfg.classifier_free:
            raise ValueError("classifier-free guidance needs a model trained with a null condition")
        if (guidance is not None or skip_guidance is not None) and null_rows:
            raise ValueError("null_rows is for training; guided sampling builds its own second pass")
        if cfg.log_mel:
            mel = torch.log10(mel + 1e-5)
        emb = self.time_embed(timestep_embedding(timesteps, cfg.latent))
        # The official fusion residual also runs on the audio layer, which has no
        # fusion MLP: its input is added to itself before attention.
        mel_feat = self.encoder_aud(mel + mel, emb)
        audio = torch.cat([mel, mel_feat], dim=-1)

        gesture, expression = x_t.split([cfg.gesture_dim, cfg.expression_dim], dim=-1)
        eps_exp = self.encoder_exp(expression, timesteps, audio, hubert, None, style, guidance, null_rows)
        sqrt_recip, sqrt_recipm1 = x0_coefs
        exp_x0 = sqrt_recip * expression - sqrt_recipm1 * eps_exp.detach()
        eps_ges = self.encoder_ges(gesture, timesteps, audio, hubert, exp_x0, style,
                                   guidance if skip_guidance is None else None, null_rows, skip_guidance)
        return torch.cat([eps_ges, eps_exp], dim=-1)
