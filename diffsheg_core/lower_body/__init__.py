"""The lower body: hips (rotation and translation) and legs under the generated upper body,
with the feet planted.

A whole-body model (layout `beat_body`, with a lower-body branch: the bundled model) makes
the hips, legs and the hips' translation itself: `plant` low-passes them, keeps the hips
within the real capture's range and lets the feet stand or step (live, `PlantStream` does
so as the frames come). For a model whose layout stops at the waist (`beat`: v8 and the
official BEAT checkpoint), `add_lower_body` cuts what a standing talker's hips and legs do
from a real full-body capture by motion matching, with the feet planted (live,
`LowerBodyStream`). One way, as DiffSHEG's expression-to-gesture flow: the upper body the
model made drives the lower body, never the reverse.

    body      the canonical body's legs (BEAT skeleton, floor y = 0): joints, feet, contacts,
              figures (feet_figures, foot_yaw); a Motion's lower body taken out or put in
    leg_ik    pins over contact spans and two-bone IK (the canonical body's and a rig's legs)
    feet      the feet pinned where they landed (plant_feet) or standing and stepping
              (FootSteps, step_feet)
    capture   the capture material (LowerBodyLibrary, assets/lower_body.npz, build) and the
              offline lower body (add_lower_body, plant)
    stream    the same live, a hop of frames at a time (LowerBodyStream, PlantStream)

`python -m diffsheg_core.lower_body --capture TAKE.npz` builds the library.
numpy only: it runs inside Blender.
"""

from __future__ import annotations

from .body import (CONTACT_HEIGHT, JOINTS, LEGS, ankle_figures, canonical_leg_length, contacts, feet_figures,
                   figures, foot_positions, foot_skating, foot_yaw, lower_rotations, upper_body, with_lower_body)
from .capture import (ASSET, HELD_OUT_S, LAYOUTS, LowerBodyLibrary, add_lower_body, arm_energy, build,
                      legs_source, main, plant, read_capture, sample, settle)
from .feet import FootSteps, plant_feet, step_feet
from .stream import LowerBodyStream, PlantStream

__all__ = [
    "ASSET", "CONTACT_HEIGHT", "HELD_OUT_S", "JOINTS", "LAYOUTS", "LEGS", "FootSteps", "LowerBodyLibrary",
    "LowerBodyStream", "PlantStream", "add_lower_body", "ankle_figures", "arm_energy", "build",
    "canonical_leg_length", "contacts", "feet_figures", "figures", "foot_positions", "foot_skating", "foot_yaw",
    "legs_source",
    "lower_rotations", "main", "plant", "plant_feet", "read_capture", "sample", "settle", "step_feet", "upper_body",
    "with_lower_body",
]
