"""`pbrsr upscale` on hostile inputs and bad options: the error's exit code and a one-line
message, never a traceback."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from pbrsr_core.asset import make_quad_asset
from pbrsr_core.errors import InvalidAsset, InvalidOptions, LimitExceeded, UnprocessableAsset
from pbrsr_core.limits import Limits
from tests.clirun import run_cli
from tests.hostile import hostile_cases, zip_with_zeros

REPO = Path(__file__).resolve().parents[3]


def assert_one_line(err: str, says: str = "", quiet: bool = True) -> None:
    """stderr ends with exactly one ``error: ...`` line and holds no traceback; with
    ``quiet`` it holds nothing else (otherwise a progress bar may precede it)."""
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("error: "), err
    assert sum(ln.startswith("error") for ln in lines) == 1, err
    if quiet:
        assert len(lines) == 1, err
    assert "Traceback" not in err
    assert says.lower() in lines[-1].lower(), (says, err)


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return hostile_cases(tmp_path_factory.mktemp("hostile"))


def test_every_hostile_case_exits_with_its_code(corpus, tmp_path, capfd):
    # cases that need non-default limits or unwrapping off cannot be expressed on this CLI
    cases = [c for c in corpus if c.limits == Limits() and c.unwrap]
    assert len(cases) >= 24
    for i, case in enumerate(cases):
        out = tmp_path / f"out{i}"
        code, err = run_cli(
            [
                "upscale",
                str(case.path),
                "-o",
                str(out),
                "--method",
                "bicubic",
                "--scale",
                "2",
                "-q",
            ],
            capfd,
        )
        assert code == case.error.exit_code, (case.name, code, err)
        assert_one_line(err, case.says)
        assert str(case.path.parent) not in err.split("error: ", 1)[1], (case.name, err)
        assert not out.exists() or not any(out.iterdir()), case.name  # no partial bundle


@pytest.fixture(scope="module")
def quad(tmp_path_factory) -> Path:
    return make_quad_asset(tmp_path_factory.mktemp("quad") / "q.glb", size=8)


def test_zip_entry_over_the_compression_ratio(tmp_path, capfd):
    z = zip_with_zeros(tmp_path / "z", 10 * 2**20, used=True)
    out = tmp_path / "o"
    code, err = run_cli(["upscale", str(z), "-o", str(out), "--method", "bicubic", "-q"], capfd)
    assert code == LimitExceeded.exit_code, err
    assert_one_line(err, "the zip entry 'model/zeros.bin' unpacks")
    assert "the limit is 200:1" in err
    assert not out.exists() or not any(out.iterdir())


def test_zip_entry_the_asset_does_not_use_is_accepted_and_left_out(tmp_path, capfd):
    z = zip_with_zeros(tmp_path / "z", 64 * 2**20, used=False)
    out = tmp_path / "o"
    args = ["upscale", str(z), "-o", str(out), "--method", "bicubic", "--scale", "2", "-q"]
    code, err = run_cli(args, capfd)
    assert code == 0, err
    assert not list(out.rglob("zeros.bin"))


def test_missing_input_file(tmp_path, capfd):
    code, err = run_cli(["upscale", str(tmp_path / "nope.glb"), "-o", str(tmp_path / "o")], capfd)
    assert code == InvalidOptions.exit_code
    assert_one_line(err, "does not exist")


@pytest.mark.parametrize(
    "extra, says",
    [
        (["--scale", "3"], "scale"),
        (["--scale", "0"], "scale"),
        (["--method", "magic"], "method"),
        (["--format", "gif"], "image_format"),
        (["--method", "direct", "--prior", "no-such-prior"], "no-such-prior"),
        (["--method", "pbrsr", "--prior", "bicubic", "--preset", "no-such-preset"], "preset"),
        (["--prior", "bicubic", "--iterations", "-1"], "iterations"),
        (["--max-size", "1"], "max_size"),
        (
            ["--lr-kernel", "box"],
            "lr_kernel: Input should be 'gaussian', 'area', 'bicubic', 'lanczos' or 'auto'",
        ),
        (["--method", "bicubic", "--max-size", "15"], "nothing to upscale"),
        (["--maps", "base_color,albedo"], "maps: Value error, unknown map role 'albedo'"),
        (["--maps", ","], "maps: List should have at least 1 item"),
        (["--method", "bicubic", "--maps", "clearcoat"], "nothing to upscale"),
        (["--maps", "normal", "--other-maps", "smear"], "other_maps: Input should be 'keep' or"),
    ],
)
def test_bad_options(quad, tmp_path, capfd, extra, says):
    out = tmp_path / "o"
    code, err = run_cli(["upscale", str(quad), "-o", str(out), "-q", *extra], capfd)
    want = UnprocessableAsset if says == "nothing to upscale" else InvalidOptions
    assert code == want.exit_code, err
    assert_one_line(err, says)
    assert not out.exists() or not any(out.iterdir())


def test_degrade_rejects_unknown_format(quad, tmp_path, capfd):
    out = tmp_path / "lr.glb"
    code, err = run_cli(["degrade", str(quad), "-o", str(out), "--format", "gif"], capfd)
    assert code == InvalidOptions.exit_code, err
    assert_one_line(err, "unknown image format 'gif'")
    assert not out.exists()


def test_degrade_rejects_a_bad_jpeg_quality(quad, tmp_path, capfd):
    out = tmp_path / "lr.glb"
    code, err = run_cli(["degrade", str(quad), "-o", str(out), "--format", "jpeg:101"], capfd)
    assert code == InvalidOptions.exit_code, err
    assert_one_line(err, "bad JPEG format 'jpeg:101'")
    assert not out.exists()


def test_degrade_rejects_unknown_kernel(quad, tmp_path, capfd):
    out = tmp_path / "lr.glb"
    code, err = run_cli(["degrade", str(quad), "-o", str(out), "--kernel", "box"], capfd)
    assert code == InvalidOptions.exit_code, err
    assert_one_line(err, "unknown LR kernel(s) box: use gaussian, area, bicubic, lanczos")
    assert not out.exists()


def test_real_binary_prints_no_traceback(corpus, tmp_path):
    """The installed console script, as a user runs it (one subprocess: torch import cost)."""
    exe = REPO / ".venv" / "bin" / "pbrsr"
    if not exe.is_file():
        pytest.skip("the pbrsr console script is not installed in .venv")
    case = next(c for c in corpus if c.name == "truncated_glb")
    proc = subprocess.run(
        [str(exe), "upscale", str(case.path), "-o", str(tmp_path / "o"), "--method", "bicubic"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert proc.returncode == InvalidAsset.exit_code, proc.stderr
    assert_one_line(proc.stderr, "truncated", quiet=False)


def test_a_run_over_the_memory_it_may_use_is_refused(quad, tmp_path, capfd):
    out = tmp_path / "o"
    args = ["upscale", str(quad), "-o", str(out), "--method", "bicubic", "-q"]
    code, err = run_cli([*args, "--memory-mb", "100"], capfd)
    assert code == LimitExceeded.exit_code, err
    assert_one_line(err, "GiB of memory and this machine has 0.1 GiB for it")
    assert "max_size" in err
    assert not out.exists() or not any(out.iterdir())
    code, err = run_cli(args, capfd)  # by default, what the machine has free
    assert code == 0, err
