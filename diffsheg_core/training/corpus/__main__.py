"""`python -m diffsheg_core.training.corpus build --out DIR --hours H`: build or extend the corpus.
`python -m diffsheg_core.training.corpus teach --audio WAV --textgrid TG --out NPZ`: teacher motion
for a recording with forced-aligned phones (for evaluating the teacher)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ...errors import DiffshegError


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core.training.corpus", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="synthesise speech and teacher motion until --hours exist")
    b.add_argument("--out", type=Path, required=True, help="corpus folder (created; reruns resume)")
    b.add_argument("--hours", type=float, required=True, help="total hours of speech wanted")
    b.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="worker processes (default: one per CPU core)")
    b.add_argument("--seed", type=int, default=0, help="corpus seed (default 0)")
    b.add_argument("--engines", default="espeak,festival,flite",
                   help="synthesisers to use, comma-separated (default espeak,festival,flite; "
                        "each must be installed)")
    b.add_argument("--text", type=Path, nargs="*", help="text files instead of Debian's fortunes")
    b.add_argument("--languages", default="",
                   help="other languages espeak-ng speaks into the corpus, comma-separated codes or "
                        "'all' (see training/corpus/languages.py); with --language-hours")
    b.add_argument("--language-hours", type=float, default=0.0,
                   help="hours of speech in those languages, beside --hours of English")
    b.add_argument("--mocap", type=Path, help="BEAT BVH take for gestures (default: shared/data/beat)")
    t = sub.add_parser("teach", help="teacher motion for a recording and its TextGrid")
    t.add_argument("--audio", type=Path, required=True)
    t.add_argument("--textgrid", type=Path, required=True)
    t.add_argument("--out", type=Path, required=True, help="motion .npz (Motion format)")
    t.add_argument("--seed", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "build":
            from .build import BuildConfig, build
            from .languages import check_languages

            languages = check_languages([c.strip() for c in args.languages.split(",") if c.strip()])
            config = BuildConfig(out=args.out, hours=args.hours, jobs=args.jobs, seed=args.seed,
                                 engines=tuple(e.strip() for e in args.engines.split(",") if e.strip()),
                                 text_files=tuple(args.text) if args.text else None, mocap=args.mocap,
                                 languages=languages, language_hours=args.language_hours)
            s = build(config)
            print(f"corpus {args.out}: {s['utterances']} utterances, {s['hours']:.3f} h of speech, "
                  f"{s['size_bytes'] / 1e6:.1f} MB; this run made {s['speech_seconds_this_run']:.0f} s "
                  f"of speech in {s['seconds_this_run']:.1f} s "
                  f"({s['speech_seconds_per_second']:.2f} s of speech per second)"
                  + (f"; {s['failed']} utterances failed (see manifest.jsonl)" if s["failed"] else ""))
        else:
            from .teacher import teach_files

            path = teach_files(args.audio, args.textgrid, seed=args.seed).save_npz(args.out)
            print(f"teacher motion written to {path}")
    except DiffshegError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
