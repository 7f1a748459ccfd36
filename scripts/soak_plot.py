"""Plots `handflow bench soak --csv` output: each stage's resident memory and open file
descriptors, and the pipeline's rate and latency, against time.

    python3 scripts/soak_plot.py out/soak.csv docs/images/soak.png
"""

import csv
import sys
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(csv_path, png_path):
    memory, fds = defaultdict(list), defaultdict(list)
    pipeline = {}
    with open(csv_path, newline="") as f:
        for row in csv.DictReader(f):
            minute = float(row["minute"])
            memory[row["stage"]].append((minute, float(row["rss_mib"])))
            fds[row["stage"]].append((minute, int(row["fds"])))
            pipeline[minute] = (float(row["samples_per_s"]), float(row["latency_p50_ms"]), float(row["latency_p99_ms"]))
    if not pipeline:
        sys.exit(f"{csv_path}: no windows")
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for stage, points in sorted(memory.items()):
        axes[0][0].plot(*zip(*points), marker="o", label=stage)
        axes[0][1].plot(*zip(*fds[stage]), marker="o", label=stage)
    minutes = sorted(pipeline)
    axes[1][0].plot(minutes, [pipeline[m][0] for m in minutes], marker="o", color="black")
    axes[1][1].plot(minutes, [pipeline[m][1] for m in minutes], marker="o", label="p50")
    axes[1][1].plot(minutes, [pipeline[m][2] for m in minutes], marker="o", label="p99")
    axes[0][0].set_ylabel("resident memory (MiB)")
    axes[0][0].set_yscale("log")
    axes[0][1].set_ylabel("open file descriptors")
    axes[1][0].set_ylabel("trajectory samples / s")
    axes[1][1].set_ylabel("glass-to-trajectory latency (ms)")
    for ax in axes[1]:
        ax.set_xlabel("minutes")
    for ax in (axes[0][0], axes[0][1], axes[1][1]):
        ax.legend(fontsize=8)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0) if ax.get_yscale() == "linear" else None
    fig.suptitle("handflow live pipeline, soak: per window")
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    print(f"wrote {png_path}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
