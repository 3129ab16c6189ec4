"""The PBRSR_* variables the entry points read into the core's runtime settings."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from pbrsr_core import runtime
from pbrsr_core.cli.environment import configure_from_env, runtime_changes
from pbrsr_core.errors import InvalidOptions


def test_each_variable_sets_its_field(tmp_path):
    env = {
        "PBRSR_CACHE_DIR": str(tmp_path / "cache"),
        "PBRSR_NPM_DIR": str(tmp_path / "npm"),
        "PBRSR_PRIOR_TILE": "96",
        "PBRSR_PRIOR_PRECISION": "fp32",
        "PBRSR_PSEUDO_GT_CACHE_MB": "0",
        "PBRSR_SHADE_REFERENCE": "1",
        "PBRSR_KERNEL_CLASSIFIER": str(tmp_path / "classifier.json"),
        "HOME": "/nowhere",
    }
    (tmp_path / "classifier.json").write_text("{}")
    assert runtime_changes(env) == {
        "cache_dir": tmp_path / "cache",
        "npm_dir": tmp_path / "npm",
        "prior_tile": 96,
        "prior_precision": "fp32",
        "pseudo_gt_cache_mb": 0,
        "shade_reference": True,
        "kernel_classifier": tmp_path / "classifier.json",
    }
    assert runtime_changes({"PBRSR_SHADE_REFERENCE": "0"}) == {"shade_reference": False}
    # unset or empty: the defaults stay
    assert runtime_changes({"PBRSR_PRIOR_TILE": " ", "PBRSR_CACHE_DIR": ""}) == {}


def test_cache_folder_falls_back_to_xdg(tmp_path):
    assert runtime_changes({"XDG_CACHE_HOME": str(tmp_path)}) == {"cache_dir": tmp_path / "pbrsr"}
    both = {"XDG_CACHE_HOME": str(tmp_path), "PBRSR_CACHE_DIR": str(tmp_path / "own")}
    assert runtime_changes(both)["cache_dir"] == tmp_path / "own"


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("PBRSR_PRIOR_TILE", "big", "PBRSR_PRIOR_TILE='big' is not a whole number"),
        ("PBRSR_PRIOR_TILE", "0", "PBRSR_PRIOR_TILE=0 is not a positive tile side"),
        ("PBRSR_PRIOR_PRECISION", "half", "PBRSR_PRIOR_PRECISION='half' is not one of"),
        ("PBRSR_PSEUDO_GT_CACHE_MB", "-5", "PBRSR_PSEUDO_GT_CACHE_MB=-5 is negative"),
        ("PBRSR_KERNEL_CLASSIFIER", "/no/such.json", "PBRSR_KERNEL_CLASSIFIER='/no/such.json' is"),
    ],
)
def test_bad_values_name_the_variable(name, value, message):
    with pytest.raises(InvalidOptions, match=message):
        runtime_changes({name: value})


def test_configure_from_env_installs_the_settings(monkeypatch, tmp_path):
    monkeypatch.setattr(runtime, "_current", runtime.Runtime())
    configure_from_env({"PBRSR_PRIOR_TILE": "64", "PBRSR_CACHE_DIR": str(tmp_path)})
    assert runtime.current().prior_tile == 64
    assert runtime.cache_dir() == tmp_path
    with runtime.configured(prior_tile=128):
        assert runtime.current().prior_tile == 128
    assert runtime.current().prior_tile == 64


def test_the_cli_reads_the_environment_and_reports_a_bad_value(tmp_path):
    exe = Path(sys.executable).with_name("pbrsr")
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "PBRSR_PRIOR_PRECISION": "half"}
    bad = subprocess.run([exe, "priors", "list"], env=env, capture_output=True, text=True)
    assert bad.returncode == InvalidOptions.exit_code
    assert "PBRSR_PRIOR_PRECISION='half' is not one of auto, fp32, bf16" in bad.stderr
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "PBRSR_CACHE_DIR": str(tmp_path / "c")}
    listing = subprocess.run([exe, "priors", "list"], env=env, capture_output=True, text=True)
    assert listing.returncode == 0, listing.stderr
    # rrdn-thick's converted weights would live in the cache named by the variable: none there
    line = next(ln for ln in listing.stdout.splitlines() if "rrdn-thick" in ln)
    assert " no " in line
