"""The model's arithmetic: multiply-adds per frame forward and per training sample, counted layer by layer,
and, given this machine's measured fp32 matmul rate, the floor they put under a driven frame and a
training step.

    python bench/model_cost.py                                   # CIL (cil + independent + regression): the count
    python bench/model_cost.py --matmul 2048 --threads 2         # ... and the limit on 2 threads of this machine
    python bench/model_cost.py --mixer gtu --head hybrid         # another row's model

What is counted: the multiply-adds (MACs) of every Conv2d and Linear layer, one MAC = 2 FLOP. BatchNorm,
ReLU, dropout, the loss and Adam's update are left out: a few elementwise operations per activation or
weight, under 2% of the total here, and bound by memory, not arithmetic.

- forward, per frame: the sum over layers of (output elements x the inputs each one sums), for the image
  CIL sees (88 x 200). Every branch of the mixer runs for every frame (the model picks the command's
  branch after computing all four), in training and in driving alike;
- training, per sample: the forward, then the backward: for every layer the gradient of its weights (the
  forward's MACs again) and of its input (again), except where the input needs no gradient (the image
  and the speed, the first layers' inputs): 3 x forward less the first layers' input gradients.

``cil_conv_layers`` computes the CIL encoder's convolutions from ``CIL_CONVS`` alone (tests/test_model_cost.py
checks one layer by hand); ``count`` measures any model by running it once with hooks on its layers.
"""
from __future__ import annotations

import argparse
import statistics
import time
from typing import Any, Sequence

import torch
from torch import nn

from cicfw.model.encoders import CIL_CONVS, IMAGE_HW


def conv_out(size: int, kernel: int, stride: int) -> int:
    """A convolution's output length without padding."""
    return (size - kernel) // stride + 1


def cil_conv_layers(image_hw: tuple[int, int] = IMAGE_HW, convs: Sequence[tuple[int, int, int]] = CIL_CONVS,
                    channels: int = 3) -> list[dict[str, int]]:
    """The CIL encoder's convolutions, one dict per layer: in/out channels, kernel, stride, output height and
    width, and MACs per frame = out_h x out_w x out_c x in_c x k x k (no padding, no groups)."""
    h, w = image_hw
    out = []
    for c_out, k, s in convs:
        h, w = conv_out(h, k, s), conv_out(w, k, s)
        out.append({"in": channels, "out": c_out, "k": k, "s": s, "h": h, "w": w,
                    "macs": h * w * c_out * channels * k * k})
        channels = c_out
    return out


def count(model: nn.Module, image_hw: tuple[int, int] = IMAGE_HW) -> list[dict[str, Any]]:
    """Every Conv2d and Linear layer ``model`` (a CICModule) runs on one frame, in order: its name, kind,
    MACs per frame, and whether its input needs a gradient in training (False for the layers that read the
    image or the speed). Runs one training-mode forward of batch 2 with hooks; the weights are untouched."""
    rows: list[dict[str, Any]] = []
    names = {m: n for n, m in model.named_modules()}

    def hook(module, inputs, output):
        x = inputs[0]
        batch = x.shape[0]
        if isinstance(module, nn.Conv2d):
            kh, kw = module.kernel_size
            macs = output.numel() // batch * (module.in_channels // module.groups) * kh * kw
        else:
            macs = output.numel() // batch * module.in_features
        rows.append({"name": names[module], "kind": type(module).__name__, "macs": int(macs),
                     "input_grad": bool(x.requires_grad)})

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, (nn.Conv2d, nn.Linear))]
    was_training = model.training
    try:
        model.train()
        with torch.random.fork_rng(devices=[]):
            image = torch.zeros(2, 3, *image_hw, dtype=torch.uint8)
            model(image, torch.zeros(2), torch.zeros(2, dtype=torch.long))
    finally:
        for h in handles:
            h.remove()
        model.train(was_training)
    return rows


def totals(rows: Sequence[dict[str, Any]]) -> dict[str, float]:
    """MACs per frame by kind, and the FLOP of a forward per frame and of a training sample (module docstring)."""
    conv = sum(r["macs"] for r in rows if r["kind"] == "Conv2d")
    fc = sum(r["macs"] for r in rows if r["kind"] == "Linear")
    forward = conv + fc
    no_input_grad = sum(r["macs"] for r in rows if not r["input_grad"])
    train = 3 * forward - no_input_grad
    return {"conv_macs": conv, "fc_macs": fc, "forward_macs": forward, "forward_flop": 2 * forward,
            "train_macs": train, "train_flop": 2 * train, "conv_share": conv / forward}


def build(encoder: str = "cil", mixer: str = "independent", head: str = "regression") -> nn.Module:
    from cicfw.model.module import CICModule

    torch.manual_seed(0)
    return CICModule(encoder=encoder, mixer=mixer, head=head)


def matmul_gflops(n: int = 2048, reps: int = 5) -> float:
    """This process's fp32 matrix-multiply rate (GFLOP/s, the median of ``reps`` n x n products on torch's
    current threads): the arithmetic ceiling the model's figures are set beside."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b  # warm-up: the thread pool, the pages
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t0)
    return 2 * n ** 3 / statistics.median(times) / 1e9


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoder", default="cil")
    ap.add_argument("--mixer", default="independent")
    ap.add_argument("--head", default="regression")
    ap.add_argument("--batch", type=int, default=120, help="the training batch the step's floor is given for (120)")
    ap.add_argument("--matmul", type=int, default=0, metavar="N",
                    help="also measure an N x N fp32 matmul's GFLOP/s here and print the limits it implies (0: skip)")
    ap.add_argument("--reps", type=int, default=5, help="timed matmuls (the median is used)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's, all cores)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    rows = count(build(args.encoder, args.mixer, args.head))
    t = totals(rows)
    print(f"model {args.encoder} + {args.mixer} + {args.head}, image {IMAGE_HW[0]}x{IMAGE_HW[1]}: "
          f"multiply-adds per frame, forward (1 MAC = 2 FLOP)")
    for r in rows:
        print(f"  {r['name']:<28} {r['kind']:<7} {r['macs']:>13,d}{'' if r['input_grad'] else '   (input needs no gradient)'}")
    print(f"convolutions {t['conv_macs']:,d} MACs ({100 * t['conv_share']:.1f}%), fully connected {t['fc_macs']:,d}")
    print(f"forward per frame: {t['forward_macs']:,d} MACs = {t['forward_flop'] / 1e9:.3f} GFLOP")
    print(f"training per sample (forward + weight and input gradients): {t['train_macs']:,d} MACs = "
          f"{t['train_flop'] / 1e9:.3f} GFLOP; a batch of {args.batch}: {args.batch * t['train_flop'] / 1e9:.1f} GFLOP")
    if args.matmul:
        g = matmul_gflops(args.matmul, args.reps)
        print(f"fp32 matmul {args.matmul}x{args.matmul} on {torch.get_num_threads()} threads: {g:.1f} GFLOP/s (median of {args.reps})")
        print(f"the arithmetic limit at that rate: forward {g * 1e9 / t['forward_flop']:.0f} frames/s "
              f"({1e3 * t['forward_flop'] / (g * 1e9):.2f} ms a frame); training {g * 1e9 / t['train_flop']:.0f} samples/s "
              f"({args.batch * t['train_flop'] / (g * 1e9):.2f} s a batch of {args.batch})")


if __name__ == "__main__":
    main()
