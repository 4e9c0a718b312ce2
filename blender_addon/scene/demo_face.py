"""The demo character's face: a stylised head with eyes, pupils, brows, nose and mouth in
one mesh, and all 51 ARKit shape keys of the BEAT layout, so speech, blinks, gaze and
brows all show in the main job's preview.

Geometry is in head-local units (a unit sphere, face towards -Y, the character's left
at +X); every shape key is a displacement of some parts, written with numpy.
"""

from __future__ import annotations

import bmesh
import bpy
import numpy as np
from mathutils import Matrix

from diffsheg_core.rigs import ARKIT51

# part: (centre, radii, colour); eyes, pupils and brows come in pairs at +-x
PARTS = {
    "skin": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.80, 0.60, 0.48, 1.0)),
    "eye_L": ((0.36, -0.86, 0.18), (0.17, 0.085, 0.13), (0.95, 0.95, 0.95, 1.0)),
    "eye_R": ((-0.36, -0.86, 0.18), (0.17, 0.085, 0.13), (0.95, 0.95, 0.95, 1.0)),
    "pupil_L": ((0.36, -0.95, 0.18), (0.07, 0.03, 0.07), (0.08, 0.12, 0.20, 1.0)),
    "pupil_R": ((-0.36, -0.95, 0.18), (0.07, 0.03, 0.07), (0.08, 0.12, 0.20, 1.0)),
    "brow_L": ((0.36, -0.87, 0.42), (0.16, 0.04, 0.035), (0.20, 0.12, 0.08, 1.0)),
    "brow_R": ((-0.36, -0.87, 0.42), (0.16, 0.04, 0.035), (0.20, 0.12, 0.08, 1.0)),
    "nose": ((0.0, -1.0, -0.05), (0.10, 0.12, 0.12), (0.78, 0.55, 0.44, 1.0)),
    "mouth": ((0.0, -0.92, -0.45), (0.32, 0.06, 0.035), (0.35, 0.05, 0.07, 1.0)),
}
MOUTH_LINE = -0.45


def build_face_mesh(name: str) -> bpy.types.Object:
    """The head as one object with a Basis and the 51 ARKit shape keys, linked to the scene."""
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    parts = np.zeros(0, dtype=np.int32)
    for index, (part, (centre, radii, _)) in enumerate(PARTS.items()):
        before = len(bm.verts)
        segments = (48, 24) if part == "skin" else (24, 12)
        made = bmesh.ops.create_uvsphere(bm, u_segments=segments[0], v_segments=segments[1], radius=1.0)
        bmesh.ops.transform(bm, verts=made["verts"], matrix=Matrix.Translation(centre) @ Matrix.Diagonal((*radii, 1.0)))
        for face in {f for v in made["verts"] for f in v.link_faces}:
            face.material_index = index
            face.smooth = True
        parts = np.concatenate([parts, np.full(len(bm.verts) - before, index, dtype=np.int32)])
    bm.to_mesh(mesh)
    bm.free()
    for part, (_, _, colour) in PARTS.items():
        material = bpy.data.materials.new(f"{name}_{part}")
        material.diffuse_color = colour
        mesh.materials.append(material)
    ob = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(ob)
    base = np.empty(3 * len(mesh.vertices))
    mesh.vertices.foreach_get("co", base)
    base = base.reshape(-1, 3)
    ob.shape_key_add(name="Basis")
    for key, offset in arkit_shapes(base, parts).items():
        block = ob.shape_key_add(name=key, from_mix=False)
        block.data.foreach_set("co", (base + offset).ravel())
    return ob


def arkit_shapes(p: np.ndarray, parts: np.ndarray) -> dict[str, np.ndarray]:
    """{ARKit name: (N, 3) displacement} for vertices `p` of the parts `parts` (indices of PARTS)."""
    names = list(PARTS)

    def on(*wanted):
        return np.isin(parts, [names.index(w) for w in wanted])[:, None].astype(np.float64)

    def centre(part):
        return np.array(PARTS[part][0])

    x, y, z = p.T
    mouth = on("mouth")
    mc = centre("mouth")
    u = np.clip((x - mc[0]) / PARTS["mouth"][1][0], -1.0, 1.0)        # -1 right corner .. 1 left
    lower = (z < mc[2]).astype(np.float64)[:, None] * mouth
    upper = (z >= mc[2]).astype(np.float64)[:, None] * mouth
    bulge = np.sqrt(np.clip(1.0 - u ** 2, 0.0, 1.0))[:, None]           # 1 mid-lip, 0 at the corners
    chin = (np.clip((MOUTH_LINE - 0.05 - z) / 0.3, 0.0, 1.0) * np.exp(-x ** 2 / 0.3) * (y < -0.2))[:, None]
    chin = chin * on("skin")
    ex, ey, ez = np.eye(3)

    def side(sign):
        return (np.sign(x) == sign).astype(np.float64)[:, None]

    def corner(sign):  # mouth vertices near the corner on that side, 0..1
        return mouth * (np.clip(sign * u, 0.0, 1.0) ** 2)[:, None]

    def gauss(c, sigma, mask=None):
        w = np.exp(-np.sum((p - np.asarray(c)) ** 2, axis=1) / (2 * sigma ** 2))[:, None]
        return w * (on("skin", "nose") if mask is None else mask)

    def squash(part, factor, axis=2):  # scale a part about its centre along one axis
        d = np.zeros_like(p)
        d[:, axis] = (p[:, axis] - centre(part)[axis]) * (factor - 1.0)
        return d * on(part)

    out: dict[str, np.ndarray] = {}
    for s, tag in ((1, "Left"), (-1, "Right")):
        eye, pupil, brow = f"eye_{tag[0]}", f"pupil_{tag[0]}", f"brow_{tag[0]}"
        ec = centre(eye)
        inner = np.clip(1.0 - s * (x - centre(brow)[0]) / 0.16, 0.0, 2.0)[:, None] / 2  # 1 at the nose end
        out[f"eyeBlink{tag}"] = squash(eye, 0.06) + squash(pupil, 0.06)
        out[f"eyeSquint{tag}"] = squash(eye, 0.55) + squash(pupil, 0.7) + gauss(ec - 0.16 * ez, 0.12) * (0.04 * ez)
        out[f"eyeWide{tag}"] = squash(eye, 1.35) + gauss(ec + 0.16 * ez, 0.12) * (0.03 * ez)
        out[f"eyeLookUp{tag}"] = on(pupil) * (0.05 * ez)
        out[f"eyeLookDown{tag}"] = on(pupil) * (-0.05 * ez)
        out[f"eyeLookIn{tag}"] = on(pupil) * (-s * 0.08 * ex)
        out[f"eyeLookOut{tag}"] = on(pupil) * (s * 0.08 * ex)
        out[f"browDown{tag}"] = on(brow) * (-0.06 * ez - 0.03 * inner * ez)
        out[f"browOuterUp{tag}"] = on(brow) * (0.09 * (1 - inner) * ez)
        out[f"cheekSquint{tag}"] = gauss((s * 0.48, -0.8, -0.12), 0.14) * (0.05 * ez)
        out[f"noseSneer{tag}"] = gauss((s * 0.12, -0.98, 0.0), 0.1) * (0.05 * ez)
        out[f"mouthSmile{tag}"] = corner(s) * (0.07 * ez + s * 0.04 * ex) + \
            gauss((s * 0.4, -0.8, -0.3), 0.12) * (0.03 * ez)
        out[f"mouthFrown{tag}"] = corner(s) * (-0.07 * ez)
        out[f"mouthDimple{tag}"] = corner(s) * (0.05 * ey + s * 0.02 * ex)
        out[f"mouthStretch{tag}"] = corner(s) * (s * 0.08 * ex - 0.02 * ez)
        out[f"mouthLowerDown{tag}"] = lower * side(s) * bulge * (-0.07 * ez)
        out[f"mouthUpperUp{tag}"] = upper * side(s) * bulge * (0.06 * ez)
        out[f"mouthPress{tag}"] = squash("mouth", 0.4) * side(s)
        out[f"mouth{tag}"] = (mouth + gauss(mc, 0.15)) * (s * 0.1 * ex)
        out[f"jaw{tag}"] = (lower + chin) * (s * 0.08 * ex)
    brow_inner = np.clip(1.0 - (np.abs(x) - 0.2) / 0.32, 0.0, 1.0)[:, None]
    out["browInnerUp"] = on("brow_L", "brow_R") * brow_inner * (0.1 * ez)
    out["cheekPuff"] = (gauss((0.45, -0.72, -0.35), 0.18) + gauss((-0.45, -0.72, -0.35), 0.18)) * \
        (p * np.array([1.0, 0.3, 0.0])) * 0.25
    out["jawOpen"] = lower * bulge * (-0.22 * ez) + chin * (-0.2 * ez)
    out["jawForward"] = (lower + chin) * (-0.07 * ey)
    out["mouthClose"] = lower * bulge * (0.12 * ez)
    out["mouthFunnel"] = squash("mouth", 0.6, axis=0) + squash("mouth", 2.6) + mouth * (-0.04 * ey)
    out["mouthPucker"] = squash("mouth", 0.45, axis=0) + squash("mouth", 1.3) + mouth * (-0.08 * ey)
    out["mouthRollLower"] = lower * (0.04 * ey + 0.02 * ez)
    out["mouthRollUpper"] = upper * (0.04 * ey - 0.02 * ez)
    out["mouthShrugLower"] = lower * (0.04 * ez) + chin * (0.02 * ez)
    out["mouthShrugUpper"] = upper * (0.04 * ez)
    assert set(out) == set(ARKIT51), set(ARKIT51) ^ set(out)
    return {name: out[name] for name in ARKIT51}
