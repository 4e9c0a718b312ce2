"""Benchmark: seconds per stage for generating motion from real speech.

Prints, side by side for each configuration, the time spent loading audio,
computing speech features, sampling (FOPPAS), and writing outputs, then frames per
second and the real-time factor (audio seconds per wall second). Run from the repo:

    python bench/bench_generate.py [--seconds 60] [--configs default,official] [--backend auto]

`default` is the bundled model with its own sampling preset (onnxruntime unless
--backend torch); `official` the full-size official BEAT network (random weights, torch)
with HuBERT features from a randomly initialised HuBERT-large-layout model (the real
model's compute; needs `transformers`), sampled with the official FOPPAS preset.
For onnxruntime against torch, threads and load, see bench_backends.py.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf
import torch

from diffsheg_core.audio import load_audio
from diffsheg_core.bvh import write_bvh
from diffsheg_core.checkpoints import ModelBundle, load_model
from diffsheg_core.conditioning import Conditioning
from diffsheg_core.config import ModelConfig
from diffsheg_core.foppas import PRESETS, sample_long
from diffsheg_core.motion import write_arkit_json
from diffsheg_core.pipeline import build_sampling, make_plan, to_motion
from diffsheg_core.runtime.backends import open_network
from diffsheg_core.settings import GenerateSettings
from diffsheg_core.speech_features import speech_features
from diffsheg_core.torch_layer.model import UniEG, state_arrays

SPEECH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "audio" / "2_scott_0_3_3.wav"


def official_bundle() -> ModelBundle:
    torch.manual_seed(0)
    model = UniEG(ModelConfig()).eval()
    dim = model.cfg.dim
    return ModelBundle(config=model.cfg, weights=state_arrays(model),
                       mean=np.zeros(dim, np.float32), std=np.ones(dim, np.float32),
                       sampling=PRESETS["official-beat"], model_id="official-size-random")


def random_hubert_large(folder: Path) -> str:
    import transformers

    torch.manual_seed(0)
    config = transformers.HubertConfig(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16,
                                       intermediate_size=4096, feat_extract_norm="layer",
                                       do_stable_layer_norm=True)
    transformers.HubertModel(config).save_pretrained(folder)
    return str(folder)


def run(bundle: ModelBundle, audio_path: Path, backend: str, device: str, hubert: str | None,
        out: Path) -> dict:
    network = open_network(bundle, backend, device)
    times = {"network": f"{network.name}/{network.device}"}
    t = time.perf_counter()
    speech = load_audio(audio_path)
    times["load"] = time.perf_counter() - t

    t = time.perf_counter()
    features = speech_features(bundle, network, speech, hubert_path=hubert)
    times["features"] = time.perf_counter() - t

    t = time.perf_counter()
    plan = make_plan(bundle, GenerateSettings(model=bundle), n_frames=len(features))
    sampler, make = build_sampling(bundle, network, plan)
    out_frames = sample_long(sampler, make, Conditioning(features, plan.style), 0)
    times["sampling"] = time.perf_counter() - t

    t = time.perf_counter()
    motion = to_motion(bundle, out_frames, meta={})
    motion.save_npz(out / "m.npz")
    write_bvh(motion, out / "m.bvh")
    write_arkit_json(motion, out / "m.json")
    times["writing"] = time.perf_counter() - t
    times["total"] = sum(times[k] for k in ("load", "features", "sampling", "writing"))
    times["frames"] = motion.n_frames
    times["audio_s"] = speech.duration
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="seconds of real speech (default 60)")
    parser.add_argument("--configs", default="default,official",
                        help="default (bundled model), official (full size, random weights)")
    parser.add_argument("--backend", default="auto", choices=["auto", "onnx", "torch"])
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    device = args.device
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        samples, sr = sf.read(SPEECH, dtype="float32")
        audio = tmp / "speech.wav"
        sf.write(audio, samples[: int(args.seconds * sr)], sr)
        results = {}
        for name in args.configs.split(","):
            if name == "default":
                results[name] = run(load_model(), audio, args.backend, device, None, tmp)
            elif name == "official":
                results[name] = run(official_bundle(), audio, "torch", device,
                                    random_hubert_large(tmp / "hubert"), tmp)
            else:
                raise SystemExit(f"unknown configuration {name}: use default, official")
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU"
    print(f"{args.seconds:g} s of real speech; {gpu}")
    names = list(results)
    print(f"{'runs on':<12}" + "".join(f"{results[n]['network']:>14}" for n in names))
    print(f"{'stage':<12}" + "".join(f"{n:>14}" for n in names))
    for key in ("load", "features", "sampling", "writing", "total"):
        print(f"{key + ' (s)':<12}" + "".join(f"{results[n][key]:>14.2f}" for n in names))
    print(f"{'frames/s':<12}" + "".join(f"{results[n]['frames'] / results[n]['total']:>14.1f}" for n in names))
    print(f"{'x real time':<12}" + "".join(f"{results[n]['audio_s'] / results[n]['total']:>14.2f}" for n in names))
    for other in names[1:]:
        ratio = results[other]["total"] / results[names[0]]["total"]
        print(f"ratio {other}/{names[0]} total time: {ratio:.1f}x")


if __name__ == "__main__":
    main()
