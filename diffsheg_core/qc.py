"""The QC report of a batch: one row per dialogue line, the lines a lead should look at first.

Per line: its status (done, skipped as already done, failed with its one-line error), the
audio length, frames, time taken and real-time factor, two figures of the motion, and the
flags that put it at the top of the report:

- `mouth_voice_correlation`: Pearson correlation of the mouth opening (ARKit `jawOpen` in
  the 'beat' layout, the jaw joint's rotation angle in 'smplx') with the speech level (RMS
  in dB, 2-frame windows, floored 60 dB under the loudest window so pauses do not dominate)
  at the motion's own frame rate, the best over lags within +-150 ms.
- `gesture_energy`: mean wrist speed in arm lengths per second (diffsheg_core.kinematics).
- `voiced_mouth_voice_correlation`: the same over voiced frames only (`voiced_frames`), and
  `lip_closures`: where the lips shut during speech; both for measuring languages
  (bench/eval_languages.py), not columns of the report.

`flags` turns a row into warnings: silent audio, lips not following the voice (below
MOUTH_VOICE_MIN), clipped audio (a peak at full scale), failed. `write_report` writes
`report.csv` and a self-contained `report.html`, flagged rows first, both atomically.

numpy only (no scipy, no training tooling): this runs inside Blender.
"""

from __future__ import annotations

import csv
import html
import io
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from .errors import DiffshegError
from .files import atomic_write
from .kinematics import wrist_positions, wrist_speed
from .motion import Motion

STATUSES = ("done", "skipped", "failed")

MAX_LAG = 0.15
"""Seconds either way within which the mouth may lead or follow the voice."""

FLOOR_DB = 60.0
"""The speech level is floored this far under its loudest window."""

MOUTH_VOICE_MIN = 0.2
"""Below this mouth-to-voice correlation the lips are flagged as not following the voice.

Measured with diffsheg-default-v8 (seed 0; the bundled v9 makes the same face) on the 25 real speech files
of shared/data/audio (English, Mandarin, Japanese, Swedish, Spanish, German, French,
Russian, Hindi; 3.6-119 s), each given at 16 kHz (since the phonetic encoder is fed speech
capped at 16 kHz, files at 22.05 and 44.1 kHz score within 0.01 of their 16 kHz figures):
- the lines themselves: 0.26-0.84 at steps=5 (median 0.58; lowest ja_mfa_2, 0.26, and
  de_thorsten_1, 0.31), 0.28-0.83 at the default 25 steps (median 0.59): none below 0.2;
- the same motions with the face frames shuffled in time (20 shuffles each, 500 in all):
  median 0.05, 95th percentile 0.21; 94 % fall below 0.2;
- each line's voice against every other line's face (600 pairs): median 0.09; 73 % below
  0.2 (another take of speech shares its rhythm, so some of these correlate by chance).
0.25 would catch a few more controls but sits 0.01 under the lowest real line; 0.3 flags
real lines. tests/test_qc.py repeats the measurement on a few files."""

SILENT_PEAK = 10 ** (-50 / 20)
"""An audio file whose peak stays under -50 dBFS holds no speech worth animating."""

CLIPPED_PEAK = 0.999
"""A peak at or above this (-0.01 dBFS: full scale in 16-bit or float audio) means clipping."""

VOICED_DB = 25.0
"""A voiced frame lies within this many dB of the clip's speech level (its 95th-percentile frame)."""

VOICED_PERIODICITY = 0.5
"""A voiced frame's normalised autocorrelation peaks at or above this at a pitch within VOICE_PITCH."""

VOICE_PITCH = (60.0, 400.0)
"""Hz: the pitch range of a voice. `voiced_frames` hears the audio above its lower end only."""

LIP_CLOSED = 0.2
"""ARKit mouthClose at or above which a peak counts as the lips shutting (bundled model on the
real take 2_scott_0_1_1: median 0.36 at the middle of p/b/m, 0.01 at vowels, 0.03 in pauses)."""


# ------------------------------------------------------------------ measures

def mouth_curve(motion: Motion) -> np.ndarray:
    """(T,) mouth opening of `motion`: ARKit jawOpen (weight), or the jaw joint's rotation
    angle (radians) where the face has no jawOpen channel (SMPL-X)."""
    if "jawOpen" in motion.face_names:
        return motion.face[:, motion.face_names.index("jawOpen")].astype(np.float64)
    if "jaw" in motion.joint_names:
        return np.linalg.norm(motion.rotations[:, motion.joint_names.index("jaw")].astype(np.float64), axis=-1)
    raise DiffshegError(f"the '{motion.rig}' motion has neither a jawOpen face channel nor a jaw joint: "
                        "its mouth opening is unknown")


def speech_level(samples: np.ndarray, sample_rate: int, fps: float, n_frames: int,
                 floor_db: float = FLOOR_DB) -> np.ndarray:
    """(n_frames,) speech level in dB at frame times i / fps: RMS over 2 / fps seconds centred
    there, floored `floor_db` under the loudest frame (so silence does not dominate)."""
    y = np.asarray(samples, np.float64).reshape(-1)
    hop = sample_rate / fps
    win = max(1, int(round(2 * hop)))
    padded = np.concatenate([np.zeros(win // 2), y, np.zeros(win)])
    starts = np.minimum((np.arange(n_frames) * hop).astype(np.int64), len(padded) - win)
    power = np.cumsum(np.concatenate([[0.0], padded ** 2]))
    rms = np.sqrt(np.maximum(power[starts + win] - power[starts], 0.0) / win)
    db = 20 * np.log10(np.maximum(rms, 1e-10))
    return np.maximum(db, db.max(initial=-200.0) - floor_db)


def lagged_correlation(a: np.ndarray, b: np.ndarray, max_shift: int,
                       where: Optional[np.ndarray] = None) -> float:
    """Best Pearson correlation of equal-rate `a` and `b` over shifts of up to `max_shift`
    samples either way; 0.0 where no overlap of 3 or more samples varies in both. `where`
    (booleans on `b`'s samples) keeps only the pairs whose `b` sample it marks."""
    n = min(len(a), len(b))
    a, b = np.asarray(a[:n], np.float64), np.asarray(b[:n], np.float64)
    keep = np.ones(n, bool) if where is None else np.asarray(where[:n], bool)
    best = -math.inf
    for k in range(-max_shift, max_shift + 1):
        x, y = (a[k:], b[: n - k]) if k >= 0 else (a[: n + k], b[-k:])
        kept = keep[: n - k] if k >= 0 else keep[-k:]
        x, y = x[kept], y[kept]
        if len(x) < 3 or x.std() < 1e-12 or y.std() < 1e-12:
            continue
        best = max(best, float(np.corrcoef(x, y)[0, 1]))
    return best if math.isfinite(best) else 0.0


def mouth_voice_correlation(motion: Motion, audio_samples: np.ndarray, sample_rate: int,
                            max_lag: float = MAX_LAG) -> float:
    """Correlation of the mouth opening with the speech level at the motion's fps, the best
    within +-`max_lag` seconds; 0.0 when either does not vary (silence, a still mouth)."""
    mouth = mouth_curve(motion)
    if len(mouth) < 3:
        return 0.0
    level = speech_level(audio_samples, int(sample_rate), motion.fps, len(mouth))
    return lagged_correlation(mouth, level, int(math.floor(max_lag * motion.fps + 1e-9)))


def periodicity(samples: np.ndarray, sample_rate: int, fps: float, n_frames: int,
                pitch: tuple[float, float] = VOICE_PITCH) -> np.ndarray:
    """(n_frames,) peak of the normalised autocorrelation over periods of 1 / pitch[1] to
    1 / pitch[0] seconds, in windows of 1 / fps seconds centred at i / fps: near 1 for a
    vowel, low for noise, fricatives and bursts. Each window's mean is taken off (so a DC
    offset is no voice) and each lag's sum is rescaled to the full window."""
    y = np.asarray(samples, np.float64).reshape(-1)
    hop = sample_rate / fps
    win = max(2, int(round(hop)))
    padded = np.concatenate([np.zeros(win // 2), y, np.zeros(win)])
    starts = np.minimum((np.arange(n_frames) * hop).astype(np.int64), len(padded) - win)
    frames = padded[starts[:, None] + np.arange(win)]
    frames -= frames.mean(axis=1, keepdims=True)
    n_fft = 1 << int(math.ceil(math.log2(2 * win)))
    spectrum = np.fft.rfft(frames, n_fft)
    auto = np.fft.irfft(spectrum.real ** 2 + spectrum.imag ** 2, n_fft)
    lags = np.arange(int(sample_rate / pitch[1]), min(int(math.ceil(sample_rate / pitch[0])), win - 1) + 1)
    if len(lags) == 0:
        return np.zeros(n_frames)
    r = auto[:, lags] / np.maximum(auto[:, :1], 1e-20) * (win / (win - lags))
    return r.max(axis=1)


def high_passed(samples: np.ndarray, sample_rate: int, cutoff: float) -> np.ndarray:
    """`samples` (float64) without their content below `cutoff` Hz, DC included (zeroed in one FFT)."""
    y = np.asarray(samples, np.float64).reshape(-1)
    spectrum = np.fft.rfft(y)
    spectrum[np.fft.rfftfreq(len(y), 1.0 / sample_rate) < cutoff] = 0.0
    return np.fft.irfft(spectrum, len(y))


def voiced_frames(samples: np.ndarray, sample_rate: int, fps: float, n_frames: int) -> np.ndarray:
    """(n_frames,) booleans: the frames at i / fps where the voice sounds, told from the audio
    alone: loud (within VOICED_DB of the clip's 95th-percentile speech level, so pauses,
    breaths and room noise drop out whatever the recording's gain) and periodic (periodicity
    at or above VOICED_PERIODICITY, so voiceless hiss and bursts drop out). On the real take
    2_scott_0_1_1 against its phone timings (15 fps) this marks 94 % of vowel frames, 89 % of
    voiced consonants, 52 % of voiceless ones (a 67 ms window at 15 fps straddles their
    neighbours) and 2 % of pauses. Both tests hear the audio above the lowest pitch
    (`high_passed`), so mains hum and rumble, loud and periodic, are no voice: unfiltered,
    76 of the 124 frames marked in zh_thchs30_1 were the 50 Hz hum of its pauses."""
    y = high_passed(samples, sample_rate, VOICE_PITCH[0])
    level = speech_level(y, sample_rate, fps, n_frames)
    loud = level >= np.percentile(level, 95) - VOICED_DB if n_frames else np.zeros(0, bool)
    return loud & (periodicity(y, sample_rate, fps, n_frames) >= VOICED_PERIODICITY)


def voiced_mouth_voice_correlation(motion: Motion, audio_samples: np.ndarray, sample_rate: int,
                                   max_lag: float = MAX_LAG) -> float:
    """mouth_voice_correlation over the voiced frames only (voiced_frames): whether the mouth
    follows the loudness of the voice while it speaks, which a clip's pauses cannot flatter
    (a mouth that merely opens for speech and shuts in pauses scores high over a whole clip)."""
    return voiced_level_correlation(mouth_curve(motion), motion.fps, audio_samples, sample_rate, max_lag)


def voiced_level_correlation(curve: np.ndarray, fps: float, audio_samples: np.ndarray, sample_rate: int,
                             max_lag: float = MAX_LAG) -> float:
    """Correlation of a per-frame `curve` with the speech level over the voiced frames, the
    best within +-`max_lag` seconds (voiced_mouth_voice_correlation's figure for any curve)."""
    sample_rate = int(sample_rate)
    level = speech_level(audio_samples, sample_rate, fps, len(curve))
    voiced = voiced_frames(audio_samples, sample_rate, fps, len(curve))
    return lagged_correlation(curve, level, int(math.floor(max_lag * fps + 1e-9)), where=voiced)


def lip_closures(motion: Motion, audio_samples: np.ndarray, sample_rate: int,
                 reach: float = 0.2) -> np.ndarray:
    """Frame indices where the lips shut during speech: peaks of ARKit mouthClose at or above
    LIP_CLOSED within `reach` seconds of a voiced frame (a stop's closure is itself silent).
    A proxy for closing on p/b/m where no phone timings exist; on the real take
    2_scott_0_1_1 (bundled model, seed 0) 58 % of these fall within a frame of a p/b/m and
    66 % of its p/b/m have one."""
    if "mouthClose" not in motion.face_names:
        raise DiffshegError(f"the '{motion.rig}' motion has no mouthClose face channel: lip closures are unknown")
    close = motion.face[:, motion.face_names.index("mouthClose")].astype(np.float64)
    peak = np.zeros(len(close), bool)
    peak[1:-1] = (close[1:-1] >= LIP_CLOSED) & (close[1:-1] >= close[:-2]) & (close[1:-1] > close[2:])
    voiced = voiced_frames(audio_samples, int(sample_rate), motion.fps, len(close))
    span = int(round(reach * motion.fps))
    in_speech = np.convolve(voiced.astype(np.float64), np.ones(2 * span + 1), "full")[span:span + len(voiced)] > 0
    return np.flatnonzero(peak & in_speech)


def gesture_energy(motion: Motion) -> float:
    """Mean wrist speed of `motion` in arm lengths per second."""
    return wrist_speed(wrist_positions(motion), motion.fps)


def audio_peak(samples: np.ndarray) -> float:
    """Largest |sample| (1.0 is full scale); 0.0 for no samples."""
    samples = np.asarray(samples)
    return float(np.abs(samples).max()) if samples.size else 0.0


# ------------------------------------------------------------------ rows

@dataclass
class QcRow:
    """One line of the report. Figures a line does not have (a failed or skipped line) are None."""

    id: str
    status: str                         # 'done' | 'skipped' | 'failed'
    error: str = ""                     # the one-line error of a failed line
    audio_seconds: Optional[float] = None
    frames: Optional[int] = None
    seconds: Optional[float] = None     # wall-clock time the line took
    realtime_factor: Optional[float] = None  # seconds taken per second of audio
    mouth_voice: Optional[float] = None
    gesture_energy: Optional[float] = None
    warnings: list[str] = field(default_factory=list)  # from generation (Motion.meta['warnings'])
    audio_peak: Optional[float] = None  # largest |sample|, 1.0 full scale

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise DiffshegError(f"QC status must be one of {', '.join(STATUSES)}, got {self.status!r}")
        self.warnings = list(self.warnings)


def measure(line_id: str, motion: Motion, audio_samples: np.ndarray, sample_rate: int,
            seconds: Optional[float] = None) -> QcRow:
    """The 'done' row of a line that produced `motion` from these samples in `seconds`."""
    audio_seconds = len(audio_samples) / sample_rate
    return QcRow(
        id=line_id, status="done", audio_seconds=audio_seconds, frames=motion.n_frames, seconds=seconds,
        realtime_factor=None if seconds is None or audio_seconds <= 0 else seconds / audio_seconds,
        mouth_voice=mouth_voice_correlation(motion, audio_samples, sample_rate),
        gesture_energy=gesture_energy(motion),
        warnings=[str(w) for w in motion.meta.get("warnings", [])],
        audio_peak=audio_peak(audio_samples))


def flags(row: QcRow) -> list[str]:
    """Why a lead should look at this line (empty: nothing unusual)."""
    out = []
    if row.status == "failed":
        out.append(f"failed: {row.error}" if row.error else "failed")
    silent = row.audio_peak is not None and row.audio_peak < SILENT_PEAK
    if silent:
        out.append(f"silent audio (peak {_dbfs(row.audio_peak)})")
    elif row.mouth_voice is not None and row.mouth_voice < MOUTH_VOICE_MIN:
        out.append(f"lips not following the voice (mouth-voice {row.mouth_voice:.2f} < {MOUTH_VOICE_MIN:g})")
    if row.audio_peak is not None and row.audio_peak >= CLIPPED_PEAK:
        out.append(f"clipped audio (peak {_dbfs(row.audio_peak)})")
    return out


def _dbfs(peak: float) -> str:
    return "-inf dBFS" if peak <= 0 else f"{20 * math.log10(peak):.1f} dBFS"


# ------------------------------------------------------------------ report

COLUMNS = ("id", "status", "flags", "error", "audio_seconds", "frames", "seconds", "realtime_factor",
           "mouth_voice", "gesture_energy", "audio_peak", "warnings")


def ordered(rows: Iterable[QcRow]) -> list[QcRow]:
    """Flagged rows first, each group in the order given."""
    rows = list(rows)
    return [r for r in rows if flags(r)] + [r for r in rows if not flags(r)]


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "; ".join(str(v) for v in value)
    return str(value)


def _cells(row: QcRow) -> list[str]:
    values = {f.name: getattr(row, f.name) for f in fields(row)}
    values["flags"] = flags(row)
    return [_cell(values[name]) for name in COLUMNS]


_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
"""What makes a spreadsheet read a cell as a formula (OWASP's CSV injection list)."""


def _inert(cell: str) -> str:
    """A text cell a spreadsheet shows as text: one starting like a formula gets a leading
    apostrophe (numbers are written as they are: '-0.5' stays a number)."""
    if cell.startswith(_FORMULA_STARTS):
        try:
            float(cell)
            return cell
        except ValueError:
            return "'" + cell
    return cell


def report_csv(rows: Sequence[QcRow]) -> str:
    """The report as CSV text, a header row and one row per line, flagged first; text that
    a spreadsheet would run as a formula (an id '=HYPERLINK(...)') is written inert."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in ordered(rows):
        writer.writerow([_inert(cell) for cell in _cells(row)])
    return buffer.getvalue()


_STYLE = """body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse;font-size:14px}th,td{border:1px solid #ccc;padding:3px 7px;text-align:left;vertical-align:top}
th{background:#eee;position:sticky;top:0}tr.flagged td{background:#fff3e0}tr.failed td{background:#fde7e7}
td.num{text-align:right;font-variant-numeric:tabular-nums}"""
_NUM_TD = '<td class="num">'
_NUMERIC = {"audio_seconds", "frames", "seconds", "realtime_factor", "mouth_voice", "gesture_energy", "audio_peak"}


def report_html(rows: Sequence[QcRow], title: str = "DiffSHEG QC report") -> str:
    """The report as one self-contained HTML page (inline style, no scripts), every text escaped."""
    rows = list(rows)
    n_flagged = sum(1 for r in rows if flags(r))
    counts = ", ".join(f"{sum(1 for r in rows if r.status == s)} {s}" for s in STATUSES)
    head = "".join(f"<th>{html.escape(name)}</th>" for name in COLUMNS)
    body = []
    for row in ordered(rows):
        kind = "failed" if row.status == "failed" else "flagged" if flags(row) else "ok"
        cells = "".join((_NUM_TD if name in _NUMERIC else "<td>") + html.escape(text) + "</td>"
                        for name, text in zip(COLUMNS, _cells(row)))
        body.append(f"<tr class=\"{kind}\">{cells}</tr>")
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>\n"
            f"<h1>{html.escape(title)}</h1>\n<p>{len(rows)} lines: {counts}; {n_flagged} flagged, listed first.</p>\n"
            f"<table><thead><tr>{head}</tr></thead><tbody>\n" + "\n".join(body) +
            "\n</tbody></table></body></html>\n")


def write_report(rows: Iterable[QcRow], out_dir) -> tuple[Path, Path]:
    """Write `out_dir/report.csv` and `out_dir/report.html` (each atomically); their paths."""
    rows = list(rows)
    out_dir = Path(out_dir)
    csv_path, html_path = out_dir / "report.csv", out_dir / "report.html"
    with atomic_write(csv_path, "w", encoding="utf-8", newline="") as fh:
        fh.write(report_csv(rows))
    with atomic_write(html_path, "w", encoding="utf-8") as fh:
        fh.write(report_html(rows))
    return csv_path, html_path
