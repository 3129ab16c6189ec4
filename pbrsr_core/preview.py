"""Before/after renders of an asset: the LR maps against the result, under two environments,
so a reader sees that the result holds up under relighting."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from .asset.images import write_image  # noqa: E402
from .asset.model import Asset  # noqa: E402
from .maps import encoded_to_param, kind_of  # noqa: E402
from .progress import Progress, ProgressFn, emit  # noqa: E402
from .render import camera as cam  # noqa: E402
from .render.light import EnvLight  # noqa: E402
from .scene import (  # noqa: E402
    asset_textures,
    make_scene,
    procedural_light,
    render_views,
    rotated_procedural_light,
)

PREVIEW_RES = 384


def preview_lights(envmap: str | None) -> dict[str, EnvLight]:
    """Two environments: the built-in procedural one and the user's map (or a second,
    rotated procedural one), so relighting is visible."""
    lights = {"studio": procedural_light()}
    if envmap:
        lights[Path(envmap).stem[:32] or "envmap"] = EnvLight.from_file(Path(envmap))
    else:
        lights["rotated"] = rotated_procedural_light(150.0)
    return lights


def preview_camera(res: int = PREVIEW_RES) -> cam.Camera:
    return cam.orbit_cameras(1, 1, 3.25, 24.0, (res, res), elev_range_deg=(25.0, 25.0))[0]


def write_previews(
    asset: Asset,
    hr: dict[int, np.ndarray],
    out_dir: Path,
    device: torch.device,
    envmap: str | None,
    progress: ProgressFn | None = None,
) -> dict[str, str]:
    """Write ``previews/{before,after}_<env>.png`` and ``preview.png``; return name -> path."""
    scene = make_scene(asset, device)
    before = asset_textures(asset, device)
    after = dict(before)
    for i, px in hr.items():
        after[i] = encoded_to_param(torch.from_numpy(px), kind_of(asset.images[i].roles)).to(device)
    camera = preview_camera()
    from .render import raster

    gb = [raster.rasterize(scene.mesh, camera)]
    (out_dir / "previews").mkdir(exist_ok=True)
    files: dict[str, str] = {}
    rows = []
    lights = preview_lights(envmap)
    done, total = 0, 2 * len(lights)
    for env, light in lights.items():
        light = light.to(device)
        pair = []
        for label, tex in (("before", before), ("after", after)):
            img = render_views(scene, tex, [camera], light, gbuffers=gb, background=0.18)[0][0]
            arr = img.cpu().numpy()
            rel = f"previews/{label}_{env}.png"
            write_image(out_dir / rel, arr, 8, "png")
            files[f"{label}_{env}"] = rel
            pair.append(arr)
            done += 1
            emit(progress, Progress(stage="preview", step=done, total=total))
        rows.append((env, pair))
    fig, axes = plt.subplots(len(rows), 2, figsize=(8, 4 * len(rows)), squeeze=False)
    for r, (env, pair) in enumerate(rows):
        for c, (label, arr) in enumerate(
            zip(("input (LR maps)", "result (HR maps)"), pair, strict=True)
        ):
            ax = axes[r][c]
            ax.imshow(np.clip(arr, 0, 1))
            ax.set_title(f"{label} - {env}", fontsize=10)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(out_dir / "preview.png", dpi=100)
    plt.close(fig)
    files["preview"] = "preview.png"
    return files
