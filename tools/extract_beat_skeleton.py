"""Make diffsheg_core/beat_skeleton.json from a BEAT BVH made for DiffSHEG.

The JSON holds the 75-joint BEAT hierarchy (names, parents, offsets, channels, End
Sites) and row 0 of the file, the template pose that `diffsheg_core.bvh.write_bvh`
gives the 28 joints the model does not drive. Run from the repository root:

    python tools/extract_beat_skeleton.py ../shared/data/beat/2_scott_0_1_1.bvh
"""

from __future__ import annotations

import argparse
from pathlib import Path

from diffsheg_core.bvh import BEAT_SKELETON_PATH, read_bvh, save_skeleton_json

NOTE = ("75-joint BEAT skeleton and template pose (row 0) of BEAT take 2_scott_0_1_1 as the "
        "DiffSHEG repository ships it (assets/data.tar.gz, bvh_rot_vis); BEAT data, CC BY-NC 4.0. "
        "Made by tools/extract_beat_skeleton.py.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bvh", type=Path, help="BEAT BVH file (15 fps, template pose in row 0)")
    parser.add_argument("--fps", type=float, default=15.0, help="real frame rate of the file")
    parser.add_argument("--out", type=Path, default=BEAT_SKELETON_PATH)
    args = parser.parse_args()
    data = read_bvh(args.bvh, fps=args.fps)
    if len(data.joint_names) != 75:
        raise SystemExit(f"{args.bvh}: expected the 75-joint BEAT skeleton, found {len(data.joint_names)} joints")
    path = save_skeleton_json(data, args.out, template_row=0, note=NOTE)
    print(f"wrote {path}: {len(data.joint_names)} joints, {data.frames.shape[1]} channels")


if __name__ == "__main__":
    main()
