"""Training DiffSHEG: `python -m diffsheg_core train --config run.toml`.

The objective is the paper's (section 3.4): lambda_t * MSE on the predicted noise +
lambda_v * MSE on the velocity of the predicted x0 + lambda_delta * Huber on x0, with
speaker-style conditioning and classifier-free dropout. AdamW, gradient clipping, EMA
weights, autocast on GPU, torch.distributed when launched by torchrun (gloo on CPU,
nccl on GPU).

Every random draw of step s (clips, timesteps, noise, dropout) comes from a generator
seeded with (seed, s, rank), so a run resumed from its last checkpoint after a kill
continues exactly as it would have. The run folder holds:
  train_state.pt      everything needed to resume (weights, EMA, optimiser, step)
  model.safetensors   the EMA model as a generation checkpoint (config, statistics, layout)
  log.jsonl           one line per logged step and per validation pass
  summary.json        final step, losses and a parameter checksum per rank
With `export` set, the final EMA model is also written there (in `export_dtype`); running
the same command again after the last step only rewrites that file.

`objective = "distill"` trains a few-step student of the `init_from` model's guided fast
sampling instead (training.distill); the run's model file is that model with the student in it.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import time
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from tqdm import tqdm

from ..checkpoints import ModelBundle, load_model, save_checkpoint
from ..config import ModelConfig
from ..style import style_names_fit
from .data import ClipDataset, DataConfig, NormStats, TakeSet, load_takes, normalisation
from .distill import REFINE_OFFSET, Distillation, guided_target
from ..diffusion import Schedule
from ..errors import DiffshegError
from ..foppas import PRESETS, FoppasConfig, with_overrides
from ..pipeline import check_skip_guidance
from ..speech_features import hubert_encoding
from ..rigs import get_layout
from ..validate import check_number
from .train_phonetic import load_phonetic, speech_encoding as phonetic_speech
from ..prior import GesturePrior
from ..torch_layer.devices import resolve_device
from ..torch_layer.export import with_graphs, with_student_graphs
from ..torch_layer.model import PhoneticEncoder, UniEG, load_state_strict, state_arrays

EXPORT_DTYPES = {"float32": torch.float32, "float16": torch.float16}
TRAINS = ("all", "gestures", "legs", "face")  # the parts of the network a run may train (TrainConfig.trains)
OBJECTIVES = ("denoise", "distill")  # what a run learns (TrainConfig.objective)
STATE_FILE = "train_state.pt"
MODEL_FILE = "model.safetensors"
LOG_FILE = "log.jsonl"
SUMMARY_FILE = "summary.json"


@dataclass
class TrainConfig:
    """A training run. `data` is a DataConfig; `model` overrides ModelConfig fields (the
    layout, its sizes, the clip length and fps come from the data)."""

    data: DataConfig = field(default_factory=DataConfig)
    # further datasets trained on beside `data` ([[datasets]] tables): each names what differs
    # from [data] (kind, root, stride, style, ...); its layout, fps and clip length are [data]'s
    datasets: list = field(default_factory=list)
    model: dict = field(default_factory=dict)
    out_dir: str = "runs/diffsheg"
    steps: int = 100_000
    batch_size: int = 32            # over all processes together
    lr: float = 2e-4
    warmup_steps: int = 0
    lr_schedule: str = "cosine"     # cosine (down to lr_min) or constant, after the warm-up
    lr_min: float = 0.0
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    lambda_t: float = 10.0          # noise prediction
    lambda_v: float = 1.0           # velocity of x0
    lambda_delta: float = 1.0       # Huber on x0
    lambda_a: float = 0.0           # acceleration of x0 (this project's addition against jitter; 0: the paper's loss)
    huber_delta: float = 1.0
    x0_weighting: str = "abar"      # abar (x0 terms weighted by abar_t per sample) or none (unweighted)
    cond_drop: float = 0.0          # classifier-free dropout probability (official SHOW: 0.2)
    style_drop: float = 0.0         # share of clips trained on the null style (all zeros): style guidance
    style_names: list = field(default_factory=list)  # names of the style classes, stored in the model file
    default_style: str | int = 0    # the style generation uses when none is asked for
    guidance: float | None = None   # default guidance scale stored in the checkpoints (guided models)
    skip_guidance: float | None = None  # default gesture skip-guidance scale stored in the checkpoints
    init_from: str = ""             # start from this checkpoint's weights (fine-tuning; see init_weights)
    # which part of the network trains; the rest keeps the weights it starts with:
    # all; gestures (the gesture branch, and a whole-body model's lower-body branch: the face
    # and the speech layer both branches read stay, so a fine-tuned model keeps its source's
    # face); legs (the lower-body branch alone: a whole-body model widened from one without
    # legs keeps its source's upper body and face); face (the expression branch alone: the
    # speech layer, the gesture and lower-body branches and the gesture prior stay, and the
    # gestures change only through the face they are fed)
    trains: str = "all"
    # denoise: the paper's loss on the data; distill: a student of init_from's guided fast
    # sampling, one pass a step (training.distill), written into a copy of init_from's file
    objective: str = "denoise"
    # fine-tuning on data that holds only some face channels (a `facegood` capture's mouth): the
    # face channels a clip leaves out of the loss learn init_from's own noise prediction there,
    # this much of the noise term's weight (0: off, as before), so what the data does not say
    # (blinks, brows) stays the model's instead of drifting with the shared weights
    keep_unsaid: float = 0.0
    # how far the data's normalisation statistics may lie from those of the model a run is
    # fine-tuned from, as a share of each channel's spread: a rebuild of the same corpus moves
    # them by up to 2 %, other data by far more; raise it only for data widened on purpose
    stats_tolerance: float = 0.05
    precision: str = "auto"         # auto (bf16/fp16 on GPU, fp32 on CPU), fp32, bf16, fp16
    device: str = "auto"
    seed: int = 0
    log_every: int = 50
    checkpoint_every: int = 1000
    validate_every: int = 1000
    val_clips: int = 256
    sampling_preset: str = "official-beat"
    sampling: dict = field(default_factory=dict)  # FOPPAS settings over the preset, e.g. {"eta": 1.0}
    model_id: str = "diffsheg-trained"
    export: str = ""                # also write the final EMA model here (e.g. a bundled weights file)
    export_dtype: str = "float32"   # float32, or float16 to halve the exported file
    card: dict = field(default_factory=dict)  # model card facts stored in the checkpoint's info
    phonetic: str = ""              # phonetic encoder (.safetensors) for speech_encoder = "phonetic"
    hubert: str = ""                # local HuBERT folder for speech_encoder = "hubert" (default: HF cache)

    @classmethod
    def from_dict(cls, values: dict) -> "TrainConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise DiffshegError(f"unknown training settings: {', '.join(sorted(unknown))} "
                                f"(known: {', '.join(sorted(known))})")
        values = dict(values)
        data = values.pop("data", {})
        datasets = values.pop("datasets", [])
        if not isinstance(datasets, list) or not all(isinstance(d, dict) for d in datasets):
            raise DiffshegError("datasets must be a list of tables ([[datasets]] in TOML), each naming what "
                                "differs from [data]")
        data_known = {f.name for f in fields(DataConfig)}
        for table in (data, *datasets):
            if set(table) - data_known:
                raise DiffshegError(f"unknown data settings: {', '.join(sorted(set(table) - data_known))}")
        shared = ("fps", "clip_len", "whole_body")
        for table in datasets:
            differ = [k for k in shared if k in table and table[k] != data.get(k, getattr(DataConfig, k))]
            if differ:
                raise DiffshegError(f"a dataset in [[datasets]] sets {', '.join(differ)} apart from [data]; "
                                    "every dataset trains one model: leave them to [data]")
        return cls(data=DataConfig(**data), datasets=[DataConfig(**{**data, **table}) for table in datasets],
                   **values)

    # numeric settings: (bounds, whole); the rest are checked where they are used
    NUMBERS = {"steps": ((1, math.inf), True), "batch_size": ((1, math.inf), True),
               "warmup_steps": ((0, math.inf), True), "log_every": ((1, math.inf), True),
               "checkpoint_every": ((1, math.inf), True), "validate_every": ((1, math.inf), True),
               "val_clips": ((0, math.inf), True), "seed": ((0, math.inf), True),
               "lr": ((0, math.inf), False), "lr_min": ((0, math.inf), False),
               "weight_decay": ((0, math.inf), False), "grad_clip": ((0, math.inf), False),
               "ema_decay": ((0, 1), False), "cond_drop": ((0, 1), False),
               "keep_unsaid": ((0, math.inf), False)}

    def check(self) -> None:
        """Refuse settings no run can use (DiffshegError naming the setting), before anything
        is loaded or written: numbers out of range, an unknown part to train, an out_dir that is a file."""
        for name, (bounds, whole) in self.NUMBERS.items():
            setattr(self, name, check_number(f"training setting {name}", getattr(self, name), bounds, whole))
        if not isinstance(self.out_dir, str) or not self.out_dir:
            raise DiffshegError(f"training setting out_dir must name a folder, got {self.out_dir!r}")
        if self.objective not in OBJECTIVES:
            raise DiffshegError(f"training setting objective must be one of {', '.join(OBJECTIVES)}, "
                                f"got {self.objective!r}")
        if self.objective == "distill" and not self.init_from:
            raise DiffshegError("objective = \"distill\" trains a student of a guided model: set init_from to it")
        for data in (self.data, *self.datasets):
            if data.face not in ("data", "source"):
                raise DiffshegError(f"data setting face must be \"data\" or \"source\", got {data.face!r}")
            if data.face == "source" and not self.keep_unsaid:
                raise DiffshegError(f"the {data.kind} dataset {data.root} takes its face from the source model "
                                    "(face = \"source\"): set keep_unsaid (for example 1.0) so it is taught")
        if self.keep_unsaid and (self.objective != "denoise" or not self.init_from):
            raise DiffshegError("keep_unsaid keeps what the data leaves out as the model fine-tuned from says it: "
                                "set init_from to that model (and objective to \"denoise\"), or keep_unsaid to 0")
        if self.trains not in TRAINS:
            raise DiffshegError(f"training setting trains must be one of {', '.join(TRAINS)} (the part of the "
                                f"network that trains), got {self.trains!r}")
        if Path(self.out_dir).exists() and not Path(self.out_dir).is_dir():
            raise DiffshegError(f"training setting out_dir {self.out_dir} is a file, not a folder: name a "
                                "folder for the run (it is created if missing)")


def read_config_file(path: str | Path, _chain: tuple[Path, ...] = ()) -> dict:
    """A JSON (.json) or TOML (any other suffix) file as a dict.

    A top-level `extends = "other.toml"` (relative to this file) starts from that file's
    settings; this file's values replace them, table by table (so a fine-tuning run can
    name only what differs from its base run).
    """
    path = Path(path)
    if not path.is_file():
        raise DiffshegError(f"{path}: no such configuration file")
    try:
        if path.suffix.lower() == ".json":
            values = json.loads(path.read_text(encoding="utf-8"))
        else:
            values = tomllib.loads(path.read_text(encoding="utf-8"))
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise DiffshegError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'TOML'} ({exc})") from exc
    base = values.pop("extends", None)
    if base is None:
        return values
    if not isinstance(base, str):
        raise DiffshegError(f"{path}: extends must be a file name, got {base!r}")
    base_path = (path.parent / base).resolve()
    if base_path in _chain or base_path == path.resolve():
        raise DiffshegError(f"{path}: extends {base}, which extends it back")
    return merge_settings(read_config_file(base_path, (*_chain, path.resolve())), values)


def merge_settings(base: dict, over: dict) -> dict:
    """`base` with `over`'s values, merged into nested tables rather than replacing them."""
    merged = dict(base)
    for key, value in over.items():
        both_tables = isinstance(value, dict) and isinstance(merged.get(key), dict)
        merged[key] = merge_settings(merged[key], value) if both_tables else value
    return merged


# ---------------------------------------------------------------- processes and devices

@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str) -> Dist:
    """One process, or one of WORLD_SIZE processes started by torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    torch_device = resolve_device(device)
    if world == 1:
        return Dist(0, 1, torch_device)
    if torch_device.type == "cuda":
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        torch_device = torch.device("cuda", local)
    dist.init_process_group("nccl" if torch_device.type == "cuda" else "gloo")
    return Dist(dist.get_rank(), dist.get_world_size(), torch_device)


def autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    if precision not in ("auto", "fp32", "bf16", "fp16"):
        raise DiffshegError(f"precision must be auto, fp32, bf16 or fp16, got '{precision}'")
    if device.type != "cuda":
        if precision in ("bf16", "fp16"):
            raise DiffshegError(f"precision '{precision}' needs a CUDA GPU; use auto or fp32 on the CPU")
        return None
    if precision == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}[precision]


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """Linear warm-up, then constant or cosine decay to lr_min at the last step."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    if cfg.lr_schedule == "constant":
        return cfg.lr
    if cfg.lr_schedule != "cosine":
        raise DiffshegError(f"lr_schedule must be cosine or constant, got '{cfg.lr_schedule}'")
    done = (step - cfg.warmup_steps) / max(cfg.steps - cfg.warmup_steps, 1)
    return cfg.lr_min + 0.5 * (cfg.lr - cfg.lr_min) * (1 + math.cos(math.pi * min(done, 1.0)))


def step_generator(seed: int, step: int, rank: int) -> torch.Generator:
    """The generator of every random draw of one step on one process."""
    return torch.Generator().manual_seed((seed * 1_000_003 + step) * 4099 + rank)


# ---------------------------------------------------------------- loss

X0_WEIGHTINGS = ("abar", "none")


def masked_mean(values: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    weight = weight.expand_as(values)
    return (values * weight).sum() / weight.sum().clamp_min(1.0)


def x0_term_weight(schedule: Schedule, index: torch.Tensor, like: torch.Tensor, how: str) -> torch.Tensor:
    """Per-sample weight (B, 1, 1) of the loss terms computed on the predicted x0.

    x0_hat = sqrt(1/abar) x_t - sqrt(1/abar - 1) eps_hat, so its error is the noise error
    times sqrt(1/abar - 1) (about 156 at t = 999). Unweighted, the velocity and Huber terms
    of the noisiest samples dwarf everything else: gradient clipping then scales every step
    down to them and the low-noise steps that finish sampling are barely learned.
    'abar' multiplies the terms by abar_t = SNR / (1 + SNR): full weight where x0 is
    recoverable, and at most the noise term's own scale where it is not (the squared
    x0 error times abar is (1 - abar) times the squared noise error). 'none' is the
    unweighted form, as the paper writes it.
    """
    if how == "none":
        return torch.ones((like.shape[0], 1, 1), dtype=like.dtype, device=like.device)
    if how != "abar":
        raise DiffshegError(f"x0_weighting must be one of {', '.join(X0_WEIGHTINGS)}, got '{how}'")
    abar = torch.from_numpy(schedule.alphas_cumprod).to(like.device, like.dtype)[index]
    return abar.view(-1, 1, 1)


def diffsheg_loss(model: torch.nn.Module, schedule: Schedule, batch: dict[str, torch.Tensor],
                  cfg: TrainConfig, gen: torch.Generator, style_dim: int, null_condition: bool,
                  source: torch.nn.Module | None = None, gesture_dim: int = 0) -> dict[str, torch.Tensor]:
    """The paper's loss terms for one batch (eq. 4, 6, 7, 8), the x0 terms weighted as
    `cfg.x0_weighting` says (see x0_term_weight). With `source` (the frozen model fine-tuned
    from, `cfg.keep_unsaid` > 0), also the noise error against its prediction on the face
    channels (those after `gesture_dim`) that a clip's mask leaves out."""
    b, device = batch["motion"].shape[0], batch["motion"].device
    index = torch.randint(len(schedule), (b,), generator=gen).to(device)
    noise = torch.randn(batch["motion"].shape, generator=gen).to(device)
    style = F.one_hot(batch["style"], style_dim).float()
    drop = (torch.rand(b, generator=gen) < cfg.cond_drop).to(device)
    if not null_condition:  # without a null speech condition, the dropout drops the style
        style = style * (~drop).float().unsqueeze(1)
    if cfg.style_drop > 0:  # the null style, which style guidance steers away from
        style = style * (torch.rand(b, generator=gen) >= cfg.style_drop).float().to(device).unsqueeze(1)
    order = torch.argsort(~drop, stable=True)  # dropped rows first: the model nulls the first rows
    index, noise, style = index[order], noise[order], style[order]
    batch = {k: v[order] for k, v in batch.items()}
    x0, mel, mask = batch["motion"], batch["mel"], batch["mask"].unsqueeze(1)
    n_null = int(drop.sum()) if null_condition else 0

    x_t = schedule.q_sample(x0, index, noise)
    extra = {"null_rows": n_null} if n_null else {}
    inputs = (x_t, schedule.model_timesteps(index), mel, batch.get("extra"), style, schedule.x0_coefs(index, x_t))
    eps = model(*inputs, **extra).float()
    x0_hat = schedule.predict_x0(x_t, index, eps)
    w = x0_term_weight(schedule, index, x0_hat, cfg.x0_weighting)
    loss_t = masked_mean((eps - noise) ** 2, mask)
    loss_v = masked_mean(w * (x0_hat.diff(dim=1) - x0.diff(dim=1)) ** 2, mask)
    loss_d = masked_mean(w * F.huber_loss(x0_hat, x0, reduction="none", delta=cfg.huber_delta), mask)
    total = cfg.lambda_t * loss_t + cfg.lambda_v * loss_v + cfg.lambda_delta * loss_d
    losses = {"loss_t": loss_t, "loss_v": loss_v, "loss_delta": loss_d}
    if source is not None:
        with torch.no_grad():
            said = source(*inputs, **extra).float()
        unsaid = (~mask[..., gesture_dim:].bool()).to(eps.dtype)
        losses["loss_unsaid"] = masked_mean((eps[..., gesture_dim:] - said[..., gesture_dim:]) ** 2, unsaid)
        total = total + cfg.lambda_t * cfg.keep_unsaid * losses["loss_unsaid"]
    if cfg.lambda_a > 0:
        losses["loss_a"] = masked_mean(w * (x0_hat.diff(n=2, dim=1) - x0.diff(n=2, dim=1)) ** 2, mask)
        total = total + cfg.lambda_a * losses["loss_a"]
    return {"loss": total, **losses}


def distill_loss(student: torch.nn.Module, teacher: torch.nn.Module, d: Distillation, schedule: Schedule,
                 batch: dict[str, torch.Tensor], gen: torch.Generator, style_dim: int) -> dict[str, torch.Tensor]:
    """The student's error against the teacher's guided step on one batch, at the distilled
    steps and the refining pass drawn evenly."""
    x0, mel, mask = batch["motion"], batch["mel"], batch["mask"].unsqueeze(1)
    b, device, g = x0.shape[0], x0.device, teacher.cfg.gesture_dim
    kinds = list(d.timesteps) + ([] if d.refine_timestep is None else [d.refine_timestep])
    pick = torch.randint(len(kinds), (b,), generator=gen)
    refine = pick == len(d.timesteps)  # rows of the refining pass
    index = torch.tensor(kinds)[pick].to(device)
    noise = torch.randn(x0.shape, generator=gen).to(device)
    style, speech = F.one_hot(batch["style"], style_dim).float(), batch.get("extra")
    x_t = schedule.q_sample(x0, index, noise)
    timesteps, coefs = schedule.model_timesteps(index), schedule.x0_coefs(index, x_t)
    skip = torch.where(refine, d.skip * d.refine_skip, d.skip).to(device)
    target, face_x0 = guided_target(teacher, d, x_t, timesteps, skip, mel, speech, style, coefs)
    # the gestures are fed the teacher's guided face, which the student's own face learns to give;
    # the refining pass's rows see their timestep moved past the schedule's
    seen = timesteps + REFINE_OFFSET * refine.to(device, timesteps.dtype)
    eps = student(x_t, timesteps, mel, speech, style, coefs, expression_x0=face_x0, gesture_timesteps=seen)
    eps_gesture, eps_face = eps[..., :g], eps[..., g:]
    loss_face = masked_mean((eps_face - target[..., g:]) ** 2, mask[..., g:])
    loss_gesture = masked_mean((eps_gesture - target[..., :g]) ** 2, mask[..., :g])
    weight = x0_term_weight(schedule, index, x_t, "abar")
    error_x0 = schedule.predict_x0(x_t, index, eps) - schedule.predict_x0(x_t, index, target)
    loss_x0 = masked_mean(weight * error_x0 ** 2, mask)
    # the error's acceleration: a student wrong by a wobble makes a window jitter more than one
    # wrong by an offset (issue 39's jitter bar)
    loss_accel = masked_mean(weight * error_x0.diff(n=2, dim=1) ** 2, mask)
    return {"loss": 10.0 * (loss_face + loss_gesture + loss_accel) + loss_x0, "loss_face": loss_face,
            "loss_gesture": loss_gesture, "loss_x0": loss_x0, "loss_accel": loss_accel}


# ---------------------------------------------------------------- the trainer

def fit_prior(takes: list, stats: NormStats, model_cfg: ModelConfig,
              kept: GesturePrior | None = None) -> GesturePrior | None:
    """The gesture prior of the training takes that hold every gesture channel (None if none
    does); with `kept` (the prior of a model whose gesture branch the run keeps as it is),
    that one for the gesture branch's channels and one fitted beside it for the lower-body
    branch's, so the upper body starts its windows as the source's did."""
    g = model_cfg.gesture_dim
    full = [stats.normalise(t.motion) for t in takes if t.mask[:g].all() and t.n_frames >= model_cfg.clip_len]
    if not full:
        return None
    if kept is None:
        return GesturePrior.fit(full, g, model_cfg.clip_len)
    lower = GesturePrior.fit([t[:, model_cfg.upper_dim:g] for t in full], model_cfg.lower_dim, model_cfg.clip_len)
    return kept.beside(lower)


def sampling_config(cfg: TrainConfig) -> FoppasConfig:
    """The FOPPAS settings the checkpoints carry: the preset with `cfg.sampling` over it."""
    try:
        config = with_overrides(PRESETS[cfg.sampling_preset], **cfg.sampling)
        config.check(cfg.data.clip_len)
    except (TypeError, ValueError) as exc:
        raise DiffshegError(f"sampling settings {cfg.sampling}: {exc}") from exc
    return config


def build_model_config(cfg: TrainConfig) -> ModelConfig:
    """The model settings over ModelConfig's defaults (mel only unless speech_encoder is set),
    with the layout, clip length and fps of the data."""
    layout = cfg.data.layout
    values = {"speech_encoder": None, **cfg.model, "gesture_dim": layout.gesture_dim,
              "expression_dim": layout.expression_dim, "layout": layout.name,
              "clip_len": cfg.data.clip_len, "fps": cfg.data.fps}
    try:
        return ModelConfig.from_dict(values)
    except (TypeError, ValueError) as exc:
        raise DiffshegError(f"model settings: {exc}") from exc


def default_guidance(cfg: TrainConfig, model_cfg: ModelConfig) -> float | None:
    """The guidance scale the run's checkpoints generate with by default; refuses settings
    under which the null condition would never be trained or could not be used."""
    if model_cfg.classifier_free and cfg.cond_drop <= 0:
        raise DiffshegError("classifier_free = true needs cond_drop above 0 (e.g. 0.15), or the null "
                            "condition is never trained")
    if cfg.guidance is None:
        return None
    if not model_cfg.classifier_free:
        raise DiffshegError("guidance needs a model with a null condition: set classifier_free = true "
                            "in [model] and cond_drop above 0")
    if not 0.0 <= cfg.guidance <= 10.0:
        raise DiffshegError(f"guidance must be between 0 and 10, got {cfg.guidance}")
    return float(cfg.guidance)


def check_styles(cfg: TrainConfig, model_cfg: ModelConfig) -> None:
    """Style names, when given, name every style class; the default style is one of them;
    the null-style share is a fraction. (A model without style classes is refused when the
    data is read.)"""
    if model_cfg.style_dim < 1:
        return
    if not style_names_fit(cfg.style_names, model_cfg.style_dim):
        raise DiffshegError(f"style_names must be {model_cfg.style_dim} different names (style_dim of the "
                            f"model), got {cfg.style_names!r}")
    known = cfg.style_names or list(range(model_cfg.style_dim))
    if cfg.default_style not in known and not (isinstance(cfg.default_style, int)
                                               and 0 <= cfg.default_style < model_cfg.style_dim):
        raise DiffshegError(f"default_style {cfg.default_style!r} is not one of the styles "
                            f"({', '.join(map(str, known))})")
    if not 0.0 <= cfg.style_drop < 1.0:
        raise DiffshegError(f"style_drop must be a share from 0 to below 1, got {cfg.style_drop}")


def phonetic_encoder(cfg: TrainConfig, model_cfg: ModelConfig) -> PhoneticEncoder | None:
    """The frozen phonetic encoder of a run whose model takes phonetic features."""
    if not model_cfg.phonetic_input:
        return None
    if not cfg.phonetic:
        raise DiffshegError("speech_encoder = \"phonetic\" needs the encoder file: set phonetic = "
                            "\"path.safetensors\" (train one with python -m diffsheg_core train-phonetic)")
    return load_phonetic(cfg.phonetic)


def fine_tuning_statistics(path: str, source: NormStats, data: NormStats,
                           tolerance: float = TrainConfig.stats_tolerance,
                           channels: np.ndarray | None = None) -> NormStats:
    """The normalisation a run fine-tuned from a model trains in: the model's own (its weights
    work in it), once the data's statistics are seen to lie within `tolerance` (a share of
    each channel's standard deviation) of it. For a model widened to more channels
    (`channels`: where each of the source's channels sits, rigs.Layout.widened_channels) the
    new channels take the data's statistics."""
    worst = float("inf")
    channels = np.arange(len(data.mean)) if channels is None else channels
    if source.mean.shape == channels.shape:
        away = np.maximum(np.abs(source.mean - data.mean[channels]), np.abs(source.std - data.std[channels]))
        if np.all(away <= tolerance * source.std):
            if len(channels) == len(data.mean):
                return source
            mean, std = data.mean.copy(), data.std.copy()
            mean[channels], std[channels] = source.mean, source.std
            return NormStats(mean, std)
        worst = float(np.max(away / source.std))
    raise DiffshegError(f"init_from {path}: it was trained with other normalisation statistics "
                        f"(up to {worst:.2f} of a channel's spread away, the limit is {tolerance}), "
                        "so on other data; train on the data it was trained on, or, for data "
                        "widened on purpose, raise stats_tolerance")


class Trainer:
    def __init__(self, cfg: TrainConfig, env: Dist):
        self.cfg, self.env = cfg, env
        cfg.check()
        if cfg.batch_size % env.world:
            raise DiffshegError(f"batch_size {cfg.batch_size} does not split evenly over {env.world} processes")
        if cfg.x0_weighting not in X0_WEIGHTINGS:
            raise DiffshegError(f"x0_weighting must be one of {', '.join(X0_WEIGHTINGS)}, "
                                f"got '{cfg.x0_weighting}'")
        if cfg.export_dtype not in EXPORT_DTYPES:
            raise DiffshegError(f"export_dtype must be one of {', '.join(EXPORT_DTYPES)}, "
                                f"got '{cfg.export_dtype}'")
        if cfg.skip_guidance is not None:
            check_skip_guidance(cfg.skip_guidance)
        if cfg.sampling_preset not in PRESETS:
            raise DiffshegError(f"unknown sampling preset '{cfg.sampling_preset}': "
                                f"choose one of {', '.join(PRESETS)}")
        self.sampling = sampling_config(cfg)
        self.out = Path(cfg.out_dir)
        self.model_cfg = build_model_config(cfg)
        self.guidance = default_guidance(cfg, self.model_cfg)
        check_styles(cfg, self.model_cfg)
        self.phonetic = phonetic_encoder(cfg, self.model_cfg)
        if self.phonetic is not None:
            self.model_cfg = replace(self.model_cfg, speech_dim=self.phonetic.cfg.dim)
        speech = (phonetic_speech(self.phonetic) if self.phonetic is not None
                  else hubert_encoding(cfg.hubert or None, device=str(env.device))
                  if self.model_cfg.has_speech_input else None)
        train, val = (TakeSet(cfg.data.layout, []), TakeSet(cfg.data.layout, []))
        strides = []
        for data in (cfg.data, *cfg.datasets):
            if data.layout != cfg.data.layout:
                raise DiffshegError(f"the {data.kind} dataset {data.root} holds the {data.layout.name} layout, "
                                    f"[data] the {cfg.data.layout.name} one: every dataset must fit one model")
            for split, found in (("train", train), ("val", val)):
                taken = load_takes(data, split, speech)
                for take in taken.takes if data.face == "source" else ():
                    take.taught = take.mask.copy()  # its face stays in the clips but leaves the data loss
                    take.taught[data.layout.gesture_dim:] = False  # (keep_unsaid teaches it)
                found.takes += taken.takes
                found.skipped += taken.skipped
            strides += [data.stride] * (len(train.takes) - len(strides))
        self.skipped = train.skipped + val.skipped
        self.stats: NormStats = normalisation(cfg.data, train)
        # the model a new run is fine-tuned from (a resumed run has its weights and statistics)
        self.source = load_model(cfg.init_from) if cfg.init_from and not (self.out / STATE_FILE).is_file() else None
        if self.source is not None:
            self.stats = fine_tuning_statistics(cfg.init_from, NormStats(self.source.mean, self.source.std),
                                                self.stats, cfg.stats_tolerance, self.widened_channels())
        self.train_set = ClipDataset(train.takes, cfg.data.clip_len, strides, self.stats)
        self.val_set = ClipDataset(val.takes, cfg.data.clip_len, cfg.data.clip_len, self.stats) \
            if val.takes and any(t.n_frames >= cfg.data.clip_len for t in val.takes) else None
        styles = max(t.style for t in train.takes)
        if styles >= self.model_cfg.style_dim:
            raise DiffshegError(f"the data has style class {styles}, but the model has only "
                                f"{self.model_cfg.style_dim}: raise style_dim in the model settings")

        torch.manual_seed(cfg.seed)
        self.model = UniEG(self.model_cfg).to(env.device)
        self.ema = UniEG(self.model_cfg).to(env.device).eval()
        self.ema.load_state_dict(self.model.state_dict())
        self.ema.requires_grad_(False)
        if cfg.trains == "legs" and not self.model_cfg.lower_dim:
            raise DiffshegError("trains = \"legs\" trains the lower-body branch alone, and this model has none: "
                                "set lower_dim in [model], or train another part")
        if cfg.trains == "face" and not cfg.init_from:
            raise DiffshegError("trains = \"face\" keeps a model's body as it is: set init_from to that model")
        # the gesture prior of the model whose gesture branch the run keeps as it is (read once;
        # a resumed run reads init_from again for it)
        self.kept_prior = ((self.source or load_model(cfg.init_from)).prior
                           if cfg.trains in ("legs", "face") and cfg.init_from else None)
        if cfg.trains == "legs" and self.kept_prior is not None and self.kept_prior.dims != self.model_cfg.upper_dim:
            raise DiffshegError(f"init_from {cfg.init_from}: its gesture prior covers {self.kept_prior.dims} channels, "
                                f"but the gesture branch makes {self.model_cfg.upper_dim}: start a lower-body branch "
                                "from a model without one (v9's recipe starts from v8)")
        m = self.model
        shared = [m.time_embed, m.encoder_aud]
        self.frozen = {"all": [],
                       "gestures": shared + [m.encoder_exp],
                       "legs": shared + [m.encoder_exp, m.encoder_ges],
                       "face": shared + [m.encoder_ges] + ([m.encoder_low] if self.model_cfg.lower_dim else []),
                       }[cfg.trains]
        for part in self.frozen:
            part.requires_grad_(False)
        # a rank whose batch drew no null rows leaves the null condition without a gradient
        self.ddp = torch.nn.parallel.DistributedDataParallel(
            self.model, find_unused_parameters=self.model_cfg.classifier_free) if env.world > 1 else self.model
        self.opt = torch.optim.AdamW([p for p in self.model.parameters() if p.requires_grad], lr=cfg.lr,
                                     weight_decay=cfg.weight_decay)
        self.amp = autocast_dtype(cfg.precision, env.device)
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp == torch.float16)
        self.schedule = Schedule.linear()
        self.step = 0
        self._prior: GesturePrior | None = None  # fitted when first exported, with the statistics in use
        # distilling: the guided model the student learns from, frozen; the run's file is its own
        # with the student in it
        self.teacher_bundle = self.teacher = self.distillation = None
        self.unsaid_source: torch.nn.Module | None = None  # keep_unsaid: init_from's model, frozen (begin)
        if cfg.objective == "distill":
            self.teacher_bundle = self.source or load_model(cfg.init_from)
            self.distillation = Distillation.of(self.teacher_bundle)
            self.teacher = UniEG(self.teacher_bundle.config).to(env.device).eval().requires_grad_(False)
            load_state_strict(self.teacher, {k: torch.from_numpy(np.array(v)).float()
                                             for k, v in self.teacher_bundle.weights.items()}, cfg.init_from)
            self.teacher_bundle.student = None  # a student of its own is replaced by this run's
            with_graphs(self.teacher_bundle)  # graphs that hold its weights by name: the file stores them once
            self._prior = self.teacher_bundle.prior  # the student starts later windows where its teacher does

    # -- state

    def state(self) -> dict:
        return {"step": self.step, "model": self.model.state_dict(), "ema": self.ema.state_dict(),
                "optimizer": self.opt.state_dict(), "scaler": self.scaler.state_dict(),
                "model_config": json.dumps(self.model_cfg.to_dict()),
                "mean": torch.from_numpy(self.stats.mean), "std": torch.from_numpy(self.stats.std)}

    def begin(self) -> bool:
        """Resume from the run folder's state, or else start from `init_from` when it is set.
        Returns whether the run resumed."""
        resumed = self.resume()
        if not resumed and self.source is not None:
            self.init_weights(self.source, self.cfg.init_from)
            self.source = None  # its weights are the model's now: the run does not hold them twice
        if self.cfg.keep_unsaid:  # what the data leaves out, as the model fine-tuned from says it
            if resumed:  # the model has trained: read the source again
                source = UniEG(self.model_cfg).to(self.env.device)
                load_state_strict(source, self.source_state(load_model(self.cfg.init_from)),
                                  f"init_from {self.cfg.init_from}")
            else:
                source = copy.deepcopy(self.model)
            self.unsaid_source = source.eval().requires_grad_(False)
        return resumed

    def resume(self) -> bool:
        path = self.out / STATE_FILE
        if not path.is_file():
            return False
        try:
            state = torch.load(path, map_location=self.env.device, weights_only=True)
        except Exception as exc:  # torch raises several types for damaged files
            raise DiffshegError(f"{path}: cannot read the training state ({exc}); delete it to start over") from exc
        if ModelConfig.from_dict(json.loads(state["model_config"])) != self.model_cfg:
            raise DiffshegError(f"{path} was saved with another model configuration: use a new out_dir "
                                "or the configuration the run was started with")
        self.model.load_state_dict(state["model"])
        self.ema.load_state_dict(state["ema"])
        self.opt.load_state_dict(state["optimizer"])
        self.scaler.load_state_dict(state["scaler"])
        self.stats = NormStats(state["mean"].cpu().numpy(), state["std"].cpu().numpy())
        self.step = int(state["step"])
        return True

    def widened_channels(self) -> np.ndarray | None:
        """Where each channel of the model fine-tuned from sits in this run's, when this run
        widens its layout (a `beat` model into `beat_body`); None when the layouts are the same."""
        theirs, ours = get_layout(self.source.config.layout), get_layout(self.model_cfg.layout)
        return None if theirs == ours else ours.widened_channels(theirs)

    def init_weights(self, source: ModelBundle, path: str) -> None:
        """Model and EMA from a generation checkpoint (`source`, read from `path`) of the same
        network on the same data (see fine_tuning_statistics).

        The differences allowed are parts the checkpoint lacks, which keep their fresh
        initialisation: a learned null condition (classifier_free), so an unguided model can
        be fine-tuned into a guided one; temporal convolutions (temporal_kernel, which start
        as the identity), added to a model without them; and the channels a wider layout adds
        (a whole-body layout's legs), which a lower-body branch of their own makes
        (lower_dim), so the checkpoint's channels are predicted exactly as it predicts them.
        """
        theirs, ours = source.config.to_dict(), self.model_cfg.to_dict()
        added = {"classifier_free"} | ({"temporal_kernel"} if not theirs.get("temporal_kernel") else set())
        if self.widened_channels() is not None:
            added |= {"layout", "gesture_dim", "lower_dim", "lower_layers"}
            grown = self.model_cfg.gesture_dim - source.config.gesture_dim
            if self.model_cfg.lower_dim != grown:
                raise DiffshegError(f"init_from {path}: layout {self.model_cfg.layout} adds {grown} gesture channels "
                                    f"to its {source.config.layout}, which a branch of their own makes: set "
                                    f"lower_dim = {grown} in [model]")
        differ = sorted(k for k in ours if k not in added and theirs.get(k) != ours[k])
        if differ:
            raise DiffshegError(f"init_from {path}: its model differs in {', '.join(differ)}; "
                                "make the [model] settings match it")
        load_state_strict(self.model, self.source_state(source), f"init_from {path}")
        self.ema.load_state_dict(self.model.state_dict())

    def source_state(self, source: ModelBundle) -> dict[str, torch.Tensor]:
        """The model's state with `source`'s weights over it (the parts it lacks keep theirs)."""
        return {**self.model.state_dict(), **{k: torch.from_numpy(np.array(v)).float() for k, v in source.weights.items()}}

    def save(self) -> None:
        """Training state, then the generation checkpoint, each written atomically."""
        self.out.mkdir(parents=True, exist_ok=True)
        tmp = self.out / (STATE_FILE + ".partial")
        torch.save(self.state(), tmp)
        os.replace(tmp, self.out / STATE_FILE)
        save_checkpoint(self.bundle(), self.out / MODEL_FILE)

    def bundle(self, dtype: torch.dtype = torch.float32) -> ModelBundle:
        """The EMA model as a generation checkpoint, with its ONNX graphs exported from the
        weights as stored (float16 weights run in float32 on both backends; a distilled
        student's products by weights in int8, `with_student_graphs`)."""
        training = {k: v for k, v in asdict(self.cfg).items() if k not in ("data", "datasets", "card")}
        if self._prior is None:
            self._prior = (self.kept_prior if self.cfg.trains == "face" else
                           fit_prior(self.train_set.takes, self.stats, self.model_cfg, self.kept_prior))
        own = ModelBundle(
            config=self.model_cfg, weights=state_arrays(self.ema, dtype), mean=self.stats.mean,
            std=self.stats.std,
            sampling=self.sampling, guidance=self.guidance, skip_guidance=self.cfg.skip_guidance,
            model_id=self.cfg.model_id, phonetic=self.phonetic.cfg if self.phonetic else None,
            phonetic_weights=state_arrays(self.phonetic, dtype) if self.phonetic else {}, prior=self._prior,
            info={**self.cfg.card, "trained_steps": self.step, "data": asdict(self.cfg.data),
                  "datasets": [asdict(d) for d in self.cfg.datasets],
                  "training": training, "style_names": list(self.cfg.style_names),
                  "default_style": self.cfg.default_style,
                  "null_style": self.cfg.style_drop > 0}, source=f"run {self.out}")
        if self.teacher_bundle is None:
            return with_graphs(own)
        teacher = self.teacher_bundle
        own.guidance = own.skip_guidance = None
        own.info = {**own.info, "distilled": self.distillation.record(teacher, self.step)}
        with_student_graphs(own, teacher.graphs.get("phonetic"))
        return replace(teacher, student=own, source=f"run {self.out}")

    # -- steps

    def batch(self, dataset: ClipDataset, indices: torch.Tensor) -> dict[str, torch.Tensor]:
        items = [dataset[int(i)] for i in indices]
        return {k: torch.stack([it[k] for it in items]).to(self.env.device) for k in items[0]}

    def train_step(self) -> dict[str, float]:
        cfg, env = self.cfg, self.env
        gen = step_generator(cfg.seed, self.step, env.rank)
        torch.manual_seed(int(torch.randint(2**62, (1,), generator=gen)))  # dropout inside the model
        per_rank = cfg.batch_size // env.world
        batch = self.batch(self.train_set, torch.randint(len(self.train_set), (per_rank,), generator=gen))
        self.ddp.train()
        for part in self.frozen:  # no dropout, and batch-norm statistics kept as they are
            part.eval()
        with torch.autocast(env.device.type, dtype=self.amp, enabled=self.amp is not None):
            losses = self.loss(self.ddp, batch, cfg, gen, self.model_cfg.classifier_free)
        for group in self.opt.param_groups:
            group["lr"] = learning_rate(cfg, self.step)
        self.opt.zero_grad(set_to_none=True)
        self.scaler.scale(losses["loss"]).backward()
        self.scaler.unscale_(self.opt)
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
        self.scaler.step(self.opt)
        self.scaler.update()
        with torch.no_grad():
            for e, p in zip(self.ema.parameters(), self.model.parameters()):
                e.lerp_(p, 1.0 - cfg.ema_decay)
            for e, b in zip(self.ema.buffers(), self.model.buffers()):
                e.copy_(b)
        self.step += 1
        out = {k: float(v.detach()) for k, v in losses.items()}
        out["grad_norm"] = float(grad_norm)
        out["lr"] = self.opt.param_groups[0]["lr"]
        return out

    def loss(self, model: torch.nn.Module, batch: dict[str, torch.Tensor], cfg: TrainConfig, gen: torch.Generator,
             null_condition: bool) -> dict[str, torch.Tensor]:
        """The run's objective on one batch (see TrainConfig.objective)."""
        if self.teacher is not None:
            return distill_loss(model, self.teacher, self.distillation, self.schedule, batch, gen,
                                self.model_cfg.style_dim)
        return diffsheg_loss(model, self.schedule, batch, cfg, gen, self.model_cfg.style_dim, null_condition,
                             self.unsaid_source, self.model_cfg.gesture_dim)

    @torch.no_grad()
    def validate(self) -> float | None:
        """Mean loss of the EMA model on fixed validation clips, timesteps and noise."""
        if self.val_set is None:
            return None
        gen = torch.Generator().manual_seed(self.cfg.seed + 12345)
        cfg = replace(self.cfg, cond_drop=0.0, style_drop=0.0)
        n = min(len(self.val_set), self.cfg.val_clips)
        total, count = 0.0, 0
        for start in range(0, n, self.cfg.batch_size):
            batch = self.batch(self.val_set, torch.arange(start, min(start + self.cfg.batch_size, n)))
            losses = self.loss(self.ema, batch, cfg, gen, False)
            total += float(losses["loss"]) * len(batch["motion"])
            count += len(batch["motion"])
        return total / count

    def param_checksum(self) -> float:
        return float(sum(p.detach().double().sum() for p in self.model.parameters()))


class RunLog:
    """log.jsonl: on resume, lines past the resumed step are dropped so the curve continues."""

    def __init__(self, path: Path, resumed_step: int, enabled: bool):
        self.path, self.enabled = path, enabled
        if enabled:
            path.parent.mkdir(parents=True, exist_ok=True)
            kept = []
            if resumed_step and path.is_file():
                kept = [ln for ln in path.read_text().splitlines() if ln and json.loads(ln)["step"] <= resumed_step]
            path.write_text("".join(ln + "\n" for ln in kept))

    def write(self, record: dict) -> None:
        if self.enabled:
            with open(self.path, "a") as fh:
                fh.write(json.dumps(record) + "\n")


def train(cfg: TrainConfig) -> dict:
    """Run (or resume) training; returns the summary that rank 0 writes to summary.json."""
    env = init_distributed(cfg.device)
    try:
        return _train(cfg, env)
    finally:
        if env.world > 1:
            dist.destroy_process_group()


def _train(cfg: TrainConfig, env: Dist) -> dict:
    trainer = Trainer(cfg, env)
    resumed = trainer.begin()
    log = RunLog(trainer.out / LOG_FILE, trainer.step if resumed else 0, env.main)
    if env.main:
        for name, reason in trainer.skipped:
            tqdm.write(f"skipped take {name}: {reason}")
        tqdm.write(f"{'resuming at step ' + str(trainer.step) if resumed else 'training'}: "
                   f"{len(trainer.train_set)} clips of {cfg.data.clip_len} frames, "
                   f"{env.world} process(es) on {env.device}")
    if trainer.step == 0:
        val = trainer.validate()
        if val is not None:
            log.write({"step": 0, "val_loss": round(val, 6)})
    bar = tqdm(total=cfg.steps, initial=trainer.step, disable=not env.main, unit="step", dynamic_ncols=True)
    window_start, window_steps = time.perf_counter(), 0
    losses: dict[str, float] = {}
    while trainer.step < cfg.steps:
        losses = trainer.train_step()
        if not math.isfinite(losses["loss"]):
            raise DiffshegError(f"the loss became {losses['loss']} at step {trainer.step}: lower lr "
                                "or grad_clip, or check the data for outliers")
        window_steps += 1
        bar.update(1)
        step = trainer.step
        if step % cfg.log_every == 0 or step == cfg.steps:
            rate = window_steps * cfg.batch_size / (time.perf_counter() - window_start)
            bar.set_postfix(loss=f"{losses['loss']:.4f}", clips_s=f"{rate:.0f}")
            log.write({"step": step, **{k: round(v, 6) for k, v in losses.items()}, "clips_per_s": round(rate, 1)})
            window_start, window_steps = time.perf_counter(), 0
        if step % cfg.validate_every == 0 or step == cfg.steps:
            val = trainer.validate()
            if val is not None:
                log.write({"step": step, "val_loss": round(val, 6)})
                bar.set_postfix(loss=f"{losses['loss']:.4f}", val=f"{val:.4f}")
        if (step % cfg.checkpoint_every == 0 or step == cfg.steps) and env.main:
            trainer.save()
    bar.close()
    checksums = [trainer.param_checksum()]
    if env.world > 1:
        gathered = [None] * env.world
        dist.all_gather_object(gathered, checksums[0])
        checksums = gathered
    summary = {"step": trainer.step, "final_loss": losses.get("loss"), "world_size": env.world,
               "param_checksums": checksums, "skipped_takes": len(trainer.skipped),
               "checkpoint": str(trainer.out / MODEL_FILE)}
    if env.main and cfg.export:
        summary["export"] = str(save_checkpoint(trainer.bundle(EXPORT_DTYPES[cfg.export_dtype]), cfg.export))
    if env.main:
        record = trainer.out / SUMMARY_FILE
        if not losses and record.is_file():  # nothing trained in this call: keep the run's record
            summary = {**json.loads(record.read_text()), "export": summary.get("export")}
        record.write_text(json.dumps(summary, indent=1))
    if env.world > 1:
        # every process leaves together: a gloo process that tears down while rank 0 is
        # still writing files can abort ("terminate called without an active exception")
        dist.barrier()
    if len(set(checksums)) > 1:
        raise DiffshegError(f"processes ended with different parameters: {checksums}")
    return summary


def main(argv: list[str] | None = None) -> int:
    """Train a DiffSHEG model from a JSON or TOML configuration."""
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core train", description=main.__doc__)
    parser.add_argument("--config", required=True, help="JSON or TOML file: TrainConfig fields, "
                        "with [data] (DataConfig) and [model] (ModelConfig overrides) tables")
    parser.add_argument("--out", help="run folder (overrides out_dir)")
    parser.add_argument("--steps", type=int, help="total steps (overrides steps)")
    parser.add_argument("--device", help="auto, cpu or cuda (overrides device)")
    args = parser.parse_args(argv)
    cfg = TrainConfig.from_dict(read_config_file(args.config))
    for name in ("out", "steps", "device"):
        value = getattr(args, name)
        if value is not None:
            setattr(cfg, "out_dir" if name == "out" else name, value)
    summary = train(cfg)
    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
