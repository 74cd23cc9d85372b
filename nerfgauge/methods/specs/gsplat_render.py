"""Render a split of a nerfgauge dataset from a checkpoint of gsplat's simple trainer
(examples/simple_trainer.py). The gsplat spec runs this file with the gsplat environment's
own interpreter (torch, gsplat, numpy, Pillow); it imports nothing of nerfgauge.

    python gsplat_render.py --ckpt RUN/out/ckpts/ckpt_N_rank0.pt --dataset DS --split test --out OUT

writes OUT/<split>/<frame>.png, RGBA with straight alpha (`evaluate` composites it onto its
background), one for each frame of DS/transforms_<split>.json, named after the frame's file.

Cameras: the trainer must run with --normalize_world_space False, so its Gaussians are in the
dataset's world. A frame's transform_matrix is OpenGL camera-to-world; gsplat takes
world-to-camera in OpenCV axes: viewmat = inverse(c2w @ diag(1, -1, -1, 1)). Intrinsics are
fl_x, fl_y, cx, cy, w, h (a frame's own over the file's), pixel (0, 0)'s centre at (0.5, 0.5)
as in gsplat and in our COLMAP export. Colours are the checkpoint's spherical harmonics
(sh0 and shN) of the trainer's degree, derived from shN's size.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def frames(dataset: Path, split: str) -> list:
    """[(name, viewmat [4, 4], K [3, 3], width, height)] of the split's frames."""
    meta = json.loads((dataset / f"transforms_{split}.json").read_text())
    cameras = []
    for frame in meta["frames"]:
        get = lambda key: frame.get(key, meta.get(key))  # noqa: E731: a frame's own intrinsics first
        width, height = int(get("w")), int(get("h"))
        fx = get("fl_x") if get("fl_x") is not None else 0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"]))
        fy = get("fl_y") if get("fl_y") is not None else fx
        cx = get("cx") if get("cx") is not None else 0.5 * width
        cy = get("cy") if get("cy") is not None else 0.5 * height
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64) @ GL_TO_CV
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
        cameras.append((Path(frame["file_path"]).name.split(".")[0], np.linalg.inv(c2w), K, width, height))
    return cameras


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True, type=Path)
    parser.add_argument("--dataset", required=True, type=Path)
    parser.add_argument("--split", required=True)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--device", default="cuda")
    args = parser.parse_args(argv)

    import torch  # torch, gsplat, PIL: the gsplat environment's, imported when it renders (frames() needs numpy only)
    from gsplat import rasterization  # gsplat: see above
    from PIL import Image  # PIL: see above

    splats = torch.load(args.ckpt, map_location=args.device, weights_only=True)["splats"]
    colours = torch.cat([splats["sh0"], splats["shN"]], 1)  # [N, K, 3]
    sh_degree = int(round(math.sqrt(colours.shape[1]))) - 1
    folder = args.out / args.split
    folder.mkdir(parents=True, exist_ok=True)
    for name, viewmat, K, width, height in frames(args.dataset, args.split):
        with torch.no_grad():
            rgb, alpha, _ = rasterization(
                means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
                opacities=torch.sigmoid(splats["opacities"]), colors=colours,
                viewmats=torch.tensor(viewmat, dtype=torch.float32, device=args.device)[None],
                Ks=torch.tensor(K, dtype=torch.float32, device=args.device)[None],
                width=width, height=height, sh_degree=sh_degree)
        alpha = alpha[0].clamp(0.0, 1.0)  # [H, W, 1]
        straight = torch.where(alpha > 0, rgb[0] / alpha.clamp(min=1e-8), torch.zeros_like(rgb[0])).clamp(0.0, 1.0)
        rgba = torch.cat([straight, alpha], dim=-1).cpu().numpy()
        Image.fromarray(np.round(rgba * 255.0).astype(np.uint8), "RGBA").save(folder / f"{name}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
