"""``python -m course_lib sfm-to-nerf SFM_OUT --images IMAGES_DIR --out NERF_DIR``: SfM poses feed a NeRF.

Turns the COLMAP text model that ``python -m course_lib sfm`` writes (``SFM_OUT/colmap``) and its
images into a NeRF data set in the Blender format; the conversion is
:func:`course_lib.data.sfm_to_nerf.sfm_to_nerf`, whose module explains poses, scale and images.
"""

from __future__ import annotations

import argparse

from course_lib.data.sfm_to_nerf import sfm_to_nerf


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sfm_out", help="output folder of `python -m course_lib sfm` (with colmap/), or a COLMAP text model folder")
    p.add_argument("--images", required=True, help="folder with the images named in the model (the P3 folder the SfM ran on)")
    p.add_argument("--out", required=True, help="output NeRF folder (Blender format: transforms_train.json, transforms_test.json, images/)")
    p.add_argument("--size", type=int, default=100, help="output image width in pixels (default 100; the height keeps the aspect)")
    p.add_argument("--test-every", type=int, default=8, help="every n-th registered image becomes a test view (default 8; 0: none)")
    p.add_argument("--percentile", type=float, default=95.0, help="robust radius of the points' sphere mapped to radius 1 (default 95)")
    p.add_argument("--alpha-dir", default=None, help="optional folder of RGBA versions of the images (transparent background kept)")


def run(args) -> int:
    s = sfm_to_nerf(args.sfm_out, args.images, args.out, args.size, args.test_every, args.percentile, args.alpha_dir)
    print(f"NeRF data set in {args.out}: {len(s['train'])} train + {len(s['test'])} test views at "
          f"{s['image_size'][0]}x{s['image_size'][1]}, camera_angle_x {s['camera_angle_x']:.4f} rad; scene centred and "
          f"scaled by {s['scale']:.4g} (points' sphere -> radius 1), cameras {s['camera_distance'][0]:.2f}-"
          f"{s['camera_distance'][1]:.2f} from the origin, near/far for it {s['near']:.2f}/{s['far']:.2f}")
    print(f"train it: python -m course_lib nerf train {args.out} --preset fast")
    return 0
