#!/usr/bin/env python3
"""Trains the detector's per-pixel fruit segmenter on simulator frames and exports it as ONNX.

The network is a tiny fully convolutional one: Conv KxK (3->h1) -> Relu -> Conv 1x1 (h1->h2)
-> Relu -> Conv 1x1 (h2->1) -> Sigmoid. As every layer after the first is 1x1, it is the same
as an MLP applied to each pixel's KxK RGB patch, and it is trained that way: in numpy, with
hand-written backpropagation, Adam and binary cross-entropy, seeded and on the CPU only.

Input data: a directory written by `glasshouse dataset --out DIR` holding rgb.npy
(N, H, W, 3) uint8, label.npy (N, H, W) uint8 (1 = fruit) and meta.json (frames, width,
height, fruit_colour per frame, seed).

Outputs: the ONNX model at --out (input `rgb` float32 [1, 3, height, width] = RGB8 / 255,
output `fruit_probability` float32 [1, 1, height, width]) and, beside it with the suffix
.json, the held-out metrics with the command line, seed, parameter count and dataset shape.
Metrics are pixel precision, recall, F1 and IoU of the fruit class at threshold 0.5 over
every pixel of the held-out frames (the last --held-out-share of each fruit colour's frames).
"""

import argparse
import hashlib
import json
import os
import shlex
import sys
import time
from pathlib import Path

# One BLAS thread, set before numpy loads: the matrices are thin, so threads only add overhead
# (2-3x slower on a busy machine), and results then cannot depend on the machine's core count.
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np  # noqa: E402

THRESHOLD = 0.5
OPSET = 13
IR_VERSION = 8
# The cost budget is stated for the camera's 640x480 frames.
COST_FRAME_PX = 640 * 480
MAX_MULTIPLY_ADDS_PER_FRAME = 150e6
MAX_ABS_DIFF_TO_REFERENCE = 1e-4
FORWARD_CHUNK_PX = 8192


def parse_args(argv):
    here = Path(__file__).resolve().parent

    class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
        pass

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--data", type=Path, required=True,
                        help="dataset directory (rgb.npy, label.npy, meta.json)")
    parser.add_argument("--out", type=Path, default=None,
                        help="ONNX file to write; metrics go beside it as .json "
                             "(default: fruit-segmenter.onnx beside train.py)")
    parser.add_argument("--seed", type=int, default=1, help="seed of sampling and initialisation")
    parser.add_argument("--epochs", type=int, default=12, help="passes over the sampled pixels")
    parser.add_argument("--samples-per-class", type=int, default=150_000,
                        help="training pixels drawn per class (fruit, non-fruit)")
    parser.add_argument("--kernel-px", type=int, default=3, choices=(3, 5),
                        help="side of the first convolution (receptive field); 5 needs "
                             "narrower hidden layers to stay within 150 M multiply-adds per "
                             "640x480 frame, e.g. --hidden 4,8")
    parser.add_argument("--hidden", type=str, default="8,8",
                        help="widths of the two hidden layers, comma separated")
    parser.add_argument("--learning-rate", type=float, default=3e-3, help="Adam step size")
    parser.add_argument("--batch", type=int, default=1024, help="pixels per Adam step")
    parser.add_argument("--held-out-share", type=float, default=0.2,
                        help="last share of each colour's frames kept for evaluation")
    parser.add_argument("--near-fruit-weight", type=float, default=8.0,
                        help="sampling weight of non-fruit pixels within 2 px of fruit "
                             "(plain non-fruit pixels weigh 1)")
    parser.add_argument("--leaf-weight", type=float, default=3.0,
                        help="sampling weight of green (leaf- or stem-coloured) non-fruit pixels")
    # Small: larger shares crowd the sample with pixels whose colour fruit and leaves share,
    # and recall drops faster than precision rises (0.5 on the simulator set: IoU 0.93 vs 0.98).
    parser.add_argument("--hard-share", type=float, default=0.05,
                        help="share of non-fruit pixels drawn, for the second half of the epochs, "
                             "in proportion to the first half's fruit probability on each pixel")
    args = parser.parse_args(argv)
    args.out = args.out or here / "fruit-segmenter.onnx"
    args.hidden_widths = [int(h) for h in args.hidden.split(",")]
    if len(args.hidden_widths) != 2 or min(args.hidden_widths) < 1:
        parser.error("--hidden takes two positive widths, e.g. 8,8")
    return args


# ---------------------------------------------------------------- data


def load_dataset(data_dir):
    """Frames as a read-only memory map (a dataset can be hundreds of MB), labels and meta."""
    meta = json.loads((data_dir / "meta.json").read_text())
    rgb = np.load(data_dir / "rgb.npy", mmap_mode="r")
    label = np.load(data_dir / "label.npy", mmap_mode="r")
    expected = (meta["frames"], meta["height"], meta["width"])
    if rgb.shape != expected + (3,) or label.shape != expected or rgb.dtype != np.uint8:
        sys.exit(f"dataset shapes {rgb.shape} {rgb.dtype} / {label.shape} "
                 f"do not match meta {expected}")
    if len(meta["fruit_colour"]) != meta["frames"]:
        sys.exit("meta.json: fruit_colour needs one entry per frame")
    return rgb, label, meta


def split_frames(colours, held_out_share):
    """Train and held-out frame indices: the last share of each colour's frames is held out,
    so both colours are evaluated whatever order the frames come in."""
    train, held_out = [], []
    for colour in sorted(set(colours)):
        frames = [i for i, c in enumerate(colours) if c == colour]
        n_held = max(1, int(round(held_out_share * len(frames)))) if len(frames) > 1 else 0
        train += frames[: len(frames) - n_held]
        held_out += frames[len(frames) - n_held:]
    return sorted(train), sorted(held_out)


def padded_unit_rgb(frame_rgb8, kernel_px):
    """RGB / 255 with a zero border, as the exported Conv pads its input with zeros."""
    pad_px = kernel_px // 2
    unit = frame_rgb8.astype(np.float64) / 255.0
    return np.pad(unit, ((pad_px, pad_px), (pad_px, pad_px), (0, 0)))


def patch_features(padded, rows, cols, kernel_px):
    """KxK patches around pixels (rows, cols), flattened in Conv weight order (c, ky, kx)."""
    return np.stack(
        [padded[rows + ky, cols + kx, c]
         for c in range(3) for ky in range(kernel_px) for kx in range(kernel_px)],
        axis=1,
    )


def frame_features(frame_rgb8, kernel_px):
    """Patches of every pixel in row-major order (slices: much faster than patch_features)."""
    height_px, width_px, _ = frame_rgb8.shape
    padded = padded_unit_rgb(frame_rgb8, kernel_px)
    out = np.empty((height_px, width_px, 3, kernel_px, kernel_px))
    for ky in range(kernel_px):
        for kx in range(kernel_px):
            out[:, :, :, ky, kx] = padded[ky: ky + height_px, kx: kx + width_px]
    return out.reshape(height_px * width_px, -1)


def near_fruit_mask(fruit, radius_px=2):
    """Non-fruit pixels within radius_px (Chebyshev) of a fruit pixel: edges are the hard part."""
    grown = fruit.copy()
    padded = np.pad(fruit, radius_px)
    height_px, width_px = fruit.shape
    for dy in range(2 * radius_px + 1):
        for dx in range(2 * radius_px + 1):
            grown |= padded[dy: dy + height_px, dx: dx + width_px]
    return grown & ~fruit


def negative_weights(frame_rgb8, fruit, args):
    """Sampling weight per non-fruit pixel: more on fruit borders and green plant parts, which
    a colour rule confuses with fruit most easily (yellow-green fruit against light leaves)."""
    rgb = frame_rgb8.astype(np.int16)
    green = (rgb[..., 1] > rgb[..., 0]) & (rgb[..., 1] > rgb[..., 2])
    weight = np.ones(fruit.shape)
    weight += (args.leaf_weight - 1.0) * green
    weight += (args.near_fruit_weight - 1.0) * near_fruit_mask(fruit)
    weight[fruit] = 0.0
    return weight.ravel()


def mixed_choice(base_weight, hard_weight, hard_share, n, rng):
    """n pixel indices drawn from base_weight, with hard_share of the draw's probability
    moved onto hard_weight (the current model's mistakes) when given."""
    p = base_weight / base_weight.sum()
    if hard_weight is not None and hard_weight.sum() > 0:
        p = (1 - hard_share) * p + hard_share * hard_weight / hard_weight.sum()
    return rng.choice(p.size, n, p=p)


def sample_pixels(rgb, label, frames, args, rng, model=None):
    """Equal numbers of fruit and non-fruit training pixels as (features, targets).

    With a model (layers, kernel_px), --hard-share of the non-fruit pixels is drawn in
    proportion to that model's fruit probability, so the second round sees the rare look-alikes
    (the lightest leaves, shaded floor) that plain sampling seldom picks. Fruit pixels are not
    mined: a few fruits have a leaf's colour, and chasing them teaches the model that leaves
    are fruit."""
    n_fruit_px = [int(label[i].sum()) for i in frames]
    fruit_total_px = max(1, sum(n_fruit_px))
    per_frame_neg = -(-args.samples_per_class // len(frames))  # ceil
    features, targets = [], []
    for i, n_fruit in zip(frames, n_fruit_px):
        frame, fruit = np.asarray(rgb[i]), np.asarray(label[i]) == 1
        prob = probability_map(model[0], frame, model[1]).ravel() if model else None
        # Each frame gives fruit pixels in proportion to its fruit area, as in the data.
        n_pos = int(round(args.samples_per_class * n_fruit / fruit_total_px)) if n_fruit else 0
        pos = rng.choice(np.flatnonzero(fruit), n_pos) if n_pos else np.empty(0, int)
        hard = None if prob is None else prob * ~fruit.ravel()
        neg = mixed_choice(negative_weights(frame, fruit, args), hard, args.hard_share,
                           per_frame_neg, rng)
        rows, cols = np.divmod(np.concatenate([pos, neg]), frame.shape[1])
        features.append(patch_features(padded_unit_rgb(frame, args.kernel_px), rows, cols,
                                       args.kernel_px))
        targets.append(np.concatenate([np.ones(pos.size), np.zeros(neg.size)]))
    return np.concatenate(features), np.concatenate(targets)


# ---------------------------------------------------------------- network


def init_layers(sizes, rng):
    """He-initialised (weight [in, out], bias [out]) pairs."""
    return [(rng.normal(0.0, np.sqrt(2.0 / n_in), (n_in, n_out)), np.zeros(n_out))
            for n_in, n_out in zip(sizes[:-1], sizes[1:])]


def forward(layers, x):
    """Activations of every layer; the last is the logit (before the sigmoid)."""
    acts = [x]
    for k, (w, b) in enumerate(layers):
        z = acts[-1] @ w + b
        acts.append(np.maximum(z, 0.0) if k < len(layers) - 1 else z[:, 0])
    return acts


def sigmoid(z):
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # stable for any z


def bce_with_logits(logit, target):
    return float(np.mean(np.maximum(logit, 0) - logit * target + np.log1p(np.exp(-np.abs(logit)))))


def backward(layers, acts, target):
    """Gradients of the mean binary cross-entropy for every (weight, bias)."""
    grad_z = ((sigmoid(acts[-1]) - target) / target.size)[:, None]
    grads = []
    for k in range(len(layers) - 1, -1, -1):
        w, _ = layers[k]
        grads.append((acts[k].T @ grad_z, grad_z.sum(axis=0)))
        if k:
            grad_z = (grad_z @ w.T) * (acts[k] > 0)
    return grads[::-1]


class Adam:
    def __init__(self, layers, learning_rate, beta1=0.9, beta2=0.999, eps=1e-8):
        self.lr, self.b1, self.b2, self.eps, self.t = learning_rate, beta1, beta2, eps, 0
        self.m = [[np.zeros_like(p) for p in layer] for layer in layers]
        self.v = [[np.zeros_like(p) for p in layer] for layer in layers]

    def step(self, layers, grads, lr_scale):
        self.t += 1
        lr = self.lr * lr_scale * np.sqrt(1 - self.b2 ** self.t) / (1 - self.b1 ** self.t)
        for layer, grad, m, v in zip(layers, grads, self.m, self.v):
            for p, g, mp, vp in zip(layer, grad, m, v):
                mp *= self.b1
                mp += (1 - self.b1) * g
                vp *= self.b2
                vp += (1 - self.b2) * g * g
                p -= lr * mp / (np.sqrt(vp) + self.eps)


def train_epochs(layers, adam, x, targets, epochs, args, rng):
    """Adam over shuffled mini-batches; epochs is this round's (first, last + 1) of the run,
    so the cosine decay runs once over both rounds: large steps first, then settle."""
    steps_per_epoch = -(-len(x) // args.batch)
    for epoch in range(*epochs):
        order = rng.permutation(len(x))
        for s in range(steps_per_epoch):
            batch = order[s * args.batch: (s + 1) * args.batch]
            progress = (epoch * steps_per_epoch + s) / (args.epochs * steps_per_epoch)
            acts = forward(layers, x[batch])
            adam.step(layers, backward(layers, acts, targets[batch]),
                      0.5 * (1 + np.cos(np.pi * progress)))
        loss = bce_with_logits(forward(layers, x)[-1], targets)
        print(f"epoch {epoch + 1:3d}/{args.epochs}: balanced training loss {loss:.4f}")


def train(rgb, label, frames, args, rng):
    """Two rounds: on a class-balanced sample, then on a fresh one where part of the non-fruit
    pixels is drawn from the first round's mistakes. Returns layers acting on raw RGB / 255."""
    features, targets = sample_pixels(rgb, label, frames, args, rng)
    print(f"round 1: {int(targets.sum())} fruit and {int((1 - targets).sum())} non-fruit pixels")
    # Standardised inputs train faster; the scaling is folded into the first layer afterwards.
    mean, std = features.mean(axis=0), features.std(axis=0) + 1e-6
    layers = init_layers([features.shape[1], *args.hidden_widths, 1], rng)
    adam = Adam(layers, args.learning_rate)
    first_round_epochs = (args.epochs + 1) // 2
    train_epochs(layers, adam, (features - mean) / std, targets, (0, first_round_epochs), args, rng)
    if first_round_epochs < args.epochs:
        model = (fold_normalisation(layers, mean, std), args.kernel_px)
        features, targets = sample_pixels(rgb, label, frames, args, rng, model)
        print(f"round 2: {args.hard_share:.0%} of non-fruit pixels drawn from round 1's mistakes")
        train_epochs(layers, adam, (features - mean) / std, targets,
                     (first_round_epochs, args.epochs), args, rng)
    return fold_normalisation(layers, mean, std)


def fold_normalisation(layers, mean, std):
    """First layer acting on raw RGB/255 patches: w' = w / std, b' = b - (mean / std) @ w."""
    (w, b), rest = layers[0], layers[1:]
    return [(w / std[:, None], b - (mean / std) @ w), *rest]


def probability_map(layers, frame_rgb8, kernel_px):
    """Per-pixel fruit probability of one frame, (H, W), with folded layers."""
    x = frame_features(frame_rgb8, kernel_px)
    # Cache-sized chunks: a whole frame's thin (N, 8) activations run several times slower.
    logit = np.concatenate([forward(layers, x[i: i + FORWARD_CHUNK_PX])[-1]
                            for i in range(0, len(x), FORWARD_CHUNK_PX)])
    return sigmoid(logit).reshape(frame_rgb8.shape[:2])


def layer_sizes(args):
    return [3 * args.kernel_px ** 2, *args.hidden_widths, 1]


def parameter_count(sizes):
    return sum((n_in + 1) * n_out for n_in, n_out in zip(sizes[:-1], sizes[1:]))


def multiply_adds_per_px(sizes):
    return sum(n_in * n_out for n_in, n_out in zip(sizes[:-1], sizes[1:]))


# ---------------------------------------------------------------- evaluation


def evaluate(layers, rgb, label, frames, colours, kernel_px):
    """Pixel counts per subset (all, and per fruit colour) over every held-out pixel."""
    counts = {}
    for i in frames:
        predicted = probability_map(layers, np.asarray(rgb[i]), kernel_px) >= THRESHOLD
        truth = np.asarray(label[i]) == 1
        for subset in ("all", colours[i]):
            c = counts.setdefault(
                subset, dict(frames=0, pixels=0, fruit_pixels=0, tp=0, fp=0, fn=0))
            c["frames"] += 1
            c["pixels"] += truth.size
            c["fruit_pixels"] += int(truth.sum())
            c["tp"] += int((predicted & truth).sum())
            c["fp"] += int((predicted & ~truth).sum())
            c["fn"] += int((~predicted & truth).sum())
    return {subset: with_scores(c) for subset, c in counts.items()}


def ratio(num, den):
    return float(num / den) if den else None


def with_scores(c):
    tp, fp, fn = c["tp"], c["fp"], c["fn"]
    return {**c,
            "precision": ratio(tp, tp + fp),
            "recall": ratio(tp, tp + fn),
            "f1": ratio(2 * tp, 2 * tp + fp + fn),
            "iou": ratio(tp, tp + fp + fn)}


def metrics_table(metrics):
    def fmt(v):
        return "   -  " if v is None else f"{v:6.4f}"
    lines = ["| subset | frames | fruit px | precision | recall | F1 | IoU |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for subset in ("all", "red", "green"):
        if subset in metrics:
            m = metrics[subset]
            lines.append(f"| {subset} | {m['frames']} | {m['fruit_pixels']} "
                         f"| {fmt(m['precision'])} | {fmt(m['recall'])} | {fmt(m['f1'])} "
                         f"| {fmt(m['iou'])} |")
    return "\n".join(lines)


# ---------------------------------------------------------------- export


def to_onnx(layers, kernel_px, metadata):
    """Conv/Relu graph with symbolic height and width; pads keep the input's H and W."""
    from onnx import TensorProto, helper, numpy_helper

    nodes, inits, previous = [], [], "rgb"
    for k, (w, b) in enumerate(layers):
        side_px = kernel_px if k == 0 else 1
        # Patch features are ordered (c, ky, kx): exactly the Conv weight layout [out, in, ky, kx].
        weight = w.T.reshape(w.shape[1], -1, side_px, side_px).astype(np.float32)
        inits += [numpy_helper.from_array(weight, f"conv{k}.weight"),
                  numpy_helper.from_array(b.astype(np.float32), f"conv{k}.bias")]
        pad_px = side_px // 2
        nodes.append(helper.make_node(
            "Conv", [previous, f"conv{k}.weight", f"conv{k}.bias"], [f"conv{k}"],
            name=f"conv{k}", kernel_shape=[side_px, side_px], pads=[pad_px] * 4,
            strides=[1, 1], dilations=[1, 1], group=1))
        last = k == len(layers) - 1
        out = "fruit_probability" if last else f"relu{k}"
        nodes.append(helper.make_node("Sigmoid" if last else "Relu", [f"conv{k}"], [out], name=out))
        previous = out
    graph = helper.make_graph(
        nodes, "fruit_segmenter",
        [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, [1, 3, "height", "width"])],
        [helper.make_tensor_value_info("fruit_probability", TensorProto.FLOAT,
                                       [1, 1, "height", "width"])],
        inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="glasshouse detector-service/model/train.py")
    model.ir_version = IR_VERSION
    model.doc_string = ("Per-pixel fruit probability from RGB8/255; "
                        "see detector-service/model/README.md")
    helper.set_model_props(model, metadata)
    return model


def check_against_reference(path, layers, frame_rgb8, kernel_px):
    """onnx's checker, then its reference runtime on a frame against the numpy forward pass."""
    import onnx
    from onnx.reference import ReferenceEvaluator

    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)
    unit = (frame_rgb8.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
    (onnx_prob,) = ReferenceEvaluator(model).run(None, {"rgb": unit})
    expected = probability_map(layers, frame_rgb8, kernel_px)
    if onnx_prob.shape != (1, 1) + frame_rgb8.shape[:2] or onnx_prob.dtype != np.float32:
        raise SystemExit(f"ONNX output {onnx_prob.shape} {onnx_prob.dtype} breaks the contract")
    diff = float(np.max(np.abs(onnx_prob[0, 0] - expected)))
    if not diff < MAX_ABS_DIFF_TO_REFERENCE:
        raise SystemExit(f"ONNX and numpy disagree: max abs difference {diff:.3g}")
    return diff, expected


def check_with_tract(path, frame_rgb8, expected):
    """The Rust side's runtime, when its Python bindings (pip `tract`) are installed: loads the
    model with symbolic H and W, as tract-onnx does, and compares on the same frame."""
    try:
        import tract
    except ImportError:
        return None
    unit = np.ascontiguousarray((frame_rgb8.astype(np.float32) / 255.0).transpose(2, 0, 1)[None])
    runnable = tract.onnx().model_for_path(str(path)).into_optimized().into_runnable()
    out = runnable.run([unit])[0].to_numpy()
    diff = float(np.max(np.abs(out[0, 0] - expected)))
    if out.shape != (1, 1) + frame_rgb8.shape[:2] or not diff < MAX_ABS_DIFF_TO_REFERENCE:
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


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    started_s = time.monotonic()
    rgb, label, meta = load_dataset(args.data)
    colours = meta["fruit_colour"]
    train_frames, held_out_frames = split_frames(colours, args.held_out_share)
    if not train_frames or not held_out_frames:
        sys.exit("need at least two frames to split into train and held-out")
    print(f"dataset {args.data}: {meta['frames']} frames of {meta['width']}x{meta['height']}, "
          f"{len(train_frames)} train, {len(held_out_frames)} held out")

    n_params = parameter_count(layer_sizes(args))
    mult_adds = multiply_adds_per_px(layer_sizes(args)) * COST_FRAME_PX
    if mult_adds > MAX_MULTIPLY_ADDS_PER_FRAME:
        sys.exit(f"{mult_adds / 1e6:.0f} M multiply-adds per 640x480 frame is over the "
                 f"{MAX_MULTIPLY_ADDS_PER_FRAME / 1e6:.0f} M budget")

    rng = np.random.default_rng(args.seed)
    layers = train(rgb, label, train_frames, args, rng)
    training_s = time.monotonic() - started_s
    metrics = evaluate(layers, rgb, label, held_out_frames, colours, args.kernel_px)
    print(metrics_table(metrics))

    args.out.parent.mkdir(parents=True, exist_ok=True)
    model_props = {"seed": str(args.seed), "threshold": str(THRESHOLD),
                   "dataset_shape": "x".join(map(str, rgb.shape))}
    args.out.write_bytes(to_onnx(layers, args.kernel_px, model_props).SerializeToString())
    check_frame = held_out_frames[0]
    diff, expected = check_against_reference(args.out, layers, np.asarray(rgb[check_frame]),
                                             args.kernel_px)
    print(f"ONNX checked: reference runtime on held-out frame {check_frame} within {diff:.2e}")
    tract_diff = check_with_tract(args.out, np.asarray(rgb[check_frame]), expected)
    print("tract: not installed, skipped" if tract_diff is None
          else f"tract: same frame within {tract_diff:.2e}")

    hidden = args.hidden_widths
    report = {
        "model": args.out.name,
        "model_sha256": sha256(args.out),
        "model_bytes": args.out.stat().st_size,
        "command": shlex.join(["python", *(sys.argv if argv is None else [__file__, *argv])]),
        "seed": args.seed,
        "architecture": (f"Conv {args.kernel_px}x{args.kernel_px} 3->{hidden[0]}, Relu, "
                         f"Conv 1x1 {hidden[0]}->{hidden[1]}, Relu, "
                         f"Conv 1x1 {hidden[1]}->1, Sigmoid"),
        "parameters": n_params,
        "multiply_adds_per_640x480_frame": mult_adds,
        "threshold": THRESHOLD,
        "dataset": {"path": str(args.data), "shape": list(rgb.shape), "seed": meta.get("seed"),
                    "train_frames": len(train_frames),
                    "held_out_frames": index_ranges(held_out_frames)},
        "training": {"epochs": args.epochs, "samples_per_class": args.samples_per_class,
                     "batch": args.batch, "learning_rate": args.learning_rate,
                     "near_fruit_weight": args.near_fruit_weight, "leaf_weight": args.leaf_weight,
                     "hard_share": args.hard_share, "seconds": round(training_s, 1),
                     "seconds_with_evaluation_and_export": round(time.monotonic() - started_s, 1)},
        "onnx_reference_max_abs_diff": diff,
        "tract_max_abs_diff": tract_diff,
        "held_out_metrics": metrics,
    }
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out} ({report['model_bytes']} bytes, {n_params} parameters, "
          f"{mult_adds / 1e6:.0f} M multiply-adds per 640x480 frame) and "
          f"{args.out.with_suffix('.json').name}; "
          f"{report['training']['seconds_with_evaluation_and_export']} s in all")


if __name__ == "__main__":
    main()
