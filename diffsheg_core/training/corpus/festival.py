"""festival through a Scheme script: it synthesises, writes the wave and prints every
segment of the utterance's Segment relation with its end time (seconds, as used to build
the wave) and its syllable's lexical stress."""

from __future__ import annotations

import subprocess
import tempfile
from pathlib import Path

import soundfile as sf

from ...errors import DiffshegError
from .phones import extend_to, from_festival_segments, merge_silences
from .synthesis import Synthesis, VoiceSpec

_SCRIPT = """
(voice_{voice})
(Parameter.set 'Duration_Stretch {stretch:.3f})
{hts_rate}
(set! utt (Utterance Text "{text}"))
(utt.synth utt)
(utt.save.wave utt "{wave}" 'riff)
(mapcar (lambda (s) (format t "SEG %s %f %s\\n" (item.name s) (item.feat s "end")
                            (item.feat s "R:SylStructure.parent.stress")))
        (utt.relation.items utt 'Segment))
"""


_HTS_RATE = """(set! hts_engine_params (append hts_engine_params (list (list "-r" {rate:.3f}))))"""
"""HTS voices ignore Duration_Stretch; their engine takes a speaking rate instead."""


def _scheme_string(text: str) -> str:
    return " ".join(text.replace("\\", " ").replace('"', "'").split())


def synthesize(text: str, voice: VoiceSpec) -> Synthesis:
    """Speak `text` with a festival voice (`voice.name`, e.g. 'kal_diphone')."""
    with tempfile.TemporaryDirectory(prefix="diffsheg_festival_") as tmp:
        wave, script = Path(tmp) / "out.wav", Path(tmp) / "say.scm"
        hts_rate = _HTS_RATE.format(rate=1.0 / voice.stretch) if voice.name.endswith("_hts") else ""
        script.write_text(_SCRIPT.format(voice=voice.name, stretch=voice.stretch, hts_rate=hts_rate,
                                         text=_scheme_string(text), wave=wave))
        try:
            run = subprocess.run(["festival", "--batch", str(script)], capture_output=True,
                                 text=True, timeout=120)
        except subprocess.TimeoutExpired as exc:
            raise DiffshegError(f"festival took over 120 s on {text[:40]!r}") from exc
        except FileNotFoundError as exc:
            raise DiffshegError("festival is not installed: run `apt-get install festival "
                                "festvox-kallpc16k festvox-kdlpc16k festvox-us-slt-hts`") from exc
        if run.returncode != 0 or not wave.is_file():
            raise DiffshegError(f"festival failed with voice {voice.name!r} (is its festvox package "
                                f"installed?): {run.stderr.strip()[-300:]}")
        samples, sr = sf.read(wave, dtype="float32", always_2d=True)
    lines = [line.split() for line in run.stdout.splitlines()]
    phones = from_festival_segments([(parts[1], float(parts[2]), parts[3] == "1")
                                     for parts in lines if len(parts) == 4 and parts[0] == "SEG"])
    if not phones:
        raise DiffshegError(f"festival printed no segments for {text[:40]!r}")
    # the wave runs on for part of a pitch period after the last segment's end
    return Synthesis(samples[:, 0], int(sr), extend_to(merge_silences(phones), len(samples) / sr), voice)
