"""Headless generation (and rendering) for one audio file or a folder of them.

    blender -b scene.blend -P batch_render.py -- --audio talk.wav [--armature NAME]
        [--face MESH ...] [--preset beat] [--output talk.mp4] [--no-render] [--save out.blend]
    python batch_render.py [--blend scene.blend] --audio talks/ --output renders/

With a folder, every audio file in it is done in turn from the same starting scene;
--output and --save are then folders. Rendering uses the scene's engine and settings,
writes a video with the audio muxed in (unless --no-render).

With no --audio and no .blend, it runs the demo: the package's own sample speech keyed
onto a demo speaker built from the embedded BEAT skeleton, saved to out/demo.blend and
rendered (Workbench, low resolution) to out/demo.mp4.

Progress goes to stdout; on failure a one-line message goes to stderr, exit code 1.

From the installed add-on: the extension zip ships this script beside the add-on, with
diffsheg_core under lib/, so it runs without a checkout:

    blender -b scene.blend -P <extension folder>/batch_render.py -- --audio talk.wav --preset rigify

where the extension folder is <Blender user config>/extensions/user_default/diffsheg
(Linux: ~/.config/blender/5.0/extensions/user_default/diffsheg; Windows:
%APPDATA%\\Blender Foundation\\Blender\\5.0\\extensions\\user_default\\diffsheg; macOS:
~/Library/Application Support/Blender/5.0/extensions/user_default/diffsheg). Blender
prints it with:

    blender -b --python-expr "import bpy; print(bpy.utils.user_resource('EXTENSIONS', path='user_default/diffsheg'))"

Inside the installed add-on, the default output folder is ./out (the working directory);
in a checkout it is out/ in the checkout.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _find_studio():
    """studio.py, beside this file in a checkout and in the installed add-on (build_addon.py
    ships it there), imported as `studio` (the name Ray's workers import it by); importing it
    makes diffsheg_core and the add-on importable (studio.ADDON: the add-on's package name)."""
    path = HERE / "studio.py"
    loaded = sys.modules.get("studio")
    if loaded is not None and Path(getattr(loaded, "__file__", "") or "").resolve() == path:
        return loaded
    if not path.is_file():
        raise SystemExit(f"batch_render: error: {HERE} is neither a checkout of the project nor the installed "
                         "add-on (no studio.py beside this script)")
    spec = importlib.util.spec_from_file_location("studio", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["studio"] = module
    try:
        spec.loader.exec_module(module)
    except ImportError as exc:
        del sys.modules["studio"]
        raise SystemExit(f"batch_render: error: {exc}") from None
    return module


import bpy  # noqa: E402

studio = _find_studio()
ADDON = studio.ADDON
OUT = HERE / "out" if studio.CHECKOUT else Path.cwd() / "out"


def addon(module: str):
    """A module of the add-on: addon("scene.bake") is blender_addon.scene.bake in a checkout."""
    return importlib.import_module(f"{ADDON}.{module}")


AUDIO_SUFFIXES = {".wav", ".flac", ".ogg", ".mp3", ".m4a", ".aiff", ".aif"}


def parse_args(argv: list[str]) -> argparse.Namespace:
    from diffsheg_core.settings import add_arguments

    p = argparse.ArgumentParser(prog="batch_render.py", description=__doc__.split("\n\n")[0])
    p.set_defaults(stems={}, reports=[])  # stem -> how many inputs have it (a folder); the reports written
    p.add_argument("--audio", help="an audio file or a folder of audio files")
    p.add_argument("--blend", help="scene to open (python mode; with blender, pass it before -P)")
    p.add_argument("--armature", help="armature object name (default: the scene's only armature)")
    p.add_argument("--face", nargs="*", default=None, help="face mesh object name(s) (default: meshes with shape keys)")
    p.add_argument("--preset", default="auto",
                   help="rig preset name or .json path (default: auto, the preset whose bone names the rig has)")
    p.add_argument("--output", help="video file (one audio) or folder (several); default out/<audio>.mp4")
    p.add_argument("--no-render", action="store_true", help="generate and key only")
    p.add_argument("--save", help=".blend to save (a folder when several audio files)")
    p.add_argument("--report", metavar="FILE", help="write each take's report (model, style, Actions, warnings) "
                                                    "to FILE too; the saved .blend holds it as the Text "
                                                    "'DiffSHEG report'")
    add_arguments(p)  # every generation option, as the CLI has them
    k = p.add_argument_group("keying")
    k.add_argument("--start-frame", type=int, default=None,
                   help="frame of the first key and the sound strip (default: the scene's start frame)")
    k.add_argument("--smoothing", type=float, default=0.0, help="Gaussian smoothing in scene frames (0 = none)")
    k.add_argument("--max-error", type=float, default=1.0, metavar="DEGREES",
                   help="largest angle between a bone's keys and the generated rotation on any frame "
                        "(default %(default)s degrees): keys go on the motion's turning points")
    k.add_argument("--max-face-error", type=float, default=0.02,
                   help="largest difference of a shape key's keys from the generated weight (default %(default)s)")
    k.add_argument("--every-frame", action="store_true",
                   help="key every frame on every channel instead (baked curves for game export)")
    k.add_argument("--no-sound", action="store_true", help="add no sound strip")
    k.add_argument("--keep-frame-range", action="store_true", help="leave the scene's frame range as it is")
    r = p.add_argument_group("regenerating a range (of the take the scene's character plays; its audio is used)")
    r.add_argument("--regenerate", metavar="START-END", type=frame_range,
                   help="generate scene frames START to END anew as a new take, with the generation options "
                        "given (another --seed, --style, ...); everything outside stays as it is")
    r.add_argument("--hold-face", action="store_true", help="with --regenerate: keep the take's face inside the range "
                                                            "(only the gestures change)")
    m = p.add_argument_group("dialogue libraries (a manifest of lines, run on Ray; README: studios)")
    m.add_argument("--manifest", help="CSV or JSON Lines, one row per line (id, audio, blend, armature, face, "
                                      "preset, generation settings, outputs); the options above are the "
                                      "defaults a row overrides; --output is the output folder")
    m.add_argument("--outputs", default="blend",
                   help="outputs of a line whose row names none, ';'-separated from blend, fbx_unreal, fbx_unity, "
                        "glb, npz, arkit_json, csv, mp4 (default %(default)s)")
    m.add_argument("--ray-address", help="the Ray cluster to run on (default $RAY_ADDRESS, else Ray on this "
                                         "machine with a worker per core)")
    m.add_argument("--workers", type=int, help="workers of the Ray started on this machine (default: one per core)")
    m.add_argument("--check", action="store_true", help="check the manifest, list every bad row, run nothing")
    return p.parse_args(argv)


def frame_range(text: str) -> tuple[int, int]:
    """'START-END' scene frames (START <= END; either may be negative: '-10--1')."""
    import re

    match = re.fullmatch(r"\s*(-?\d+)\s*-\s*(-?\d+)\s*", text)
    if match is None or int(match.group(1)) > int(match.group(2)):
        raise argparse.ArgumentTypeError(f"expected START-END frames with START <= END (e.g. 120-240), got {text!r}")
    return int(match.group(1)), int(match.group(2))


def script_args() -> list[str]:
    """Arguments after '--' under Blender; all arguments under plain Python."""
    argv = sys.argv
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return [] if Path(argv[0]).name.lower().startswith("blender") else argv[1:]


def audio_files(source: str) -> list[Path]:
    from diffsheg_core.errors import AudioError
    from diffsheg_core.files import resolve_path

    path = resolve_path(source, "audio", AudioError)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in AUDIO_SUFFIXES)
        if not files:
            raise AudioError(f"{path}: no audio files ({', '.join(sorted(AUDIO_SUFFIXES))}) in this folder")
        return files
    if not path.is_file():
        raise AudioError(f"{path}: no such audio file or folder")
    return [path]


def find_targets(args):
    return studio.find_targets(bpy.context.scene, args.armature, args.face)


def printer(label: str):
    last = [-1]

    def report(p) -> None:
        percent = int(100 * p.fraction)
        if percent // 10 != last[0] // 10:
            last[0] = percent
            print(f"{label}: generating {percent}%", flush=True)

    return report


def output_for(args, audio: Path, several: bool, suffix: str, explicit: str | None) -> Path:
    if explicit and not several:
        return Path(explicit).expanduser().resolve()
    folder = Path(explicit).expanduser().resolve() if explicit else OUT
    return folder / f"{output_stem(audio, args.stems)}{suffix}"


def output_stem(audio: Path, stems: dict[str, int]) -> str:
    """The outputs' name for `audio`: its stem, or stem_extension where another input of the
    folder has the same stem (talk.wav and talk.flac give talk_wav and talk_flac)."""
    return f"{audio.stem}_{audio.suffix.lstrip('.').lower()}" if stems.get(audio.stem, 0) > 1 else audio.stem


def bake_options(args, scene, armature, faces):
    """The keying options of the command line (those of the panel's lower half)."""
    return addon("scene.bake").keying_options(
        scene, armature, faces, args.preset, args.start_frame, every_frame=args.every_frame,
        max_error=args.max_error, max_face_error=args.max_face_error, smoothing=args.smoothing,
        add_sound=not args.no_sound, set_frame_range=not args.keep_frame_range)


def run_one(args, audio: Path, label: str, several: bool) -> None:
    """Generate the whole clip of `audio` as a new take, then save and render as asked."""
    from diffsheg_core.settings import from_arguments

    settings = from_arguments(args)  # every generation option checked before anything else
    scene = bpy.context.scene
    armature, faces = find_targets(args)
    check_outputs(args, scene, audio, several)
    request = addon("features.generate").Request(audio, bake_options(args, scene, armature, faces), settings)
    generate_and_write(args, scene, request, label, several)


def run_regenerate(args) -> None:
    """Generate scene frames args.regenerate of the take playing anew, as a new take."""
    from diffsheg_core.audio import check_audio_path
    from diffsheg_core.errors import DiffshegError
    from diffsheg_core.settings import from_arguments

    settings = from_arguments(args)
    scene = bpy.context.scene
    armature, faces = find_targets(args)
    options = bake_options(args, scene, armature, faces)
    first, last = args.regenerate
    span = addon("features.regenerate").prepare_range(scene, options, first, last)
    if not span.source.audio_path:
        raise DiffshegError(f"take '{span.take}' was made without an audio file: it cannot be regenerated")
    audio = check_audio_path(span.source.audio_path)
    check_outputs(args, scene, audio, several=False)
    request = addon("features.generate").Request(audio, options, settings, hold_face=args.hold_face, range=span)
    generate_and_write(args, scene, request, f"{span.take} frames {first}-{last}", several=False)


def check_outputs(args, scene, audio: Path, several: bool) -> None:
    """Refuse, before anything runs, outputs that cannot be written or would overwrite an input."""
    from diffsheg_core.checkpoints import files_read
    from diffsheg_core.errors import DiffshegError
    from diffsheg_core.files import check_outputs as check

    if not args.no_render and scene.camera is None:
        raise DiffshegError("the scene has no camera to render with: add one, or pass --no-render")
    check([output_for(args, audio, several, ".blend", args.save) if args.save else None,
           None if args.no_render else output_for(args, audio, several, ".mp4", args.output),
           Path(args.report).expanduser() if args.report and not args.reports else None],
          inputs=[audio, *files_read(args.model), bpy.data.filepath or None])


def generate_and_write(args, scene, request, label: str, several: bool) -> None:
    """Run `request`, key it, report, then save and render as the arguments ask."""
    report = addon("scene.report")
    started = time.perf_counter()
    motion = request.run(printer(label), None)
    result = request.apply(scene, motion)
    seconds = time.perf_counter() - started
    meta = request.made_with(motion)
    details = report.report_details(result, seconds, report.model_label(meta), meta)
    report.write_report(details)  # the Text "DiffSHEG report", saved with the .blend
    if args.report:
        write_text_report(args, details, several, label)
    print(one_line(f"{label}: {report.report_line(result, seconds)}"), flush=True)
    audio = request.path
    if args.save:
        path = output_for(args, audio, several, ".blend", args.save)
        path.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
        print(f"{label}: saved {path}", flush=True)
    if not args.no_render:
        path = output_for(args, audio, several, ".mp4", args.output)
        path.parent.mkdir(parents=True, exist_ok=True)
        addon("scene.demo").set_video_output(scene)
        scene.render.filepath = str(path)
        print(f"{label}: rendering frames {scene.frame_start}-{scene.frame_end} with "
              f"{scene.render.engine} to {path}", flush=True)
        bpy.ops.render.render(animation=True)
        print(f"{label}: wrote {path}", flush=True)


def one_line(text: str, width: int = 120) -> str:
    """`text` cut to `width` characters, as a console line."""
    return text if len(text) <= width else text[: width - 3] + "..."


def write_text_report(args, details: str, several: bool, label: str) -> None:
    """The reports of this run so far into args.report (each file of a folder under its label)."""
    from diffsheg_core.files import atomic_write

    args.reports.append(f"== {label}\n{details}" if several else details)
    with atomic_write(Path(args.report).expanduser(), "w", encoding="utf-8") as fh:
        fh.write("\n".join(args.reports))


def run_manifest(args) -> int:
    """The lines of args.manifest on Ray (studio.py); the exit code."""
    from diffsheg_core.errors import DiffshegError

    if args.audio or args.save or args.regenerate or args.hold_face:
        raise DiffshegError("--manifest names the audio and outputs of every line: leave out --audio, --save, "
                            "--regenerate and --hold-face (--output is the output folder)")
    defaults = vars(args)  # the options are the defaults of every row (manifest.read_manifest)
    out = Path(args.output).expanduser().resolve() if args.output else OUT / Path(args.manifest).stem
    return studio.run_manifest(Path(args.manifest).expanduser().resolve(), out, defaults,
                                        address=args.ray_address, workers=args.workers, check_only=args.check)


def run_demo(args) -> None:
    from diffsheg_core.audio import SAMPLE_SPEECH

    demo = addon("scene.demo")
    build_beat_armature, build_face, setup_preview = demo.build_beat_armature, demo.build_face, demo.setup_preview

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = 24, 1.0
    armature = build_beat_armature()
    build_face(armature)
    setup_preview(scene, armature)
    args.audio, args.armature, args.preset = str(SAMPLE_SPEECH), armature.name, "beat"
    args.output = args.output or str(OUT / "demo.mp4")
    args.save = args.save or str(OUT / "demo.blend")
    run_one(args, SAMPLE_SPEECH, "demo", several=False)


def main(argv: list[str]) -> int:
    from diffsheg_core.errors import DiffshegError

    args = parse_args(argv)
    try:
        if args.manifest:
            return run_manifest(args)
        if args.blend:
            bpy.ops.wm.open_mainfile(filepath=str(Path(args.blend).expanduser().resolve()))
        if args.hold_face and args.regenerate is None:
            raise DiffshegError("--hold-face goes with --regenerate START-END (a whole new take has a face of its "
                                "own: for the same face with other gestures, pass --face-seed)")
        if args.regenerate is not None:
            if args.audio is not None or not bpy.data.filepath:
                raise DiffshegError("--regenerate works on a .blend holding a take (--blend, or blender -b "
                                    "scene.blend) and uses the take's own audio: leave out --audio")
            run_regenerate(args)
            return 0
        if args.audio is None:
            if bpy.data.filepath:
                raise DiffshegError("no --audio given: pass an audio file or folder")
            run_demo(args)
            return 0
        files = audio_files(args.audio)
        args.stems = {stem: [f.stem for f in files].count(stem) for stem in {f.stem for f in files}}
        with tempfile.TemporaryDirectory() as tmp:
            start = Path(tmp) / "start.blend"
            bpy.ops.wm.save_as_mainfile(filepath=str(start), copy=True)
            for i, audio in enumerate(files):
                if i:
                    bpy.ops.wm.open_mainfile(filepath=str(start))  # every file starts from the same scene
                run_one(args, audio, f"[{i + 1}/{len(files)}] {audio.name}", several=len(files) > 1)
    except DiffshegError as exc:
        print(f"batch_render: error: {exc}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:  # Ctrl-C: the outputs already finished stay, the one under way is not written
        print("batch_render: cancelled", file=sys.stderr, flush=True)
        return 130
    except Exception as exc:  # one line, not a traceback
        print(f"batch_render: unexpected {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(script_args()))
