"""Test PSNR against the budget, and along one 2400-s run, primitives 128 px, compact
(docs/results.md, "Quality past 600 s"):

    python docs/benchmarks/psnr_against_budget_to_2400.py q3 q4 q5 [q4-checkpoints.csv] OUT.png

q3, q4, q5: `nerfgauge bench train` folders (their train.json rows: budget, steps, test PSNR
and its edges and interior parts); the CSV (step,psnr,psnr_edges,psnr_interior): the 2400-s
run's checkpoints, each turned into a model and scored on the test views as its end is."""
import csv
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

folders = [a for a in sys.argv[1:-1] if not a.endswith(".csv")]
tables = [a for a in sys.argv[1:-1] if a.endswith(".csv")]
rows = sorted(((f, r) for f in folders for r in json.load(open(f"{f}/train.json"))["rows"]),
              key=lambda fr: fr[1]["budget"])
for folder, r in rows:
    print(f"{folder} {r['budget']:.0f} s: {r['steps']} steps, {r['steps_per_second']:.1f} steps/s, test {r['psnr']:.2f} "
          f"(edges {r['psnr_edges']:.2f}, interior {r['psnr_interior']:.2f}), SSIM {r['ssim']:.4f}")
parts = (("psnr", "o-", "whole frame"), ("psnr_interior", "s--", "interior"), ("psnr_edges", "^:", "edges"))
fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.6))
for part, style, label in parts:
    # points, not a line: the folders may hold runs of different code (q3's 1200 s and q5's)
    axes[0].plot([r["budget"] for _, r in rows], [r[part] for _, r in rows], style[0], label=label)
for folder, r in rows:
    axes[0].annotate(folder, (r["budget"], r["psnr"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
axes[0].set_xscale("log"); axes[0].set_xlabel("training budget (s)"); axes[0].set_title("end of each run", fontsize=8)
for table in tables:
    points = sorted((int(p["step"]), p) for p in csv.DictReader(open(table)))
    for part, style, label in parts:
        axes[1].plot([s for s, _ in points], [float(p[part]) for _, p in points], style, markersize=3, label=label)
    axes[1].set_title(f"along one run: its checkpoints ({Path(table).name})", fontsize=8)
axes[1].set_xlabel("step")
for ax in axes:
    ax.set_ylabel("test PSNR (dB)"); ax.grid(alpha=0.3)
axes[0].legend(fontsize=8)
fig.suptitle("compact NeRF, primitives 128 px, 100 views, nothing else running", fontsize=8)
fig.tight_layout(); fig.savefig(sys.argv[-1], dpi=110)
