"""Dialogue libraries at studio scale: the lines of a manifest run as Ray tasks.

`run_manifest` (the driver: batch_render.py --manifest) checks the whole manifest first
(diffsheg_core.manifest lists every bad row before anything runs), skips the lines its
ledger records as done with the same inputs and settings, and sends every other line to
Ray as one task: on a cluster given by address (or $RAY_ADDRESS), else on a Ray started
here (the embedded default: one worker per core). A task (`process_line`, in a worker
process with bpy) generates the line, keys it as a take into the character, writes every
output asked for atomically, and takes the take back out, so the next line on that
worker starts from the same character: each worker opens a character file and loads a
model once, not once per line. A worker that dies is retried by Ray and its line redone
from scratch; a line that fails (bad audio, a character without a camera for a video)
fails alone. A task writes its line's outputs as hidden staged files beside their final
names (in the output folder itself, so the relative paths a .blend or FBX saves resolve
from there); the driver records the line as done and then renames them into place
(diffsheg_core.ledger.Ledger), so a driver or worker killed at any moment leaves under
the outputs' names only outputs of lines recorded done, and the next run finishes or
removes what it left. An output that cannot be put in place fails its line alone. The
driver writes the QC report (diffsheg_core.qc) at the end.

It sits beside batch_render.py, outside the add-on: at the root of a checkout, and in the
installed add-on beside its __init__.py (build_addon.py ships both there). On import it
makes diffsheg_core and the add-on importable from either place (`_find_packages`); Ray's
workers import it by its name, `studio`, with WORKER_PATH on their PYTHONPATH.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _find_packages() -> tuple[str, list[str]]:
    """Make diffsheg_core and the add-on importable, from a checkout (blender_addon/ beside
    this file) or from inside the installed add-on (this file beside its __init__.py, the
    core under lib/: build_addon.py ships it there). Returns the add-on's package name and
    the folders a Ray worker needs on its path to import this module (by its name, studio)."""
    if (HERE / "blender_addon" / "__init__.py").is_file():  # a checkout
        if str(HERE) not in sys.path:
            sys.path.insert(0, str(HERE))
        return "blender_addon", [str(HERE)]
    if (HERE / "__init__.py").is_file() and (HERE / "lib" / "diffsheg_core").is_dir():
        if str(HERE / "lib") not in sys.path:
            sys.path.insert(0, str(HERE / "lib"))
        # the extension's wheels (Blender adds them at start-up; a bare `python` may not)
        wheels = HERE.parents[1] / ".local" / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" \
            / "site-packages"
        if wheels.is_dir() and str(wheels) not in sys.path:
            sys.path.append(str(wheels))
        paths = [str(HERE), str(HERE / "lib")]
        init = HERE / "__init__.py"
        for name, module in list(sys.modules.items()):  # the enabled add-on (bl_ext.user_default.diffsheg)
            file = getattr(module, "__file__", None)
            if file and Path(file).resolve() == init:
                return name, paths
        name = "diffsheg_batch_addon"  # not enabled: import the add-on's package without registering it
        spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[str(HERE)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        return name, paths
    raise ImportError(f"{HERE} is neither a checkout of the project nor the installed add-on (no "
                      "blender_addon/ beside studio.py, nor lib/diffsheg_core)")


ADDON, WORKER_PATH = _find_packages()
CHECKOUT = ADDON == "blender_addon"


def addon(module: str):
    """A module of the add-on: addon("scene.bake") is blender_addon.scene.bake in a checkout."""
    return importlib.import_module(f"{ADDON}.{module}")


from diffsheg_core.errors import DiffshegError  # noqa: E402  (needs lib/ on sys.path)

RETRIES = 3  # times Ray runs a line again whose worker died
LOOPBACK_ONLY = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's switch for a single-machine Ray on 127.0.0.1 (its default on Windows and macOS), "0"."""


# ---------------------------------------------------------------- the worker's side

_opened: dict = {"blend": None}   # the character file this worker process has open
_models: dict = {}                # model path (None: bundled) -> loaded ModelBundle


def process_line(line, out_dir: str) -> dict:
    """Generate one manifest line in this process and write its outputs, keyed onto its
    character first when it names one (a line without a .blend writes the motion's own
    files: npz, arkit_json, csv), staged beside their final names in `out_dir` under a name
    of this attempt's own; returns what the driver records and reports (the outputs' final
    paths, the attempt's name). Raises DiffshegError for a line that cannot be done."""
    import diffsheg_core
    from diffsheg_core.ledger import stage_name, staged_path
    from diffsheg_core.manifest import output_name

    started = time.perf_counter()
    generate = lambda: diffsheg_core.generate(  # noqa: E731
        str(line.audio), settings=replace(line.settings, model=_model(line.settings.model)))
    staged = stage_name()
    finals = {kind: Path(out_dir) / output_name(line.id, kind) for kind in line.outputs}
    paths = {kind: staged_path(out_dir, staged, final.name) for kind, final in finals.items()}
    try:
        if line.blend is None:
            motion = generate()
            write_outputs(paths, None, None, [], motion)
            frames, keys = motion.n_frames, 0
        else:
            motion, frames, keys = _key_and_write(line, generate, paths)
    except BaseException:
        for path in paths.values():
            path.unlink(missing_ok=True)
        raise
    return {"outputs": [str(p) for p in finals.values()], "staged": staged,
            "frames": frames, "keys": keys, "worker": os.getpid(),
            "qc": _measure(line, motion, time.perf_counter() - started)}


def _key_and_write(line, generate, paths: dict) -> tuple:
    """Open the line's character, key the generated motion into it as a take, write the
    outputs, and take the take back out; (motion, frames, keys)."""
    import bpy

    bake = addon("scene.bake")

    _open_character(line.blend)
    scene = bpy.context.scene
    armature, faces = find_targets(scene, line.armature, line.face)
    options = bake.keying_options(scene, armature, faces, line.preset, line.start_frame, every_frame=line.every_frame,
                             max_error=line.max_error, max_face_error=line.max_face_error)
    motion = generate()
    undo: list = []
    try:
        result = bake.bake_motion(scene, motion, str(line.audio), options, undo)
        write_outputs(paths, scene, armature, faces, motion)
    finally:
        for step in reversed(undo):  # the character as it was, for the next line
            step()
    return motion, result.n_frames, result.n_keys


def _open_character(blend: Path) -> None:
    """Open the line's character file, unless it is the one this worker has open."""
    import bpy

    key = str(blend)
    if _opened["blend"] == key:
        return
    bpy.ops.wm.open_mainfile(filepath=key)
    _opened["blend"] = key


def _model(model):
    """The loaded model of `model` (a path, or None for the bundled one), once per worker."""
    from diffsheg_core.checkpoints import ModelBundle, load_model

    if isinstance(model, ModelBundle):
        return model
    key = str(model) if model is not None else None
    if key not in _models:
        _models[key] = load_model(model)
    return _models[key]


def find_targets(scene, armature_name: str | None, face_names) -> tuple:
    """The named armature (or the scene's only one) and face meshes (or every mesh with
    shape keys); DiffshegError naming what is missing."""
    objects = scene.objects
    if armature_name:
        armature = objects.get(armature_name)
        if armature is None or armature.type != "ARMATURE":
            raise DiffshegError(f"no armature named '{armature_name}' in the scene")
    else:
        armatures = [o for o in objects if o.type == "ARMATURE"]
        if len(armatures) > 1:
            raise DiffshegError(f"several armatures ({', '.join(o.name for o in armatures)}): name one "
                                "(--armature NAME, or the manifest's 'armature' column)")
        armature = armatures[0] if armatures else None
    if face_names is None:
        return armature, [o for o in objects if o.type == "MESH" and o.data.shape_keys is not None]
    faces = []
    for name in face_names:
        ob = objects.get(name)
        if ob is None or ob.type != "MESH":
            raise DiffshegError(f"no mesh named '{name}' in the scene")
        faces.append(ob)
    return armature, faces


def write_outputs(paths: dict[str, Path], scene, armature, faces, motion) -> None:
    """Each output of `paths` (kind -> where), written whole or not at all."""
    from diffsheg_core.motion import write_arkit_json, write_livelink_csv

    exports = addon("features.exports")

    writers = {
        "npz": lambda p: motion.save_npz(p),
        "arkit_json": lambda p: write_arkit_json(motion, p),
        "csv": lambda p: write_livelink_csv(motion, p),
        "fbx_unreal": lambda p: exports.export_fbx(p, armature, faces, "unreal"),
        "fbx_unity": lambda p: exports.export_fbx(p, armature, faces, "unity"),
        "glb": lambda p: exports.export_glb(p, armature, faces),
        "blend": lambda p: _save_blend(p),
        "mp4": lambda p: _render_video(scene, p),
    }
    for kind, path in paths.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        writers[kind](path)


def _save_blend(path: Path) -> None:
    import bpy

    _replace_when_written(path, lambda tmp: bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True))


def _render_video(scene, path: Path) -> None:
    import bpy

    if scene.camera is None:
        raise DiffshegError("the character's scene has no camera to render the video (mp4) with: add one, "
                            "or leave mp4 out of the line's outputs")
    old = scene.render.filepath

    def render(tmp: Path) -> None:
        addon("scene.demo").set_video_output(scene)
        scene.render.filepath = str(tmp)
        bpy.ops.render.render(animation=True)

    try:
        _replace_when_written(path, render)
    finally:
        scene.render.filepath = old


def _replace_when_written(path: Path, write) -> None:
    """`write(tmp)` to a temporary name beside `path`, then put it in place; no file at
    either name if writing fails."""
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        write(tmp)
        if not tmp.is_file():
            raise DiffshegError(f"{path}: nothing was written")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _measure(line, motion, seconds: float):
    """The line's row of the QC report (diffsheg_core.qc)."""
    from diffsheg_core import qc
    from diffsheg_core.audio import load_audio

    speech = load_audio(str(line.audio))
    return qc.measure(line.id, motion, speech.samples, speech.sample_rate, seconds)


# ---------------------------------------------------------------- the driver

def run_manifest(manifest: Path, out_dir: Path, defaults: dict, address: str | None = None,
                 workers: int | None = None, check_only: bool = False, log=print) -> int:
    """Run every line of `manifest` not done yet on Ray; returns the exit code (0: every
    line done or skipped as done before, 1: some failed; the report says which)."""
    from diffsheg_core import qc
    from diffsheg_core.ledger import Ledger, line_keys
    from diffsheg_core.manifest import read_manifest

    lines = read_manifest(Path(manifest), defaults, presets=["auto", *addon("scene.preset").available_presets()],
                          style_names=_style_names(defaults.get("model")),
                          languages=_face_languages(defaults.get("model")))
    if check_only:
        log(f"{manifest}: {len(lines)} lines, all good")
        return 0
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ledger = Ledger(out_dir)
    for problem in ledger.recover():  # what a killed driver or worker left
        log(problem)
    keys = line_keys(lines)  # each file hashed once
    rows = [qc.QcRow(id=line.id, status="skipped") for line in lines if ledger.done(line, keys[line.id])]
    todo = [line for line in lines if not ledger.done(line, keys[line.id])]
    log(f"{len(lines)} lines: {len(rows)} done before, {len(todo)} to do")
    if todo:
        rows += _run_on_ray(todo, keys, out_dir, ledger, address, workers, log)
        ledger.clean_staging()  # what workers that died left
    qc.write_report(rows, out_dir)
    failed = sum(r.status == "failed" for r in rows)
    log(f"{sum(r.status == 'done' for r in rows)} done, {sum(r.status == 'skipped' for r in rows)} skipped "
        f"(done before), {failed} failed; report: {out_dir / 'report.html'}")
    return 1 if failed else 0


def _style_names(model) -> list[str] | None:
    from diffsheg_core.checkpoints import stored_style_names

    return stored_style_names(model) or None


def _face_languages(model) -> list[str]:
    from diffsheg_core.checkpoints import stored_face_languages

    return stored_face_languages(model)


def _run_on_ray(lines: list, keys: dict, out_dir: Path, ledger, address: str | None, workers: int | None,
                log) -> list:
    """Run `lines` as Ray tasks, recording each done with its key of `keys`; the QC rows of
    their results, in the order they finish."""
    from diffsheg_core import qc

    ray = _start_ray(address, workers)
    task = ray.remote(num_cpus=1, max_retries=RETRIES)(_task)
    try:
        pending = {task.remote(line, str(out_dir)): line for line in lines}
        rows = []
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            line = pending.pop(ready[0])
            try:
                result = ray.get(ready[0])
                ledger.commit(line, result["staged"], result["outputs"], keys[line.id])
            except Exception as exc:  # the line's own error, its worker lost RETRIES times, or an output
                rows.append(qc.QcRow(id=line.id, status="failed", error=_one_line(exc)))  # not put in place
                log(f"[{len(lines) - len(pending)}/{len(lines)}] {line.id}: failed: {rows[-1].error}")
                continue
            rows.append(result["qc"])
            keyed = f"{result['keys']:,} keys, " if result["keys"] else ""
            log(f"[{len(lines) - len(pending)}/{len(lines)}] {line.id}: done, {result['frames']} frames, "
                f"{keyed}{rows[-1].seconds:.1f} s")
        return rows
    except KeyboardInterrupt:  # the lines under way are cancelled; what is recorded stays
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        ray.shutdown()


def _task(line, out_dir: str) -> dict:
    """The Ray task: one line, with the error a user can act on as a plain message."""
    try:
        return process_line(line, out_dir)
    except DiffshegError:
        raise
    except Exception as exc:
        raise DiffshegError(f"unexpected {type(exc).__name__}: {exc}") from None


def _start_ray(address: str | None, workers: int | None):
    """Connect to the cluster at `address` or $RAY_ADDRESS, or start Ray here with a
    worker per core (`workers` to choose) on the loopback address: no usage statistics, no
    dashboard, the project importable in every worker (the same checkout path on every node)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    address = address or os.environ.get("RAY_ADDRESS") or None
    if not address:  # one machine: Ray's single-machine mode keeps it on 127.0.0.1, instead of
        os.environ.setdefault(LOOPBACK_ONLY, "0")  # asking the route to 8.8.8.8 for an address (read at import)
    try:
        import ray
    except ImportError:
        raise DiffshegError("manifests run on Ray, which is not installed: pip install ray==2.60.0 (in the "
                            "Python that has the bpy module; see the README's studio section)") from None

    paths = [*WORKER_PATH, os.environ.get("PYTHONPATH", "")]
    runtime_env = {"env_vars": {"PYTHONPATH": os.pathsep.join(p for p in paths if p),
                                "RAY_USAGE_STATS_ENABLED": "0"}}
    if address:
        try:
            ray.init(address=address, runtime_env=runtime_env, log_to_driver=False)
        except ConnectionError as exc:
            raise DiffshegError(f"could not join the Ray cluster at {address} ({exc}): is it running (ray status "
                                "on the head)? A cluster with token authentication needs its token here: "
                                "RAY_AUTH_MODE=token RAY_AUTH_TOKEN=$(ray get-auth-token) on the head's "
                                "machine, or the token copied over") from None
    else:  # "local": a new Ray, not one `ray start` left
        ray.init(address="local", num_cpus=workers or os.cpu_count(), include_dashboard=False,
                 runtime_env=runtime_env, log_to_driver=False)
    return ray


def _one_line(exc: BaseException) -> str:
    """The message a failed line reports: its DiffshegError's, without Ray's traceback."""
    cause = getattr(exc, "cause", None) or exc
    text = str(cause).strip().splitlines()
    return text[-1] if text else type(cause).__name__

