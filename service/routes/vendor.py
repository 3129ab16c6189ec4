"""``/vendor/three/<path>``: the dashboard's 3D viewer library, three.js's ES modules served
from pbrsr's npm packages (``tools/npm``, installed by ``scripts/setup``; ``PBRSR_NPM_DIR``
elsewhere), so the page loads nothing from a CDN. Only the files the viewer imports."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from pbrsr_core import runtime

from ..deps import SettingsDep
from ..problems import ProblemError

router = APIRouter(include_in_schema=False)

PACKAGE = "three"
# what service/static/viewer3d.js imports, and what those import in turn
VIEWER_FILES = frozenset(
    {
        "build/three.module.js",
        "build/three.core.js",
        "examples/jsm/controls/OrbitControls.js",
        "examples/jsm/environments/RoomEnvironment.js",
        "examples/jsm/loaders/GLTFLoader.js",
        "examples/jsm/loaders/DRACOLoader.js",
        "examples/jsm/libs/meshopt_decoder.module.js",
        # fetched by DRACOLoader when a model has Draco meshes
        "examples/jsm/libs/draco/gltf/draco_wasm_wrapper.js",
        "examples/jsm/libs/draco/gltf/draco_decoder.wasm",
        "examples/jsm/utils/BufferGeometryUtils.js",
        "examples/jsm/utils/SkeletonUtils.js",
        "LICENSE",
    }
)


@router.get("/vendor/three/{path:path}")
def vendor_file(path: str, settings: SettingsDep) -> FileResponse:
    if path not in VIEWER_FILES:
        raise ProblemError(404, "not-found", "not a file of the dashboard's viewer")
    root = Path(settings.npm_dir).expanduser() if settings.npm_dir else runtime.npm_dir()
    file = root / PACKAGE / path
    if not file.is_file():
        raise ProblemError(
            404,
            "not-found",
            "the dashboard's 3D viewer (npm package 'three') is not installed: run scripts/setup",
        )
    media = {".js": "text/javascript", ".wasm": "application/wasm"}.get(file.suffix, "text/plain")
    return FileResponse(file, media_type=media, headers={"Cache-Control": "max-age=86400"})
