"""The files ``dsg-eval`` writes besides ``report.json``: the Markdown tables (``report.md``) and the labelled
error grid (``grid.png``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["fmt", "grid", "markdown", "region_lines", "u8"]


def u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def grid(
    rows: list[list[np.ndarray]],
    col_labels: list[str] | None = None,
    row_labels: list[str] | None = None,
) -> np.ndarray:
    """Tiles ``rows[i][j]`` (equal sizes) on white with 2 px borders; ``col_labels`` above the columns and
    ``row_labels`` (lines split at ``\\n``) left of the rows, in black (pillow's default font); a column or the
    label column is as wide as its widest label."""
    from PIL import Image, ImageDraw, ImageFont

    pad = 2
    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    font = ImageFont.load_default()
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    size = lambda t: draw.multiline_textbbox((0, 0), t, font=font)[2:]  # noqa: E731
    cols = [
        max([w] + ([size(col_labels[j])[0] + 2 * pad] if col_labels and j < len(col_labels) else []))
        for j in range(ncol)
    ]
    left = max([size(t)[0] + 2 * pad for t in row_labels or []], default=0)
    top = max([size(t)[1] + 2 * pad for t in col_labels or []], default=0)
    rh = max([h] + [size(t)[1] for t in row_labels or []])
    x0 = np.cumsum([left + pad] + [c + pad for c in cols[:-1]])
    out = np.full((top + len(rows) * (rh + pad) + pad, int(x0[-1]) + cols[-1] + pad, 3), 255, np.uint8)
    for i, r in enumerate(rows):
        y = top + pad + i * (rh + pad) + (rh - h) // 2
        for j, img in enumerate(r):
            x = int(x0[j]) + (cols[j] - w) // 2
            out[y : y + h, x : x + w] = img
    if not (col_labels or row_labels):
        return out
    im = Image.fromarray(out)
    d = ImageDraw.Draw(im)
    for j, t in enumerate((col_labels or [])[:ncol]):
        d.text((int(x0[j]) + (cols[j] - size(t)[0]) // 2, pad), t, fill=(0, 0, 0), font=font)
    for i, t in enumerate((row_labels or [])[: len(rows)]):
        d.multiline_text(
            (pad, top + pad + i * (rh + pad) + (rh - size(t)[1]) // 2), t, fill=(0, 0, 0), font=font
        )
    return np.asarray(im)


def fmt(v) -> str:
    return "-" if v is None else f"{v:.4f}" if isinstance(v, float) and abs(v) < 2 else f"{v:.2f}"


def markdown(r: dict[str, Any]) -> str:
    lines = [
        f"# Evaluation of `{Path(r['world']).name}` on `{r['state']}`",
        "",
        f"{r['views']} views at {r['image_size'][0]}x{r['image_size'][1]}, {r['num_gaussians']} Gaussians"
        + (", the world's own training views included." if r.get("training_views") else "."),
        "",
        "| view | PSNR (dB) | SSIM | mask IoU |",
        "| --- | --- | --- | --- |",
    ]
    for v in r["per_view"]:
        lines.append(f"| {v['view']} | {fmt(v['psnr'])} | {fmt(v['ssim'])} | {fmt(v.get('mean_mask_iou'))} |")
    m = r["mean"]
    lines.append(f"| **mean** | **{fmt(m['psnr'])}** | **{fmt(m['ssim'])}** | **{fmt(m['mask_iou'])}** |")
    if "view_alignment" in r:
        va = r["view_alignment"]
        lines += [
            "",
            f"Each camera aligned to the world first ({va['kept']} of {r['views']} moved, rotation rms "
            f"{va['rotation_deg_rms']:.3f} deg); unaligned mean PSNR {fmt(r['mean_unaligned']['psnr'])} dB.",
        ]
    if r["object_iou"]:
        lines += ["", "| object | IoU |", "| --- | --- |"]
        lines += [f"| {k} | {fmt(v)} |" for k, v in r["object_iou"].items()]
    lines += region_lines(r.get("error_by_region"))
    return "\n".join(lines) + "\n"


def region_lines(by_region: dict[str, Any] | None) -> list[str]:
    """Markdown table of :mod:`.regions`' error breakdown (nothing without one)."""
    if not by_region:
        return []
    seen = by_region.get("mean_psnr_seen")
    lines = [
        "",
        f"Error by region (outline: within {by_region['outline_radius']} px of an id change):",
        "",
        "| region | pixels | PSNR (dB) | share of the squared error |",
        "| --- | --- | --- | --- |",
    ]
    rows = [*by_region["regions"].items(), *((f"object {n}", e) for n, e in by_region["per_object"].items())]
    rows += [
        (f"background: {p.replace('_', ' ')}", e)
        for p, e in (by_region.get("background_parts") or {}).items()
    ]
    for name, e in rows:
        share = "-" if e["pixel_share"] is None else f"{100 * e['pixel_share']:.1f} %"
        err = "-" if e["error_share"] is None else f"{100 * e['error_share']:.1f} %"
        lines.append(f"| {name} | {share} | {fmt(e['psnr'])} | {err} |")
    if seen is not None:
        lines += ["", f"Mean PSNR of the views without their unseen pixels: {fmt(seen)} dB."]
    return lines
