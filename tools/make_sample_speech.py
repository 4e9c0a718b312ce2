"""Make the sample speech the project ships: diffsheg_core/samples/sample_speech.wav.

About ten seconds of synthetic English from Debian's espeak-ng in two voices, so a
new user can press "Generate" before they have recorded anything. The output is
16 kHz mono 16-bit PCM. Run from the repository root:

    python tools/make_sample_speech.py [--output PATH]

Needs the `espeak-ng` program (Debian/Ubuntu: apt-get install espeak-ng).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import librosa
import numpy as np
import soundfile as sf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from diffsheg_core.audio import SAMPLE_SPEECH, Audio, load_audio, resample  # noqa: E402

OUTPUT_RATE = 16000
PAUSE_S = 0.35
TRIM_DB = 40  # espeak-ng pads each line with silence; trim it so PAUSE_S sets the gaps
PEAK = 0.89  # about -1 dBFS


@dataclass(frozen=True)
class Line:
    """One sentence: espeak-ng voice, speed (words per minute), pitch (0-99) and text."""

    voice: str
    speed: int
    pitch: int
    text: str


LINES = (
    Line("en-us", 180, 45, "Good morning, everyone! Today I will show you three simple ideas."),
    Line("en-gb+f3", 185, 60, "Really? Only three? Well then, let's start."),
    Line("en-us", 175, 40, "Look: on the left, the old way; on the right, the new one."),
)


def synthesise(line: Line, workdir: Path) -> Audio:
    """Speak one line with espeak-ng into a WAV file and load it."""
    wav = workdir / "line.wav"
    subprocess.run(
        ["espeak-ng", "-v", line.voice, "-s", str(line.speed), "-p", str(line.pitch),
         "-w", str(wav), line.text],
        check=True,
    )
    speech = load_audio(wav)
    _, (start, end) = librosa.effects.trim(speech.samples, top_db=TRIM_DB)
    return Audio(speech.samples[start:end], speech.sample_rate, None)


def make_speech(lines: tuple[Line, ...] = LINES) -> Audio:
    """All lines at OUTPUT_RATE, separated by short pauses, peak-normalised."""
    with tempfile.TemporaryDirectory() as tmp:
        parts = [resample(synthesise(line, Path(tmp)), OUTPUT_RATE).samples for line in lines]
    pause = np.zeros(int(PAUSE_S * OUTPUT_RATE), dtype=np.float32)
    pieces = [piece for part in parts for piece in (part, pause)][:-1]
    samples = np.concatenate(pieces)
    samples *= PEAK / np.abs(samples).max()
    return Audio(samples=samples, sample_rate=OUTPUT_RATE, path=None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=SAMPLE_SPEECH)
    args = parser.parse_args()
    if shutil.which("espeak-ng") is None:
        sys.exit("espeak-ng not found: install it (Debian/Ubuntu: apt-get install espeak-ng)")
    speech = make_speech()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    sf.write(args.output, speech.samples, speech.sample_rate, subtype="PCM_16")
    print(f"wrote {args.output}: {speech.duration:.2f} s at {speech.sample_rate} Hz")


if __name__ == "__main__":
    main()
