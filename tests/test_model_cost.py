"""bench/model_cost.py: the CIL network's multiply-adds per frame and per training sample, checked against
a hand computation (the figures docs/training.md's "Cost" section quotes)."""
from __future__ import annotations

from conftest import load_bench_script


def test_the_first_two_convolutions_by_hand():
    layers = load_bench_script("model_cost").cil_conv_layers()
    # conv 1: 3 -> 32 channels, 5x5, stride 2, no padding, on 88 x 200:
    # (88 - 5) // 2 + 1 = 42 rows, (200 - 5) // 2 + 1 = 98 columns; each output sums 3 x 5 x 5 inputs
    assert (layers[0]["h"], layers[0]["w"]) == (42, 98)
    assert layers[0]["macs"] == 42 * 98 * 32 * (3 * 5 * 5) == 9_878_400
    # conv 2: 32 -> 32, 3x3, stride 1: 40 x 96 outputs of 32 x 3 x 3 inputs each
    assert (layers[1]["h"], layers[1]["w"]) == (40, 96)
    assert layers[1]["macs"] == 40 * 96 * 32 * (32 * 3 * 3) == 35_389_440
    # the last one leaves 256 x 2 x 16 = 8192 features, the first FC's input
    assert (layers[-1]["out"], layers[-1]["h"], layers[-1]["w"]) == (256, 2, 16)


def test_the_counted_model_agrees_with_the_formula_and_the_stated_totals():
    m = load_bench_script("model_cost")
    model = m.build()
    rows = m.count(model)
    convs = [r for r in rows if r["kind"] == "Conv2d"]
    assert [r["macs"] for r in convs] == [layer["macs"] for layer in m.cil_conv_layers()]
    first_fc = next(r for r in rows if r["name"] == "encoder.image_fc.0.0")
    assert first_fc["macs"] == 8192 * 512
    # every branch runs for every frame: 4 x (512*256 + 256*256 + 256*1)
    assert sum(r["macs"] for r in rows if r["name"].startswith("mixer.")) == 4 * (512 * 256 + 256 * 256 + 256)
    t = m.totals(rows)
    assert t["conv_macs"] == 160_707_456 and t["forward_macs"] == 166_295_552
    assert round(t["forward_flop"] / 1e9, 2) == 0.33  # "about 0.33 GFLOP a frame forward"
    # the backward: weight and input gradients of every layer, less the input gradients of the layers that
    # read the image (conv 1) and the speed (its first FC, 1 -> 128)
    assert [r["name"] for r in rows if not r["input_grad"]] == ["encoder.convs.0", "encoder.speed_fc.0.0"]
    assert t["train_macs"] == 3 * 166_295_552 - 9_878_400 - 128
    assert 0.97 < t["train_flop"] / 1e9 < 0.99  # "about 1 GFLOP a training sample"
    assert all(p.grad is None for p in model.parameters())  # counting trains nothing
