"""One row per map of a run's report: what a user reads first about each map (the CLI's
table after ``pbrsr upscale``, a finished job's summary, the dashboard's table)."""

from __future__ import annotations

CHANNELS = "RGBA"


def map_rows(report: dict) -> list[dict]:
    """Per map of ``report`` (``report.json``), by image index: its name and label, LR and
    output size, factor (1: kept as it is, for ``maps`` or under ``max_size``), what each
    channel entry was made from (``made_by``: one entry for a colour or normal map, one per
    channel of a data map) on one line (``made_from``) and, where PBR-SR measured it, the
    consistency PSNR to its LR map per role (dB)."""
    consistency: dict[int, dict[str, float]] = {}
    for key, db in (report.get("consistency_psnr_db") or {}).items():
        index, _, role = key.partition(":")
        consistency.setdefault(int(index), {})[role] = round(float(db), 2)
    rows = [
        {
            "index": img["index"],
            "name": img["name"],
            "label": img.get("label"),
            "lr_size": img["lr_size"],
            "size": img["hr_size"],
            "scale": img["scale"],
            "made_by": img.get("made_by") or [],
            "consistency_db": consistency.get(img["index"], {}),
        }
        for img in report.get("images", [])
    ]
    rows += [
        {
            "index": img["index"],
            "name": img["name"],
            "label": img.get("label"),
            "lr_size": img["size"],
            "size": img["size"],
            "scale": 1,
            "made_by": [f"kept ({img.get('reason', 'max_size')})"],
            "consistency_db": {},
        }
        for img in report.get("kept", [])
    ]
    for row in rows:
        row["made_from"] = made_by_text(row["made_by"])
    return sorted(rows, key=lambda r: r["index"])


def made_by_text(made_by: list[str]) -> str:
    """``made_by`` on one line: the entry itself, or each channel's after its letter."""
    if len(made_by) == 1:
        return made_by[0]
    if len(set(made_by)) == 1 and made_by:
        return f"{made_by[0]} (each channel)"
    return "; ".join(f"{CHANNELS[c]}: {m}" for c, m in enumerate(made_by))
