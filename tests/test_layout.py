"""The package boundaries, read from the source (ast): what each package may import."""

from __future__ import annotations

import ast
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
