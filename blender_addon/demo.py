"""A demo character made from nothing but the package: the BEAT skeleton (embedded in
diffsheg_core) as an armature with simple limb shapes, a head mesh with a few ARKit
shape keys, a camera, and Workbench preview render settings."""

from __future__ import annotations

import bmesh
import bpy
import numpy as np
from mathutils import Matrix, Vector

from diffsheg_core.bvh import beat_skeleton
from diffsheg_core.rigs import ARKIT51

SCALE = 0.01  # BEAT offsets are centimetres

# ARKit shapes the demo face has: vertex selector (x, y, z in head-local units, Z up,
# face towards -Y) -> displacement.
_FACE_SHAPES = {
    "jawOpen": (lambda v: v.z < -0.1 and v.y < 0.0, Vector((0.0, 0.0, -0.06))),
    "mouthSmileLeft": (lambda v: -0.45 < v.z < -0.1 and v.y < -0.5 and v.x > 0.15, Vector((0.03, 0.0, 0.03))),
    "mouthSmileRight": (lambda v: -0.45 < v.z < -0.1 and v.y < -0.5 and v.x < -0.15, Vector((-0.03, 0.0, 0.03))),
    "browInnerUp": (lambda v: v.z > 0.3 and v.y < -0.5 and abs(v.x) < 0.35, Vector((0.0, 0.0, 0.05))),
    "eyeBlinkLeft": (lambda v: 0.05 < v.z < 0.35 and v.y < -0.7 and 0.15 < v.x < 0.5, Vector((0.0, 0.04, -0.02))),
    "eyeBlinkRight": (lambda v: 0.05 < v.z < 0.35 and v.y < -0.7 and -0.5 < v.x < -0.15, Vector((0.0, 0.04, -0.02))),
}
assert set(_FACE_SHAPES) <= set(ARKIT51)


def _to_blender(offset) -> Vector:
    """BEAT (Y up, facing +Z) -> Blender (Z up, facing -Y), in metres."""
    x, y, z = offset
    return Vector((x, -z, y)) * SCALE


def build_beat_armature(name: str = "DemoSpeaker"):
    """The 75-joint BEAT skeleton as an armature (bone names as the BVH importer gives)."""
    skel = beat_skeleton()
    positions: list[Vector] = []
    for j, parent in enumerate(skel.parents):
        base = positions[parent] if parent >= 0 else Vector((0.0, 0.0, 1.0))
        positions.append(base + _to_blender(skel.offsets[j]))
    children = {j: [c for c, p in enumerate(skel.parents) if p == j] for j in range(len(skel.parents))}
    arm = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    for j, joint in enumerate(skel.joint_names):
        eb = arm.edit_bones.new(joint)
        eb.head = positions[j]
        if children[j]:
            tail = sum((positions[c] for c in children[j]), Vector()) / len(children[j])
        elif j in skel.end_sites:
            tail = positions[j] + _to_blender(skel.end_sites[j])
        else:
            tail = positions[j] + Vector((0.0, 0.0, 0.03))
        if (tail - eb.head).length < 1e-3:
            tail = eb.head + Vector((0.0, 0.0, 0.03))
        eb.tail = tail
    for j, parent in enumerate(skel.parents):
        if parent >= 0:
            arm.edit_bones[skel.joint_names[j]].parent = arm.edit_bones[skel.joint_names[parent]]
    bpy.ops.object.mode_set(mode="OBJECT")
    _add_limb_shapes(ob)
    return ob


def _add_limb_shapes(armature) -> None:
    """A tapered box per bone, parented to it, so Workbench renders the body."""
    for bone in armature.data.bones:
        if bone.length < 0.015 or bone.name.startswith(("Head", "Hips")) or "End" in bone.name:
            continue
        width = 0.06 if bone.name.startswith(("Spine", "Neck")) else 0.012 if "Hand" in bone.name and bone.name[-1].isdigit() else 0.035
        mesh = bpy.data.meshes.new(f"shape_{bone.name}")
        bm = bmesh.new()
        bmesh.ops.create_cube(bm, size=1.0)
        bmesh.ops.transform(bm, verts=bm.verts, matrix=Matrix.Diagonal((width, bone.length, width, 1.0)) @
                            Matrix.Translation((0.0, 0.5, 0.0)))
        bm.to_mesh(mesh)
        bm.free()
        shape = bpy.data.objects.new(mesh.name, mesh)
        bpy.context.scene.collection.objects.link(shape)
        _parent_to_bone(shape, armature, bone.name, at_head=True)


def _parent_to_bone(ob, armature, bone_name: str, at_head: bool) -> None:
    bone = armature.data.bones[bone_name]
    ob.parent, ob.parent_type, ob.parent_bone = armature, "BONE", bone_name
    # Bone parenting puts the child at the bone's tail; move it back to the head.
    ob.matrix_parent_inverse = Matrix.Translation((0.0, -bone.length if at_head else 0.0, 0.0))


def build_face(armature, name: str = "DemoFace"):
    """A head (UV sphere) with a few ARKit shape keys, parented to the Head bone."""
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=1.0)
    bm.to_mesh(mesh)
    bm.free()
    ob = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(ob)
    ob.shape_key_add(name="Basis")
    for shape, (select, offset) in _FACE_SHAPES.items():
        key = ob.shape_key_add(name=shape, from_mix=False)
        for v, base in zip(key.data, mesh.vertices):
            if select(base.co):
                v.co = base.co + offset / 0.11
    ob.scale = (0.09, 0.1, 0.11)
    head = armature.data.bones["Head"]
    ob.parent, ob.parent_type, ob.parent_bone = armature, "BONE", "Head"
    ob.matrix_parent_inverse = Matrix.Translation((0.0, -head.length + 0.09, 0.01)) @ \
        head.matrix_local.to_3x3().inverted().to_4x4()
    return ob


def setup_preview(scene, resolution: tuple[int, int] = (320, 240)) -> None:
    """Camera on the speaker and a small Workbench render to MP4 with the audio."""
    cam_data = bpy.data.cameras.new("DemoCamera")
    cam = bpy.data.objects.new("DemoCamera", cam_data)
    scene.collection.objects.link(cam)
    cam.location = (0.0, -3.0, 1.3)
    cam.rotation_euler = (np.radians(90.0), 0.0, 0.0)
    cam_data.lens = 40
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    set_video_output(scene)


def set_video_output(scene) -> None:
    """MP4 (H.264) with AAC audio, so the sound strip is muxed into the video."""
    settings = scene.render.image_settings
    if "media_type" in settings.bl_rna.properties:  # Blender 5.0
        settings.media_type = "VIDEO"
    settings.file_format = "FFMPEG"
    scene.render.ffmpeg.format = "MPEG4"
    scene.render.ffmpeg.codec = "H264"
    scene.render.ffmpeg.audio_codec = "AAC"
