"""PNG plots from a benchmark result: engine scaling curves, scan lateness histograms.

Owns: the figures' layout (matplotlib, imported only when plots are asked for).
Does not know: how anything was measured, the markdown.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softplc.bench.cells import stat


def write_plots(results: dict[str, Any], directory: Path) -> list[str]:
    """PNG files for the sections that have data; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")  # no display on a server
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    written: list[str] = []
    engine = results["sections"].get("engine", {})
    families = engine.get("families", {}) if isinstance(engine, dict) else {}
    if families:
        fig, axes = plt.subplots(
            1, len(families), figsize=(4 * len(families), 4), sharey=True, squeeze=False
        )
        for ax, (family, data) in zip(axes[0], families.items(), strict=True):
            series: dict[str, list[tuple[float, float]]] = {}
            for r in data.get("rows", []):
                median = stat(r.get("round_us"), "median")
                if isinstance(median, (int, float)) and median > 0:
                    series.setdefault(str(r.get("engine")), []).append((r["n_transitions"], median))
            for engine_name, points in sorted(series.items()):
                points.sort()
                ax.plot(
                    [p[0] for p in points], [p[1] for p in points], marker="o", label=engine_name
                )
            ax.set(xscale="log", yscale="log", xlabel="transitions", title=family)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        axes[0][0].set_ylabel("µs per firing round (median)")
        fig.suptitle("Engine scaling: softplc vs SNAKES vs plain reference")
        written.append(_save(fig, directory / "engine_scaling.png"))
    scan = results["sections"].get("scan", {})
    histograms = scan.get("histograms", {}) if isinstance(scan, dict) else {}
    for period in sorted({k.rsplit("_", 1)[-1] for k in histograms}):
        fig, ax = plt.subplots(figsize=(8, 5))
        for name, h in sorted(histograms.items()):
            if not name.endswith("_" + period) or not h.get("counts"):
                continue
            edges, counts = h["edges_us"], h["counts"]
            ax.stairs(counts, edges, label=name.rsplit("_", 1)[0])
        ax.set(
            xscale="symlog",
            yscale="log",
            xlabel="lateness (µs, logarithmic above 1)",
            ylabel="scans",
            title=f"Scan lateness at {period} period",
        )
        ax.legend()
        ax.grid(True, alpha=0.3)
        written.append(_save(fig, directory / f"lateness_{period}.png"))
    for _path in written:
        plt.close("all")
    return written


def _save(fig: Any, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    return str(path)
