"""Look at the feet: the real capture and the generated motion of the same speech, side by side.

Keys, on two copies of the BEAT demo speaker standing on a floor (left: the real capture of
2_scott_0_1_1's held-out last seconds, its BEAT BVH upper body and BEAT2 SMPL-X hips and
legs; right: the bundled model's take of the same speech), renders them with Workbench from
a whole-body camera and from a low camera on the feet, and writes OUT/feet.mp4 (the two
views one above the other) and OUT/feet_sheet.png (a contact sheet of frames), so that a
reviewer sees what lower_body.feet_figures measures. Prints those figures for both.

    python bench/render_feet.py [--seconds 12] [--seed 0] [--out out/render-feet]

Needs bpy and ffmpeg. A few minutes on the 2-core CI box.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from blender_addon.scene.bake import BakeOptions, bake_motion  # noqa: E402
from blender_addon.scene.demo import build_beat_armature  # noqa: E402
from blender_addon.scene.preset import load_preset  # noqa: E402
from diffsheg_core import generate, lower_body  # noqa: E402
from diffsheg_core.audio import Audio, load_audio  # noqa: E402
from diffsheg_core.bvh import bvh_to_motion, read_bvh  # noqa: E402

DATA = REPO.parent / "shared" / "data"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
TAKE_NPZ = DATA / "beat2" / "2_scott_0_1_1.npz"
FPS = 15.0
APART = 1.4  # metres between the two speakers


def capture_take(seconds: float | None):
    """The capture's last `seconds` (None: all of it), BEAT BVH upper body and BEAT2 SMPL-X hips
    and legs, and the frames of the take they are."""
    upper = bvh_to_motion(read_bvh(TAKE_BVH, fps=FPS))
    lower, trans, _ = lower_body.read_capture(TAKE_NPZ, FPS)
    n = min(upper.n_frames, len(lower))
    part = slice(0 if seconds is None else n - int(seconds * FPS), n)
    face = np.zeros((part.stop - part.start, 0), np.float32)
    body = replace(upper, rotations=upper.rotations[part], face_names=[], face=face, meta={})
    return lower_body.with_lower_body(body, lower[part], trans[part],
                                      lower_body.contacts(lower[part], trans[part], FPS)), part


def generated_take(part: slice, seed: int):
    """The bundled model's take of the same speech."""
    audio = load_audio(TAKE_WAV)
    rate = audio.sample_rate
    speech = Audio(audio.samples[int(part.start * rate / FPS): int(part.stop * rate / FPS)], rate)
    return generate(speech, seed=seed, device="cpu")


def speaker(scene, motion, name: str, x: float):
    armature = build_beat_armature(name)
    armature.location.x = x
    bake_motion(scene, motion, None, BakeOptions(armature=armature, preset=load_preset("beat"), add_sound=False,
                                                 set_frame_range=True))
    return armature


def camera(scene, name: str, location, lens: float, pitch: float):
    data = bpy.data.cameras.new(name)
    data.lens = lens
    cam = bpy.data.objects.new(name, data)
    scene.collection.objects.link(cam)
    cam.location, cam.rotation_euler = location, (np.radians(pitch), 0.0, 0.0)
    return cam


def render(scene, cam, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    scene.camera = cam
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(folder / "f_")
    bpy.ops.render.render(animation=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=12.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/render-feet")
    args = p.parse_args()
    if shutil.which("ffmpeg") is None:
        raise SystemExit("render_feet: ffmpeg is missing: bash tools/install_system_packages.sh")
    out = Path(args.out)
    frames = out / "frames"
    shutil.rmtree(frames, ignore_errors=True)
    capture, part = capture_take(args.seconds)
    made = generated_take(part, args.seed)
    for name, motion in (("capture", capture), ("generated", made)):
        figures = lower_body.feet_figures(lower_body.lower_rotations(motion),
                                          motion.root_translation.astype(np.float64), motion.fps)
        print(f"{name}: " + ", ".join(f"{k} {v:.3g}" for k, v in figures.items()), flush=True)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = 15, 1.0
    speaker(scene, capture, "Capture", -APART / 2)
    speaker(scene, made, "Generated", APART / 2)
    bpy.ops.mesh.primitive_plane_add(size=6.0)
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.render.resolution_x, scene.render.resolution_y = 640, 300
    world = bpy.data.worlds.new("FeetWorld")
    world.color = (0.18, 0.2, 0.24)
    scene.world = world
    render(scene, camera(scene, "Wide", (0.0, -5.2, 0.95), 35, 90.0), frames / "wide")
    render(scene, camera(scene, "Feet", (0.0, -2.6, 0.45), 35, 80.0), frames / "feet")
    out.mkdir(parents=True, exist_ok=True)
    fps = str(scene.render.fps)
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-framerate", fps, "-i", str(frames / "wide" / "f_%04d.png"),
                    "-framerate", fps, "-i", str(frames / "feet" / "f_%04d.png"), "-filter_complex", "vstack",
                    "-pix_fmt", "yuv420p", str(out / "feet.mp4")], check=True)
    step = max(1, (scene.frame_end - scene.frame_start) // 12)
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(out / "feet.mp4"), "-vf",
                    f"select='not(mod(n\\,{step}))',scale=320:-1,tile=4x3", "-frames:v", "1",
                    str(out / "feet_sheet.png")], check=True)
    print(f"wrote {out / 'feet.mp4'} and {out / 'feet_sheet.png'} (left: the capture, right: generated)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
