"""The demo speaker's body: MakeHuman's CC0 base mesh (assets/makehuman_body.npz, made by
tools/make_demo_body.py; licence in assets/README.md) fitted to the BEAT skeleton, skinned
to it and dressed by region, with the 51 ARKit shape keys of the Face Units targets.

Fitting: every BEAT bone gets an affine map from the base mesh's pose (an A-pose, MakeHuman's
joint centres) to the BEAT rest pose (a T-pose): limbs and the spine are turned onto the
BEAT bone and stretched along it to its length, the head, hands and feet follow their chain
rigidly at the body's scale. A vertex moves by its skin weights' blend of those maps
(linear blend skinning from one rest pose to the other); shape-key offsets by the same
blend of the maps' linear parts.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import bpy
import numpy as np

ASSET = Path(__file__).resolve().parent / "assets" / "makehuman_body.npz"

# region: colour (a material each); regions are in the base mesh's own coordinates (decimetres,
# Y up, facing +Z, the character's left at +X), see face_regions
COLOURS = {
    "skin": (0.80, 0.60, 0.48, 1.0),
    "shirt": (0.20, 0.36, 0.56, 1.0),
    "trousers": (0.16, 0.16, 0.19, 1.0),
    "shoes": (0.10, 0.07, 0.05, 1.0),
    "hair": (0.16, 0.10, 0.06, 1.0),
    "brows": (0.18, 0.11, 0.07, 1.0),
    "lips": (0.66, 0.36, 0.34, 1.0),
    "eye": (0.93, 0.93, 0.91, 1.0),
    "iris": (0.20, 0.13, 0.08, 1.0),
    "teeth": (0.92, 0.90, 0.84, 1.0),
    "tongue": (0.70, 0.35, 0.35, 1.0),
    "lashes": (0.08, 0.06, 0.05, 1.0),
}


@lru_cache(maxsize=1)
def load_asset() -> dict[str, np.ndarray]:
    with np.load(ASSET) as data:
        return {k: data[k] for k in data.files}


def to_blender(p: np.ndarray) -> np.ndarray:
    """MakeHuman (decimetres, Y up, facing +Z) -> Blender (metres, Z up, facing -Y)."""
    p = np.asarray(p, dtype=np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1) * 0.1


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction a onto direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def bone_maps(beat: dict[str, np.ndarray], mh: dict[str, np.ndarray]) -> dict[str, tuple]:
    """{BEAT bone: (A, source point, target point)}: x -> target + A (x - source), from the base
    mesh's pose (`mh`: its joint centres, Blender coordinates) to the BEAT rest pose (`beat`:
    joint heads, Blender coordinates)."""
    legs = [np.linalg.norm(beat[f"{s}UpLeg"] - beat[f"{s}Foot"]) /
            np.linalg.norm(mh[f"{c}-upper-leg"] - mh[f"{c}-ankle"]) for s, c in (("Left", "l"), ("Right", "r"))]
    scale = float(np.mean(legs))  # the body's size from its legs; the rest is stretched along the bones
    maps: dict[str, tuple] = {}

    def stretch(bone, src_a, src_b, tgt_a, tgt_b, turned=np.eye(3)):
        src, tgt = turned @ (src_b - src_a), tgt_b - tgt_a
        rotation = _turn(src, tgt) @ turned
        u = tgt / np.linalg.norm(tgt)
        along = np.linalg.norm(tgt) / np.linalg.norm(src)
        maps[bone] = ((scale * (np.eye(3) - np.outer(u, u)) + along * np.outer(u, u)) @ rotation, src_a, tgt_a)
        return rotation

    def rigid(bone, src, tgt, rotation=np.eye(3)):
        maps[bone] = (scale * rotation, src, tgt)

    rigid("Hips", mh["pelvis"], beat["Hips"])
    spine = ("Spine", "Spine1", "Spine2", "Spine3", "Neck")
    height = beat["Neck"][2] - beat["Hips"][2]
    points = [mh["pelvis"] + (mh["neck"] - mh["pelvis"]) * (beat[b][2] - beat["Hips"][2]) / height for b in spine]
    for i, bone in enumerate(spine[:-1]):
        stretch(bone, points[i], points[i + 1], beat[bone], beat[spine[i + 1]])
    for bone in ("Neck", "Neck1", "Head"):
        rigid(bone, mh["neck"], beat["Neck"])
    for side, c in (("Left", "l"), ("Right", "r")):
        clavicle = mh[f"{c}-clavicle"] * np.array([0.0, 1.0, 1.0])
        stretch(f"{side}Shoulder", clavicle, mh[f"{c}-shoulder"], beat[f"{side}Shoulder"], beat[f"{side}Arm"])
        arm = stretch(f"{side}Arm", mh[f"{c}-shoulder"], mh[f"{c}-elbow"], beat[f"{side}Arm"], beat[f"{side}ForeArm"])
        forearm = stretch(f"{side}ForeArm", mh[f"{c}-elbow"], mh[f"{c}-hand"], beat[f"{side}ForeArm"],
                          beat[f"{side}Hand"], arm)
        for bone in beat:
            if bone.startswith(f"{side}Hand"):
                rigid(bone, mh[f"{c}-hand"], beat[f"{side}Hand"], forearm)
        thigh = stretch(f"{side}UpLeg", mh[f"{c}-upper-leg"], mh[f"{c}-knee"], beat[f"{side}UpLeg"], beat[f"{side}Leg"])
        shin = stretch(f"{side}Leg", mh[f"{c}-knee"], mh[f"{c}-ankle"], beat[f"{side}Leg"], beat[f"{side}Foot"], thigh)
        for bone in ("Foot", "ForeFoot", "ToeBase"):
            rigid(side + bone, mh[f"{c}-ankle"], beat[f"{side}Foot"], shin)
    return maps


def fitted(beat: dict[str, np.ndarray]):
    """(vertices (N, 3), per-vertex linear maps (N, 3, 3)) of the base mesh in the BEAT rest pose."""
    data = load_asset()
    mh = dict(zip(data["joint_names"].tolist(), to_blender(data["joints"])))
    maps = bone_maps(beat, mh)
    bones = data["bones"].tolist()
    linear = np.stack([maps[b][0] for b in bones])                                   # (B, 3, 3)
    offset = np.stack([maps[b][2] - maps[b][0] @ maps[b][1] for b in bones])          # (B, 3)
    w, idx = data["weight"][..., None], data["weight_bone"]
    per_vertex = np.einsum("vk,vkij->vij", data["weight"], linear[idx])
    verts = np.einsum("vij,vj->vi", per_vertex, to_blender(data["verts"])) + np.sum(w * offset[idx], axis=1)
    return verts, per_vertex


def face_regions(data: dict[str, np.ndarray]) -> np.ndarray:
    """Each face's COLOURS index, by part and by where its centre lies."""
    names = list(COLOURS)
    faces, part, parts = data["faces"].astype(np.int64), data["face_part"], data["parts"].tolist()
    p = data["verts"]
    x, y, z = p[faces].mean(axis=1).T
    ax = np.abs(x)
    hand = np.array([b.startswith(("LeftHand", "RightHand")) for b in data["bones"].tolist()])
    hand = hand[data["weight_bone"][:, 0]][faces].mean(axis=1) > 0.5
    region = np.full(len(faces), names.index("skin"))
    body = part == parts.index("body")
    neck = (y > 5.62 - 0.5 * np.clip(z - 0.3, 0.0, None) ** 2) & (ax < 0.75)  # skin above a round collar
    region[body & (y > 0.95) & (y < 6.6) & ~hand & ~neck] = names.index("shirt")
    region[body & (y <= 0.95)] = names.index("trousers")
    region[body & (y < -7.6)] = names.index("shoes")
    hairline = np.interp(z, [-1.2, 0.25, 0.6, 0.9, 1.1], [6.85, 6.9, 7.45, 7.8, 7.86])  # low at the nape, high at the brow
    ear = (ax > 0.62) & (y < 7.6) & (z > 0.25)
    region[body & (y > 6.6) & (y > hairline) & ~ear] = names.index("hair")
    for sx in (-1.0, 1.0):  # arched brows
        u, v = (x - sx * 0.33) / 0.21, (y - 7.56 + 0.6 * (x - sx * 0.3) ** 2) / 0.04
        region[body & (z > 1.2) & (u ** 2 + v ** 2 < 1.0)] = names.index("brows")
    region[body & (z > 1.3) & (((x / 0.27) ** 2 + ((y - 6.6) / 0.11) ** 2) < 1.0)] = names.index("lips")
    for side in ("l", "r"):
        eye = part == parts.index(f"helper-{side}-eye")
        region[eye] = names.index("eye")
        region[eye & (z > p[np.unique(faces[eye]), 2].mean() + 0.13)] = names.index("iris")  # a 1.5 cm eyeball's front
    region[np.isin(part, [parts.index(n) for n in parts if "teeth" in n])] = names.index("teeth")
    region[part == parts.index("helper-tongue")] = names.index("tongue")
    region[np.isin(part, [parts.index(n) for n in parts if "eyelashes" in n])] = names.index("lashes")
    return region


def build_body(armature, beat: dict[str, np.ndarray], name: str):
    """The body mesh, fitted to the armature's rest pose (`beat`: joint heads in the armature's
    space), skinned to it (vertex groups, an Armature modifier) and parented to it."""
    data = load_asset()
    verts, _ = fitted(beat)
    faces = data["faces"].astype(np.int64)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    mesh.loops.add(faces.size)
    mesh.loops.foreach_set("vertex_index", faces.ravel().astype(np.int32))
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 4, dtype=np.int32))
    mesh.polygons.foreach_set("loop_total", np.full(len(faces), 4, dtype=np.int32))
    mesh.update()
    mesh.validate()
    for colour_name, colour in COLOURS.items():
        material = bpy.data.materials.new(f"{name}_{colour_name}")
        material.diffuse_color = colour
        mesh.materials.append(material)
    mesh.polygons.foreach_set("material_index", face_regions(data).astype(np.int32))
    mesh.shade_smooth()
    ob = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(ob)
    bones = data["bones"].tolist()
    quantised = np.round(data["weight"] * 100).astype(np.int32)  # group vertices by (bone, weight in %)
    for b, bone in enumerate(bones):
        group = ob.vertex_groups.new(name=bone)
        rows, cols = np.nonzero((data["weight_bone"] == b) & (quantised > 0))
        weights = quantised[rows, cols]
        for value in np.unique(weights):
            group.add(rows[weights == value].tolist(), value / 100.0, "REPLACE")
    ob.parent = armature
    modifier = ob.modifiers.new("Armature", "ARMATURE")
    modifier.object = armature
    return ob


def add_face_keys(ob, beat: dict[str, np.ndarray]) -> None:
    """A Basis and the 51 ARKit shape keys (Face Units targets, carried through the fit)."""
    data = load_asset()
    _, per_vertex = fitted(beat)
    base = np.empty(3 * len(ob.data.vertices), dtype=np.float32)
    ob.data.vertices.foreach_get("co", base)
    base = base.reshape(-1, 3)
    ob.shape_key_add(name="Basis")
    offsets = data["key_offsets"]
    for k, key in enumerate(data["key_names"].tolist()):
        rows = data["key_verts"][offsets[k]:offsets[k + 1]].astype(np.int64)
        delta = to_blender(data["key_deltas"][offsets[k]:offsets[k + 1]].astype(np.float64))
        co = base.copy()
        co[rows] += np.einsum("vij,vj->vi", per_vertex[rows], delta)
        block = ob.shape_key_add(name=key, from_mix=False)
        block.data.foreach_set("co", co.ravel())
        block.value = 0.0  # shape_key_add gives 1.0 in Blender 5.0
