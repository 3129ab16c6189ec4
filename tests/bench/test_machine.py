"""The machine line of a benchmark: its CPU, threads and measured convolution speed."""

import math

import pytest
import torch

from pbrsr_bench.machine import conv_gflops, machine


def test_the_reference_convolution_measures_a_finite_speed_and_restores_the_threads():
    before = torch.get_num_threads()
    speed = conv_gflops(1, size=32, repeats=2)
    assert math.isfinite(speed) and speed > 0
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("args", [(0, 32, 1), (1, 2, 1), (1, 32, 0)])
def test_the_reference_convolution_refuses_nonsense(args):
    with pytest.raises(ValueError, match="at least"):
        conv_gflops(*args)


def test_the_machine_line_names_the_threads_and_the_speed_on_them():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        line = machine()
    finally:
        torch.set_num_threads(before)
    assert "2 torch threads" in line
    assert line.count("GFLOPS") == 1 and "on one thread" in line
    gflops = float(line.split("float32: ")[1].split(" GFLOPS")[0])
    assert gflops > 0
