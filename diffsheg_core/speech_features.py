"""The speech features a model is conditioned on, one recipe for a whole take, a long take
read in pieces and a live window: `frame_features`.

The features of motion frame i (`conditioning.SpeechFeatures`) are the mel frame centred at
i / fps and the model's second speech input when it has one: the phonetic encoder's
posteriors, four recogniser frames stacked per motion frame (`phonetic.stack_posteriors`), or
HuBERT (official models; whole recordings only). A piece or a window is computed over its
audio and some context before it (and, live, a lookahead after), read from a frame that
starts on a whole sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Iterator, Optional, Union

import numpy as np

from .audio import (MEL_N_FFT, MEL_RATE, PIECE_SECONDS, Audio, AudioFile, SpeechEncoding, mel_frames,
                    n_motion_frames, require_hubert)
from .checkpoints import ModelBundle
from .conditioning import SpeechFeatures
from .errors import DiffshegError
from .phonetic import (PhoneticConfig, log_mel, normalised, raw_log_mel, receptive_field, recogniser_frames,
                       stack_posteriors)

MARGIN_SECONDS = 2  # audio read either side of a piece: far more than the resampler's and the encoder's reach
LEVEL_EDGE_S = 0.03  # a running level counts the recogniser frames centred this far before the audio read ends:
# past their FFT's half window (14 ms) and the resampler's reach, so the frames are whole


class RunningLevel:
    """The phonetic encoder's level (`phonetic.log_mel`'s band means) over a recording's
    recogniser frames counted so far, each once, from reads that overlap: a long recording's
    piece by piece (`_phonetic_level`, the whole recording's level), a live session's window by
    window (the level of what it heard so far). A live window took its own few seconds' until
    2026-12-06, whose mean moved with the frames at the edge of the audio it read: a window read
    one sample shorter moved a phone's probability in its middle from 0.82 to 0.95, and with
    every window reading 10 ms less the jaw's open vowels over bilabials fell from 2.45 to 2.34
    (seeds 0-7). Counted over every whole frame heard, the level no longer depends on where a
    window's audio ends."""

    def __init__(self, n_mels: int):
        self.total = np.zeros(n_mels)  # summed over the recogniser frames counted
        self.count = 0
        self.next = 0  # the first frame of the recording not counted yet

    def add(self, raw: np.ndarray, offset: int, upto: int) -> np.ndarray:
        """Count the frames of `raw` ((n_mels, N) `raw_log_mel`, recogniser frames from `offset`
        of the recording) not counted yet, up to frame `upto`; the (n_mels, 1) mean so far (before
        any is counted, `raw`'s own)."""
        first, upto = max(self.next, offset), min(upto, offset + raw.shape[1])
        if upto > first:
            self.total += raw[:, first - offset: upto - offset].sum(axis=1, dtype=np.float64)
            self.count += upto - first
            self.next = upto
        if not self.count:
            return raw.mean(axis=1, keepdims=True)
        return (self.total / self.count)[:, None].astype(np.float32)


@dataclass(frozen=True)
class Recording:
    """What a piece's features need of the whole recording it is cut from."""

    n_posteriors: int                # its recogniser frames (the posteriors are clipped to them)
    level: Optional[np.ndarray]      # its mean log-mel per band (utterance normalisation), or None


def frame_features(bundle: ModelBundle, network, speech: Union[Audio, AudioFile], first: int, end: int, *,
                   before: int = 0, stop: Optional[int] = None, recording: Optional[Recording] = None,
                   running: Optional[RunningLevel] = None, hubert_path: Optional[str] = None,
                   hubert_quirk: bool = False) -> SpeechFeatures:
    """The float32 features of motion frames [first, end) of `speech`, computed over its
    audio from `before` frames before `first` (earlier, to a frame on a whole sample) to
    sample `stop` (None: the end; a lookahead past `end`).

    `recording`: the whole recording's recogniser frames and level, for a piece of a long
    one; None: the audio read stands for the recording (a whole take, or a live window,
    which knows nothing of the audio outside it). `running`: a live session's level, which
    counts the whole frames of the audio read and is taken off instead of the read's own."""
    cfg = bundle.config
    rate = speech.sample_rate
    start, sample = max(0, first - before), 0  # the frame the audio read starts at, and its sample
    if start:  # a piece or a window (whole frame rates only)
        fps = int(cfg.fps)
        start = start // whole_sample_frames(rate, fps) * whole_sample_frames(rate, fps)
        sample = start * rate // fps
    audio = speech.read(sample, speech.n_samples if stop is None else stop)
    mel, second = mel_frames(audio, cfg.fps)[first - start: end - start], None
    if cfg.phonetic_input:
        phonetic = _phonetic(bundle)
        per_second = phonetic.fps * phonetic.subframes
        offset = round(start / cfg.fps * per_second)  # the recording's recogniser frame the read starts at
        if running is None:
            mel_in = log_mel(audio, phonetic, None if recording is None else recording.level)
        else:
            raw = raw_log_mel(audio, phonetic)
            upto = math.floor(((sample + audio.n_samples) / rate - LEVEL_EDGE_S) * per_second) + 1
            mel_in = normalised(raw, phonetic, running.add(raw, offset, upto))
        posteriors = network.phone_posteriors(mel_in)
        if recording is None:
            second = stack_posteriors(posteriors, end - first, phonetic.subframes, first - start)
        else:
            second = stack_posteriors(posteriors, end - first, phonetic.subframes, first,
                                      recording.n_posteriors, offset=offset)
    elif cfg.has_speech_input:
        if start or first or recording is not None or end != n_motion_frames(audio, cfg.fps):
            raise DiffshegError(f"model {bundle.model_id} takes HuBERT features, which are computed over "
                                "the whole recording only")
        second = hubert_encoding(hubert_path, hubert_quirk, str(network.device)).encode(audio, end)
    return SpeechFeatures(mel.astype(np.float32), None if second is None else second.astype(np.float32))


def speech_features(bundle: ModelBundle, network, audio: Audio, hubert_path: Optional[str] = None,
                    hubert_quirk: bool = False) -> SpeechFeatures:
    """The speech features of a whole recording's motion frames."""
    return frame_features(bundle, network, audio, 0, n_motion_frames(audio, bundle.config.fps),
                          hubert_path=hubert_path, hubert_quirk=hubert_quirk)


def speech_chunks(bundle: ModelBundle, network, speech: Union[Audio, AudioFile],
                  hubert_path: Optional[str] = None, hubert_quirk: bool = False) -> Iterator[SpeechFeatures]:
    """`speech_features` of `speech` in order, PIECE_SECONDS at a time, so a long recording is
    never held whole: each piece is read with MARGIN_SECONDS of audio either side, its
    features computed as for the whole recording and the margins' frames dropped (equal to
    float32 rounding; a recording that fits one piece gives exactly `speech_features`).
    HuBERT models still read the whole recording."""
    cfg = bundle.config
    if (cfg.has_speech_input and not cfg.phonetic_input) or not float(cfg.fps).is_integer() \
            or speech.duration <= PIECE_SECONDS:
        yield speech_features(bundle, network, speech.read(0, speech.n_samples), hubert_path, hubert_quirk)
        return
    fps = int(cfg.fps)
    total = n_motion_frames(speech, fps)
    recording = None
    if cfg.phonetic_input:
        phonetic = _phonetic(bundle)
        n_post = recogniser_frames(speech.n_samples, speech.sample_rate, phonetic)
        recording = Recording(n_post, _phonetic_level(speech, phonetic, n_post))
    for t0 in range(0, int(np.ceil(speech.duration)), PIECE_SECONDS):
        first, last = t0 * fps, min((t0 + PIECE_SECONDS) * fps, total)
        if first >= last:
            return
        yield frame_features(bundle, network, speech, first, last, before=MARGIN_SECONDS * fps,
                             stop=_piece_stop(t0, speech.sample_rate), recording=recording)


def _piece_stop(t0: int, sample_rate: int) -> int:
    """The sample a piece from t0 seconds is read to: MARGIN_SECONDS past its end."""
    return (t0 + PIECE_SECONDS + MARGIN_SECONDS) * sample_rate


def _phonetic_level(speech: Union[Audio, AudioFile], phonetic: PhoneticConfig, n_post: int) -> Optional[np.ndarray]:
    """The whole recording's mean log-mel per band over its `n_post` recogniser frames (the
    encoder's utterance normalisation), summed piece by piece (read as `speech_chunks` reads them)."""
    if phonetic.normalise != "utterance":
        return None
    rate, per_second = speech.sample_rate, phonetic.fps * phonetic.subframes
    level = RunningLevel(phonetic.n_mels)
    for t0 in range(0, int(np.ceil(speech.duration)), PIECE_SECONDS):
        start = max(0, t0 - MARGIN_SECONDS)
        frames = raw_log_mel(speech.read(start * rate, _piece_stop(t0, rate)), phonetic)
        mean = level.add(frames, round(start * per_second), min(round((t0 + PIECE_SECONDS) * per_second), n_post))
    return mean


def whole_sample_frames(sample_rate: int, fps: int) -> int:
    """The fewest frames that span a whole number of samples (3 at 16 kHz and 15 fps)."""
    return fps // math.gcd(sample_rate, fps)


def margin_frames(bundle: ModelBundle, fps: int) -> int:
    """Frames of audio before a window that its features depend on: the mel's half window
    and the phonetic encoder's reach, rounded up."""
    reach_s = MEL_N_FFT / 2 / MEL_RATE
    if bundle.config.phonetic_input:
        phonetic = bundle.phonetic
        reach_s += (receptive_field(phonetic) + phonetic.subframes) / (phonetic.fps * phonetic.subframes)
    return int(math.ceil(reach_s * fps)) + 1


# --- the phonetic encoder and HuBERT ------------------------------------------------


def _phonetic(bundle: ModelBundle) -> PhoneticConfig:
    if bundle.phonetic is None:
        raise DiffshegError("this model takes phonetic features, but no phonetic encoder came with "
                            "it: export the model again from its training run")
    return bundle.phonetic


@lru_cache(maxsize=1)  # the 1.2 GB model is loaded once per process
def _hubert_encoder(hubert_path: Optional[str], device: str):
    require_hubert(hubert_path)  # says what to install before torch comes in
    from .torch_layer.hubert import load_hubert

    return load_hubert(hubert_path, device)


def hubert_encoding(hubert_path: Optional[str] = None, hubert_quirk: bool = False,
                    device: str = "cpu") -> SpeechEncoding:
    """HuBERT as the second speech input (the official models'), loaded once per process."""
    encoder = _hubert_encoder(hubert_path, device)
    from .torch_layer.hubert import hubert_features

    return SpeechEncoding(f"hubert:{hubert_path or 'cache'}:{hubert_quirk}",
                          lambda audio, n: hubert_features(audio, n, official_quirk=hubert_quirk,
                                                           encoder=encoder))
