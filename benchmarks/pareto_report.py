"""Markdown table and PNG plots of ``benchmarks.pareto`` (input: the ``pareto.json`` dictionary)."""

from __future__ import annotations

import io
from typing import Any

AXIS_COLORS = {
    "default": "black",
    "resolution": "tab:blue",
    "sh_degree": "tab:orange",
    "alpha_min": "tab:green",
    "t_min": "tab:red",
    "budget": "tab:purple",
    "storage": "tab:brown",
    "combined": "tab:pink",
    "world": "tab:gray",
}


def _f(v, nd: int = 2) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def _settings(r: dict) -> str:
    sh = "all" if r["sh_degree"] is None else str(r["sh_degree"])
    extra = []
    if r["fraction"] != 1.0:
        extra.append(f"{round(100 * r['fraction'])}% Gaussians")
    if r["storage"] != "float32":
        extra.append(r["storage"])
    if r.get("world"):
        extra.append(f"world {r['world_label']}")
    s = f"{r['size']} px, alpha_min {r['alpha_min'] * 255:g}/255, t_min {r['t_min']:g}, SH {sh}"
    return s + (", " + ", ".join(extra) if extra else "")


def _table(rows: list[dict], front_key: str, rec: str | None) -> list[str]:
    out = [
        (
            "| setting | what | Gaussians | step (ms) | steps/s | full render (ms) | PSNR (dB) | dPSNR | SSIM "
            "| mask IoU | front |"
        ),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        name = f"**{r['name']}**" if r["name"] == rec else r["name"]
        mark = ("yes" if r.get(front_key) else "") + (" (recommended)" if r["name"] == rec else "")
        out.append(
            f"| {name} | {_settings(r)} | {r['gaussians']} | {_f(r['step_ms'])} | {_f(r['steps_per_s'], 0)} "
            f"| {_f(r.get('full_render_ms'))} | {_f(r['psnr'])} | {r['psnr'] - rows[0]['psnr']:+.2f} "
            f"| {_f(r['ssim'], 4)} | {_f(r['mask_iou'], 4)} | {mark} |"
        )
    return out


def markdown(res: dict[str, Any]) -> str:
    b = res["bundled"]
    rec = res.get("recommended")
    rec_name = rec["name"] if rec else None
    lines = [
        "# Run time against error (`python -m benchmarks.pareto`)",
        "",
        (
            f"Mode `{res['mode']}`; machine: {res['machine']['cpus']} CPUs; wall time {res['wall_seconds']:.0f} s; "
            f"code {res['git']}."
        ),
        "",
        f"## Bundled world: {b['kind']} (`{b['world']}`)",
        "",
        (
            f"{b['test_views']} views of the `{b['scene']}` capture's test states (MuJoCo ground truth; dsg-synth "
            f"{b['capture']['version']}, seed {b['capture']['seed']}, lighting `{b['capture']['lighting']}`: the "
            "data the world was trained on). " + res["method"]
        ),
        "",
        *_table(b["points"], "on_front", rec_name),
        "",
        f"Pareto front (step time, PSNR; all points): {', '.join(b['front'])}.",
        f"Front at {res['default_size']} px: {', '.join(b['front_default_size'])}.",
        "",
    ]
    if rec:
        vs = rec["vs_default"]
        lines += [
            "## Recommended default",
            "",
            f"Rule: {rec['rule']}.",
            "",
            (
                f"**{rec['name']}**: `render_settings={rec['render_settings']}` at {rec['size']} px: "
                f"{rec['psnr']:.2f} dB, {rec['step_ms']:.2f} ms per step ({rec['steps_per_s']:.0f} steps/s); "
                f"against today's default: {vs['psnr_delta_db']:+.3f} dB, {vs['step_speedup']:.2f}x steps."
            ),
            "",
        ]
        if res.get("world_level_note"):
            lines += [res["world_level_note"], ""]
    sc = res.get("scenes")
    if sc:
        lines += [
            f"## The seven scenes: {sc['kind']}",
            "",
            sc["note"],
            "",
            "Mean over the scenes (" + ", ".join(sc["names"]) + "):",
            "",
            *_table(sc["mean_points"], "on_front", rec_name),
            "",
            f"Front of the means: {', '.join(sc['front'])}.",
            "",
            (
                "| scene | Gaussians | default PSNR | default steps/s | recommended dPSNR | best at "
                f"{res['default_size']} px | recommended vs best |"
            ),
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for name, s in sc["per_scene"].items():
            d = s["points"][0]
            chk = s.get("recommended_check") or {}
            lines.append(
                f"| {name} | {d['gaussians']} | {_f(d['psnr'])} | {_f(d['steps_per_s'], 0)} | "
                f"{chk.get('psnr_delta_vs_default', 0):+.2f} | {chk.get('best', '-')} | "
                f"{chk.get('psnr_delta_vs_best', 0):+.2f} |"
            )
        lines.append("")
    tr = res.get("training")
    if tr:
        lines += [
            "## Training time against error",
            "",
            tr["note"],
            "",
            "| preset | step | training time (s) | novel-state PSNR (dB) | SSIM | mask IoU | Gaussians |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for c in tr["curves"]:
            for p in c["points"]:
                lines.append(
                    f"| {c['preset']} | {p['step']} / {c['iterations']} | {p['train_seconds']:.0f} | "
                    f"{_f(p['psnr'])} | {_f(p['ssim'], 4)} | {_f(p['mask_iou'], 4)} | {p['gaussians'] or '-'} |"
                )
        lines.append("")
    if res.get("notes"):
        lines += ["## Notes", ""] + [f"- {n}" for n in res["notes"]] + [""]
    return "\n".join(lines)


def _scatter(ax, rows: list[dict], title: str, rec: str | None) -> None:
    seen = set()
    for r in rows:
        lab = r["axis"] if r["axis"] not in seen else None
        seen.add(r["axis"])
        ax.scatter(
            r["step_ms"], r["psnr"], color=AXIS_COLORS.get(r["axis"], "gray"), s=28, label=lab, zorder=3
        )
        if r.get("on_front") or r["name"] in ("default", rec):  # the rest: colour legend and the table
            ax.annotate(
                r["name"], (r["step_ms"], r["psnr"]), fontsize=6, xytext=(3, 2), textcoords="offset points"
            )
    front = sorted((r for r in rows if r.get("on_front")), key=lambda r: r["step_ms"])
    if front:
        ax.plot(
            [r["step_ms"] for r in front],
            [r["psnr"] for r in front],
            "k--",
            lw=1,
            zorder=2,
            label="Pareto front",
        )
        ax.scatter(
            [r["step_ms"] for r in front],
            [r["psnr"] for r in front],
            s=90,
            facecolors="none",
            edgecolors="k",
            zorder=4,
        )
    for r in rows:
        if r["name"] == rec:
            ax.scatter(
                r["step_ms"],
                r["psnr"],
                marker="*",
                s=260,
                color="gold",
                edgecolors="k",
                zorder=5,
                label="recommended",
            )
    ax.set_xlabel("env step time (ms, median; lower is faster)")
    ax.set_ylabel("PSNR on test states (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, loc="lower right")


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=130)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


def pareto_png(res: dict[str, Any]) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = res["recommended"]["name"] if res.get("recommended") else None
    sc = res.get("scenes")
    fig, axes = plt.subplots(1, 2 if sc else 1, figsize=(13 if sc else 7.5, 5.5), squeeze=False)
    b = res["bundled"]
    _scatter(axes[0, 0], b["points"], f"{b['scene']}: {b['kind']}", rec)
    if sc:
        _scatter(axes[0, 1], sc["mean_points"], f"mean of {len(sc['names'])} scenes ({sc['kind']})", rec)
    fig.tight_layout()
    return _png(fig)


def training_png(training: dict[str, Any]) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for c in training["curves"]:
        pts = [p for p in c["points"] if p["psnr"] is not None]
        ax.plot(
            [max(p["train_seconds"], 0.1) for p in pts],
            [p["psnr"] for p in pts],
            "o-",
            label=f"{c['preset']} ({c['reached_step']}/{c['iterations']} steps"
            + (")" if c["finished"] else f", capped at {c['cap_minutes']:g} min)"),
        )
    ax.set_xscale("log")
    xs = [p["train_seconds"] for c in training["curves"] for p in c["points"]] or [1.0]
    ticks = [
        t
        for t in (1, 2, 5, 10, 20, 30, 60, 120, 240, 360, 600, 1200, 2400)
        if min(xs) / 1.5 <= t <= max(xs) * 1.5
    ]
    ax.set_xticks(ticks)
    ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("training wall-clock (s, log scale)")
    ax.set_ylabel("novel-state PSNR (dB)")
    ax.set_title(f"DSG-World training on {training['scene']} at {training['size']} px", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)
