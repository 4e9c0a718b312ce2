"""Command line: `python -m diffsheg_core generate|live|train|evaluate ...`."""

from __future__ import annotations

import argparse
import sys
import threading
import time
import warnings
from pathlib import Path
from dataclasses import replace
from typing import Optional, Sequence

from .errors import DiffshegError
from .live import cli as live_cli


def _generate_parser(sub: argparse._SubParsersAction) -> None:
    from .settings import add_arguments

    p = sub.add_parser("generate", help="generate motion from a speech recording",
                       description="Generate body, hand, head and face motion from speech.")
    p.add_argument("audio", nargs="?", help="speech file (WAV/FLAC/OGG/MP3); default: the bundled sample")
    p.add_argument("-o", "--output", default="out/motion.npz", help="motion .npz to write (default %(default)s)")
    p.add_argument("--bvh", help="also write a BVH (beat layout: 75-joint BEAT skeleton)")
    p.add_argument("--arkit-json", help="also write face weights as the official ARKit JSON")
    p.add_argument("--csv", help="also write face weights as a Live Link Face CSV")
    p.add_argument("--talkshow", help="also write SMPL-X motion as a TalkSHOW-layout .npz")
    add_arguments(p)
    p.add_argument("--dataset", choices=["beat", "show"],
                   help="official checkpoints: the dataset whose configuration to use (default: told from the "
                        "tensor shapes)")
    p.add_argument("--config", dest="dataset", choices=["beat", "show"], help=argparse.SUPPRESS)  # its old name
    p.add_argument("--stats", help="folder of the official normalisation statistics (official checkpoints)")
    p.add_argument("--no-prior", action="store_true",
                   help="start later FOPPAS windows from pure noise, as in the paper, instead of from "
                        "the model's gesture prior (models that have one)")
    p.add_argument("--no-refine", action="store_true",
                   help="keep each FOPPAS window as sampled, without the last pass of the network over its "
                        "gestures (models that set one)")
    p.add_argument("--hubert", help="local folder of facebook/hubert-large-ls960-ft (models that use HuBERT)")
    p.add_argument("--hubert-official-quirk", action="store_true",
                   help="feed HuBERT 22.05 kHz audio as the official code does (default: correct 16 kHz)")


def run_generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from . import motion as motion_io
    from .audio import SAMPLE_SPEECH
    from .checkpoints import files_read, load_model
    from .files import check_outputs
    from .foppas import sampling_settings
    from .pipeline import generate, open_speech
    from .runtime.backends import open_network
    from .settings import from_arguments

    audio_path = args.audio or str(SAMPLE_SPEECH)
    if args.audio is None:
        print(f"no audio given: using the bundled sample speech {SAMPLE_SPEECH}")
    check_outputs([args.output, args.bvh, args.arkit_json, args.csv, args.talkshow],
                  inputs=[audio_path, *files_read(args.model, args.stats, args.hubert)])
    if Path(args.output).suffix.lower() != ".npz":
        raise DiffshegError(f"-o/--output writes the motion as .npz, not {Path(args.output).name}: give a .npz "
                            "there, and --bvh, --arkit-json, --csv or --talkshow for the other formats")
    started = time.perf_counter()
    settings = from_arguments(args)  # every option checked before the model loads
    speech = open_speech(audio_path)  # checked now, read piece by piece while generating
    bundle = load_model(settings.model, dataset=args.dataset, stats_dir=args.stats)
    network = open_network(bundle, settings.backend, settings.device, settings.precision, settings.threads)
    if not bundle.trained:
        print(f"warning: model '{bundle.model_id}' is UNTRAINED (random weights): "
              "the motion is not learned from data", file=sys.stderr)
    bar = tqdm(total=1000, unit="‰", desc="generating", leave=False,
               bar_format="{l_bar}{bar}| {elapsed}<{remaining}")

    def on_progress(p) -> None:
        bar.set_postfix_str(f"clip {p.clip + 1}/{p.n_clips}", refresh=False)
        bar.update(int(p.fraction * 1000) - bar.n)

    sampling = None  # the named sampling (the distilled student's, where it applies), unless changed below
    if args.no_prior or args.no_refine:
        sampling = replace(sampling_settings(bundle.sampling, settings.sampling),
                           **({"prior_start": False} if args.no_prior else {}),
                           **({"refine": None} if args.no_refine else {}))
    cancel = threading.Event()
    try:
        result = generate(speech, settings=settings, model=bundle, sampling=sampling, hubert_path=args.hubert,
                          hubert_quirk=args.hubert_official_quirk, progress=on_progress, cancel=cancel)
    except KeyboardInterrupt:
        cancel.set()
        raise
    finally:
        bar.close()
    elapsed = time.perf_counter() - started
    written = [result.save_npz(args.output)]
    if args.bvh:
        from .bvh import write_bvh
        written.append(write_bvh(result, args.bvh))
    if args.arkit_json:
        written.append(motion_io.write_arkit_json(result, args.arkit_json))
    if args.csv:
        written.append(motion_io.write_livelink_csv(result, args.csv))
    if args.talkshow:
        written.append(motion_io.write_talkshow_npz(result, args.talkshow))
    for path in written:
        print(f"wrote {path}")
    print(f"{result.n_frames} frames at {result.fps:g} fps = {result.duration:.1f} s of motion in "
          f"{elapsed:.1f} s ({result.n_frames / elapsed:.1f} frames/s, "
          f"{result.duration / elapsed:.2f}x real time) on {network.name}/{network.device} with {bundle.model_id}")
    return 0


def _delegate(command: str, module: str, argv: Sequence[str]) -> int:
    import importlib

    try:
        tool = importlib.import_module(f"diffsheg_core.{module}")
    except ModuleNotFoundError as exc:  # the add-on's copy ships generation alone; torch is an extra
        raise DiffshegError(f"'{command}' needs the tooling of diffsheg_core and its packages (torch, onnx, "
                            f"scipy, librosa), which this installation lacks (no module named '{exc.name}'; "
                            "the Blender add-on's copy ships generation alone): from a checkout of the "
                            "repository, pip install -e \".[train]\" (see README)") from None
    return tool.main(list(argv)) or 0


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"warning: {message}", file=sys.stderr)


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    warnings.showwarning = _show_warning  # one plain line per warning, not a source location
    delegated = {"train": "training.train", "evaluate": "training.evaluate",
                 "train-autoencoder": "training.autoencoder", "train-phonetic": "training.train_phonetic",
                 "export-onnx": "torch_layer.export", "add-face": "training.faces"}
    if argv and argv[0] in delegated:
        try:
            return _delegate(argv[0], delegated[argv[0]], argv[1:])
        except DiffshegError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core",
                                     description="Speech-driven gesture and expression generation (DiffSHEG).")
    sub = parser.add_subparsers(dest="command", required=True,
                                metavar="{generate,live,train,evaluate,train-autoencoder,train-phonetic,"
                                        "export-onnx,add-face}")
    _generate_parser(sub)
    live_cli.add_parser(sub)
    sub.add_parser("train", help="train a model (see: train --help)")
    sub.add_parser("evaluate", help="evaluate motion against references (see: evaluate --help)")
    sub.add_parser("train-autoencoder", help="train the motion autoencoder for Fréchet distances")
    sub.add_parser("train-phonetic", help="train the phonetic speech encoder on the synthetic corpus")
    sub.add_parser("export-onnx", help="add ONNX graphs (the torch-free runtime's) to a model file")
    sub.add_parser("add-face", help="add a language's own face (its fine-tuned face branch) to a model file")
    args = parser.parse_args(argv)
    try:
        return live_cli.run(args) if args.command == "live" else run_generate(args)
    except DiffshegError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cancelled", file=sys.stderr)
        return 130
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
