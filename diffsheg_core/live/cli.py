"""`python -m diffsheg_core live`: speech from a microphone, a file at real time or a socket,
motion out over VMC as it is made, the performance recorded on Ctrl-C or at the end. A line
typed (or piped by an agent) on standard input changes the emotion while it runs: `sad`,
`happy=0.5`, `neutral`."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from ..errors import DiffshegError

DEFAULT_OSC_PORT = 39539  # VMC's marionette port


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..settings import add_arguments
    from .engine import HOPS, LOOKAHEADS, LiveConfig

    p = sub.add_parser("live", help="generate live from a microphone, a file played at real time or a socket",
                       description="Live: speech in as it arrives, motion out within a fraction of a second. "
                                   "Ctrl-C ends the session and writes the recording. While it runs, a line on "
                                   "standard input (sad, happy=0.5, neutral) changes the emotion.")
    p.add_argument("--source", default="mic",
                   help="mic, mic:DEVICE (name or index), a speech file played at real time, or "
                        "tcp://HOST:PORT[?rate=16000] taking raw 16-bit mono PCM (default: mic)")
    p.add_argument("--speed", type=float, default=1.0, help="play a file source this many times real time (demos)")
    p.add_argument("--osc", metavar="HOST:PORT",
                   help=f"send the motion over the VMC protocol (OSC/UDP) to HOST:PORT (VSeeFace, Warudo, VNyan "
                        f"listen on {DEFAULT_OSC_PORT})")
    p.add_argument("--record", metavar="OUT.npz",
                   help="write the performance as a Motion .npz, with the audio beside it as OUT.wav")
    p.add_argument("--latency-log", metavar="LOG.json",
                   help="write each shown frame's time in the audio and its latency (s) as JSON")
    p.add_argument("--hop", type=int,
                   help=f"new frames per window, {HOPS[0]}-{HOPS[1]}: fewer, lower latency and more compute "
                        f"(default {LiveConfig.hop})")
    p.add_argument("--lookahead", type=int,
                   help=f"frames of audio a window waits for past its new frames, {LOOKAHEADS[0]}-{LOOKAHEADS[1]} "
                        f"(default {LiveConfig.lookahead})")
    add_arguments(p)


def run(args: argparse.Namespace) -> int:
    from ..checkpoints import files_read
    from ..files import check_outputs
    from ..settings import from_arguments
    from .engine import LiveConfig
    from .session import LiveSession, latency_summary
    from .sources import FileSource, TcpSource, open_source

    record = Path(args.record) if args.record else None
    audio_out = record.with_suffix(".wav") if record else None
    if record is not None and record.suffix != ".npz":
        raise DiffshegError(f"--record {record}: the recording is a Motion .npz; name it e.g. take.npz")
    source = open_source(args.source, speed=args.speed)
    if args.speed != 1.0 and not isinstance(source, FileSource):
        raise DiffshegError(f"--speed plays a speech file faster than real time; {source.description} is "
                            "live and comes as fast as it is spoken: leave --speed out")
    check_outputs([record, audio_out, args.latency_log], inputs=[getattr(source, "path", None), *files_read(args.model)])
    settings = from_arguments(args)
    live = LiveConfig.chosen(args.hop, args.lookahead)
    session = LiveSession(source, settings, live)
    sender = _vmc_sender(args.osc, session) if args.osc else None
    emotion = ", ".join(f"{k} {v:g}" for k, v in (settings.emotion or {}).items()) or "neutral"

    def started() -> None:
        """Say what runs once the source has started: a socket's port is then known (port 0)."""
        where = (f"listening on {source.description} for raw 16-bit mono PCM" if isinstance(source, TcpSource)
                 else f"live from {source.description}")
        print(f"{where}, model {session.bundle.model_id}, hop {live.hop} frames, lookahead {live.lookahead}, "
              f"{'upper body only' if session.legs is None else 'whole body'}, emotion {emotion}"
              f"{f', VMC to {args.osc}' if sender else ''}; Ctrl-C ends, a line (sad, happy=0.5, neutral) "
              "changes the emotion", file=sys.stderr, flush=True)

    threading.Thread(target=_emotions_from, args=(sys.stdin, session), name="diffsheg-live-emotion",
                     daemon=True).start()

    def show(frame) -> None:
        if sender is not None:
            sender.send(frame.rotations, frame.face, frame.time, frame.root_translation)

    try:
        result = session.run_to_end(show, on_status=lambda line: print(f"\r{line:<90}", end="", file=sys.stderr),
                                    on_start=started)
    finally:
        if sender is not None:
            sender.close()
    print(file=sys.stderr)
    summary = latency_summary(result.latencies)
    shown = (f"latency p50 {summary['p50']:.3f} s, p95 {summary['p95']:.3f} s, max {summary['max']:.3f} s"
             if result.latencies else "no frame was shown")
    pace = f" at {args.speed:g}x" if args.speed != 1.0 else ""
    compute = "" if result.load is None else f"; compute {result.load:.2f} s per s of speech{pace}"  # None: too little
    print(f"{result.motion.n_frames} frames ({result.audio.duration:.1f} s of audio); {shown}{compute}"
          + (f"; {result.underrun_seconds:.1f} s without audio filled with silence" if result.underrun_seconds else "")
          + (f"; {result.dropped_seconds:.1f} s of audio dropped (it came faster than real time)"
             if result.dropped_seconds else ""))
    if record is not None and result.motion.n_frames:
        _write_recording(result, record, audio_out)
    elif record is not None:
        print(f"no audio came: {record} not written", file=sys.stderr)
    if args.latency_log:
        _write_latency_log(result.latencies, summary, Path(args.latency_log))
    if result.error:
        print(f"error: {result.error}", file=sys.stderr)
        return 1
    return 0


def _emotions_from(lines, session) -> None:
    """Each line of `lines` (standard input) an emotion for the session from then on; a bad
    one is said and changes nothing. Ends with the input."""
    try:
        for line in lines:
            if line.strip():
                try:
                    session.set_emotion(line.strip())
                    print(f"\nemotion: {line.strip()}", file=sys.stderr)
                except DiffshegError as exc:
                    print(f"\nignored {line.strip()!r}, the emotion stays as it was: {exc}", file=sys.stderr)
    except (OSError, ValueError):  # no standard input to read (closed, detached)
        return


def _vmc_sender(address: str, session):
    from .vmc import VmcSender, parse_address

    host, port = parse_address(address)
    return VmcSender(host, port, session.bundle.rig_layout, legs=session.legs is not None)


def _write_recording(result, record: Path, audio_out: Path) -> None:
    import soundfile as sf
    from dataclasses import replace

    from ..files import atomic_write

    with atomic_write(audio_out) as fh:
        sf.write(fh, result.audio.samples, result.audio.sample_rate, format="WAV", subtype="FLOAT")
    motion = replace(result.motion, meta={**result.motion.meta, "audio_file": str(audio_out)})
    motion.save_npz(record)
    print(f"wrote {record} and {audio_out}")


def _write_latency_log(latencies, summary: dict, path: Path) -> None:
    from ..files import atomic_write

    with atomic_write(path, "w", encoding="utf-8") as fh:
        json.dump({"frames": [{"t": round(t, 6), "latency": round(lat, 6)} for t, lat in latencies],
                   "summary": summary}, fh)
    print(f"wrote {path}")
