"""A demo character made from nothing but the package: the BEAT skeleton (embedded in
diffsheg_core) as an armature with simple limb shapes, a stylised head with all 51 ARKit
shape keys (demo_face.py), a wide and a close-up camera that the preview cuts between,
and Workbench preview render settings."""

from __future__ import annotations

import bmesh
import bpy
import numpy as np
from mathutils import Matrix, Vector

from diffsheg_core.bvh import beat_skeleton

from .demo_face import build_face_mesh

SCALE = 0.01  # BEAT offsets are centimetres


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
    _add_torso(ob)
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


def _add_torso(armature) -> None:
    """A rounded chest and belly around the spine, so the body reads as a body."""
    for bone, size, lift in (("Spine2", (0.17, 0.11, 0.2), 0.0), ("Spine", (0.15, 0.1, 0.14), 0.0)):
        mesh = bpy.data.meshes.new(f"shape_{bone}_body")
        bm = bmesh.new()
        bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=12, radius=1.0)
        bmesh.ops.transform(bm, verts=bm.verts, matrix=Matrix.Diagonal((size[0], size[2], size[1], 1.0)))
        bm.to_mesh(mesh)
        bm.free()
        shape = bpy.data.objects.new(mesh.name, mesh)
        bpy.context.scene.collection.objects.link(shape)
        _parent_to_bone(shape, armature, bone, at_head=True)
        shape.location.y += lift


def _parent_to_bone(ob, armature, bone_name: str, at_head: bool) -> None:
    bone = armature.data.bones[bone_name]
    ob.parent, ob.parent_type, ob.parent_bone = armature, "BONE", bone_name
    # Bone parenting puts the child at the bone's tail; move it back to the head.
    ob.matrix_parent_inverse = Matrix.Translation((0.0, -bone.length if at_head else 0.0, 0.0))


def build_face(armature, name: str = "DemoFace"):
    """The demo head (demo_face.py: eyes, brows, mouth, all 51 ARKit shape keys), parented
    to the Head bone."""
    ob = build_face_mesh(name)
    ob.scale = (0.09, 0.1, 0.11)
    head = armature.data.bones["Head"]
    ob.parent, ob.parent_type, ob.parent_bone = armature, "BONE", "Head"
    ob.matrix_parent_inverse = Matrix.Translation((0.0, -head.length + 0.09, 0.01)) @ \
        head.matrix_local.to_3x3().inverted().to_4x4()
    return ob


CUT_SECONDS = 4.0  # the preview cuts between the wide shot and the face's close-up


def setup_preview(scene, armature, resolution: tuple[int, int] = (640, 360)) -> None:
    """A wide (whole body) and a close-up (face) camera, cut between every CUT_SECONDS
    through timeline markers, and a Workbench render to MP4 with the audio."""
    head = armature.matrix_world @ armature.data.bones["Head"].head_local
    hips = armature.matrix_world @ armature.data.bones["Hips"].head_local
    wide = _camera(scene, "DemoCamera", (0.0, -4.2, hips.z - 0.05), lens=40)
    close = _camera(scene, "DemoCloseUp", (0.0, -1.1, head.z + 0.05), lens=55)
    close.location -= hips  # then kept this far from the hips as they shift their weight
    walk = close.constraints.new("COPY_LOCATION")
    walk.target, walk.subtarget, walk.use_offset = armature, "Hips", True
    follow = close.constraints.new("DAMPED_TRACK")  # keeps the moving head in frame
    follow.target, follow.subtarget, follow.track_axis = armature, "Head", "TRACK_NEGATIVE_Z"
    follow.head_tail = 1.0
    world = bpy.data.worlds.new("DemoWorld")
    world.color = (0.18, 0.2, 0.24)
    scene.world = world
    scene.camera = wide
    fps = scene.render.fps / scene.render.fps_base
    for i in range(64):  # the timeline of a take of up to about four minutes; later frames stay on the last
        marker = scene.timeline_markers.new(f"shot {i + 1}", frame=scene.frame_start + round(i * CUT_SECONDS * fps))
        marker.camera = close if i % 2 else wide
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "MATERIAL"
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    set_video_output(scene)


def _camera(scene, name: str, location, lens: float):
    data = bpy.data.cameras.new(name)
    data.lens = lens
    cam = bpy.data.objects.new(name, data)
    scene.collection.objects.link(cam)
    cam.location = location
    cam.rotation_euler = (np.radians(90.0), 0.0, 0.0)
    return cam


def set_video_output(scene) -> None:
    """MP4 (H.264) with AAC audio, so the sound strip is muxed into the video."""
    settings = scene.render.image_settings
    if "media_type" in settings.bl_rna.properties:  # Blender 5.0
        settings.media_type = "VIDEO"
    settings.file_format = "FFMPEG"
    scene.render.ffmpeg.format = "MPEG4"
    scene.render.ffmpeg.codec = "H264"
    scene.render.ffmpeg.audio_codec = "AAC"
