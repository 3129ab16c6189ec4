"""`pbrsr priors install` (idempotent, quiet) and `pbrsr priors list`."""

from __future__ import annotations

import pytest
import typer
from typer.testing import CliRunner

from pbrsr_core.cli import priors as priors_cli
from pbrsr_core.prior import rrdn
from pbrsr_core.prior.registry import clear_cache


@pytest.fixture
def app():
    a = typer.Typer()
    priors_cli.register(a)

    @a.callback()
    def _root() -> None:  # keep "priors" a sub-command
        pass

    return a


@pytest.mark.skipif(not (rrdn.package_dir() / "package.json").is_file(), reason="no npm package")
def test_install_then_noop_then_list(app, tmp_path, set_runtime):
    set_runtime(cache_dir=tmp_path)
    clear_cache()
    runner = CliRunner()
    first = runner.invoke(app, ["priors", "install", "rrdn-thick"])
    assert first.exit_code == 0, first.output
    assert "converted 4 model(s)" in first.output
    mtimes = [rrdn.weights_file(s).stat().st_mtime_ns for s in rrdn.SCALES]
    second = runner.invoke(app, ["priors", "install", "rrdn-thick", "--quiet"])
    assert second.exit_code == 0 and second.output == ""
    assert [rrdn.weights_file(s).stat().st_mtime_ns for s in rrdn.SCALES] == mtimes
    listing = runner.invoke(app, ["priors", "list"])
    assert listing.exit_code == 0
    line = next(ln for ln in listing.output.splitlines() if "rrdn-thick" in ln)
    assert "yes" in line and "x2, x3, x4, x8" in line and "MB" in line


def test_list_shows_not_installed(app, tmp_path, set_runtime):
    set_runtime(cache_dir=tmp_path / "empty")
    out = CliRunner().invoke(app, ["priors", "list"]).output
    line = next(ln for ln in out.splitlines() if "rrdn-thick" in ln)
    assert " no " in line and "pbrsr priors install" in line
