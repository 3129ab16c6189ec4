"""The Khronos glTF-Validator (npm ``gltf-validator``), run through ``node``.

``tools/npm/validate.mjs`` calls ``validateBytes`` with external resources loaded only from the
asset's own folder and prints the report as JSON; :func:`validate_gltf` runs it and returns
the parsed report's ``issues`` part.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

from ..errors import PbrsrError

_REPO_ROOT = Path(__file__).resolve().parents[2]
_SCRIPT = _REPO_ROOT / "tools" / "npm" / "validate.mjs"
_PACKAGE = _REPO_ROOT / "tools" / "npm" / "node_modules" / "gltf-validator"


class ValidatorUnavailable(PbrsrError):
    """node or the gltf-validator package is not installed here."""

    code = "validator-unavailable"
    http_status = 503
    exit_code = 9


def validator_available() -> bool:
    """True when node and the npm package are both present."""
    return shutil.which("node") is not None and _PACKAGE.is_dir() and _SCRIPT.is_file()


def validate_gltf(path: Path, *, max_issues: int = 200, timeout_s: float = 120.0) -> dict:
    """Validate one ``.gltf``/``.glb`` file.

    Returns ``{"numErrors", "numWarnings", "numInfos", "numHints", "messages": [{"code",
    "message", "severity" (0 error, 1 warning, 2 info, 3 hint), "pointer"}], "info": {...}}``.
    Raises :class:`ValidatorUnavailable` when node or the package is missing (run
    ``./scripts/setup``), and when the validator itself fails.
    """
    node = shutil.which("node")
    if node is None:
        raise ValidatorUnavailable(
            "The glTF-Validator needs Node.js: install node (>= 18) and run ./scripts/setup."
        )
    if not _PACKAGE.is_dir() or not _SCRIPT.is_file():
        raise ValidatorUnavailable(
            "The npm package gltf-validator is not installed: run "
            "'npm ci --prefix tools/npm' (./scripts/setup does it)."
        )
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such asset file: {path.name}")
    env = {k: v for k, v in os.environ.items() if k in ("PATH", "HOME", "LANG", "TMPDIR")}
    try:
        proc = subprocess.run(
            [node, str(_SCRIPT), str(path), str(int(max_issues))],
            capture_output=True,
            timeout=timeout_s,
            env=env,
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        raise ValidatorUnavailable(
            f"the glTF-Validator took longer than {timeout_s:.0f} s"
        ) from exc
    if proc.returncode != 0:
        raise ValidatorUnavailable(
            "the glTF-Validator failed: " + proc.stderr.decode("utf-8", "replace").strip()[:500]
        )
    try:
        report = json.loads(proc.stdout)
    except json.JSONDecodeError as exc:
        raise ValidatorUnavailable("the glTF-Validator printed something that is not JSON") from exc
    issues = dict(report.get("issues", {}))
    issues.setdefault("numErrors", 0)
    issues.setdefault("numWarnings", 0)
    issues.setdefault("messages", [])
    issues["info"] = report.get("info", {})
    return issues
