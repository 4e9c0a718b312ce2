"""Training the phonetic speech encoder (`torch_layer.model.PhoneticEncoder`): a small convolutional
phone recogniser over a fine log-mel, trained on the project's synthetic corpus, whose phone
timings are exact. Its front end and phone set are `diffsheg_core.phonetic`.

    python -m diffsheg_core train-phonetic --corpus ../corpus/v1 --out ../runs/phonetic.safetensors
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ..audio import load_audio
from ..checkpoints import FORMAT as MODEL_FORMAT, load_model, read_safetensors, write_safetensors
from ..errors import CheckpointError, DiffshegError
from ..torch_layer.model import PhoneticEncoder, load_state_strict, state_arrays
from ..phonetic import BILABIALS, PHONES, PhoneticConfig, fingerprint, log_mel, phonetic_encoding
from .corpus.phones import Phone

FORMAT = "diffsheg-phonetic/1"


def frame_labels(phones: list[Phone], n_frames: int, rate: float) -> np.ndarray:
    """(n_frames,) phone index at each recogniser frame's centre (silence outside phones)."""
    index = {p: i for i, p in enumerate(PHONES)}
    labels = np.zeros(n_frames, np.int64)
    t = np.arange(n_frames) / rate
    for p in phones:
        labels[(t >= p.start) & (t < p.end)] = index.get(p.label, 0)
    return labels


def torch_posteriors(encoder: PhoneticEncoder):
    """The encoder's phone probabilities as a numpy function (`phonetic.Posteriors`)."""
    def posteriors(mel: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            x = torch.from_numpy(mel)[None].to(encoder.mel_mean.device, encoder.mel_mean.dtype)
            return encoder(x)[0].float().softmax(0).T.cpu().numpy()
    return posteriors


def speech_encoding(encoder: PhoneticEncoder):
    """The encoder as a model's second speech input (training features)."""
    return phonetic_encoding(encoder.cfg, torch_posteriors(encoder),
                             fingerprint(encoder.cfg, state_arrays(encoder)))


def encoder_from(cfg: PhoneticConfig, tensors: dict, source: str) -> PhoneticEncoder:
    encoder = PhoneticEncoder(cfg)
    load_state_strict(encoder, {k: np.asarray(v, np.float32) for k, v in tensors.items()}, source)
    return encoder.eval()


def save_phonetic(encoder: PhoneticEncoder, path: str | Path, info: dict) -> Path:
    return write_safetensors(state_arrays(encoder), {
        "format": FORMAT, "config": encoder.cfg.metadata(), "info": json.dumps(info)}, path)


def load_phonetic(path: str | Path) -> PhoneticEncoder:
    """The encoder of an encoder file (train-phonetic) or the one stored in a model file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such phonetic encoder file; train one with "
                              "python -m diffsheg_core train-phonetic")
    meta, tensors = read_safetensors(path, "train the encoder again (python -m diffsheg_core train-phonetic)")
    if meta.get("format") == MODEL_FORMAT:  # a model file: the encoder stored in it
        model = load_model(path)
        if model.phonetic is None:
            raise CheckpointError(f"{path}: this model holds no phonetic encoder (its speech input is "
                                  f"{model.config.speech_encoder or 'the mel alone'})")
        return encoder_from(model.phonetic, model.phonetic_weights, str(path))
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a phonetic encoder nor a model file (format {meta.get('format')!r})")
    return encoder_from(PhoneticConfig.from_metadata(meta["config"], str(path)), tensors, str(path))


# ---------------------------------------------------------------- training

@dataclass
class PhoneticTrainConfig:
    epochs: int = 60
    batch_size: int = 16
    crop_seconds: float = 3.0
    lr: float = 2e-3
    label_smoothing: float = 0.1
    val_fraction: float = 0.1
    seed: int = 0


def corpus_utterances(root: Path, split: str, val_fraction: float
                      ) -> list[tuple[str, Path, list[Phone]]]:
    """(name, wav, phones) of one split of the corpus, split by name as the trainer does."""
    from .corpus.teacher import load_utterance
    from .data import DataConfig, find_sources

    sources = find_sources(DataConfig(kind="corpus", root=str(root), val_fraction=val_fraction), split)
    return [(s.name, s.files["audio"], load_utterance(s.files["motion"])[1]) for s in sources if not s.missing]


def labelled_mels(utterances: list[tuple[str, Path, list[Phone]]], cfg: PhoneticConfig
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(log-mel, frame labels) of every utterance."""
    rate = cfg.fps * cfg.subframes
    out = []
    for _, wav, phones in tqdm(utterances, desc="log-mel", unit="utt", disable=None, leave=False):
        mel = log_mel(load_audio(wav), cfg)
        out.append((mel, frame_labels(phones, mel.shape[1], rate)))
    return out


def _crops(items: list[tuple[np.ndarray, np.ndarray]], length: int, rng: np.random.Generator
           ) -> tuple[torch.Tensor, torch.Tensor]:
    mels, labels = [], []
    for mel, lab in items:
        n = mel.shape[1]
        start = int(rng.integers(0, max(n - length, 0) + 1))
        m, y = mel[:, start:start + length], lab[start:start + length]
        pad = length - m.shape[1]
        mels.append(np.pad(m, ((0, 0), (0, pad)), mode="edge"))
        labels.append(np.pad(y, (0, pad), constant_values=-100))
    return torch.from_numpy(np.stack(mels)), torch.from_numpy(np.stack(labels))


def evaluate_phonetic(encoder: PhoneticEncoder, data: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Frame accuracy, and the mean bilabial probability at bilabial and at other frames."""
    bil = [PHONES.index(p) for p in BILABIALS]
    hits, total, at_bil, at_other = 0, 0, [], []
    with torch.inference_mode():
        for mel, lab in data:
            prob = encoder(torch.from_numpy(mel)[None])[0].softmax(0).numpy()
            hits += int((prob.argmax(0) == lab).sum())
            total += len(lab)
            p_bil = prob[bil].sum(0)
            is_bil = np.isin(lab, bil)
            at_bil.append(p_bil[is_bil])
            at_other.append(p_bil[~is_bil & (lab != 0)])
    return {"frame_accuracy": hits / max(total, 1),
            "p_bilabial_at_bilabials": float(np.concatenate(at_bil).mean()),
            "p_bilabial_at_other_phones": float(np.concatenate(at_other).mean())}


def train_phonetic(root: str | Path, cfg: PhoneticConfig, tcfg: PhoneticTrainConfig
                   ) -> tuple[PhoneticEncoder, dict]:
    root = Path(root)
    torch.manual_seed(tcfg.seed)
    rng = np.random.default_rng(tcfg.seed)
    train = labelled_mels(corpus_utterances(root, "train", tcfg.val_fraction), cfg)
    val = labelled_mels(corpus_utterances(root, "val", tcfg.val_fraction), cfg)
    if not train:
        raise DiffshegError(f"{root}: the corpus has no training utterances")
    encoder = PhoneticEncoder(cfg)
    every = np.concatenate([m for m, _ in train], axis=1)
    encoder.mel_mean.copy_(torch.from_numpy(every.mean(1, keepdims=True)))
    encoder.mel_std.copy_(torch.from_numpy(every.std(1, keepdims=True) + 1e-3))
    opt = torch.optim.AdamW(encoder.parameters(), lr=tcfg.lr, weight_decay=1e-4)
    length = int(round(tcfg.crop_seconds * cfg.fps * cfg.subframes))
    steps = tcfg.epochs * max(len(train) // tcfg.batch_size, 1)
    bar = tqdm(range(steps), desc="train-phonetic", unit="step", disable=None)
    for step in bar:
        for group in opt.param_groups:
            group["lr"] = tcfg.lr * 0.5 * (1 + np.cos(np.pi * step / steps))
        picks = rng.choice(len(train), tcfg.batch_size, replace=len(train) < tcfg.batch_size)
        mel, labels = _crops([train[i] for i in picks], length, rng)
        loss = nn.functional.cross_entropy(encoder(mel), labels, ignore_index=-100,
                                           label_smoothing=tcfg.label_smoothing)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        bar.set_postfix(loss=f"{loss.item():.3f}")
    encoder.eval()
    metrics = evaluate_phonetic(encoder, val) if val else {}
    return encoder, {"train_utterances": len(train), "val_utterances": len(val), "steps": steps, **metrics}


def main(argv: list[str] | None = None) -> int:
    """Train the phonetic encoder on the project's corpus (exact phone timings)."""
    parser = argparse.ArgumentParser(prog="diffsheg train-phonetic", description=main.__doc__)
    parser.add_argument("--corpus", required=True, help="corpus folder (python -m diffsheg_core.training.corpus build)")
    parser.add_argument("--out", required=True, help="where to write the encoder (.safetensors)")
    parser.add_argument("--epochs", type=int, default=PhoneticTrainConfig.epochs)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    encoder, report = train_phonetic(args.corpus, PhoneticConfig(),
                                     PhoneticTrainConfig(epochs=args.epochs, seed=args.seed))
    save_phonetic(encoder, args.out, {"corpus": str(args.corpus), **report})
    print(json.dumps({"out": args.out, **report}), file=sys.stdout)
    return 0
