"""A demo character made from nothing but the package: the BEAT skeleton (embedded in
diffsheg_core) as an armature, a person's body on it (demo_body.py: MakeHuman's CC0 base mesh
fitted to the skeleton, skinned, clothed by region) with all 51 ARKit shape keys, a wide and
a close-up camera that the preview cuts between, and Workbench preview render settings."""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Vector

from diffsheg_core.bvh import beat_skeleton

from .demo_body import add_face_keys, build_body

SCALE = 0.01  # BEAT offsets are centimetres


def _to_blender(offset) -> Vector:
    """BEAT (Y up, facing +Z) -> Blender (Z up, facing -Y), in metres."""
    x, y, z = offset
    return Vector((x, -z, y)) * SCALE


def build_beat_armature(name: str = "DemoSpeaker", body: bool = True):
    """The 75-joint BEAT skeleton as an armature (bone names as the BVH importer gives), with
    the demo speaker's body mesh (`name` + "Body") skinned to it unless `body` is False."""
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
    if body:
        build_body(ob, rest_heads(ob), f"{name}Body")
    return ob


def rest_heads(armature) -> dict[str, np.ndarray]:
    """Every bone's rest head in the armature's space."""
    return {b.name: np.array(b.head_local) for b in armature.data.bones}


def body_of(armature):
    """The demo speaker's body mesh (build_beat_armature)."""
    return bpy.data.objects[f"{armature.name}Body"]


def build_face(armature):
    """The demo speaker's face: the 51 ARKit shape keys (Face Units targets) on its body mesh,
    which it returns."""
    ob = body_of(armature)
    if ob.data.shape_keys is None:
        add_face_keys(ob, rest_heads(armature))
    return ob


CUT_SECONDS = 4.0  # the preview cuts between the wide shot and the face's close-up


def setup_preview(scene, armature, resolution: tuple[int, int] = (640, 360)) -> None:
    """A wide (whole body) and a close-up (face) camera, cut between every CUT_SECONDS
    through timeline markers, and a Workbench render to MP4 with the audio."""
    head = armature.matrix_world @ armature.data.bones["Head"].head_local
    hips = armature.matrix_world @ armature.data.bones["Hips"].head_local
    wide = _camera(scene, "DemoCamera", (0.0, -4.2, hips.z - 0.05), lens=40)
    close = _camera(scene, "DemoCloseUp", (0.0, -1.1, head.z + 0.05), lens=50)
    close.location -= hips  # then kept this far from the hips as they shift their weight
    walk = close.constraints.new("COPY_LOCATION")
    walk.target, walk.subtarget, walk.use_offset = armature, "Hips", True
    follow = close.constraints.new("DAMPED_TRACK")  # keeps the moving head in frame
    follow.target, follow.subtarget, follow.track_axis = armature, "Head", "TRACK_NEGATIVE_Z"
    follow.head_tail = 0.7  # between the eyes and the nose of the demo body
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
    scene.display.render_aa = "FXAA"  # one sample: half the time of the default 8 in software GL, alike at 640x360
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
