"""Make the mel filterbanks the runtime reads: diffsheg_core/assets/mel_filters.npz.

`diffsheg_core.audio.mel_spectrogram` must run inside Blender, where librosa (and
scipy, numba) cannot be installed, so the filterbanks it needs are computed here once
with `librosa.filters.mel(sr=18000, n_fft=..., n_mels=...)` (librosa's defaults:
fmin 0, fmax sr / 2, Slaney mel scale, Slaney area normalisation, float32) and stored,
one (n_mels, 1 + n_fft // 2) float32 array per bank under the key
`sr18000_nfft{n_fft}_mels{n_mels}`. Run from the repository root:

    python tools/make_mel_filters.py [--bank NFFTxMELS ...] [--output PATH] [--check]

The default banks are the official DiffSHEG mel (n_fft 2048, 128 mels) and the
phonetic encoder's log-mel (n_fft 512, 64 mels); `--bank 1024x80` adds another one.
`--check` writes nothing and exits 1 unless the stored file holds exactly these banks,
equal to what librosa gives now.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import librosa
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from diffsheg_core.audio import (  # noqa: E402
    MEL_FILTERS, MEL_N_FFT, MEL_N_MELS, MEL_RATE, mel_filter_key,
)

# (n_fft, n_mels): the official DiffSHEG mel, and PhoneticConfig's defaults in phonetic.py.
BANKS = ((MEL_N_FFT, MEL_N_MELS), (512, 64))


def make_banks(banks) -> dict[str, np.ndarray]:
    """{key: (n_mels, 1 + n_fft // 2) float32} for each (n_fft, n_mels)."""
    return {mel_filter_key(n_fft, n_mels):
            librosa.filters.mel(sr=MEL_RATE, n_fft=n_fft, n_mels=n_mels).astype(np.float32)
            for n_fft, n_mels in banks}


def _bank(text: str) -> tuple[int, int]:
    try:
        n_fft, n_mels = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NFFTxMELS such as 1024x80, got {text!r}") from None
    if n_fft < 2 or n_mels < 1:
        raise argparse.ArgumentTypeError(f"n_fft must be at least 2 and n_mels at least 1, got {text!r}")
    return n_fft, n_mels


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bank", type=_bank, action="append", default=[],
                        help="another bank to store, as NFFTxMELS (repeatable)")
    parser.add_argument("--output", type=Path, default=MEL_FILTERS)
    parser.add_argument("--check", action="store_true",
                        help="compare the stored file with librosa instead of writing it")
    args = parser.parse_args(argv)
    banks = make_banks(dict.fromkeys(BANKS + tuple(args.bank)))
    if args.check:
        if not args.output.is_file():
            print(f"{args.output} does not exist", file=sys.stderr)
            return 1
        with np.load(args.output, allow_pickle=False) as stored:
            same = set(stored.files) == set(banks) and all(
                stored[key].dtype == np.float32 and np.array_equal(stored[key], bank)
                for key, bank in banks.items())
        print(f"{args.output}: {'up to date' if same else 'differs from librosa ' + librosa.__version__}")
        return 0 if same else 1
    args.output.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.output, **banks)
    for key, bank in banks.items():
        print(f"{key}: {bank.shape[0]} x {bank.shape[1]}")
    print(f"wrote {args.output} ({args.output.stat().st_size} bytes, librosa {librosa.__version__})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
