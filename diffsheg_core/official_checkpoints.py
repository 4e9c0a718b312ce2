"""The official DiffSHEG checkpoints (BEAT and SHOW): what the official scripts use for each
dataset (`OFFICIAL`), the network's state dict in their torch pickles (under `encoder`,
optional `module.` prefixes), the shapes of its tensors read without torch
(`official_shapes`), the network configuration inferred from those shapes
(`config_from_state`), and the normalisation statistics they were trained with
(`official_stats`: plain .npy arrays for BEAT, a pickled dict for SHOW, read without running
code). The pickle itself is read with torch, `weights_only=True`, by `torch_layer.official`;
`load_official` loads such a file strictly into a ModelBundle (`checkpoints.load_model`
dispatches to it). numpy only here: torch comes in with the pickle.
"""

from __future__ import annotations

import os
import pickle
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np
from numpy.lib import format as npy_format

from .config import ModelConfig
from .errors import CheckpointError
from .foppas import PRESETS, FoppasConfig

if TYPE_CHECKING:
    from .checkpoints import ModelBundle

STATS_ENV = "DIFFSHEG_OFFICIAL_STATS"
STYLE_KEY = "encoder_exp.pid_embed.0.weight"  # official networks: (time embedding, style classes)


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


def _encoder_state(raw) -> Optional[dict]:
    """The network's entries of an unpickled official checkpoint (under key `encoder`,
    `module.` prefixes dropped); None when it holds no dict."""
    state = raw.get("encoder", raw) if isinstance(raw, dict) else None
    return {k.removeprefix("module."): v for k, v in state.items()} if isinstance(state, dict) else None


def official_state_dict(raw: dict, path: Path) -> dict[str, np.ndarray]:
    """The network's state dict (numpy) from an official checkpoint (key `encoder`, optional `module.`)."""
    state = _encoder_state(raw)
    if state is None or not all(hasattr(v, "numpy") for v in state.values()):
        raise CheckpointError(f"{path}: no state dict found (expected a dict with key 'encoder' "
                              "holding the network's tensors)")
    return {k: v.detach().cpu().numpy() for k, v in state.items()}


class _Shape(tuple):
    """A tensor of a checkpoint read for its shape alone."""


class _StandIn:
    """Whatever else a checkpoint's pickle names (storage types, optimiser settings): ignored."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state) -> None:
        pass


class _ShapeReader(pickle.Unpickler):
    """Unpickles a torch checkpoint into the shapes of its tensors: every class the file
    names is replaced by a stand-in, so nothing of the file runs and torch is not needed."""

    def find_class(self, module: str, name: str):
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return lambda storage, offset, size, *rest: _Shape(size)
        if (module, name) == ("collections", "OrderedDict"):
            return dict
        return _StandIn

    def persistent_load(self, pid) -> None:
        return None  # the tensors' data, which shapes do not need


def official_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    """The shape of every tensor of an official checkpoint's network, from the pickle in its
    zip archive (torch.save's format) without torch or the weights; {} when it cannot tell."""
    try:
        with zipfile.ZipFile(path) as zf:
            name = next(n for n in zf.namelist() if n.rpartition("/")[2] == "data.pkl")
            with zf.open(name) as fh:
                state = _encoder_state(_ShapeReader(fh).load()) or {}
    except Exception:  # not a zip, not a pickle, damaged: loading the file says what is wrong
        return {}
    return {k: tuple(v) for k, v in state.items() if isinstance(v, _Shape)}


def config_from_state(state: dict[str, np.ndarray], dataset: Optional[str], path: Path) -> ModelConfig:
    """Infer the network configuration from tensor shapes (heads: 8, as the official models)."""
    try:
        blocks = {int(m.group(1)) for k in state
                  if (m := re.match(r"encoder_exp\.temporal_decoder_blocks\.(\d+)\.", k))}
        gesture_dim = state["encoder_ges.out.weight"].shape[0]
        expression_dim = state["encoder_exp.out.weight"].shape[0]
        cfg = dict(
            gesture_dim=gesture_dim, expression_dim=expression_dim,
            style_dim=state[STYLE_KEY].shape[1],
            mel_dim=state["encoder_aud.sa_block.norm.weight"].shape[0],
            audio_latent=state["encoder_exp.audio_proj.weight"].shape[0],
            speech_encoder="hubert" if "encoder_exp.hubert_encoder.0.weight" in state else None,
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
            f"{expression_dim}; pass --dataset beat or --dataset show")
    setup = OFFICIAL[name]
    return ModelConfig(**cfg, clip_len=setup.clip_len, layout=setup.layout)


STATS_FIX = "use the file from the DiffSHEG repository's assets/data.tar.gz"
SHOW_STATS = {"pose_mean": 165, "pose_std": 165, "expression_mean": 100, "expression_std": 100}
_RECONSTRUCT = np.zeros(0).__reduce__()[0]  # numpy's own array rebuilder, whichever module holds it
_ARRAY_GLOBALS = {("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
                  ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,
                  ("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays inside plain containers and nothing else: a pickle runs code
    by naming a callable global, and these three globals only build arrays and dtypes."""

    def find_class(self, module: str, name: str):
        if (module, name) not in _ARRAY_GLOBALS:
            raise pickle.UnpicklingError(f"it names the global {module}.{name}, which a statistics file "
                                         "never needs")
        return _ARRAY_GLOBALS[module, name]


def _stats_vector(values, size: int, where: str) -> np.ndarray:
    """`values` if it is `size` finite floating-point numbers; else CheckpointError naming `where`."""
    if not isinstance(values, np.ndarray) or values.dtype.kind != "f" or values.shape != (size,):
        found = (f"an array of dtype {values.dtype} and shape {values.shape}" if isinstance(values, np.ndarray)
                 else f"a {type(values).__name__}")
        raise CheckpointError(f"{where}: expected {size} floating-point statistics, found {found}; {STATS_FIX}")
    if not np.isfinite(values).all():
        raise CheckpointError(f"{where}: the statistics hold NaN or infinite values; {STATS_FIX}")
    return values


def _beat_stats(path: Path, size: int) -> np.ndarray:
    """One BEAT statistics vector: a plain .npy array (never unpickled)."""
    try:
        with open(path, "rb") as fh:
            values = npy_format.read_array(fh, allow_pickle=False)
    except (ValueError, EOFError) as exc:  # not .npy, an object array, or truncated
        raise CheckpointError(f"{path}: not a plain array of statistics ({exc}); {STATS_FIX}") from None
    return _stats_vector(values, size, str(path))


def _show_stats(path: Path) -> dict[str, np.ndarray]:
    """The SHOW statistics: a .npy holding a pickled dict of arrays, unpickled by
    `_ArrayUnpickler` so that a crafted file cannot run code (np.load(allow_pickle=True) would)."""
    try:
        with open(path, "rb") as fh:
            version = npy_format.read_magic(fh)
            read_header = {(1, 0): npy_format.read_array_header_1_0,
                           (2, 0): npy_format.read_array_header_2_0}.get(version)
            if read_header is None:
                raise ValueError(f".npy format version {version[0]}.{version[1]} is not the one numpy "
                                 "writes for pickled data")
            shape, _, dtype = read_header(fh)
            if dtype != object or shape != ():
                raise ValueError(f"it holds an array of dtype {dtype} and shape {shape}, not a pickled dict")
            stats = _ArrayUnpickler(fh, encoding="latin1").load()
    except pickle.UnpicklingError as exc:
        raise CheckpointError(f"{path}: refused to load: {exc}; {STATS_FIX}") from None
    except Exception as exc:  # a damaged pickle or header raises many types
        raise CheckpointError(f"{path}: cannot read these statistics ({exc}); {STATS_FIX}") from None
    stats = stats.item() if isinstance(stats, np.ndarray) and stats.shape == () else stats
    if not isinstance(stats, dict) or set(stats) != set(SHOW_STATS):
        found = sorted(map(str, stats)) if isinstance(stats, dict) else type(stats).__name__
        raise CheckpointError(f"{path}: expected a dict of {', '.join(SHOW_STATS)}, found {found}; {STATS_FIX}")
    return {key: _stats_vector(stats[key], size, f"{path} ('{key}')") for key, size in SHOW_STATS.items()}


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
        mean = np.concatenate([_beat_stats(folder / "axis_angle_mean.npy", 141),
                               _beat_stats(folder / "facial51_mean.npy", 51)])
        std = np.concatenate([_beat_stats(folder / "axis_angle_std.npy", 141),
                              _beat_stats(folder / "facial51_std.npy", 51)])
    else:
        stats = _show_stats(folder / "talkshow_mean_std.npy")
        pose_mean, pose_std = stats["pose_mean"], stats["pose_std"]
        # pose 165: jaw 3, eyes 6, global 3, body 63 (SMPL-X joints 1..21), hands 90
        body_ids = [j - 1 for j in (3, 6, 9) + tuple(range(12, 22))]
        gesture = np.concatenate([12 + 3 * np.array(body_ids)[:, None] + np.arange(3)]).ravel()
        gesture = np.concatenate([gesture, np.arange(75, 165)])
        mean = np.concatenate([pose_mean[gesture], pose_mean[:3], stats["expression_mean"]])
        # The official SHOW data pipeline uses the jaw's *mean* as its std; the published
        # model was trained that way, so its output is denormalised the same way.
        std = np.concatenate([pose_std[gesture], pose_mean[:3], stats["expression_std"]])
    return mean.astype(np.float32), std.astype(np.float32)


def load_official(path: Path, dataset: Optional[str], stats_dir: Optional[str | Path]) -> ModelBundle:
    """An official checkpoint loaded strictly into a ModelBundle (`dataset` None: told by its
    shapes), with the statistics of `official_stats` and the official sampling settings.
    Needs torch to read the pickle."""
    from .checkpoints import TORCH_HOW_TO, ModelBundle, check_weights  # checkpoints imports this module

    try:
        from .torch_layer.model import UniEG, load_state_strict
        from .torch_layer.official import read_official_pickle
    except ImportError:
        raise CheckpointError(f"{path}: official DiffSHEG checkpoints are torch pickles and need torch, "
                              f"which this installation lacks: {TORCH_HOW_TO}") from None
    state = official_state_dict(read_official_pickle(path), path)
    check_weights(state, str(path))
    cfg = config_from_state(state, dataset, path)
    name = "beat" if cfg.layout == "beat" else "show"
    load_state_strict(UniEG(cfg), state, str(path),
                      hint=f"the checkpoint is not the official {name.upper()} model: try --dataset "
                           f"{'show' if name == 'beat' else 'beat'}, or the file is truncated")
    mean, std = official_stats(name, stats_dir, beside=path.parent)
    setup = OFFICIAL[name]
    return ModelBundle(config=cfg, weights=state, mean=mean, std=std, sampling=setup.sampling,
                       guidance=setup.guidance if cfg.classifier_free else None,
                       model_id=f"official-{name}:{path.name}", trained=True,
                       info={"source": "DiffSHEG official checkpoint", "dataset": name}, source=str(path))
