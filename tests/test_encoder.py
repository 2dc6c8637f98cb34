"""The CIL encoder's sizes: the flattened convolution output its first FC takes, counted by hand."""
from __future__ import annotations

import pytest
import torch

from cicfw.model.encoders import IMAGE_HW, CILEncoder, conv_out_hw


def test_cil_s_convolutions_leave_2_by_16_of_an_88_by_200_image():
    # by hand, (n - k) // s + 1 per layer: 88x200 -> 42x98 -> 40x96 -> 19x47 -> 17x45 -> 8x22 -> 6x20 -> 4x18 -> 2x16
    assert conv_out_hw((88, 200)) == (2, 16)
    encoder = CILEncoder()
    assert encoder.image_fc[0][0].in_features == 256 * 2 * 16


@pytest.mark.parametrize("hw", [IMAGE_HW, (100, 100), (96, 161)])
def test_the_counted_size_is_what_the_convolutions_give(hw):
    with torch.no_grad():
        got = CILEncoder().eval().convs(torch.zeros(1, 3, *hw))
    assert tuple(got.shape[2:]) == conv_out_hw(hw)
