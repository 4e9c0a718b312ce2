"""The add-on in a fresh Blender, as a new user gets it: nothing installed but Blender.

    python tools/test_fresh_blender.py [--work DIR] [--keep]

1. builds the linux-x64 extension zip (build_addon.py; its wheels come from the wheel cache);
2. makes, or reuses, a virtual environment holding nothing but `pip install bpy==5.0.1`
   (Blender as a Python module, with only the packages Blender itself ships: numpy,
   requests, zstandard...); it lives in $DIFFSHEG_FRESH_BPY (default
   ~/.cache/diffsheg/fresh-bpy-5.0.1) and is made again whenever it holds anything else;
3. in that Python, with a throwaway Blender user folder (BLENDER_USER_RESOURCES), installs
   and enables the zip with bpy.ops.extensions.package_install_files, builds a Rigify rig
   and appends the real ARKit face (shared/data/rigs/beat_face_arkit51.blend), sets the
   scene's DiffSHEG settings (a few seconds of real speech, preset rigify), calls
   bpy.ops.diffsheg.generate() and checks that the rig's bones and the face's jawOpen
   shape key are keyed, that onnxruntime came from the extension's wheels, and that
   torch, scipy, librosa and numba were never imported;
4. runs the installed extension's batch_render.py headless on one audio file
   (--no-render --save) and checks the saved scene's keys.

Prints each step's time and 'fresh Blender: passed' (exit 0), or what failed (exit 1).
Needs CPython 3.11 (PYTHON=...), PyPI the first time (bpy, the wheels), ../shared/data.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import wave
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
FACE_BLEND = DATA / "rigs" / "beat_face_arkit51.blend"
SPEECH = DATA / "audio" / "12_zhao_2_3_3.wav"
BPY_VERSION = "5.0.1"
VENV_ENV = "DIFFSHEG_FRESH_BPY"
# distributions a venv may hold besides bpy's own requirements
VENV_TOOLS = {"pip", "setuptools", "wheel"}
FORBIDDEN = ("torch", "scipy", "librosa", "numba")

if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import build_addon  # noqa: E402


class Failed(Exception):
    pass


def default_venv() -> Path:
    env = os.environ.get(VENV_ENV)
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "diffsheg" / f"fresh-bpy-{BPY_VERSION}"


def venv_python(venv: Path) -> Path:
    return venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


# What the venv holds, against the closure of bpy's requirements (read from its metadata).
_INVENTORY = r"""
import json, re
from importlib import metadata
names = {}
for dist in metadata.distributions():
    names[re.sub(r"[-_.]+", "-", dist.metadata["Name"]).lower()] = dist
def closure(name, seen):
    name = re.sub(r"[-_.]+", "-", name).lower()
    if name in seen or name not in names:
        return
    seen.add(name)
    for req in names[name].requires or []:
        if "extra ==" in req:
            continue
        closure(re.match(r"[A-Za-z0-9_.-]+", req).group(0), seen)
needed = set()
closure("bpy", needed)
print(json.dumps({"bpy": names["bpy"].version if "bpy" in names else None,
                  "installed": sorted(names), "needed": sorted(needed)}))
"""


def venv_problem(venv: Path) -> str | None:
    """Why the cached venv cannot be used (None: it holds bpy and its requirements only)."""
    python = venv_python(venv)
    if not python.is_file():
        return "no venv yet"
    proc = subprocess.run([str(python), "-I", "-c", _INVENTORY], capture_output=True, text=True, env=clean_env())
    if proc.returncode != 0:
        return f"its python does not run ({proc.stderr.strip()[-200:]})"
    inventory = json.loads(proc.stdout)
    if inventory["bpy"] != BPY_VERSION:
        return f"bpy is {inventory['bpy']}, not {BPY_VERSION}"
    extra = sorted(set(inventory["installed"]) - set(inventory["needed"]) - VENV_TOOLS)
    if extra:
        return f"it holds more than bpy and its requirements: {', '.join(extra)}"
    return None


def fresh_venv(venv: Path, python: str) -> Path:
    problem = venv_problem(venv)
    if problem is None:
        print(f"venv: reusing {venv}", flush=True)
        return venv_python(venv)
    print(f"venv: making {venv} ({problem})", flush=True)
    shutil.rmtree(venv, ignore_errors=True)
    venv.parent.mkdir(parents=True, exist_ok=True)
    run([python, "-m", "venv", str(venv)], "create the venv")
    run([str(venv_python(venv)), "-m", "pip", "install", "-q", "--disable-pip-version-check",
         f"bpy=={BPY_VERSION}"], f"pip install bpy=={BPY_VERSION}")
    problem = venv_problem(venv)
    if problem is not None:
        raise Failed(f"the new venv is not fresh: {problem}")
    return venv_python(venv)


def clean_env(user: Path | None = None) -> dict:
    """The environment of a user's Blender: no PYTHONPATH, no user site-packages, and
    (given) a Blender user folder of its own."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON") and k != "VIRTUAL_ENV"}
    env["PYTHONNOUSERSITE"] = "1"
    if user is not None:
        env["BLENDER_USER_RESOURCES"] = str(user)
    return env


def run(command: list[str], what: str, **kwargs) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in command], capture_output=True, text=True, **kwargs)
    if proc.returncode != 0:
        raise Failed(f"{what} failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def cut_wav(source: Path, target: Path, seconds: float, offset: float) -> Path:
    """A few seconds of a real PCM WAV, with the standard library only."""
    with wave.open(str(source)) as src:
        rate = src.getframerate()
        src.setpos(int(offset * rate))
        frames = src.readframes(int(seconds * rate))
        with wave.open(str(target), "wb") as dst:
            dst.setnchannels(src.getnchannels())
            dst.setsampwidth(src.getsampwidth())
            dst.setframerate(rate)
            dst.writeframes(frames)
    return target


# Runs inside the fresh bpy. argv: mode, then mode's arguments. Prints one RESULT line.
INSIDE = r'''
import json, os, sys
from pathlib import Path
import bpy

FORBIDDEN = ("torch", "scipy", "librosa", "numba")


def fcurves(id_data):
    """The F-curves of id_data's assigned action (layered actions in 4.4+, action.fcurves before)."""
    ad = id_data.animation_data
    if ad is None or ad.action is None:
        return []
    action = ad.action
    slot = getattr(ad, "action_slot", None)
    if slot is not None and hasattr(action, "layers"):
        from bpy_extras.anim_utils import action_get_channelbag_for_slot
        bag = action_get_channelbag_for_slot(action, slot)
        if bag is not None:
            return list(bag.fcurves)
        if bpy.app.version >= (5, 0):
            return []
    return list(action.fcurves)


def keyed(id_data):
    """{data_path: number of keyframes} over the F-curves with keys."""
    out = {}
    for fc in fcurves(id_data):
        if len(fc.keyframe_points):
            out[fc.data_path] = max(out.get(fc.data_path, 0), len(fc.keyframe_points))
    return out


def face_and_rig_report(rig, face):
    bones = sorted({p.split('"')[1] for p in keyed(rig) if p.startswith("pose.bones[")})
    shapes = keyed(face.data.shape_keys)
    jaw = [fc for fc in fcurves(face.data.shape_keys) if fc.data_path == 'key_blocks["jawOpen"].value']
    values = [k.co[1] for k in jaw[0].keyframe_points] if jaw else []
    types = sorted({k.type for k in jaw[0].keyframe_points}) if jaw else []
    return {"bones": bones, "n_rig_keys": max(keyed(rig).values(), default=0),
            "shape_keys": len(shapes), "jaw_keys": len(values), "jaw_types": types,
            "jaw_range": [min(values), max(values)] if values else None}


class Layout:
    """Stands in for a UI layout: records the labels a draw() writes."""
    def __init__(self, texts):
        self.texts = texts
    def label(self, text="", **kw):
        self.texts.append(text)
    def operator(self, idname, **kw):  # returns the operator's properties, as Blender's does
        self.texts.append(f"[{kw.get('text', idname)}]")
        return type("OperatorProperties", (), {})()
    def __getattr__(self, name):  # box, row, column, prop, template_list, ...
        return lambda *a, **kw: self
    active = True


def drawn(cls, context):
    """The labels cls.draw writes (a panel's or the preferences' draw, on a stand-in self)."""
    texts = []
    cls.draw(type("Self", (), {"layout": Layout(texts), "install_status": "", "torch_build": "CPU"})(), context)
    return texts


mode = sys.argv[1]
if mode == "install":
    zip_path, face_blend, audio, scene_out = sys.argv[2:6]
    # the user's scene: a Rigify rig and the ARKit face (factory settings reset the add-ons: first)
    import addon_utils
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon_utils.enable("rigify", default_set=True)
    bpy.ops.object.armature_human_metarig_add()
    bpy.ops.pose.rigify_generate()
    rig = bpy.data.objects["rig"]
    with bpy.data.libraries.load(face_blend) as (src, dst):
        dst.objects = ["Neutral"]
    face = dst.objects[0]
    bpy.context.scene.collection.objects.link(face)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = 24, 1.0
    bpy.ops.wm.save_as_mainfile(filepath=scene_out, copy=True)

    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                      enable_on_install=True)
    module = "bl_ext.user_default.diffsheg"
    bpy.ops.wm.save_userpref()  # as Blender's auto-save does: the next start has it enabled
    addon = sys.modules[module]
    prefs = drawn(sys.modules[module + ".ui.preferences"].DIFFSHEG_AP_preferences, bpy.context)
    ext_dir = Path(addon.__file__).parent

    s = scene.diffsheg
    s.audio_path = audio
    s.armature = rig
    s.face_meshes.add().object = face
    s.preset = "rigify"
    s.set_steps, s.steps = True, 10
    status = bpy.ops.diffsheg.generate()
    report = face_and_rig_report(rig, face)
    ort = sys.modules.get("onnxruntime")
    panel = sys.modules[module + ".ui.panel"].DIFFSHEG_PT_generate
    saved_soxr, sys.modules["soxr"] = sys.modules.get("soxr"), None  # as if a wheel had gone missing
    missing = drawn(panel, bpy.context)[:2]
    sys.modules["soxr"] = saved_soxr
    print("RESULT", json.dumps({
        "install": sorted(result), "enabled": module in bpy.context.preferences.addons,
        "generate": sorted(status), "model": s.model_label, "report": s.last_report,
        "keys": report, "frames": [scene.frame_start, scene.frame_end],
        "forbidden": [m for m in FORBIDDEN if m in sys.modules],
        "onnxruntime": getattr(ort, "__file__", None), "ext_dir": str(ext_dir),
        "core": sys.modules["diffsheg_core"].__file__, "prefs": prefs, "missing": missing,
        "user": bpy.utils.resource_path("USER"),
    }), flush=True)
elif mode == "dash-p":
    # `blender -b scene.blend -P batch_render.py -- ARGS` as the bpy module can do it: the
    # user's preferences (the extension enabled), the scene, then the script as __main__
    import runpy
    blend, script, args = sys.argv[2], sys.argv[3], sys.argv[4:]
    bpy.ops.wm.read_userpref()
    bpy.ops.wm.open_mainfile(filepath=blend)
    enabled = "bl_ext.user_default.diffsheg" in sys.modules
    sys.argv = ["blender", "-b", blend, "-P", script, "--", *args]
    try:
        runpy.run_path(script, run_name="__main__")
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    print("RESULT", json.dumps({"exit": code, "enabled": enabled,
                                "own_import": "diffsheg_batch_addon" in sys.modules,
                                "forbidden": [m for m in FORBIDDEN if m in sys.modules]}), flush=True)
elif mode == "check":
    out = {}
    for blend in sys.argv[2:]:
        bpy.ops.wm.open_mainfile(filepath=blend)
        rig, face = bpy.data.objects["rig"], bpy.data.objects["Neutral"]
        out[blend] = face_and_rig_report(rig, face)
    print("RESULT", json.dumps(out), flush=True)
os._exit(0)  # skip Blender's exit-time teardown
'''


def inside(python: Path, user: Path, work: Path, *args) -> dict:
    script = work / "inside.py"
    script.write_text(INSIDE)
    proc = run([python, script, *args], f"the fresh Blender ({args[0]})", env=clean_env(user), cwd=work,
               timeout=600)
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    if not lines:
        raise Failed(f"the fresh Blender ({args[0]}) printed no result:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def check(condition: bool, message: str) -> None:
    if not condition:
        raise Failed(message)


def check_keys(keys: dict, frames: int, where: str) -> None:
    check(len(keys["bones"]) >= 20, f"{where}: only {len(keys['bones'])} rig bones keyed: {keys['bones']}")
    for bone in ("upper_arm_fk.L", "forearm_fk.R", "head"):
        check(bone in keys["bones"], f"{where}: bone {bone} not keyed (keyed: {keys['bones']})")
    check("jaw_master" not in keys["bones"], f"{where}: the jaw bone is keyed beside the face's jawOpen key")
    # sparse keys by default: poses on the motion's turning points, not one on every frame
    check(frames // 24 <= keys["jaw_keys"] < frames, f"{where}: jawOpen has {keys['jaw_keys']} keys, expected "
                                                      f"sparse keys (at least one a second, fewer than {frames})")
    check(keys["jaw_types"] == ["GENERATED"], f"{where}: jawOpen's keys are typed {keys['jaw_types']}, not GENERATED")
    check(keys["jaw_range"] is not None and keys["jaw_range"][1] - keys["jaw_range"][0] > 0.05,
          f"{where}: jawOpen does not move: {keys['jaw_range']}")
    check(keys["shape_keys"] >= 40, f"{where}: only {keys['shape_keys']} shape keys keyed")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", help="working folder (default: a temporary one, removed after)")
    parser.add_argument("--venv", default=None, help=f"the fresh venv (default ${VENV_ENV} or "
                                                     f"~/.cache/diffsheg/fresh-bpy-{BPY_VERSION})")
    parser.add_argument("--keep", action="store_true", help="keep the working folder")
    args = parser.parse_args(argv)
    python = os.environ.get("PYTHON") or sys.executable
    start = time.perf_counter()
    stamp = [start]

    def step(label: str) -> None:
        now = time.perf_counter()
        print(f"{label}: {now - stamp[0]:.1f} s", flush=True)
        stamp[0] = now

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="diffsheg-fresh-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        zip_path = build_addon.build(work / "dist", ["linux-x64"], legacy=False)["linux-x64"]
        step(f"built {zip_path.name} ({zip_path.stat().st_size / 1e6:.1f} MB)")
        py = fresh_venv(Path(args.venv).expanduser() if args.venv else default_venv(), python)
        step("venv")
        user = work / "user"
        shutil.rmtree(user, ignore_errors=True)
        seconds = 6.0
        clip = cut_wav(SPEECH, work / "zhao_6s.wav", seconds, offset=10.0)
        scene = work / "scene.blend"

        got = inside(py, user, work, "install", zip_path, FACE_BLEND, clip, scene)
        step("install, Rigify rig, generate")
        check(got["install"] == ["FINISHED"] and got["enabled"], f"the extension did not install/enable: {got}")
        check(got["generate"] == ["FINISHED"], f"generate did not finish: {got['report']}")
        check(not got["forbidden"], f"generation imported {got['forbidden']}")
        check(got["core"].startswith(got["ext_dir"]), f"diffsheg_core came from {got['core']}, not the extension")
        check(got["onnxruntime"] and "/extensions/.local/" in got["onnxruntime"].replace(os.sep, "/"),
              f"onnxruntime came from {got['onnxruntime']}, not the extension's wheels")
        check(any("Generation is ready" in t for t in got["prefs"]) and
              any("GPU support" in t for t in got["prefs"]), f"preferences say: {got['prefs']}")
        check(got["missing"] == ["Missing Python packages: soxr", f"They come with the extension: install "
                                 f"{zip_path.name} again (Edit > Preferences > Get Extensions > Install from Disk)"],
              f"with soxr missing the panel says: {got['missing']}")
        frames = round(seconds * 24)
        check_keys(got["keys"], frames, "operator")
        check(got["frames"] == [1, frames], f"frame range {got['frames']}, expected [1, {frames}]")
        print(f"generate: {got['report'][:160]}", flush=True)

        batch = Path(got["ext_dir"]) / "batch_render.py"
        check(batch.is_file(), f"the installed extension has no batch_render.py ({got['ext_dir']})")
        batch_args = ["--audio", clip, "--preset", "rigify", "--armature", "rig", "--face", "Neutral",
                      "--steps", "5", "--no-render", "--save"]
        saved_p = work / "batch" / "dash_p.blend"
        got = inside(py, user, work, "dash-p", scene, batch, *batch_args, saved_p)
        check(got["exit"] == 0 and saved_p.is_file(), f"blender -b -P batch_render.py failed: {got}")
        check(got["enabled"] and not got["own_import"], f"batch_render.py did not use the enabled extension: {got}")
        check(not got["forbidden"], f"batch_render.py imported {got['forbidden']}")
        step("blender -b scene.blend -P <extension>/batch_render.py")
        saved = work / "batch" / "python.blend"
        proc = run([py, batch, "--blend", scene, *batch_args, saved],
                   "python <extension>/batch_render.py", env=clean_env(user), cwd=work, timeout=600)
        check(saved.is_file(), f"batch_render.py saved no scene:\n{proc.stdout[-2000:]}")
        reports = [l for l in proc.stdout.splitlines() if " keys, preset " in l]
        check(bool(reports), f"batch_render.py printed no report line:\n{proc.stdout[-2000:]}")
        print(f"batch: {reports[-1][:160]}", flush=True)
        step("python <extension>/batch_render.py --blend")
        got = inside(py, user, work, "check", saved_p, saved)
        for blend, keys in got.items():
            check_keys(keys, frames, Path(blend).name)
        step("check the saved scenes")
    except (Failed, build_addon.BuildError, subprocess.TimeoutExpired) as exc:
        print(f"fresh Blender: FAILED: {exc}", file=sys.stderr, flush=True)
        print(f"(working folder {work})", file=sys.stderr)
        return 1
    finally:
        if not args.work and not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(f"fresh Blender: passed in {time.perf_counter() - start:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
