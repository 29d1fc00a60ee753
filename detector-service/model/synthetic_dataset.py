#!/usr/bin/env python3
"""Writes a small synthetic dataset in the layout of `glasshouse dataset --out DIR`.

Shaded discs of fruit colour among leaves, stems, grey structure, floor and a constant sky,
with the simulator's albedo ranges and Lambert shading factor in [0.45, 1]; about a third of
the frames also hold one fruit of a fixed unripe yellow or leaf-green colour, as the row scenes
do. It exists to test train.py without the simulator; models trained on it are not for use.
Usage: python synthetic_dataset.py --out DIR [--frames 40 --width 160 --height 120 --seed 7]
"""

import argparse
import json
from pathlib import Path

import numpy as np

SKY_RGB = (170, 200, 230)
FLOOR_ALBEDO = (120.0, 112.0, 104.0)
STRUCTURE_ALBEDO = (150.0, 150.0, 155.0)
STEM_ALBEDO = (45.0, 95.0, 35.0)
LEAF_RANGE = ((45, 80), (115, 160), (25, 50))
FRUIT_RANGE = {
    "red": ((190, 225), (20, 40), (15, 35)),
    "green": ((135, 160), (170, 195), (35, 60)),
}
# Row scenes also hold a few fruits of fixed unripe colours, still labelled fruit; the green
# one has a leaf's colour and cannot be told from leaves by colour.
OTHER_UNRIPE_ALBEDOS = ((230.0, 200.0, 30.0), (70.0, 125.0, 30.0))
AMBIENT, DIFFUSE = 0.45, 0.55


def albedo_in(rng, ranges):
    return np.array([rng.uniform(lo, hi) for lo, hi in ranges])


def paint(image, mask, albedo, shading):
    """Lambert-shaded RGB8 like the simulator: round(albedo * shading), shading per pixel."""
    image[mask] = np.clip(albedo[None, :] * shading[mask][:, None] + 0.5, 0, 255).astype(np.uint8)


def ellipse_mask(shape_px, centre_px, radii_px, angle_rad):
    rows, cols = np.mgrid[: shape_px[0], : shape_px[1]]
    dy, dx = rows - centre_px[0], cols - centre_px[1]
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    u, v = (c * dx + s * dy) / radii_px[1], (-s * dx + c * dy) / radii_px[0]
    return u * u + v * v <= 1.0, u, v


def frame(rng, height_px, width_px, colour):
    """One frame and its fruit label."""
    image = np.empty((height_px, width_px, 3), np.uint8)
    label = np.zeros((height_px, width_px), np.uint8)
    image[:] = SKY_RGB
    horizon_px = int(rng.uniform(0.1, 0.35) * height_px)
    floor_px = int(rng.uniform(0.75, 0.9) * height_px)
    flat = np.full((height_px, width_px), rng.uniform(0.6, 1.0))
    below = np.zeros((height_px, width_px), bool)
    below[floor_px:] = True
    paint(image, below, np.array(FLOOR_ALBEDO), flat)
    for _ in range(rng.integers(1, 4)):  # rails and posts
        bar = np.zeros_like(below)
        if rng.random() < 0.5:
            y = rng.integers(horizon_px, height_px - 4)
            bar[y : y + rng.integers(2, 6)] = True
        else:
            x = rng.integers(0, width_px - 4)
            bar[:, x : x + rng.integers(2, 6)] = True
        paint(image, bar, np.array(STRUCTURE_ALBEDO), np.full(flat.shape, rng.uniform(0.45, 1)))
    for _ in range(rng.integers(2, 5)):  # stems
        stem = np.zeros_like(below)
        x = rng.integers(0, width_px - 3)
        stem[horizon_px // 2 : floor_px, x : x + rng.integers(1, 4)] = True
        paint(image, stem, np.array(STEM_ALBEDO), np.full(flat.shape, rng.uniform(0.45, 1)))
    # Fruit and leaves in random depth order, so leaves cover fruit and fruit covers leaves.
    items = ["leaf"] * int(rng.integers(25, 45)) + ["fruit"] * int(rng.integers(2, 6))
    if rng.random() < 0.3:
        items.append("other")
    for kind in rng.permutation(items):
        centre = (rng.uniform(horizon_px * 0.5, floor_px), rng.uniform(0, width_px))
        if kind == "leaf":
            radii = (rng.uniform(2, 6), rng.uniform(5, 14))
            mask, _, _ = ellipse_mask(image.shape, centre, radii, rng.uniform(0, np.pi))
            shading = np.full(flat.shape, rng.uniform(0.45, 1))
            paint(image, mask, albedo_in(rng, LEAF_RANGE), shading)
            label[mask] = 0
        else:
            radius = rng.uniform(3, 8)
            radii = (radius, radius * rng.uniform(0.8, 1.2))
            mask, u, v = ellipse_mask(image.shape, centre, radii, 0)
            normal_z = np.sqrt(np.clip(1 - u * u - v * v, 0, 1))
            n_dot_l = (0.3 * u - 0.2 * v + normal_z) / np.sqrt(1.13)
            shading = AMBIENT + DIFFUSE * np.clip(n_dot_l, 0, 1)
            albedo = (albedo_in(rng, FRUIT_RANGE[colour]) if kind == "fruit"
                      else np.array(OTHER_UNRIPE_ALBEDOS[rng.integers(2)]))
            paint(image, mask, albedo, shading)
            label[mask] = 1
    return image, label


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, required=True, help="dataset directory to write")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--width", type=int, default=160, help="frame width in pixels")
    parser.add_argument("--height", type=int, default=120, help="frame height in pixels")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    colours = ["red" if i % 2 == 0 else "green" for i in range(args.frames)]
    frames = [frame(rng, args.height, args.width, c) for c in colours]
    args.out.mkdir(parents=True, exist_ok=True)
    np.save(args.out / "rgb.npy", np.stack([f[0] for f in frames]))
    np.save(args.out / "label.npy", np.stack([f[1] for f in frames]))
    meta = {"frames": args.frames, "width": args.width, "height": args.height,
            "fruit_colour": colours, "seed": args.seed}
    (args.out / "meta.json").write_text(json.dumps(meta) + "\n")
    (args.out / "done").write_text("")


if __name__ == "__main__":
    main()
