"""Model files: the bundled default, our own checkpoints, and the official DiffSHEG ones.

A `ModelBundle` is everything generation needs besides audio: the network, its
normalisation statistics, its default sampling settings and where it came from.

Our format is a safetensors file (no pickle): tensors `model.*`, `norm.mean`,
`norm.std`, optionally `phonetic.*` (the phonetic encoder) and `prior.*` (the gesture
prior), and JSON metadata (config, sampling, guidance scales, model id, model card).
Official checkpoints are torch pickles holding the state dict under `encoder`; they
are read with `weights_only=True` and loaded strictly.
"""

from __future__ import annotations

import json
import os
import pickle
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .errors import CheckpointError
from .foppas import PRESETS, FoppasConfig
from .model import ModelConfig, UniEG
from .phonetic import PhoneticEncoder, config_metadata, encoder_from, state_tensors
from .prior import GesturePrior
from .rigs import Layout, get_layout

FORMAT = "diffsheg-core/1"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "default.safetensors"
PHONETIC_PREFIX = "phonetic."
STATS_ENV = "DIFFSHEG_OFFICIAL_STATS"


@dataclass
class ModelBundle:
    model: UniEG
    mean: np.ndarray                 # (D,) normalisation, gesture then expression
    std: np.ndarray
    sampling: FoppasConfig
    guidance: Optional[float] = None  # default classifier-free scale (None: unguided)
    skip_guidance: Optional[float] = None  # default gesture skip-guidance scale (None: off; see UniEG)
    model_id: str = "unnamed"
    trained: bool = True
    info: dict = field(default_factory=dict)
    phonetic: Optional[PhoneticEncoder] = None  # the speech encoder of models with speech_encoder "phonetic"
    prior: Optional[GesturePrior] = None  # where later FOPPAS windows start from (see prior.py)

    @property
    def config(self) -> ModelConfig:
        return self.model.cfg

    @property
    def layout(self) -> Layout:
        return get_layout(self.config.layout)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def normalise(self, motion: np.ndarray) -> np.ndarray:
        return (motion - self.mean) / self.std

    def denormalise(self, motion: np.ndarray) -> np.ndarray:
        return motion * self.std + self.mean


# ---------------------------------------------------------------- strict loading

def load_state_strict(model: torch.nn.Module, state: dict[str, torch.Tensor], source: str,
                      hint: str = "") -> None:
    """Load `state` into `model`, refusing any missing, unexpected or misshapen key.

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
    model.load_state_dict(state, strict=True)


# ---------------------------------------------------------------- our format

def write_safetensors(tensors: dict[str, torch.Tensor], meta: dict[str, str], path: str | Path) -> Path:
    """Write atomically: a run killed mid-write leaves the previous file, not a broken one."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    save_file(tensors, str(tmp), metadata=meta)
    os.replace(tmp, path)
    return path


def read_safetensors(path: Path, fix: str) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """Metadata and tensors of a safetensors file; a damaged file raises CheckpointError
    ending in `fix`."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    try:
        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
        return meta, load_file(str(path))
    except Exception as exc:  # safetensors raises several types for damaged files
        raise CheckpointError(f"{path}: cannot read this safetensors file ({exc}); {fix}") from exc


def save_checkpoint(bundle: ModelBundle, path: str | Path) -> Path:
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in bundle.model.state_dict().items()}
    tensors["norm.mean"] = torch.from_numpy(np.asarray(bundle.mean, dtype=np.float32))
    tensors["norm.std"] = torch.from_numpy(np.asarray(bundle.std, dtype=np.float32))
    if bundle.phonetic is not None:
        tensors.update(state_tensors(bundle.phonetic, PHONETIC_PREFIX))
    if bundle.prior is not None:
        tensors.update(bundle.prior.tensors())
    meta = {
        "format": FORMAT,
        "config": json.dumps(bundle.config.to_dict()),
        "sampling": json.dumps(asdict(bundle.sampling)),
        "guidance": json.dumps(bundle.guidance),
        "skip_guidance": json.dumps(bundle.skip_guidance),
        "model_id": bundle.model_id,
        "trained": json.dumps(bundle.trained),
        "info": json.dumps(bundle.info, default=str),
        **({"phonetic": config_metadata(bundle.phonetic)} if bundle.phonetic is not None else {}),
    }
    return write_safetensors(tensors, meta, path)


def _load_ours(path: Path, device: torch.device) -> ModelBundle:
    meta, tensors = read_safetensors(path, "it may be truncated: download or export it again")
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a diffsheg-core checkpoint (format tag "
                              f"{meta.get('format')!r}, expected {FORMAT!r})")
    try:
        cfg = ModelConfig.from_dict(json.loads(meta["config"]))
        sampling = FoppasConfig(**json.loads(meta["sampling"]))
        mean, std = tensors.pop("norm.mean").numpy(), tensors.pop("norm.std").numpy()
    except (KeyError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: checkpoint metadata is incomplete ({exc})") from exc
    model = UniEG(cfg)
    state = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    load_state_strict(model, state, str(path))
    return ModelBundle(
        model=model.to(device).eval(), mean=mean, std=std, sampling=sampling,
        guidance=json.loads(meta.get("guidance", "null")),
        skip_guidance=json.loads(meta.get("skip_guidance", "null")), model_id=meta.get("model_id", path.stem),
        trained=json.loads(meta.get("trained", "true")), info=json.loads(meta.get("info", "{}")),
        phonetic=_stored_phonetic(cfg, meta, tensors, path), prior=_stored_prior(cfg, tensors, path))


def _stored_phonetic(cfg: ModelConfig, meta: dict, tensors: dict, path: Path) -> Optional[PhoneticEncoder]:
    if not cfg.phonetic_input:
        return None
    state = {k[len(PHONETIC_PREFIX):]: v for k, v in tensors.items() if k.startswith(PHONETIC_PREFIX)}
    if "phonetic" not in meta or not state:
        raise CheckpointError(f"{path}: the model takes phonetic features but the file holds no phonetic "
                              "encoder; export it again from its training run")
    return encoder_from(meta["phonetic"], state, f"{path} (phonetic encoder)")


def _stored_prior(cfg: ModelConfig, tensors: dict, path: Path) -> Optional[GesturePrior]:
    prior = GesturePrior.from_tensors(tensors, str(path))
    if prior is not None and (prior.dims != cfg.gesture_dim or prior.max_len < cfg.clip_len):
        raise CheckpointError(f"{path}: its gesture prior covers {prior.dims} channels over "
                              f"{prior.max_len} frames, but the model has {cfg.gesture_dim} gesture "
                              f"channels in {cfg.clip_len}-frame windows; export it again")
    return prior


# ---------------------------------------------------------------- official checkpoints

@dataclass(frozen=True)
class OfficialSetup:
    """What the official scripts use for one dataset, besides the weights."""

    name: str
    layout: str
    clip_len: int
    sampling: FoppasConfig
    guidance: Optional[float]
    stats_files: tuple[str, ...]


OFFICIAL = {
    "beat": OfficialSetup("beat", "beat", 34, PRESETS["official-beat"], None,
                          ("axis_angle_mean.npy", "axis_angle_std.npy", "facial51_mean.npy",
                           "facial51_std.npy")),
    "show": OfficialSetup("show", "smplx", 88, PRESETS["official-show"], 1.25,
                          ("talkshow_mean_std.npy",)),
}


def _read_pickle(path: Path) -> dict:
    try:
        return torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"{path}: refused to load: the file needs arbitrary code to unpickle ({exc}). "
            "Only plain tensors and containers are accepted; re-save the checkpoint's state "
            "dict with torch.save({'encoder': model.state_dict()}, path) in a trusted environment."
        ) from exc
    except (RuntimeError, EOFError, OSError) as exc:
        raise CheckpointError(f"{path}: cannot read this torch checkpoint ({exc}); it may be "
                              "truncated or not a checkpoint at all") from exc


def official_state_dict(raw: dict, path: Path) -> dict[str, torch.Tensor]:
    """The network's state dict from an official checkpoint (key `encoder`, optional `module.`)."""
    state = raw.get("encoder", raw) if isinstance(raw, dict) else None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(f"{path}: no state dict found (expected a dict with key 'encoder' "
                              "holding the network's tensors)")
    return {k[len("module."):] if k.startswith("module.") else k: v for k, v in state.items()}


def config_from_state(state: dict[str, torch.Tensor], dataset: Optional[str], path: Path) -> ModelConfig:
    """Infer the network configuration from tensor shapes (heads: 8, as the official models)."""
    try:
        blocks = {int(m.group(1)) for k in state
                  if (m := re.match(r"encoder_exp\.temporal_decoder_blocks\.(\d+)\.", k))}
        gesture_dim = state["encoder_ges.out.weight"].shape[0]
        expression_dim = state["encoder_exp.out.weight"].shape[0]
        cfg = dict(
            gesture_dim=gesture_dim, expression_dim=expression_dim,
            style_dim=state["encoder_exp.pid_embed.0.weight"].shape[1],
            mel_dim=state["encoder_aud.sa_block.norm.weight"].shape[0],
            audio_latent=state["encoder_exp.audio_proj.weight"].shape[0],
            use_hubert="encoder_exp.hubert_encoder.0.weight" in state,
            latent=state["time_embed.0.weight"].shape[1],
            layers=len(blocks),
            ff=state["encoder_exp.temporal_decoder_blocks.0.ffn.linear1.weight"].shape[0],
            heads=8,
            pe_length=state["encoder_exp.PE.pe"].shape[1],
            classifier_free="encoder_exp.null_cond_emb" in state,
        )
    except KeyError as exc:
        raise CheckpointError(f"{path}: not a DiffSHEG network: key {exc} is missing; the file is "
                              "truncated or holds another model") from exc
    name = dataset or {(141, 51): "beat", (129, 103): "show"}.get((gesture_dim, expression_dim))
    if name not in OFFICIAL:
        raise CheckpointError(
            f"{path}: cannot tell the dataset from gesture/expression sizes {gesture_dim}/"
            f"{expression_dim}; pass --config beat or --config show")
    setup = OFFICIAL[name]
    return ModelConfig(**cfg, clip_len=setup.clip_len, layout=setup.layout)


def official_stats(dataset: str, stats_dir: Optional[str | Path],
                   beside: Optional[Path] = None) -> tuple[np.ndarray, np.ndarray]:
    """Normalisation statistics the official model was trained with, from `stats_dir`,
    else $DIFFSHEG_OFFICIAL_STATS, else the folder `beside` (the checkpoint's own)."""
    setup = OFFICIAL[dataset]
    help_text = (f"official {dataset.upper()} checkpoints need the official normalisation statistics "
                 f"({', '.join(setup.stats_files)}), found in the DiffSHEG repository's "
                 f"assets/data.tar.gz: put them beside the checkpoint, or pass their folder with "
                 f"--stats DIR (or set {STATS_ENV})")
    folder = stats_dir or os.environ.get(STATS_ENV)
    if not folder and beside is not None and all((beside / f).is_file() for f in setup.stats_files):
        folder = beside
    if not folder:
        raise CheckpointError(help_text)
    folder = Path(folder)
    missing = [f for f in setup.stats_files if not (folder / f).is_file()]
    if missing:
        raise CheckpointError(f"{folder}: missing {', '.join(missing)}; {help_text}")
    if dataset == "beat":
        mean = np.concatenate([np.load(folder / "axis_angle_mean.npy"), np.load(folder / "facial51_mean.npy")])
        std = np.concatenate([np.load(folder / "axis_angle_std.npy"), np.load(folder / "facial51_std.npy")])
    else:
        stats = np.load(folder / "talkshow_mean_std.npy", allow_pickle=True).item()
        pose_mean, pose_std = np.asarray(stats["pose_mean"]), np.asarray(stats["pose_std"])
        # pose 165: jaw 3, eyes 6, global 3, body 63 (SMPL-X joints 1..21), hands 90
        body_ids = [j - 1 for j in (3, 6, 9) + tuple(range(12, 22))]
        gesture = np.concatenate([12 + 3 * np.array(body_ids)[:, None] + np.arange(3)]).ravel()
        gesture = np.concatenate([gesture, np.arange(75, 165)])
        mean = np.concatenate([pose_mean[gesture], pose_mean[:3], stats["expression_mean"]])
        # The official SHOW data pipeline uses the jaw's *mean* as its std; the published
        # model was trained that way, so its output is denormalised the same way.
        std = np.concatenate([pose_std[gesture], pose_mean[:3], stats["expression_std"]])
    return mean.astype(np.float32), std.astype(np.float32)


def _load_official(path: Path, dataset: Optional[str], stats_dir, device: torch.device) -> ModelBundle:
    state = official_state_dict(_read_pickle(path), path)
    cfg = config_from_state(state, dataset, path)
    name = "beat" if cfg.layout == "beat" else "show"
    model = UniEG(cfg)
    load_state_strict(model, state, str(path),
                      hint=f"the checkpoint is not the official {name.upper()} model: try --config "
                           f"{'show' if name == 'beat' else 'beat'}, or the file is truncated")
    mean, std = official_stats(name, stats_dir, beside=path.parent)
    setup = OFFICIAL[name]
    return ModelBundle(model=model.to(device).eval(), mean=mean, std=std, sampling=setup.sampling,
                       guidance=setup.guidance if cfg.classifier_free else None,
                       model_id=f"official-{name}:{path.name}", trained=True,
                       info={"source": "DiffSHEG official checkpoint", "dataset": name})


# ---------------------------------------------------------------- the default and entry point

def untrained_bundle(seed: int = 0) -> ModelBundle:
    """A small randomly initialised model, used only until trained weights are bundled.

    Its output is noise around the rest pose: it is labelled untrained everywhere.
    """
    cfg = ModelConfig(latent=128, layers=2, ff=256, heads=4, use_hubert=False)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = UniEG(cfg).eval()
    dim = cfg.dim
    return ModelBundle(model=model, mean=np.zeros(dim, np.float32), std=np.full(dim, 0.05, np.float32),
                       sampling=PRESETS["official-beat"], model_id="untrained-beat-small",
                       trained=False, info={"note": "random weights; no learned motion"})


def load_model(source: str | Path | None = None, *, device: str | torch.device = "cpu",
               dataset: Optional[str] = None, stats_dir: str | Path | None = None) -> ModelBundle:
    """Load a model: None = the bundled default; else a checkpoint path (ours or official)."""
    device = torch.device(device)
    if source is None:
        if DEFAULT_WEIGHTS.is_file():
            return _load_ours(DEFAULT_WEIGHTS, device)
        return untrained_bundle()
    path = Path(source).expanduser()
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    if dataset is not None and dataset not in OFFICIAL:
        raise CheckpointError(f"unknown configuration '{dataset}': choose beat or show")
    with open(path, "rb") as fh:
        head = fh.read(16)
    if path.suffix == ".safetensors" or head[8:9] == b"{":
        return _load_ours(path, device)
    return _load_official(path, dataset, stats_dir, device)
