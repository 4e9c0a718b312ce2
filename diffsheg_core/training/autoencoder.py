"""The motion autoencoders whose latent space the Fréchet distances are measured in:
FMD on whole motion (gesture + expression), FGD on gesture, FED on expression.

Each is a 1-D convolutional encoder over a clip of normalised motion down to one latent
vector, and a mirror decoder trained to reconstruct the clip (position + velocity loss).
`python -m diffsheg_core.autoencoder --data-config data.json --out ae.pt` trains all three.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ..errors import DiffshegError
from ..rigs import Layout, get_layout

log = logging.getLogger(__name__)

PARTS = ("motion", "gesture", "expression")
"""What each autoencoder sees; their distances are FMD, FGD and FED."""


@dataclass
class AutoencoderConfig:
    clip_len: int = 32            # frames per clip, divisible by 4
    hidden: int = 128
    latent: int = 64
    steps: int = 3000
    batch_size: int = 64
    lr: float = 1e-3
    velocity_weight: float = 1.0
    seed: int = 0

    @classmethod
    def from_dict(cls, values: dict) -> "AutoencoderConfig":
        known = {f.name for f in fields(cls)}
        if set(values) - known:
            raise DiffshegError(f"unknown autoencoder settings: {sorted(set(values) - known)}")
        return cls(**values)


class ClipAutoencoder(nn.Module):
    """(B, T, C) clip -> (B, latent) -> (B, T, C)."""

    def __init__(self, channels: int, cfg: AutoencoderConfig):
        super().__init__()
        if cfg.clip_len % 4:
            raise DiffshegError(f"autoencoder clip length must be divisible by 4, got {cfg.clip_len}")
        h, t4 = cfg.hidden, cfg.clip_len // 4
        self.channels, self.hidden, self.t4 = channels, h, t4
        act = nn.LeakyReLU(0.2)
        self.encoder = nn.Sequential(
            nn.Conv1d(channels, h, 3, padding=1), act,
            nn.Conv1d(h, h, 4, stride=2, padding=1), act,
            nn.Conv1d(h, h, 4, stride=2, padding=1), act,
            nn.Flatten(), nn.Linear(h * t4, cfg.latent))
        self.expand = nn.Linear(cfg.latent, h * t4)
        self.decoder = nn.Sequential(
            act, nn.ConvTranspose1d(h, h, 4, stride=2, padding=1), act,
            nn.ConvTranspose1d(h, h, 4, stride=2, padding=1), act,
            nn.Conv1d(h, channels, 3, padding=1))

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x.transpose(1, 2))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.expand(z).view(-1, self.hidden, self.t4)).transpose(1, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(x))


def part_slice(layout: Layout, part: str) -> slice:
    return {"motion": slice(0, layout.dim), "gesture": slice(0, layout.gesture_dim),
            "expression": slice(layout.gesture_dim, layout.dim)}[part]


def split_clips(motion: np.ndarray, clip_len: int, stride: int | None = None) -> np.ndarray:
    """(N, clip_len, D) windows of a (T, D) motion; non-overlapping unless `stride` is given."""
    stride = stride or clip_len
    starts = range(0, len(motion) - clip_len + 1, stride)
    if len(motion) < clip_len:
        raise DiffshegError(f"motion of {len(motion)} frames is shorter than one autoencoder clip "
                            f"({clip_len} frames)")
    return np.stack([motion[s : s + clip_len] for s in starts])


class MotionFeatures:
    """The three autoencoders of one layout with the statistics they normalise with."""

    def __init__(self, layout: Layout, cfg: AutoencoderConfig, mean: np.ndarray, std: np.ndarray,
                 nets: dict[str, ClipAutoencoder] | None = None):
        self.layout, self.cfg = layout, cfg
        self.mean, self.std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
        self.nets = nets or {p: ClipAutoencoder(part_slice(layout, p).stop - part_slice(layout, p).start, cfg)
                             for p in PARTS}

    def clips(self, motion: np.ndarray) -> np.ndarray:
        """Normalised non-overlapping clips of a raw (T, D) layout motion."""
        if motion.ndim != 2 or motion.shape[1] != self.layout.dim:
            raise DiffshegError(f"motion of shape {motion.shape} does not fit layout '{self.layout.name}'")
        return split_clips((motion - self.mean) / self.std, self.cfg.clip_len).astype(np.float32)

    @torch.no_grad()
    def features(self, motions: list[np.ndarray]) -> dict[str, np.ndarray]:
        """Latent vectors (N, latent) of every non-overlapping clip of `motions`, per part."""
        clips = torch.from_numpy(np.concatenate([self.clips(m) for m in motions]))
        return {p: net.eval().encode(clips[..., part_slice(self.layout, p)]).numpy()
                for p, net in self.nets.items()}

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"layout": self.layout.name, "config": asdict(self.cfg),
                    "mean": torch.from_numpy(self.mean), "std": torch.from_numpy(self.std),
                    "nets": {p: n.state_dict() for p, n in self.nets.items()}}, path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "MotionFeatures":
        path = Path(path)
        if not path.is_file():
            raise DiffshegError(f"{path}: no such autoencoder file; train one with "
                                "`python -m diffsheg_core.autoencoder`")
        try:
            raw = torch.load(path, map_location="cpu", weights_only=True)
            cfg = AutoencoderConfig.from_dict(raw["config"])
            feats = cls(get_layout(raw["layout"]), cfg, raw["mean"].numpy(), raw["std"].numpy())
            for p in PARTS:
                feats.nets[p].load_state_dict(raw["nets"][p])
        except (KeyError, RuntimeError, OSError, TypeError) as exc:
            raise DiffshegError(f"{path}: not a motion autoencoder file ({exc})") from exc
        return feats


def train_autoencoders(motions: list[np.ndarray], layout: Layout, mean: np.ndarray, std: np.ndarray,
                       cfg: AutoencoderConfig, stride: int = 4) -> tuple[MotionFeatures, dict[str, float]]:
    """Train the three autoencoders on overlapping clips of raw (T, D) motions.
    Returns them and each one's final reconstruction error (mean absolute, normalised units)."""
    feats = MotionFeatures(layout, cfg, mean, std)
    data = torch.from_numpy(np.concatenate(
        [split_clips((m - feats.mean) / feats.std, cfg.clip_len, stride) for m in motions]).astype(np.float32))
    gen = torch.Generator().manual_seed(cfg.seed)
    errors = {}
    for part, net in feats.nets.items():
        torch.manual_seed(cfg.seed)
        x_all = data[..., part_slice(layout, part)]
        opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
        net.train()
        for _ in tqdm(range(cfg.steps), desc=f"autoencoder ({part})", disable=None, leave=False):
            x = x_all[torch.randint(len(x_all), (cfg.batch_size,), generator=gen)]
            y = net(x)
            loss = (y - x).abs().mean() + cfg.velocity_weight * (y.diff(dim=1) - x.diff(dim=1)).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        with torch.no_grad():
            errors[part] = float((net.eval()(x_all) - x_all).abs().mean())
    return feats, errors


def main(argv: list[str] | None = None) -> int:
    """Train the FMD / FGD / FED autoencoders on the training split of a dataset."""
    from .data import DataConfig, load_takes, normalisation

    parser = argparse.ArgumentParser(prog="diffsheg train-autoencoder", description=main.__doc__)
    parser.add_argument("--data-config", required=True, help="JSON or TOML file with the data settings")
    parser.add_argument("--out", required=True, help="where to write the autoencoders (.pt)")
    parser.add_argument("--steps", type=int, help="training steps per autoencoder")
    args = parser.parse_args(argv)
    from .train import read_config_file

    settings = read_config_file(args.data_config)
    data_cfg = DataConfig(**settings.get("data", {}))
    ae_cfg = AutoencoderConfig.from_dict(settings.get("autoencoder", {}))
    if args.steps:
        ae_cfg.steps = args.steps
    train = load_takes(data_cfg, "train")
    stats = normalisation(data_cfg, train)
    short = [t.name for t in train.takes if t.n_frames < ae_cfg.clip_len]
    if short:
        print(f"skipping {len(short)} takes shorter than the {ae_cfg.clip_len}-frame autoencoder clip: "
              f"{', '.join(short[:5])}{' ...' if len(short) > 5 else ''}", file=sys.stderr)
    usable = [t.motion for t in train.takes if t.n_frames >= ae_cfg.clip_len]
    if not usable:
        raise DiffshegError(f"no training take is at least {ae_cfg.clip_len} frames long: "
                            "the autoencoder needs longer recordings")
    feats, errors = train_autoencoders(usable, train.layout, stats.mean, stats.std, ae_cfg)
    feats.save(args.out)
    print(json.dumps({"out": args.out, "takes": len(usable), "skipped": len(train.skipped) + len(short),
                      "reconstruction_error": errors}))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except DiffshegError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
