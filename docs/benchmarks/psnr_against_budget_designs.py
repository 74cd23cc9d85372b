"""Test PSNR against the training budget for each design issue 52 tried on the pixel's
outline, primitives 128 px, 100 views, idle (docs/results.md, "Where more steps go"):

    python docs/benchmarks/psnr_against_budget_designs.py docs/benchmarks/psnr-against-budget-designs.csv OUT.png

The CSV (design, folder, budget_s, steps, steps_per_second, psnr, psnr_interior, psnr_edges,
date): one row a finished run, each scored on the test views through its render filter
(`nerfgauge render` + `nerfgauge evaluate`, or `nerfgauge bench train`). The dashed line is
item 3's target for the last design: its 600-s figure + 1 dB."""
import csv
import sys
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

rows = list(csv.DictReader(open(sys.argv[1])))
by_design = defaultdict(list)
for r in rows:
    by_design[r["design"]].append(r)
fig, axes = plt.subplots(1, 2, figsize=(10, 4.4), sharex=True)
for design, runs in by_design.items():  # the CSV's order: oldest design first
    budgets = sorted({int(r["budget_s"]) for r in runs})
    for ax, part in zip(axes, ("psnr", "psnr_interior")):
        # a design's runs at one budget (two pairs of linear light) are each a point, the line their mean
        ax.plot([int(r["budget_s"]) for r in runs], [float(r[part]) for r in runs], "o", markersize=4,
                color=f"C{list(by_design).index(design)}")
        means = [sum(float(r[part]) for r in runs if int(r["budget_s"]) == b) /
                 sum(1 for r in runs if int(r["budget_s"]) == b) for b in budgets]
        ax.plot(budgets, means, "-", color=f"C{list(by_design).index(design)}", label=design)
last = list(by_design.values())[-1]
target = [float(r["psnr"]) for r in last if int(r["budget_s"]) == 600][0] + 1.0
axes[0].axhline(target, color="grey", linestyle="--", linewidth=1)
axes[0].annotate("item 3: 600 s + 1 dB", (600, target), fontsize=7, xytext=(2, 3), textcoords="offset points")
axes[0].set_title("whole frame", fontsize=8)
axes[1].set_title("interior (covered, no edge in the pixel)", fontsize=8)
for ax in axes:
    ax.set_xscale("log"); ax.minorticks_off(); ax.set_xticks([600, 1200, 2400], ["600", "1200", "2400"])
    ax.set_xlabel("training budget (s)"); ax.set_ylabel("test PSNR (dB)"); ax.grid(alpha=0.3)
fig.legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="lower center", ncol=3)
fig.suptitle("compact NeRF, primitives 128 px, 100 views, one run a point, nothing else running", fontsize=8)
fig.tight_layout(rect=(0, 0.1, 1, 1)); fig.savefig(sys.argv[2], dpi=110)
