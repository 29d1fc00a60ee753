#!/usr/bin/env python3
"""Trains the detector's per-pixel fruit segmenter on simulator frames and exports it as ONNX.

The network is a small fully convolutional one with a fine and a coarse path (README.md draws
it):

- full resolution: Conv 3x3 on the input, for colour and edges;
- 1/4 resolution: Conv 4x4 with stride 4 on the input;
- 1/8 resolution: Conv 2x2 with stride 2, then dilated Conv 3x3 layers (dilations 1, 2, 3, 4)
  with residual additions, which see about 170 px around each pixel: the shape and shading of
  what the pixel belongs to. DepthToSpace brings this back to 1/4 resolution, where it meets
  the 1/4 features, and again to full resolution;
- a head of 1x1 convolutions on the full-resolution features and the coarse path's, then a
  sigmoid.

It is trained on random crops of the frames, in numpy, with hand-written backpropagation, Adam
and a weighted binary cross-entropy, seeded and on one CPU thread. --logit-offset then sets the
operating point.

Input data: directories written by `glasshouse dataset --out DIR`, each holding rgb.npy
(N, H, W, 3) uint8, label.npy (N, H, W) uint8 (1 = fruit), depth.npy (N, H, W) uint16 in
millimetres (0 = no depth; read for the metrics and --depth) and meta.json (frames, width,
height, fruit_colour per frame, seed, world).

Outputs: the ONNX model at --out (input `rgb` float32 [1, 3, height, width] = RGB8 / 255, or
with --depth `rgbd` float32 [1, 4, height, width] with depth in metres as the fourth channel;
output `fruit_probability` float32 [1, 1, height, width]; height and width multiples of 8, the
metadata's `size_multiple`) and, beside it with the suffix .json, the held-out metrics with
the command line, seed, parameter count and datasets. Metrics are pixel precision, recall, F1
and IoU of the fruit class at the detector's threshold 0.5 on the --test datasets (or, without
them, on the last --held-out-share of each fruit colour's frames), over every pixel and over
the pixels with depth (those the detector turns into points).
"""

import argparse
import hashlib
import json
import os
import shlex
import sys
import time
from pathlib import Path

# One BLAS thread, set before numpy loads: results then cannot depend on the machine's core
# count, and the machine is shared.
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
os.environ["MKL_NUM_THREADS"] = "1"

import numpy as np  # noqa: E402
from numpy.lib.stride_tricks import as_strided  # noqa: E402

THRESHOLD = 0.5
OPSET = 13
IR_VERSION = 8
# Height and width of the input must be multiples of this (the context path's stride); the
# runtime pads the image with zeros at the bottom and right up to it and crops the output.
SIZE_MULTIPLE = 8
# The cost is stated for the camera's 640x480 frames.
COST_FRAME_PX = 640 * 480
MAX_MULTIPLY_ADDS_PER_FRAME = 400e6
MAX_ABS_DIFF_TO_REFERENCE = 1e-4
DEPTH_SCALE_M = 0.001
# The unit depth is normalised to before the first layers.
DEPTH_UNIT_M = 0.1
F32 = np.float32


def parse_args(argv):
    here = Path(__file__).resolve().parent

    class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
        pass

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--data", type=Path, nargs="+", required=True,
                        help="training dataset directories (rgb.npy, label.npy, meta.json)")
    parser.add_argument("--test", type=Path, nargs="*", default=[],
                        help="held-out dataset directories (other scene seeds); without them "
                             "the last --held-out-share of each colour's training frames is "
                             "held out")
    parser.add_argument("--out", type=Path, default=None,
                        help="ONNX file to write; metrics go beside it as .json "
                             "(default: fruit-segmenter.onnx beside train.py)")
    parser.add_argument("--seed", type=int, default=1, help="seed of sampling and initialisation")
    parser.add_argument("--depth", action="store_true",
                        help="feed depth (metres, 0 = none) as a fourth input channel, input "
                             "`rgbd`: for comparison only, the detector feeds colour and "
                             "refuses such a model (README.md: it gained nothing)")
    parser.add_argument("--steps", type=int, default=12000, help="Adam steps")
    parser.add_argument("--batch", type=int, default=8, help="crops per Adam step")
    parser.add_argument("--crop-px", type=int, default=160,
                        help="side of the training crops (a multiple of 4)")
    parser.add_argument("--fruit-crop-share", type=float, default=0.6,
                        help="share of crops centred near a fruit pixel (the rest anywhere)")
    parser.add_argument("--fruit-weight", type=float, default=2.0,
                        help="loss weight of fruit pixels against 1 for the rest")
    parser.add_argument("--full-channels", type=int, default=8,
                        help="channels of the full-resolution Conv 3x3 (colour, edges)")
    parser.add_argument("--quarter-channels", type=int, default=16,
                        help="channels of the 1/4-resolution Conv 4x4 stride 4")
    parser.add_argument("--context-channels", type=int, default=32,
                        help="channels of the 1/8-resolution context layers")
    parser.add_argument("--dilations", type=str, default="1,2,3,4",
                        help="dilations of the context layers (Conv 3x3 at 1/8 resolution)")
    parser.add_argument("--up8-channels", type=int, default=8,
                        help="channels the context hands back at 1/4 resolution")
    parser.add_argument("--mid-channels", type=int, default=16,
                        help="channels of the 1/4-resolution layer joining context and detail")
    parser.add_argument("--up-channels", type=int, default=4,
                        help="full-resolution channels the coarse path hands the head")
    parser.add_argument("--head-channels", type=int, default=8,
                        help="width of the head's hidden 1x1 layer")
    parser.add_argument("--colour-weights", type=str, default="leaf-green=3",
                        help="how much more often crops come from frames of these fruit "
                             "colours (colour=weight, comma separated; others weigh 1)")
    parser.add_argument("--logit-offset", type=float, default=3.0,
                        help="added to the output's logit at export, which moves the "
                             "detector's 0.5 threshold to a trained probability of "
                             "1 / (1 + e^offset) (3.0: 0.047); chosen in the planning loop on "
                             "tuning seeds (README.md)")
    parser.add_argument("--learning-rate", type=float, default=3e-3, help="Adam step size")
    parser.add_argument("--held-out-share", type=float, default=0.2,
                        help="without --test: last share of each colour's frames held out")
    args = parser.parse_args(argv)
    args.out = args.out or here / "fruit-segmenter.onnx"
    args.dilation_list = [int(d) for d in args.dilations.split(",") if d]
    if args.crop_px % SIZE_MULTIPLE or args.crop_px < 16:
        parser.error(f"--crop-px must be a multiple of {SIZE_MULTIPLE}, at least 16")
    args.colour_weight = {}
    for item in filter(None, args.colour_weights.split(",")):
        colour, _, weight = item.partition("=")
        args.colour_weight[colour.strip()] = float(weight)
    if min([args.full_channels, args.quarter_channels, args.context_channels, args.up8_channels,
            args.mid_channels, args.up_channels, args.head_channels, *args.dilation_list]) < 1:
        parser.error("channel counts and dilations must be positive")
    return args


# ---------------------------------------------------------------- data


class Dataset:
    """Frames of one or more dataset directories as read-only memory maps (a dataset can be
    gigabytes), with each frame's fruit colour and world."""

    def __init__(self, dirs, with_depth):
        self.parts, self.index, self.colours, self.worlds = [], [], [], []
        shape = None
        for d in dirs:
            meta = json.loads((d / "meta.json").read_text())
            rgb = np.load(d / "rgb.npy", mmap_mode="r")
            label = np.load(d / "label.npy", mmap_mode="r")
            # Depth is read when present: the metrics count the pixels with depth apart.
            depth = (np.load(d / "depth.npy", mmap_mode="r") if (d / "depth.npy").exists()
                     else None)
            if with_depth and depth is None:
                sys.exit(f"{d}: --depth needs depth.npy (a newer `glasshouse dataset`)")
            expected = (meta["frames"], meta["height"], meta["width"])
            if rgb.shape != expected + (3,) or label.shape != expected or rgb.dtype != np.uint8:
                sys.exit(f"{d}: shapes {rgb.shape} {rgb.dtype} / {label.shape} "
                         f"do not match meta {expected}")
            if depth is not None and (depth.shape != expected or depth.dtype != np.uint16):
                sys.exit(f"{d}: depth.npy {depth.shape} {depth.dtype} is not {expected} uint16")
            if len(meta["fruit_colour"]) != meta["frames"]:
                sys.exit(f"{d}/meta.json: fruit_colour needs one entry per frame")
            if shape not in (None, expected[1:]):
                sys.exit(f"{d}: frames of {expected[1:]} among frames of {shape}")
            shape = expected[1:]
            world = world_name(meta)
            part = len(self.parts)
            self.parts.append((d, meta, rgb, label, depth))
            for i in range(meta["frames"]):
                self.index.append((part, i))
                self.colours.append(meta["fruit_colour"][i])
                self.worlds.append(world)
        self.height, self.width = shape
        self.with_depth = with_depth

    def __len__(self):
        return len(self.index)

    def frame(self, k):
        """(rgb uint8 (H, W, 3), depth uint16 (H, W) or None, fruit bool (H, W))."""
        part, i = self.index[k]
        _, _, rgb, label, depth = self.parts[part]
        return (np.asarray(rgb[i]), None if depth is None else np.asarray(depth[i]),
                np.asarray(label[i]) == 1)

    def describe(self):
        return [{"path": str(d), "shape": list(rgb.shape), "seed": meta.get("seed"),
                 "scenarios": meta.get("scenarios"), "world": world_name(meta),
                 "fruit_colours": sorted(set(meta["fruit_colour"]))}
                for d, meta, rgb, _, _ in self.parts]


def world_name(meta):
    """`realistic` when the frames have the realistic world's light, else `clean`."""
    world = meta.get("world") or {}
    return "realistic" if world.get("perception", {}).get("shadows") else "clean"


def split_frames(colours, held_out_share):
    """Train and held-out frame indices: the last share of each colour's frames is held out."""
    train, held_out = [], []
    for colour in sorted(set(colours)):
        frames = [i for i, c in enumerate(colours) if c == colour]
        n_held = max(1, int(round(held_out_share * len(frames)))) if len(frames) > 1 else 0
        train += frames[: len(frames) - n_held]
        held_out += frames[len(frames) - n_held:]
    return sorted(train), sorted(held_out)


def input_planes(rgb8, depth_mm, with_depth):
    """The model's input as (H, W, C) float32: RGB8 / 255 and, with depth, metres."""
    planes = [rgb8.astype(F32) / F32(255)]
    if with_depth:
        planes.append((depth_mm.astype(F32) * F32(DEPTH_SCALE_M))[..., None])
    return np.concatenate(planes, axis=2)


def padded_to_multiple(x):
    """Zero rows and columns at the bottom and right up to multiples of SIZE_MULTIPLE."""
    h, w = x.shape[:2]
    ph, pw = (-h) % SIZE_MULTIPLE, (-w) % SIZE_MULTIPLE
    if ph or pw:
        x = np.pad(x, ((0, ph), (0, pw)) + ((0, 0),) * (x.ndim - 2))
    return x


class CropSampler:
    """Random crops, each with a one-pixel margin for the full-resolution Conv (zeros beyond
    the frame, as the exported Conv pads): a share centred near a fruit pixel, the rest
    anywhere, frames drawn in proportion to their colour's weight. Crops start on the coarsest
    grid, as in a whole frame."""

    def __init__(self, data, frames, args, rng):
        self.data, self.frames, self.args, self.rng = data, frames, args, rng
        self.fruit_px = {k: np.flatnonzero(data.frame(k)[2]) for k in frames}
        self.with_fruit = [k for k in frames if self.fruit_px[k].size]
        self.p_all = self._weights(frames)
        self.p_fruit = self._weights(self.with_fruit)

    def _weights(self, frames):
        w = np.array([self.args.colour_weight.get(self.data.colours[k], 1.0) for k in frames])
        return w / w.sum() if len(frames) else w

    def batch(self):
        a, c = self.args, self.args.crop_px
        h, w = self.data.height, self.data.width
        xs, ys = [], []
        for _ in range(a.batch):
            if self.with_fruit and self.rng.random() < a.fruit_crop_share:
                k = self.with_fruit[self.rng.choice(len(self.with_fruit), p=self.p_fruit)]
                px = self.fruit_px[k][self.rng.integers(self.fruit_px[k].size)]
                cy, cx = divmod(int(px), w)
                top = cy - c // 2 + int(self.rng.integers(-c // 3, c // 3 + 1))
                left = cx - c // 2 + int(self.rng.integers(-c // 3, c // 3 + 1))
            else:
                k = self.frames[self.rng.choice(len(self.frames), p=self.p_all)]
                top = int(self.rng.integers(0, h - c + 1))
                left = int(self.rng.integers(0, w - c + 1))
            top = min(max(0, top), h - c) // SIZE_MULTIPLE * SIZE_MULTIPLE
            left = min(max(0, left), w - c) // SIZE_MULTIPLE * SIZE_MULTIPLE
            rgb, depth, fruit = self.data.frame(k)
            # The crop and its margin, zeros where the margin leaves the frame.
            y0, y1, x0, x1 = max(top - 1, 0), min(top + c + 1, h), max(left - 1, 0), \
                min(left + c + 1, w)
            planes = input_planes(rgb[y0:y1, x0:x1],
                                  None if depth is None else depth[y0:y1, x0:x1],
                                  self.data.with_depth)
            xs.append(np.pad(planes, ((y0 - (top - 1), top + c + 1 - y1),
                                      (x0 - (left - 1), left + c + 1 - x1), (0, 0))))
            ys.append(fruit[top: top + c, left: left + c])
        return np.stack(xs), np.stack(ys).astype(F32)


def input_statistics(data, frames, rng, n_frames=64):
    """Per-channel mean and standard deviation of the input, from a sample of frames."""
    pick = rng.choice(frames, min(n_frames, len(frames)), replace=False)
    c_in = 3 + data.with_depth
    xs = [input_planes(*data.frame(k)[:2], data.with_depth)[::4, ::4].reshape(-1, c_in)
          for k in sorted(pick)]
    x = np.concatenate(xs).astype(np.float64)
    mean, std = x.mean(axis=0), x.std(axis=0) + 1e-3
    if data.with_depth:
        # Depth is scaled so that a fruit's relief (a few cm) is a tenth of a unit and the
        # step at a silhouette a few units: what the first layers must tell apart.
        mean[3], std[3] = 0.0, DEPTH_UNIT_M
    return mean.astype(F32), std.astype(F32)


# ---------------------------------------------------------------- layers (NHWC, float32)


def conv_forward(x, w, b, stride=1, dilation=1):
    """Valid convolution of x (N, H, W, C) with w (k, k, C, O): output and the im2col columns."""
    k, _, c_in, c_out = w.shape
    n, h, wd, _ = x.shape
    span = dilation * (k - 1) + 1
    ho, wo = (h - span) // stride + 1, (wd - span) // stride + 1
    if k == 1 and stride == 1:
        cols = x
    else:
        s = x.strides
        cols = np.ascontiguousarray(as_strided(
            x, shape=(n, ho, wo, k, k, c_in),
            strides=(s[0], s[1] * stride, s[2] * stride, s[1] * dilation, s[2] * dilation, s[3]),
            writeable=False))
    out = cols.reshape(-1, k * k * c_in) @ w.reshape(-1, c_out)
    out += b
    return out.reshape(n, ho, wo, c_out), cols


def conv_backward(g, cols, w, x_shape, stride=1, dilation=1, need_input=True):
    """Gradients of conv_forward: (input, weight, bias); input is None unless need_input."""
    k, _, c_in, c_out = w.shape
    n, ho, wo, _ = g.shape
    g2 = g.reshape(-1, c_out)
    gw = (cols.reshape(-1, k * k * c_in).T @ g2).reshape(w.shape)
    gb = g2.sum(axis=0)
    if not need_input:
        return None, gw, gb
    gcols = g2 @ w.reshape(-1, c_out).T
    if k == 1 and stride == 1:
        return gcols.reshape(x_shape), gw, gb
    gcols = gcols.reshape(n, ho, wo, k, k, c_in)
    gx = np.zeros(x_shape, F32)
    for ky in range(k):
        for kx in range(k):
            y0, x0 = ky * dilation, kx * dilation
            gx[:, y0: y0 + stride * (ho - 1) + 1: stride,
               x0: x0 + stride * (wo - 1) + 1: stride, :] += gcols[:, :, :, ky, kx, :]
    return gx, gw, gb


def pad_hw(x, p):
    return np.pad(x, ((0, 0), (p, p), (p, p), (0, 0))) if p else x


def depth_to_space(x, block):
    """ONNX DepthToSpace, mode DCR, in NHWC: channel (i * block + j) * C + c of a cell goes to
    row offset i, column offset j, channel c."""
    n, h, w, cb = x.shape
    c = cb // (block * block)
    return (x.reshape(n, h, w, block, block, c).transpose(0, 1, 3, 2, 4, 5)
            .reshape(n, h * block, w * block, c))


def space_to_depth(g, block):
    """The adjoint of depth_to_space (for its gradient)."""
    n, hb, wb, c = g.shape
    h, w = hb // block, wb // block
    return (g.reshape(n, h, block, w, block, c).transpose(0, 1, 3, 2, 4, 5)
            .reshape(n, h, w, block * block * c))


def sigmoid(z):
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # stable for any z


# ---------------------------------------------------------------- network


class Network:
    """Parameters (weights (k, k, C_in, C_out), biases (C_out,)) by name, and the forward and
    backward passes over normalised inputs (`folded` moves the normalisation into the two
    convolutions that read the input, for export). The layers, by name:

    full      Conv 3x3, input -> F, Relu                          full resolution
    down4     Conv 4x4 stride 4, input -> D4, Relu                1/4
    down8     Conv 2x2 stride 2, D4 -> D8, Relu                   1/8
    contextI  Conv 3x3 dilation d_I, D8 -> D8, Relu, added        1/8
    up8       Conv 1x1 D8 -> 4 U8, Relu, DepthToSpace 2           1/8 -> 1/4
    mid       Conv 1x1 (U8 + D4) -> M, Relu (Concat with down4)   1/4
    up4       Conv 1x1 M -> 16 U4, Relu, DepthToSpace 4           1/4 -> full
    head      Conv 1x1 (F + U4) -> H, Relu (Concat with full)     full
    out       Conv 1x1 H -> 1, then the sigmoid                   full
    """

    LOW_RES = {"down4": 16, "mid": 16, "up4": 16, "down8": 64, "up8": 64}

    def __init__(self, params, dilations):
        self.params, self.dilations = params, list(dilations)

    @classmethod
    def initial(cls, args, c_in, rng):
        """He-initialised weights, zero biases; the residual branches start small."""
        f, d4, d8 = args.full_channels, args.quarter_channels, args.context_channels
        u8, m, u4, hh = args.up8_channels, args.mid_channels, args.up_channels, args.head_channels
        shapes = {"full": (3, c_in, f), "down4": (4, c_in, d4), "down8": (2, d4, d8)}
        for i, _ in enumerate(args.dilation_list):
            shapes[f"context{i}"] = (3, d8, d8)
        shapes.update({"up8": (1, d8, 4 * u8), "mid": (1, u8 + d4, m), "up4": (1, m, 16 * u4),
                       "head": (1, f + u4, hh), "out": (1, hh, 1)})
        params = {}
        for name, (k, n_in, n_out) in shapes.items():
            std = np.sqrt(2.0 / (k * k * n_in)) * (0.5 if name.startswith("context") else 1.0)
            params[name + ".weight"] = rng.normal(0, std, (k, k, n_in, n_out)).astype(F32)
            params[name + ".bias"] = np.zeros(n_out, F32)
        return cls(params, args.dilation_list)

    def p(self, name):
        return self.params[name + ".weight"], self.params[name + ".bias"]

    def _conv_relu(self, cache, name, x, stride=1, dilation=1):
        z, cache[name] = conv_forward(x, *self.p(name), stride=stride, dilation=dilation)
        z = np.maximum(z, 0, out=z)
        cache[name + "_out"] = z
        return z

    def forward(self, x):
        """Logits (N, H, W) of x (N, H + 2, W + 2, C): normalised input with a one-pixel
        margin. Returns the logits and the cache for backward."""
        cache = {}
        full = self._conv_relu(cache, "full", x)
        d4 = self._conv_relu(cache, "down4", np.ascontiguousarray(x[:, 1:-1, 1:-1, :]),
                             stride=4)
        ctx = self._conv_relu(cache, "down8", d4, stride=2)
        for i, dil in enumerate(self.dilations):
            z, cols = conv_forward(pad_hw(ctx, dil), *self.p(f"context{i}"), dilation=dil)
            r = np.maximum(z, 0)
            cache[f"context{i}"] = (cols, r > 0, ctx.shape)
            ctx = ctx + r
        cache["context_out"] = ctx
        u8 = depth_to_space(self._conv_relu(cache, "up8", ctx), 2)
        mid = self._conv_relu(cache, "mid", np.concatenate([u8, d4], axis=3))
        u4 = depth_to_space(self._conv_relu(cache, "up4", mid), 4)
        hidden = self._conv_relu(cache, "head", np.concatenate([full, u4], axis=3))
        logit, cache["out"] = conv_forward(hidden, *self.p("out"))
        return logit[..., 0], cache

    def backward(self, g_logit, cache):
        """Gradients of every parameter given d loss / d logit (N, H, W)."""
        grads = {}

        def back(name, g, x_shape, stride=1, dilation=1, need_input=True):
            gx, grads[name + ".weight"], grads[name + ".bias"] = conv_backward(
                g, cache[name], self.p(name)[0], x_shape, stride, dilation, need_input)
            return gx

        def relu_back(name, g):
            return g * (cache[name + "_out"] > 0)

        hidden = cache["head_out"]
        g = back("out", g_logit[..., None], hidden.shape)
        g = back("head", relu_back("head", g), cache["head"].shape)
        n_full = cache["full_out"].shape[3]
        g_full, g_u4 = g[..., :n_full], space_to_depth(g[..., n_full:], 4)
        g = back("mid", relu_back("mid", back("up4", relu_back("up4", g_u4),
                                              cache["up4"].shape)),
                 cache["mid"].shape)
        n_u8 = g.shape[3] - cache["down4_out"].shape[3]
        g_u8, g_d4 = space_to_depth(g[..., :n_u8], 2), g[..., n_u8:]
        g_ctx = back("up8", relu_back("up8", g_u8), cache["up8"].shape)
        for i in range(len(self.dilations) - 1, -1, -1):
            dil = self.dilations[i]
            cols, active, shape = cache[f"context{i}"]
            padded = (shape[0], shape[1] + 2 * dil, shape[2] + 2 * dil, shape[3])
            gx, grads[f"context{i}.weight"], grads[f"context{i}.bias"] = conv_backward(
                g_ctx * active, cols, self.p(f"context{i}")[0], padded, dilation=dil)
            g_ctx = g_ctx + gx[:, dil:-dil, dil:-dil, :]
        g_d4 = g_d4 + back("down8", relu_back("down8", g_ctx), cache["down4_out"].shape,
                           stride=2)
        back("down4", relu_back("down4", g_d4), None, stride=4, need_input=False)
        back("full", relu_back("full", np.ascontiguousarray(g_full)), None, need_input=False)
        return grads

    def folded(self, mean, std):
        """Parameters acting on raw inputs: the normalisation (x - mean) / std moved into the
        convolutions that read the input. Exact, also at the frame border: training pads the
        raw input with zeros before normalising, as the exported Conv pads the raw input."""
        out = dict(self.params)
        for name in ("full", "down4"):
            w, b = self.p(name)
            w2 = w / std[None, None, :, None]
            out[name + ".weight"] = w2.astype(F32)
            out[name + ".bias"] = (b - np.einsum("yxco,c->o", w2, mean)).astype(F32)
        return out

    def parameter_count(self):
        return int(sum(v.size for v in self.params.values()))

    def multiply_adds_per_px(self):
        """Multiply-adds per input pixel (a layer at 1/4 resolution counts 1/16 per pixel)."""
        total = 0.0
        for name, w in self.params.items():
            if name.endswith(".weight"):
                layer = name.split(".")[0]
                share = self.LOW_RES.get(layer, 64 if layer.startswith("context") else 1)
                total += w.size / share
        return total

    def architecture(self):
        def io(name):
            w = self.params[name + ".weight"]
            return f"{w.shape[2]}->{w.shape[3]}"
        dil = ", ".join(f"Conv 3x3 dilation {d} {io(f'context{i}')}, Relu, Add"
                        for i, d in enumerate(self.dilations))
        return (f"full: Conv 3x3 {io('full')}, Relu; 1/4: Conv 4x4 stride 4 {io('down4')}, Relu; "
                f"1/8: Conv 2x2 stride 2 {io('down8')}, Relu, {dil}, Conv 1x1 {io('up8')}, Relu, "
                f"DepthToSpace 2; 1/4: Concat, Conv 1x1 {io('mid')}, Relu, Conv 1x1 {io('up4')}, "
                f"Relu, DepthToSpace 4; full: Concat, Conv 1x1 {io('head')}, Relu, "
                f"Conv 1x1 {io('out')}, Sigmoid")


def forward_folded(params, dilations, x_raw):
    """Probability (H, W) of one raw input (H, W, C) with folded parameters: the same
    arithmetic as the exported graph (zero padding at the border), for evaluation."""
    h, w = x_raw.shape[:2]
    x = padded_to_multiple(x_raw)[None]
    logit, _ = Network(params, dilations).forward(pad_hw(x, 1))
    return sigmoid(logit[0, :h, :w])


class Adam:
    def __init__(self, params, learning_rate, beta1=0.9, beta2=0.999, eps=1e-8):
        self.lr, self.b1, self.b2, self.eps, self.t = learning_rate, beta1, beta2, eps, 0
        self.m = {k: np.zeros_like(v) for k, v in params.items()}
        self.v = {k: np.zeros_like(v) for k, v in params.items()}

    def step(self, params, grads, lr_scale):
        self.t += 1
        lr = self.lr * lr_scale * np.sqrt(1 - self.b2 ** self.t) / (1 - self.b1 ** self.t)
        for k, g in grads.items():
            m, v = self.m[k], self.v[k]
            m *= self.b1
            m += (1 - self.b1) * g
            v *= self.b2
            v += (1 - self.b2) * g * g
            params[k] -= (lr * m / (np.sqrt(v) + self.eps)).astype(F32)


def train(data, frames, args, rng):
    """Adam on weighted binary cross-entropy over random crops, cosine decay of the step.
    Returns the network and the input normalisation."""
    mean, std = input_statistics(data, frames, rng)
    net = Network.initial(args, 3 + data.with_depth, rng)
    adam = Adam(net.params, args.learning_rate)
    sampler = CropSampler(data, frames, args, rng)
    started, running = time.monotonic(), None
    for step in range(args.steps):
        x, y = sampler.batch()
        logit, cache = net.forward((x - mean) / std)
        weight = np.where(y > 0, F32(args.fruit_weight), F32(1.0))
        p = sigmoid(logit)
        loss = float(np.mean(weight * (np.maximum(logit, 0) - logit * y
                                       + np.log1p(np.exp(-np.abs(logit))))))
        running = loss if running is None else 0.98 * running + 0.02 * loss
        g = (weight * (p - y) / y.size).astype(F32)
        grads = net.backward(g, cache)
        adam.step(net.params, grads, 0.5 * (1 + np.cos(np.pi * step / args.steps)))
        if (step + 1) % 100 == 0 or step + 1 == args.steps:
            print(f"step {step + 1:5d}/{args.steps}: weighted loss {running:.4f} "
                  f"({time.monotonic() - started:.0f} s)", flush=True)
    return net, mean, std


# ---------------------------------------------------------------- evaluation


def probability_map(params, dilations, rgb8, depth_mm, with_depth):
    return forward_folded(params, dilations, input_planes(rgb8, depth_mm, with_depth))


def evaluate(params, dilations, data, frames):
    """Pixel counts per subset (all, per fruit colour, per world and colour) over every pixel
    of the held-out frames, and over those with depth."""
    counts = {}
    worlds = set(data.worlds[k] for k in frames)
    for k in frames:
        rgb, depth, truth = data.frame(k)
        predicted = probability_map(params, dilations, rgb, depth, data.with_depth) >= THRESHOLD
        has_depth = np.ones_like(truth) if depth is None else depth > 0
        subsets = ["all", data.colours[k]]
        if len(worlds) > 1:
            subsets.append(f"{data.worlds[k]} {data.colours[k]}")
        for subset in subsets:
            for scope, mask in (("pixels", None), ("with_depth", has_depth)):
                c = counts.setdefault(subset, {}).setdefault(
                    scope, dict(frames=0, pixels=0, fruit_pixels=0, tp=0, fp=0, fn=0))
                t, pr = (truth, predicted) if mask is None else (truth[mask], predicted[mask])
                c["frames"] += 1
                c["pixels"] += int(t.size)
                c["fruit_pixels"] += int(t.sum())
                c["tp"] += int((pr & t).sum())
                c["fp"] += int((pr & ~t).sum())
                c["fn"] += int((~pr & t).sum())
    return {subset: {scope: with_scores(c) for scope, c in scopes.items()}
            for subset, scopes in counts.items()}


def ratio(num, den):
    return float(num / den) if den else None


def with_scores(c):
    tp, fp, fn = c["tp"], c["fp"], c["fn"]
    return {**c,
            "precision": ratio(tp, tp + fp),
            "recall": ratio(tp, tp + fn),
            "f1": ratio(2 * tp, 2 * tp + fp + fn),
            "iou": ratio(tp, tp + fp + fn)}


def metrics_table(metrics, scope):
    def fmt(v):
        return "   -  " if v is None else f"{v:6.4f}"
    lines = ["| subset | frames | fruit px | precision | recall | F1 | IoU |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for subset in sorted(metrics, key=lambda s: (s != "all", s)):
        m = metrics[subset][scope]
        lines.append(f"| {subset} | {m['frames']} | {m['fruit_pixels']} "
                     f"| {fmt(m['precision'])} | {fmt(m['recall'])} | {fmt(m['f1'])} "
                     f"| {fmt(m['iou'])} |")
    return "\n".join(lines)


# ---------------------------------------------------------------- export


def to_onnx(params, dilations, with_depth, metadata):
    """The graph of Network.forward in NCHW with symbolic height and width."""
    from onnx import TensorProto, helper, numpy_helper

    input_name = "rgbd" if with_depth else "rgb"
    c_in = 4 if with_depth else 3
    nodes, inits = [], []

    def conv(name, source, stride=1, dilation=1, pad=0):
        w, b = params[name + ".weight"], params[name + ".bias"]
        k = w.shape[0]
        # (k, k, C_in, C_out) to ONNX's [C_out, C_in, ky, kx].
        inits.append(numpy_helper.from_array(
            np.ascontiguousarray(w.transpose(3, 2, 0, 1)).astype(F32), name + ".weight"))
        inits.append(numpy_helper.from_array(b.astype(F32), name + ".bias"))
        nodes.append(helper.make_node(
            "Conv", [source, name + ".weight", name + ".bias"], [name], name=name,
            kernel_shape=[k, k], pads=[pad] * 4, strides=[stride, stride],
            dilations=[dilation, dilation], group=1))
        return name

    def op(kind, inputs, name, **attrs):
        nodes.append(helper.make_node(kind, inputs, [name], name=name, **attrs))
        return name

    def conv_relu(name, source, **kw):
        return op("Relu", [conv(name, source, **kw)], name + "_relu")

    full = conv_relu("full", input_name, pad=1)
    d4 = conv_relu("down4", input_name, stride=4)
    ctx = conv_relu("down8", d4, stride=2)
    for i, dil in enumerate(dilations):
        r = conv_relu(f"context{i}", ctx, dilation=dil, pad=dil)
        ctx = op("Add", [ctx, r], f"context{i}_add")
    u8 = op("DepthToSpace", [conv_relu("up8", ctx)], "up8_space", blocksize=2, mode="DCR")
    mid = conv_relu("mid", op("Concat", [u8, d4], "mid_in", axis=1))
    u4 = op("DepthToSpace", [conv_relu("up4", mid)], "up4_space", blocksize=4, mode="DCR")
    hidden = conv_relu("head", op("Concat", [full, u4], "head_in", axis=1))
    op("Sigmoid", [conv("out", hidden)], "fruit_probability")
    graph = helper.make_graph(
        nodes, "fruit_segmenter",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT,
                                       [1, c_in, "height", "width"])],
        [helper.make_tensor_value_info("fruit_probability", TensorProto.FLOAT,
                                       [1, 1, "height", "width"])],
        inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="glasshouse detector-service/model/train.py")
    model.ir_version = IR_VERSION
    model.doc_string = ("Per-pixel fruit probability from RGB8/255"
                        + (" and depth in metres" if with_depth else "")
                        + f"; height and width multiples of {SIZE_MULTIPLE}; "
                        "see detector-service/model/README.md")
    helper.set_model_props(model, metadata)
    return model


def onnx_input(rgb8, depth_mm, with_depth):
    """One frame as the exported model's NCHW input, padded to the size multiple."""
    x = padded_to_multiple(input_planes(rgb8, depth_mm, with_depth))
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def check_against_reference(path, params, dilations, rgb8, depth_mm, with_depth):
    """onnx's checker, then its reference runtime on a frame against the numpy forward pass."""
    import onnx
    from onnx.reference import ReferenceEvaluator

    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)
    x = onnx_input(rgb8, depth_mm, with_depth)
    name = model.graph.input[0].name
    (onnx_prob,) = ReferenceEvaluator(model).run(None, {name: x})
    h, w = rgb8.shape[:2]
    expected = probability_map(params, dilations, rgb8, depth_mm, with_depth)
    if onnx_prob.shape != (1, 1) + x.shape[2:] or onnx_prob.dtype != np.float32:
        raise SystemExit(f"ONNX output {onnx_prob.shape} {onnx_prob.dtype} breaks the contract")
    diff = float(np.max(np.abs(onnx_prob[0, 0, :h, :w] - expected)))
    if not diff < MAX_ABS_DIFF_TO_REFERENCE:
        raise SystemExit(f"ONNX and numpy disagree: max abs difference {diff:.3g}")
    return diff, expected


def check_with_tract(path, rgb8, depth_mm, with_depth, expected):
    """The Rust side's runtime, when its Python bindings (pip `tract`) are installed: loads the
    model and fixes the input size, as tract-onnx does in the detector, and compares on the
    same frame."""
    try:
        import tract
    except ImportError:
        return None
    x = onnx_input(rgb8, depth_mm, with_depth)
    model = tract.onnx().model_for_path(str(path))
    # As the Rust side does: a plan per image size (both paths then agree on H and W).
    model.set_input_fact(0, ",".join(map(str, x.shape)) + ",f32")
    runnable = model.into_optimized().into_runnable()
    out = runnable.run([x])[0].to_numpy()
    h, w = rgb8.shape[:2]
    diff = float(np.max(np.abs(out[0, 0, :h, :w] - expected)))
    if out.shape != (1, 1) + x.shape[2:] or not diff < MAX_ABS_DIFF_TO_REFERENCE:
        raise SystemExit(f"tract output {out.shape} differs from numpy by {diff:.3g}")
    return diff


def index_ranges(indices):
    """Sorted indices as text ranges, "192-239" or "0-3,8", to keep the metrics file short."""
    ranges, start = [], None
    for k, i in enumerate(indices):
        start = i if start is None else start
        if k + 1 == len(indices) or indices[k + 1] != i + 1:
            ranges.append(str(i) if i == start else f"{start}-{i}")
            start = None
    return ",".join(ranges)


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---------------------------------------------------------------- main


def require_onnx():
    """Exits before any training when the export would fail at its end."""
    import importlib.util
    if importlib.util.find_spec("onnx") is None:
        sys.exit("the onnx package is missing: the model could not be exported after training "
                 "(scripts/train-detector installs onnx 1.17.0 into .venv); nothing was trained")


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    require_onnx()
    started_s = time.monotonic()
    data = Dataset(args.data, args.depth)
    if args.test:
        test = Dataset(args.test, args.depth)
        train_frames, held_out = list(range(len(data))), list(range(len(test)))
        if (test.height, test.width) != (data.height, data.width):
            sys.exit("--test frames differ in size from --data frames")
    else:
        test = data
        train_frames, held_out = split_frames(data.colours, args.held_out_share)
    if not train_frames or not held_out:
        sys.exit("need training and held-out frames")
    if min(data.height, data.width) < args.crop_px:
        sys.exit(f"--crop-px {args.crop_px} is larger than the {data.width}x{data.height} frames")
    print(f"training on {len(train_frames)} frames of {data.width}x{data.height}, "
          f"evaluating on {len(held_out)}", flush=True)

    rng = np.random.default_rng(args.seed)
    probe = Network.initial(args, 3 + args.depth, np.random.default_rng(0))
    mult_adds = probe.multiply_adds_per_px() * COST_FRAME_PX
    if mult_adds > MAX_MULTIPLY_ADDS_PER_FRAME:
        sys.exit(f"{mult_adds / 1e6:.0f} M multiply-adds per 640x480 frame is over the "
                 f"{MAX_MULTIPLY_ADDS_PER_FRAME / 1e6:.0f} M budget")

    net, mean, std = train(data, train_frames, args, rng)
    training_s = time.monotonic() - started_s
    params = net.folded(mean, std)
    params["out.bias"] = (params["out.bias"] + F32(args.logit_offset)).astype(F32)
    metrics = evaluate(params, net.dilations, test, held_out)
    print("every pixel:\n" + metrics_table(metrics, "pixels"))
    print("pixels with depth:\n" + metrics_table(metrics, "with_depth"))

    args.out.parent.mkdir(parents=True, exist_ok=True)
    model_props = {"seed": str(args.seed), "threshold": str(THRESHOLD),
                   "size_multiple": str(SIZE_MULTIPLE),
                   "input": "rgbd" if args.depth else "rgb",
                   "dataset_shape": "x".join(map(str, (len(train_frames), data.height,
                                                        data.width)))}
    args.out.write_bytes(
        to_onnx(params, net.dilations, args.depth, model_props).SerializeToString())
    check_frame = held_out[0]
    rgb8, depth_mm, _ = test.frame(check_frame)
    diff, expected = check_against_reference(args.out, params, net.dilations, rgb8, depth_mm,
                                             args.depth)
    print(f"ONNX checked: reference runtime on held-out frame {check_frame} within {diff:.2e}")
    tract_diff = check_with_tract(args.out, rgb8, depth_mm, args.depth, expected)
    print("tract: not installed, skipped" if tract_diff is None
          else f"tract: same frame within {tract_diff:.2e}")

    report = {
        "model": args.out.name,
        "model_sha256": sha256(args.out),
        "model_bytes": args.out.stat().st_size,
        "command": shlex.join(["python", *(sys.argv if argv is None else [__file__, *argv])]),
        "seed": args.seed,
        "input": "rgbd" if args.depth else "rgb",
        "architecture": net.architecture(),
        "parameters": net.parameter_count(),
        "multiply_adds_per_pixel": mult_adds / COST_FRAME_PX,
        "multiply_adds_per_640x480_frame": int(mult_adds),
        "threshold": THRESHOLD,
        "size_multiple": SIZE_MULTIPLE,
        "training_data": data.describe(),
        "held_out_data": (test.describe() if args.test
                          else {"frames": index_ranges(held_out)}),
        "training": {"steps": args.steps, "batch": args.batch, "crop_px": args.crop_px,
                     "fruit_crop_share": args.fruit_crop_share,
                     "colour_weights": args.colour_weight,
                     "fruit_weight": args.fruit_weight, "learning_rate": args.learning_rate,
                     "logit_offset": args.logit_offset,
                     "input_mean": [float(v) for v in mean],
                     "input_std": [float(v) for v in std],
                     "seconds": round(training_s, 1),
                     "seconds_with_evaluation_and_export": round(time.monotonic() - started_s, 1)},
        "onnx_reference_max_abs_diff": diff,
        "tract_max_abs_diff": tract_diff,
        "held_out_metrics": metrics,
    }
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out} ({report['model_bytes']} bytes, {report['parameters']} parameters, "
          f"{mult_adds / 1e6:.0f} M multiply-adds per 640x480 frame) and "
          f"{args.out.with_suffix('.json').name}; "
          f"{report['training']['seconds_with_evaluation_and_export']} s in all")


if __name__ == "__main__":
    main()
